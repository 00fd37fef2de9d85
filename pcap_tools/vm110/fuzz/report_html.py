"""`coverage.html` of a `--coverage` run: edges over time and the buckets, one self-contained file
with the analysis report's conventions (inline CSS and SVG, no script, nothing fetched)."""
from __future__ import annotations

import html
from pathlib import Path
from typing import Any, Optional

from .. import __version__
from ..analysis.report_html import COLORS, Chart, page_head
from ..fileio import write_text
from ..timefmt import stamp


def _e(value: object) -> str:
    return html.escape(str(value))


def _edges_plot(points: list[dict[str, Any]]) -> str:
    if not points:
        c = Chart(0, 1, 0, 1, "", "")
        c.parts.append('<text x="320" y="110" text-anchor="middle">no coverage recorded</text>')
        return c.svg("edges-time", "Edges covered over time")
    t1 = max(p["s"] for p in points)
    top = max(p["edges"] for p in points)
    c = Chart(0, t1, 0, top * 1.1 or 1, "time since the run started (s)", "edges covered")
    c.axes()
    c.steps([(p["s"], p["edges"]) for p in points], COLORS[0])
    return c.svg("edges-time", "Edges covered over time")


def _bug_row(bucket: dict[str, Any], finding: dict[str, Any], started: Optional[float]) -> str:
    """One bug: what it is, how often, when first seen, the case that found it and where to look
    (its finding, its pcap and the display filter of its packets there)."""
    first = bucket.get("first")
    when = stamp(first, started) if started is not None and first is not None else "-"
    shown = finding.get("display_filter")
    where = _e(bucket["file"]) + (f"<br>{_e(finding['pcap'])}" if finding.get("pcap") else "")
    if shown:
        where += f"<br><code class='filter'>{_e(shown)}</code>"
    case = f"{finding['case_index']}: {finding.get('mutation', '')}" if "case_index" in finding else "-"
    return (f"<tr><td>{_e(bucket['headline'])}</td><td>{bucket['count']}</td><td>{_e(when)}</td>"
            f"<td>{_e(case)}</td><td>{where}</td></tr>")


def _notes(summary: dict[str, Any], cov: dict[str, Any]) -> str:
    """What a reader of the plot must know: the run ended early, triggers not confirmed, a
    resumed corpus."""
    notes = []
    if summary.get("stopped_early"):
        notes.append(f"Stopped early: {_e(summary['stopped_early'])}.")
    replayed = [u for u in summary.get("unreproduced", []) if "not_replayed" not in u]
    if replayed:
        notes.append(f"{len(replayed)} trigger(s) did not happen again when replayed: not counted "
                     "as bugs (listed in findings.json, unreproduced).")
    lost = len(summary.get("unreproduced", [])) - len(replayed)
    if lost:
        # (the controller was gone for good, or the run interrupted: a bug may be among them)
        notes.append(f"{lost} trigger(s) could not be replayed: listed in findings.json (unreproduced, "
                     "not_replayed says why) with the cases that may have caused them.")
    resumed = cov.get("resumed")
    if resumed:
        stored = resumed.get("stored_edges")
        notes.append(f"Resumed {resumed['cases']} of the {resumed['of']} cases of --corpus "
                     + (f"({resumed['edges']} edges once played" + (f", the runs that kept them {stored}" if stored
                                                                    else "") + ")."
                        if resumed["cases"] == resumed["of"]
                        else "(the run ended first: its coverage is not all restored)."))
    if cov.get("corpus_skipped"):
        notes.append(f"{len(cov['corpus_skipped'])} unreadable --corpus file(s) skipped (in findings.json).")
    return "".join(f"<p class='warning'>{n}</p>" for n in notes)


def render(summary: dict[str, Any]) -> str:
    cov = summary.get("coverage", {})
    found = {f.get("file"): f for f in summary.get("findings", [])}
    rows = "".join(_bug_row(b, found.get(b["file"], {}), summary.get("started"))
                   for b in summary.get("buckets", []))
    return "".join([
        page_head("VM-110 fuzz coverage"),
        f"<h1>vm110 fuzz --coverage: {_e(summary.get('target', ''))}</h1>",
        (f"<p>{summary.get('cases_run', 0)} cases in {summary.get('duration_s', 0):.1f} s; {cov.get('edges', 0)} "
         f"edges of a {cov.get('map_size', 0)}-byte map; corpus {cov.get('corpus', 0)} cases.</p>"),
        _notes(summary, cov),
        _edges_plot(cov.get("edges_over_time", [])),
        "<h2>Findings (one row per signature)</h2>",
        ("<table class='findings'><tr><th>finding</th><th>triggers</th><th>first seen (UTC, from the run's start)</th>"
         f"<th>case</th><th>finding, pcap, display filter</th></tr>{rows}</table>") if rows
        else "<p>none</p>",
        f"<p>vm110 {_e(__version__)}</p></body></html>"])


def write_coverage_html(path: Path, summary: dict[str, Any]) -> None:
    write_text(path, render(summary))
