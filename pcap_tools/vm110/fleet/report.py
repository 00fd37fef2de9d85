"""`vm110 fleet report`: one self-contained HTML page over a dataset, in the manner of the
capture report (vm110.analysis.report_html: inline CSS and SVG, no script, nothing fetched).

Machines ranked by findings and by link quality; trends per week; the spread of jitter and ack
latency across machines; every finding with its capture, frame and display filter.
"""
from __future__ import annotations

import datetime as dt
import html
import shlex
from typing import Sequence

from .. import __version__
from ..analysis.report_html import COLORS, Chart, page_head
from .query import NAMED, Args, Fleet, Result, machine_key

MAX_FINDINGS = 500           # finding rows on the page (the dataset holds them all)
SHARED = ("captures", "senders", "streams")     # read by several sections: once, into memory
ROW_H, LABEL_W, PLOT_W = 18, 190, 420
LABEL_CHARS = 30            # of a machine's name beside its row (the label column holds about this)


def _e(value: object) -> str:
    return html.escape("" if value is None else str(value))


def _cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".")
    if isinstance(value, (dt.datetime, dt.date)):
        return value.isoformat(sep=" ") if isinstance(value, dt.datetime) else value.isoformat()
    return "" if value is None else str(value)


def _table(result: Result, cls: str = "") -> str:
    head = "".join(f"<th>{_e(c.replace('_', ' '))}</th>" for c in result.columns)
    body = "".join("<tr>" + "".join(f"<td>{_e(_cell(v))}</td>" for v in row) + "</tr>" for row in result.rows)
    return f'<table class="{cls}"><tr>{head}</tr>{body}</table>'


def _name(row: Sequence, width: int) -> str:
    """A machine's name from its key columns (site/machine, or the file of a capture with neither)."""
    return "/".join(str(v) for v in row[:width] if v is not None)


def _trend_chart(fleet: Fleet, metric: str, columns: list[tuple[str, str]], ylabel: str, caption: str) -> str:
    """Weekly values of `columns` (name, legend) of the `trend` query for `metric`."""
    res = fleet.run(NAMED["trend"].sql(fleet, Args(metric=metric, by="week")))
    rows = [r for r in res.rows if r[0] is not None]
    if not rows:
        return f"<p>{_e(caption)}: no data.</p>"
    t0 = rows[0][0]
    days = [(r[0] - t0).days for r in rows]
    series = []
    for name, label in columns:
        i = res.columns.index(name)
        series.append((label, [(d, float(r[i])) for d, r in zip(days, rows) if r[i] is not None]))
    top = max([v for _, pts in series for _, v in pts] + [0.0])
    chart = Chart(min(days) - 1, max(days) + 1, 0, top * 1.15 or 1.0, f"days since the week of {t0.isoformat()}",
                  ylabel, xint=True)
    chart.axes()
    legend = []
    for n, (label, pts) in enumerate(series):
        color = COLORS[n % len(COLORS)]
        if len(pts) > 1:
            chart.polyline(pts, color)
        chart.points(pts, color)
        legend.append((label, color))
    chart.legend(legend)
    return chart.svg(f"trend-{metric}", caption)


def _spread(fleet: Fleet, sql: str, caption: str, unit: str, name: str) -> str:
    """Per machine, the range (min to max) of a per-capture value with its median marked: one row
    each, so that a machine out of line stands out."""
    res = fleet.run(sql)
    rows = [r for r in res.rows if r[-1] is not None]
    if not rows:
        return f"<p>{_e(caption)}: no data.</p>"
    width = len(res.columns) - 3
    top = max(float(r[-1]) for r in rows) or 1.0
    height = ROW_H * len(rows) + 52
    parts = []
    for i, row in enumerate(rows):
        low, mid, high = (float(v) for v in row[-3:])
        y = 14 + i * ROW_H

        def x(v: float) -> float:
            return LABEL_W + v / top * PLOT_W
        machine = _name(row, width)     # a capture's path would run off the left: its end, whole on hover
        label = machine if len(machine) <= LABEL_CHARS else "…" + machine[-LABEL_CHARS + 1:]
        parts.append(f'<text x="{LABEL_W - 6}" y="{y + 4}" text-anchor="end"><title>{_e(machine)}</title>{_e(label)}'
                     '</text>'
                     f'<line x1="{x(low):.1f}" x2="{x(high):.1f}" y1="{y}" y2="{y}" stroke="{COLORS[0]}" '
                     'stroke-width="4">'
                     f"<title>{_e(f'min {low:g}, median {mid:g}, max {high:g} {unit}')}</title></line>"
                     f'<circle class="point" cx="{x(mid):.1f}" cy="{y}" r="4" fill="{COLORS[3]}"/>')
    axis_y = 14 + len(rows) * ROW_H
    for k in range(5):
        v = top * k / 4
        parts.append(f'<text x="{LABEL_W + v / top * PLOT_W:.1f}" y="{axis_y + 12}" '
                     f'text-anchor="middle">{v:.3g}</text>')
    parts.append(f'<text x="{LABEL_W + PLOT_W / 2}" y="{axis_y + 28}" text-anchor="middle">'
                 f"{_e(unit)} (line: min to max over its captures; dot: median)</text>")
    w = LABEL_W + PLOT_W + 30
    return (f'<figure data-plot="{_e(name)}"><figcaption>{_e(caption)}</figcaption>'
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{height}" viewBox="0 0 {w} {height}">'
            + "".join(parts) + "</svg></figure>")


def _findings(fleet: Fleet) -> str:
    who = [c for c in fleet.who("findings") if c != "file"]
    lead = "".join(f"{c}, " for c in who)
    # (a finding of the whole capture, no_eglink or frames not read, has no item: a row all the same)
    res = fleet.run(f"SELECT {lead}file, rule, severity, message, frame, time, sender, filter FROM findings "
                    f"ORDER BY severity = 'error' DESC, rule, {lead}file, item LIMIT {MAX_FINDINGS + 1}")
    total = fleet.run("SELECT count(*) FROM findings").rows[0][0]
    rows = []
    n = len(who)
    for row in res.rows[:MAX_FINDINGS]:
        file, rule, severity, message, frame, time, sender, flt = row[n:]
        command = f"wireshark -r {shlex.quote(file)} -Y {shlex.quote(flt)}" if flt else ""
        rows.append(f"<tr><td>{_e(_name(row, n))}</td><td>{_e(file)}</td>"
                    f'<td class="{_e(severity)}">{_e(rule)}</td><td>{_e(message)}</td><td>{_e(frame)}</td>'
                    f"<td>{_e(_cell(time))}</td><td>{_e(sender)}</td>"
                    f'<td><code class="filter">{_e(flt)}</code></td>'
                    f'<td><code class="filter">{_e(command)}</code></td></tr>')
    head = "".join(f"<th>{h}</th>" for h in ("machine", "capture", "finding", "message", "frame", "time (UTC)",
                                             "sender", "display filter", "open it"))
    more = f"<p>{total - MAX_FINDINGS} more in the dataset (table findings).</p>" if total > MAX_FINDINGS else ""
    return f'<table class="findings"><tr>{head}</tr>{"".join(rows)}</table>{more}'


def render(fleet: Fleet) -> str:
    fleet.in_memory(SHARED)
    # A machine as the rankings have it: a capture without site and machine is one of its own
    # (by its file), not one blank machine of all such captures.
    keys, who = machine_key(fleet)
    w = ", ".join(keys)
    facts = fleet.run(f"SELECT count(*), (SELECT count(*) FROM (SELECT DISTINCT {who} FROM captures)), "
                      "min(first_time), max(last_time), count(*) FILTER (WHERE status <> 'ok') FROM captures").rows[0]
    captures, machines, first, last, bad = facts
    span = f"{_cell(first)} to {_cell(last)}" if first is not None else "no readable capture"
    jitter_sql = (f"SELECT {w}, min(j), median(j), max(j) FROM (SELECT {who}, capture_id, max(jitter_max_ms) AS j "
                  f"FROM streams WHERE type = 'VRPI' GROUP BY ALL) GROUP BY ALL ORDER BY max(j) DESC, {w}")
    vrpo_sql = jitter_sql.replace("'VRPI'", "'VRPO'")
    latency_sql = (f"SELECT {w}, min(l), median(l), max(l) FROM (SELECT {who}, capture_id, "
                   "quantile_cont(latency_first_ms, 0.95) AS l FROM commands WHERE acked GROUP BY ALL) "
                   f"GROUP BY ALL ORDER BY max(l) DESC, {w}")
    out = [page_head("VM-110 EG-Link fleet report"),
           "<h1>VM-110 EG-Link fleet report</h1>",
           (f"<p>{captures} captures of {machines} machines, {_e(span)} (capture time, UTC); "
            f"{bad} damaged or unreadable. Dataset {_e(fleet.dataset.url)}, vm110 {_e(__version__)}.</p>"),
           "<h2>Machines ranked by findings</h2>",
           _table(fleet.run(NAMED["worst-machines"].sql(fleet, Args(limit=1_000_000)))),
           "<h2>Links</h2>",
           _table(fleet.run(NAMED["worst-links"].sql(fleet, Args(limit=1_000_000)))),
           "<h2>Trends per week</h2>",
           _trend_chart(fleet, "loss", [("loss_pct", "loss %")], "%", "Lost packets (share of sent)"),
           _trend_chart(fleet, "jitter", [("vrpi_jitter_max_ms", "VRPI max"), ("vrpo_jitter_max_ms", "VRPO max"),
                                          ("vrpi_jitter_mean_ms", "VRPI mean"), ("vrpo_jitter_mean_ms", "VRPO mean")],
                        "ms", "Jitter"),
           _trend_chart(fleet, "latency", [("vrci_ack_p95_ms", "VRCI p95"), ("vrco_ack_p95_ms", "VRCO p95"),
                                           ("vrci_ack_p50_ms", "VRCI p50"), ("vrco_ack_p50_ms", "VRCO p50")],
                        "ms", "Ack latency (VRCI: the controller's VRAO; VRCO: the base unit's VRAI)"),
           _trend_chart(fleet, "watchdog", [("watchdog", "violations")], "violations", "Watchdog violations"),
           "<h2>Across machines</h2>",
           _spread(fleet, jitter_sql, "VRPI jitter (max per capture)", "ms", "spread-vrpi-jitter"),
           _spread(fleet, vrpo_sql, "VRPO jitter (max per capture)", "ms", "spread-vrpo-jitter"),
           _spread(fleet, latency_sql, "Ack latency (p95 per capture, from the first transmission)", "ms",
                   "spread-ack-latency"),
           "<h2>Failing commands</h2>",
           _table(fleet.run(NAMED["failing-commands"].sql(fleet, Args(limit=50)))),
           "<h2>Overlapping captures</h2>",
           ("<p>Two captures of one machine that share a sender and overlap in time: the same link captured twice "
            "(a tap and a mirror port, a ring-buffer file and a merged file), counted twice in every sum above.</p>"),
           _table(fleet.run(NAMED["overlaps"].sql(fleet, Args(limit=1_000_000)))),
           "<h2>Captures without EG-Link traffic</h2>",
           ("<p>Not one EG-Link packet (a dead link, the wrong interface): nothing said of the link, so apart "
            "from the rankings.</p>"),
           _table(fleet.run(NAMED["no-eglink"].sql(fleet, Args()))),
           "<h2>Captures with errors</h2>",
           _table(fleet.run(NAMED["errors"].sql(fleet, Args()))),
           "<h2>Findings</h2>",
           "<p>Each with its capture, frame, time, sender and the display filter that shows it in Wireshark.</p>",
           _findings(fleet),
           "</body></html>"]
    return "\n".join(out)
