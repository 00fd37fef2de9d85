"""`coverage.html` of a `--coverage` run: edges over time and the buckets, one self-contained file
with the analysis report's conventions (inline CSS and SVG, no script, nothing fetched)."""
from __future__ import annotations

import html
from pathlib import Path
from typing import Any

from .. import __version__
from ..analysis.report_html import COLORS, CSS, Chart
from ..fileio import write_text


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


def render(summary: dict[str, Any]) -> str:
    cov = summary.get("coverage", {})
    rows = "".join(f"<tr><td>{_e(b['headline'])}</td><td>{b['count']}</td><td>{_e(b['file'])}</td></tr>"
                   for b in summary.get("buckets", []))
    return "".join([
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>VM-110 fuzz coverage</title>",
        f"<style>{CSS}</style></head><body><h1>vm110 fuzz --coverage: {_e(summary.get('target', ''))}</h1>",
        (f"<p>{summary.get('cases_run', 0)} cases in {summary.get('duration_s', 0):.1f} s; {cov.get('edges', 0)} "
         f"edges of a {cov.get('map_size', 0)}-byte map; corpus {cov.get('corpus', 0)} cases.</p>"),
        _edges_plot(cov.get("edges_over_time", [])),
        "<h2>Bugs (one row per signature)</h2>",
        f"<table class='findings'><tr><th>bug</th><th>hits</th><th>finding</th></tr>{rows}</table>" if rows
        else "<p>none</p>",
        f"<p>vm110 {_e(__version__)}</p></body></html>"])


def write_coverage_html(path: Path, summary: dict[str, Any]) -> None:
    write_text(path, render(summary))
