"""The HTML report: one self-contained file (inline CSS and SVG, no script, nothing fetched).

Plots per capture: interval histogram with nominal and watchdog lines, interval over time with
the watchdog line, serial gap timeline, ack latency distribution, retransmissions per command and
the state timeline. Each plot is an <svg> inside <figure data-plot="...">.
"""
from __future__ import annotations

import html
import math
from typing import Iterable, Optional, Sequence

from .. import __version__
from ..fileio import write_text
from ..printable import escaped
from ..timefmt import since
from . import summary

W, H = 640, 220
ML, MR, MT, MB = 72, 16, 14, 34           # plot margins
MAX_POINTS = 2000                          # gap markers per sender
MIN_BAR = 3                                # px: the narrowest and lowest bar drawn
HIST_BAR_PX = 6                            # px: the narrowest histogram bin (narrower ones are merged)
KEY_ROW = 15                               # px per legend row below a plot
CHAR_PX = 6.5                              # px: the widest a character of the 11 px labels takes
LABEL_ROW = 13                             # px between rows of line labels
OVERFLOW = "#7f7f7f"                       # the histogram's bars of the intervals beyond its bins and below 0
RELAYS, RESTART = "#c62828", "#6a1b9a"     # the state timeline's relays-open row and restart lines
Bar = tuple[float, float, float]          # a histogram bar: left, width, count (data units)
COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
          "#bcbd22", "#17becf")
CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1400px;overflow-wrap:anywhere}
h1{font-size:22px}h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ccc}h3{font-size:15px}
table{border-collapse:collapse;margin:8px 0;display:block;overflow-x:auto;max-width:100%}
td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}
th{background:#f2f2f2}td:first-child,th:first-child{text-align:left}
.ok{color:#fff;background:#2a8a2a;padding:4px 10px;border-radius:4px}
.fail{color:#fff;background:#c62828;padding:4px 10px;border-radius:4px}
.error{color:#c62828}.warning{color:#a66a00}.note{color:#1565c0}
figure{display:inline-block;margin:8px 12px 8px 0;vertical-align:top}figcaption{font-weight:600}
svg{max-width:100%;height:auto}svg text{font:11px sans-serif}pre{background:#f6f6f6;padding:8px;overflow:auto}
.findings td{text-align:left}code.filter{user-select:all;background:#f6f6f6;padding:0 4px}
@media (max-width:700px){body{margin:8px}}
"""


def page_head(title: str) -> str:
    """A self-contained page's start, to its <body>: laid out for the screen it is read on (a
    phone took it for a desktop page 980 px wide, its text too small to read)."""
    return ('<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"\n<title>{html.escape(title)}</title>\n<style>{CSS}</style></head><body>")


def _e(value: object) -> str:
    return html.escape(str(value))


def _num(value: Optional[float], digits: int = 2) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _ticks(low: float, high: float, count: int = 5) -> list[float]:
    if high <= low:
        return [low]
    raw = (high - low) / count
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10) if m * mag >= raw), default=raw)
    first = math.ceil(low / step) * step
    return [first + i * step for i in range(int((high - first) / step) + 1)]


def _above(low: float, high: float) -> float:
    """`high`, or where `low` leaves no span (equal, or a number so large that adding 1 changes
    nothing: a hostile capture's timestamps), a value a span above it."""
    if high > low:
        return high
    return low + max(1.0, abs(low) * 1e-9)


class Chart:
    """A tiny SVG plotter: linear axes, then lines, bars, points and rectangles in data units."""

    def __init__(self, x0: float, x1: float, y0: float, y1: float, xlabel: str, ylabel: str,
                 xtime: bool = False, xint: bool = False, origin: Optional[float] = None) -> None:
        self.x0, self.x1 = x0, _above(x0, x1)
        self.origin = x0 if origin is None else origin   # a time axis counts seconds from this
        self.y0, self.y1 = y0, _above(y0, y1)
        self.parts: list[str] = []
        self.xlabel, self.ylabel, self.xtime, self.xint = xlabel, ylabel, xtime, xint
        self.xtick_min = self.x0          # no x ticks left of this (the histogram's slot of negative intervals)
        self.xtick_max = self.x1          # no x ticks right of this (the histogram's overflow slot)
        self.extra = 0                    # px below the plot (a legend)

    def x(self, v: float) -> float:
        return ML + (v - self.x0) / (self.x1 - self.x0) * (W - ML - MR)

    def y(self, v: float) -> float:
        return H - MB - (v - self.y0) / (self.y1 - self.y0) * (H - MT - MB)

    def axes(self, yticks: bool = True) -> None:
        p = self.parts
        p.append(f'<rect x="{ML}" y="{MT}" width="{W - ML - MR}" height="{H - MT - MB}" fill="none" stroke="#999"/>')
        # Time axes count seconds from the start of the capture (its first record, which need not be
        # the earliest), so their ticks are placed on that.
        base = self.origin if self.xtime else 0.0
        for t in _ticks(self.xtick_min - base, self.xtick_max - base):
            if self.xint and t != int(t):
                continue
            p.append(f'<text x="{self.x(t + base):.1f}" y="{H - MB + 14}" text-anchor="middle">{t:g}</text>')
        for t in _ticks(self.y0, self.y1) if yticks else ():
            p.append(f'<text x="{ML - 4}" y="{self.y(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
            p.append(f'<line x1="{ML}" x2="{W - MR}" y1="{self.y(t):.1f}" y2="{self.y(t):.1f}" stroke="#eee"/>')
        p.append(f'<text x="{(ML + W - MR) / 2}" y="{H - 4}" text-anchor="middle">{_e(self.xlabel)}</text>')
        if self.ylabel:
            p.append(f'<text x="12" y="{(MT + H - MB) / 2}" text-anchor="middle" '
                     f'transform="rotate(-90 12 {(MT + H - MB) / 2})">{_e(self.ylabel)}</text>')

    def vline(self, v: float, color: str, label: str, title: str = "", y: float = MT + 11) -> None:
        """A dashed line at v, its label at height y."""
        if self.x0 <= v <= self.x1:
            hover = f"<title>{_e(title)}</title>" if title else ""
            self.parts.append(f'<line class="marker" x1="{self.x(v):.1f}" x2="{self.x(v):.1f}" y1="{MT}" '
                              f'y2="{H - MB}" stroke="{color}" stroke-dasharray="4 3">{hover}</line>'
                              + (self._vlabel(self.x(v), color, label, y) if label else ""))

    @staticmethod
    def vlabel_at(x: float) -> tuple[str, float]:
        """(text-anchor, offset) of a line's label: right of its line, or left of it when the line
        is in the plot's right half (where the text would run past the edge)."""
        return ("end", -3) if x > (ML + W - MR) / 2 else ("start", 3)

    @classmethod
    def _vlabel(cls, x: float, color: str, label: str, y: float) -> str:
        anchor, dx = cls.vlabel_at(x)
        return f'<text x="{x + dx:.1f}" y="{y:.1f}" text-anchor="{anchor}" fill="{color}">{_e(label)}</text>'

    def hline(self, v: float, color: str, label: str) -> None:
        if self.y0 <= v <= self.y1:
            self.parts.append(f'<line class="marker" x1="{ML}" x2="{W - MR}" y1="{self.y(v):.1f}" '
                              f'y2="{self.y(v):.1f}" stroke="{color}" stroke-dasharray="4 3"/>'
                              f'<text x="{W - MR - 3}" y="{self.y(v) - 3:.1f}" text-anchor="end" fill="{color}">'
                              f'{_e(label)}</text>')

    def bars(self, items: Iterable[tuple[float, float, float]], color: str, cls: str = "bar", title: str = "") -> None:
        """Bars at least MIN_BAR px wide (centred on their bin) and MIN_BAR px high: a bin far
        narrower than a pixel, or a count of 1 beside thousands, still shows."""
        for left, width, height in items:
            x, x2 = self.x(left), self.x(left + width)
            if x2 - x - 1 < MIN_BAR:
                x, x2 = (x + x2 - MIN_BAR) / 2, (x + x2 + MIN_BAR) / 2 + 1
            top = min(self.y(height), self.y(self.y0) - MIN_BAR)
            self.parts.append(f'<rect class="{cls}" x="{x:.1f}" y="{top:.1f}" width="{x2 - x - 1:.1f}" '
                              f'height="{self.y(self.y0) - top:.1f}" fill="{color}">'
                              + (f"<title>{_e(title)}</title>" if title else "") + "</rect>")

    def polyline(self, points: Iterable[tuple[float, float]], color: str) -> None:
        pts = " ".join(f"{self.x(a):.1f},{self.y(b):.1f}" for a, b in points)
        self.parts.append(f'<polyline class="series" points="{pts}" fill="none" stroke="{color}"/>')

    def steps(self, points: list, color: str) -> None:
        """A step line: each value holds from its time to the next (gaps show as one jump)."""
        stepped = [pt for (a, b), (c, _) in zip(points, points[1:] + [points[-1]]) for pt in ((a, b), (c, b))]
        self.polyline(stepped, color)

    def legend(self, items: list) -> None:
        for i, (label, color) in enumerate(items):
            self.parts.append(f'<text x="{W - MR - 6}" y="{MT + 14 + 13 * i}" text-anchor="end" fill="{color}">'
                              f'{_e(label)}</text>')

    def points(self, points: Iterable[tuple[float, float]], color: str) -> None:
        for a, b in points:
            self.parts.append(f'<circle class="point" cx="{self.x(a):.1f}" cy="{self.y(b):.1f}" r="3" fill="{color}"/>')

    def rect(self, a: float, b: float, row: float, height: float, color: str, title: str) -> None:
        x, x2 = self.x(a), self.x(b)
        self.parts.append(f'<rect class="segment" x="{x:.1f}" y="{self.y(row + height):.1f}" '
                          f'width="{max(x2 - x, 1):.1f}" height="{self.y(row) - self.y(row + height):.1f}" '
                          f'fill="{color}"><title>{_e(title)}</title></rect>')

    def key(self, rows: list[tuple[str, list[tuple[str, str]]]]) -> None:
        """A legend below the plot: per row a label, then a swatch and a name per entry; what does
        not fit the width is counted ("+3 more")."""
        for i, (label, entries) in enumerate(rows):
            y = H + 4 + KEY_ROW * i
            self.parts.append(f'<text x="{ML - 4}" y="{y + 10}" text-anchor="end">{_e(label)}</text>')
            x: float = ML
            for k, (name, color) in enumerate(entries):
                width = 14 + CHAR_PX * len(name) + 10
                if x + width > W - MR:
                    self.parts.append(f'<text x="{x}" y="{y + 10}">+{len(entries) - k} more</text>')
                    break
                self.parts.append(f'<rect class="swatch" x="{x}" y="{y + 1}" width="10" height="10" fill="{color}"/>'
                                  f'<text x="{x + 14}" y="{y + 10}">{_e(name)}</text>')
                x += width
        self.extra = KEY_ROW * len(rows) + 8

    def svg(self, name: str, caption: str) -> str:
        height = H + self.extra
        return (f'<figure data-plot="{_e(name)}"><figcaption>{_e(caption)}</figcaption>'
                f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{height}" viewBox="0 0 {W} {height}">'
                + "".join(self.parts) + "</svg></figure>")


def _empty(name: str, caption: str, why: str) -> str:
    c = Chart(0, 1, 0, 1, "", "")
    c.parts.append(f'<text class="empty" x="{W / 2}" y="{H / 2}" text-anchor="middle">{_e(why)}</text>')
    return c.svg(name, caption)


def _histogram_plot(p: dict) -> str:
    """The report's bins (the bulk of the intervals: up to p99.9, at most 4 x the median) scaled
    to the data, not stretched to a far watchdog (a line out of range is named at the edge
    instead), a separate grey bar right of a break for the intervals beyond them (one 3 s
    watchdog gap among 100 ms intervals), and one left of a break for the negative intervals (the
    clock stepped back 20 s among 100 ms intervals: an axis from -20000 left them a sliver)."""
    name = f"{p['type']} interval histogram — {p['sender']}"
    hist = p.get("plot", {}).get("histogram", [])
    if len(hist) < 2:
        return _empty("interval-histogram", name, "fewer than two packets")
    # The bin width from the bins themselves: the report's rounded bin_ms is 0 for tiny bins.
    width = (hist[-1][0] - hist[0][0]) / (len(hist) - 1)
    back = _stepped_back(p, hist)
    hist = _without_lowest(hist, back)
    body, (over_at, over) = hist[:-1], hist[-1]
    maximum = p["interval_ms"]["max"]
    beyond = bool(over) and maximum is not None and maximum > over_at + width
    # Without the negative intervals the rest starts at its first bin, and at 0 at the least; its
    # bins are wide (from the lowest interval): the last one, kept on the axis, up to the maximum.
    low = max(next(a for a, n in hist if n), 0.0) if back else hist[0][0]
    high = max(over_at, maximum) if back and over and not beyond else over_at
    mid, span = (low + high) / 2, high - low
    span = max(span, 1.0, 0.04 * abs(mid))           # all intervals alike: a readable span around them
    x0, x1 = mid - span / 2 - 0.04 * span, mid + span / 2 + 0.04 * span
    limit, nominal = p["watchdog"]["limit_ms"], p.get("nominal_ms")
    # (a VRPO stream with no burst interval has no nominal period: no line, and no label to format)
    lines = [(v, color, f"{name} {v:g} ms") for v, color, name in ((nominal, "#2a8a2a", "nominal"),
                                                                   (limit, "#c62828", "watchdog")) if v]
    for v, _, _ in lines:              # a line close to the data widens the axis to it, a far one not
        if v < x0 and x1 - v <= 2 * (x1 - x0):
            x0 = v - 0.04 * (x1 - v)
        elif v > x1 and v - x0 <= 2 * (x1 - x0):
            x1 = v + 0.04 * (v - x0)
    # Bins narrower than a few pixels are merged for display, so that a bar is wide enough to see;
    # the intervals of the last bin join them when they all lie within one bin width of its start.
    shown = _merge(body if beyond else hist, width, x0, (x1 - x0) * HIST_BAR_PX / (W - ML - MR))
    if back:                                   # what is left lies from 0 to the maximum
        shown = _clip(shown, 0.0, maximum)
    slot = 0.12 * (x1 - x0) if beyond else 0.0
    under = 0.12 * (x1 - x0) if back else 0.0
    top = max([n for _, _, n in shown] + ([over] if beyond else []) + [back]) * 1.1
    c = Chart(x0 - under, x1 + slot, 0, top, "interval (ms)", "intervals (count)")
    c.xtick_min, c.xtick_max = x0, x1
    c.axes()
    c.bars(shown, COLORS[0])
    taken = [_overflow(c, x1, slot, over_at, over, maximum)] if beyond else []
    if back:
        _underflow(c, x0, under, back, p["interval_ms"]["min"])
    _line_labels(c, lines, x0, x1, taken)
    return c.svg("interval-histogram", name)


def _stepped_back(p: dict, hist: list) -> int:
    """The stream's negative intervals (its clock stepped back), unless nothing else is left to
    scale the plot to."""
    back = p.get("time_backwards", 0)
    return back if back < sum(n for _, n in hist) else 0


def _without_lowest(hist: list, n: int) -> list:
    """The histogram without its n lowest intervals: the negative ones fill the first bins
    (bins that start at the lowest interval, or a first bin they are clipped into)."""
    out = []
    for a, count in hist:
        taken = min(n, count)
        n -= taken
        out.append([a, count - taken])
    return out


def _clip(bars: list[Bar], low: float, high: Optional[float]) -> list[Bar]:
    """Bars (left, width, count) cut to [low, high], where their intervals are known to lie."""
    out = []
    for a, w, n in bars:
        left, right = max(a, low), a + w if high is None else min(a + w, high)
        out.append((left, max(right - left, 0.0), n))
    return out


def _overflow(c: Chart, x1: float, slot: float, over_at: float, over: int, maximum: float) -> tuple:
    """The intervals beyond the bins as a grey bar right of a break; the box its "max" label takes."""
    c.parts.append(f'<line x1="{c.x(x1):.1f}" x2="{c.x(x1):.1f}" y1="{MT}" y2="{H - MB}" stroke="#999" '
                   'stroke-dasharray="2 2"/>')
    c.parts.append(f'<text x="{c.x(x1 + slot / 2):.1f}" y="{H - MB + 14}" text-anchor="middle">'
                   f'≥{over_at:.0f}</text>')
    c.bars([(x1 + slot * 0.2, slot * 0.6, over)], OVERFLOW, "bar overflow",
           f"{over} intervals of {over_at:g} ms or more (max {maximum:g} ms)")
    label, x, y = f"max {maximum:.0f}", c.x(x1 + slot / 2), min(c.y(over), H - MB - MIN_BAR) - 3
    c.parts.append(f'<text x="{x:.1f}" y="{y:.1f}" text-anchor="middle" fill="{OVERFLOW}">{label}</text>')
    half = CHAR_PX * len(label) / 2
    return (x - half, x + half, y - 11, y + 3)


def _underflow(c: Chart, x0: float, under: float, back: int, minimum: float) -> None:
    """The negative intervals (the report's time_backwards) as a grey bar left of a break, named
    in a key below the plot: the slot is too narrow for the name."""
    what = f"{back} interval{'s' if back > 1 else ''} < 0 (clock stepped back)"
    c.parts.append(f'<line x1="{c.x(x0):.1f}" x2="{c.x(x0):.1f}" y1="{MT}" y2="{H - MB}" stroke="#999" '
                   'stroke-dasharray="2 2"/>')
    c.parts.append(f'<text class="underflow" x="{c.x(x0 - under / 2):.1f}" y="{H - MB + 14}" '
                   'text-anchor="middle">&lt;0</text>')
    c.bars([(x0 - under * 0.8, under * 0.6, back)], OVERFLOW, "bar underflow", f"{what}, min {minimum:g} ms")
    c.key([("", [(f"{what}, min {minimum:.0f} ms", OVERFLOW)])])


def _line_labels(c: Chart, lines: list, x0: float, x1: float, taken: list) -> None:
    """The nominal and watchdog lines: in range a dashed line labelled beside it, off the scale
    named at that edge, below the other labels. Each label goes on the first row where it
    overlaps no other (two lines close together, the overflow bar's label)."""
    for v, color, label in lines:
        if x0 <= v <= x1:
            anchor, dx = c.vlabel_at(c.x(v))
            text, at, row = label, c.x(v) + dx, 0
        else:
            right = v > x1
            text = f"{'' if right else '← '}{label}{' →' if right else ''}"
            anchor, at, row = ("end", W - MR - 3, 1) if right else ("start", c.x(x0) + 3, 1)
        left = at - CHAR_PX * len(text) if anchor == "end" else at
        y = _free_row(taken, left, left + CHAR_PX * len(text), row)
        if row == 0:
            c.vline(v, color, label, y=y)
        else:
            c.parts.append(f'<text class="offscale" x="{at:.1f}" y="{y:.1f}" text-anchor="{anchor}" '
                           f'fill="{color}">{_e(text)}</text>')


def _free_row(taken: list, left: float, right: float, row: int) -> float:
    """The baseline of the first label row from `row` on where a label from x `left` to `right`
    overlaps none of the `taken` boxes (left, right, top, bottom); its box is then taken."""
    while True:
        y = MT + 11 + LABEL_ROW * row
        if not any(left < r and a < right and y - 11 < b and t < y + 3 for a, r, t, b in taken):
            taken.append((left, right, y - 11, y + 3))
            return y
        row += 1


def _merge(hist: list, width: float, origin: float, least: float) -> list[Bar]:
    """(left, width, count) of the non-empty bins, merged into bins of at least `least` (aligned
    on `origin`) where the given ones are narrower."""
    if width >= least:
        return [(a, width, n) for a, n in hist if n]
    merged: dict[int, int] = {}
    for a, n in hist:
        if n:
            k = math.floor((a + width / 2 - origin) / least)
            merged[k] = merged.get(k, 0) + n
    return [(origin + k * least, least, n) for k, n in sorted(merged.items())]


def _series_plot(p: dict, t0: float) -> str:
    """Intervals over time, from the first record (`t0`) or any earlier arrival."""
    name = f"{p['type']} interval over time — {p['sender']}"
    series = p.get("plot", {}).get("series", [])
    if not series:
        return _empty("interval-time", name, "fewer than two packets")
    limit = p["watchdog"]["limit_ms"]
    c = Chart(min(t0, *(t for t, _ in series)), max(t for t, _ in series), 0, max(*(v for _, v in series), limit) * 1.1,
              "time since capture start (s)", "interval (ms, max per bucket)", xtime=True, origin=t0)
    c.axes()
    c.steps(series, COLORS[0])
    c.hline(limit, "#c62828", f"watchdog {limit:g} ms")
    return c.svg("interval-time", name)


def _gap_plot(report: dict, t0: float, span: tuple[float, float]) -> str:
    """Gaps over the capture's `span` (earliest, latest record), in s from its first record `t0`."""
    senders = [s for s in report["senders"] if s["serial"]["gaps"]]
    if not senders:
        return _empty("serial-gaps", "Serial gaps", "no serial gaps")
    top = max(g["count"] for s in senders for g in s["serial"]["gaps"])
    c = Chart(*span, 0, top * 1.2, "time since capture start (s)", "packets missing (count)", xtime=True,
              origin=t0)
    c.axes()
    for i, s in enumerate(senders):
        gaps = s["serial"]["gaps"]
        step = max(1, math.ceil(len(gaps) / MAX_POINTS))       # a page stays small on a bad day
        c.points(((g["time"], g["count"]) for g in gaps[::step]), COLORS[i % len(COLORS)])
    c.legend([(s["id"], COLORS[i % len(COLORS)]) for i, s in enumerate(senders)])
    return c.svg("serial-gaps", "Serial gaps")


def _latency_plot(report: dict) -> str:
    values = {n: [c["latency_first_ms"] for c in cmd["list"] if c["latency_first_ms"] is not None]
              for n, cmd in report["commands"].items()}
    every = [v for vs in values.values() for v in vs]
    if not every:
        return _empty("ack-latency", "Ack latency", "no acknowledged commands")
    low, high = min(every), max(every)
    bins = 30
    width = max((high - low) / bins, 1e-3)
    counts = {n: [0] * (bins + 1) for n in values}
    for n, vs in values.items():
        for v in vs:
            counts[n][min(int((v - low) / width), bins)] += 1
    c = Chart(low, low + width * (bins + 1), 0, max(max(v) for v in counts.values()) * 1.1,
              "ack latency from the first transmission (ms)", "commands (count)")
    c.axes()
    for i, cs in enumerate(counts.values()):
        c.bars(((low + k * width + i * width / 2, width / 2, m) for k, m in enumerate(cs) if m), COLORS[i])
    c.legend([(n, COLORS[i]) for i, n in enumerate(counts)])
    return c.svg("ack-latency", "Ack latency distribution")


def _retransmission_plot(report: dict) -> str:
    hists = {n: {int(k): v for k, v in cmd["retransmission_histogram"].items()}
             for n, cmd in report["commands"].items()}
    keys = sorted({k for h in hists.values() for k in h})
    if not keys:
        return _empty("retransmissions", "Retransmissions per command", "no commands")
    c = Chart(-0.5, keys[-1] + 0.5, 0, max(v for h in hists.values() for v in h.values()) * 1.1,
              "retransmissions of a command (count)", "commands (count)", xint=True)
    c.axes()
    for i, h in enumerate(hists.values()):
        c.bars(((k - 0.4 + i * 0.4, 0.4, v) for k, v in h.items()), COLORS[i])
    c.legend([(n, COLORS[i]) for i, n in enumerate(hists)])
    return c.svg("retransmissions", "Retransmissions per command")


def _state_plot(st: dict, t0: float, span: tuple[float, float], restarts: list[tuple[float, str]]) -> str:
    """The base unit's state over the capture's `span` (earliest, latest record), with every
    sender's restarts as vertical lines; in s from its first record `t0`."""
    fields = list(st["segments"])
    t1 = span[1]
    c = Chart(*span, 0, len(fields) + 1, "time since capture start (s)", "", xtime=True, origin=t0)
    c.axes(yticks=False)
    key: list[tuple[str, list[tuple[str, str]]]] = []
    for row, f in enumerate(reversed(fields)):
        values = sorted({s["value"] for s in st["segments"][f]})
        colors = {v: COLORS[i % len(COLORS)] for i, v in enumerate(values)}
        names = {s["value"]: s["name"] for s in st["segments"][f]}
        key.insert(0, (f, [(str(names[v]), colors[v]) for v in values]))
        for s in st["segments"][f]:
            color = colors[s["value"]]
            end = s["end"] if s["end"] is not None else t1
            c.rect(s["start"], end, row + 0.1, 0.8, color, f"{f}: {s['name']} from {s['start'] - t0:.3f} s")
    for ep in st["episodes_relays_open"]:
        end = ep["end"] if ep["end"] is not None else t1
        c.rect(ep["start"], end, len(fields) + 0.1, 0.8, RELAYS, "ES-Link relays open")
    for time, who in restarts:      # named in the legend and on hover: labels of close restarts would overlap
        c.vline(time, RESTART, "", title=f"restart of {who} at {time - t0:.3f} s")
    for row, label in enumerate([*reversed(fields), "relays open"]):
        c.parts.append(f'<text x="{ML - 4}" y="{c.y(row + 0.5) + 4:.1f}" text-anchor="end">{_e(label)}</text>')
    marks = [("ES-Link relays open", RELAYS)] + ([("restart (dashed line)", RESTART)] if restarts else [])
    c.key([*key, ("marks", marks)])
    return c.svg("state-timeline", f"State timeline — {st['sender']}")


def _table(header: list[str], rows: list[list[object]]) -> str:
    head = "".join(f"<th>{_e(h.replace('_', ' '))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_e(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _findings_table(verdict: dict, t0: float) -> str:
    """Every located item of every finding, with the display filter that shows it in Wireshark."""
    findings, wireshark = verdict["findings"], summary.in_wireshark(verdict)
    rows = []
    for f in findings:
        for item in f.get("items", []):
            what = summary.details(item, skip=("sender",))
            frames = item.get("frames", [item["frame"]])
            # A watchdog item names the packet that ended the silence, and the time the silence began.
            when = ("silence from " if item.get("until_end") is False else "") + since(item["time"], t0)
            rows.append(f'<tr><td class="{_e(f["severity"])}">{_e(f["rule"])}</td>'
                        f"<td>{_e(', '.join(map(str, frames[:10])) + (' …' if len(frames) > 10 else ''))}</td>"
                        f"<td>{when}</td><td>{_e(item.get('sender', ''))}</td>"
                        f"<td>{_e(what)}</td>"
                        f'<td><code class="filter">{_e(item["filter"])}</code></td></tr>')
        if f.get("more"):
            where = (f'{_e(wireshark)}: <code class="filter">{_e(f["filter"])}</code>' if f.get("filter")
                     else f'the reports keep the first {len(f["items"])}')
            rows.append(f'<tr><td>{_e(f["rule"])}</td><td colspan="5">… {f["more"]} more ({where})</td></tr>')
    if not rows:
        return ""
    head = "".join(f"<th>{h}</th>" for h in ("finding", "frames", "time (s)", "sender", "what", "display filter"))
    why = (f'<p>No Wireshark filter for the rules: {_e(verdict["no_filters"])}</p>' if "no_filters" in verdict
           else "")
    return f'<h3>Findings</h3><table class="findings"><tr>{head}</tr>{"".join(rows)}</table>{why}'


def _section(report: dict) -> str:
    cap, crc, verdict = report["capture"], report["crc"], report["verdict"]
    t0 = cap["first_time"] or 0.0
    t1 = cap["last_time"] or t0 + 1
    # The plots cover every record: the last need not be the latest (appended captures).
    span = (t0, t1) if cap["earliest_time"] is None else (cap["earliest_time"], cap["latest_time"])
    # (file names: any characters; an RTL override or a newline shown as its escape, as on the terminal)
    out = [f"<h2>{_e(escaped(cap['file']))}</h2>",
           (f'<p><span class="{"ok" if verdict["ok"] else "fail"}">{"OK" if verdict["ok"] else "FAIL"}</span> '
            f"({summary.counted(verdict['findings'])}) {cap['packets']} packets, {cap['eglink_packets']} EG-Link, "
            f"{_num(cap['duration_s'], 1)} s; "
            f"{_e(summary.crc_words(crc))}"
            + (f"; {_e(summary.time_range(cap))}" if cap["first_time"] is not None else "") + "</p>")]
    if verdict["findings"]:
        out.append("<ul>" + "".join(f'<li class="{_e(f["severity"])}">{_e(f["severity"])}: {_e(f["message"])}</li>'
                                    for f in verdict["findings"]) + "</ul>")
        out.append(_findings_table(verdict, t0))
    if report["illegal"]["total"]:
        out.append("<h3>Illegal packets</h3>"
                   + _table(["reason", "packets"], list(report["illegal"]["by_reason"].items())))
    out.append("<h3>Senders</h3>")
    out.append(_table(["sender", "packets by type", "scope", "received", "lost", "gaps", "duplicates",
                       "out of order", "wraps", "restarts"],
                      [[s["id"], ", ".join(f"{k} {v}" for k, v in s["by_type"].items()),
                        f'{s["serial"]["scope"]} ({s["serial"]["scope_reason"]})',
                        s["serial"]["received"], s["serial"]["lost"], summary.open_gaps(s["serial"]["gaps"]),
                        s["serial"]["duplicates"], s["serial"]["out_of_order"], s["serial"]["wraps"],
                        "; ".join([str(s["serial"]["restarts"])] + [
                            f"{since(r['time'], t0)} s frame {r['frame']}: {r['from']} → {r['to']}"
                            + (f" port {r['port_from']} → {r['port_to']}" if "port_from" in r else "")
                            for r in s["serial"]["restart_events"]])]
                       for s in report["senders"]]))
    out.append("<h3>Periodic streams (ms)</h3>")
    out.append(_table(["stream", "sender", "count", "min", "mean", "p50", "p95", "p99", "p99.9", "max",
                       "jitter final", "jitter mean", "jitter max", "watchdog violations"],
                      [[p["type"], p["sender"], p["count"], *(_num(p["interval_ms"][k]) for k in
                                                              ("min", "mean", "p50", "p95", "p99", "p999", "max")),
                        *(_num((p["jitter_ms"] or {}).get(k), 3) for k in ("final", "mean", "max")),
                        f"{len(p['watchdog']['violations'])} (> {p['watchdog']['limit_ms']:g})"]
                       for p in report["periodic"]]))
    out.append("<h3>Commands</h3>")
    keys = ("commands", "transmissions", "retransmissions", "acked", "unacked", "interrupted", "failed",
            "spurious_retransmissions", "acks_without_command", "duplicate_acks")
    out.append(_table(["type", *keys, "latency p50 (ms)", "latency p95 (ms)", "latency max (ms)"],
                      [[n, *(c[k] for k in keys), *(_num(c["ack_latency_ms"][k]) for k in ("p50", "p95", "max"))]
                       for n, c in report["commands"].items()]))
    b = report["vrpo_bursts"]
    out.append(f"<p>VRPO bursts: {b['complete']} complete, {b['incomplete']} incomplete.</p>")
    out.append("<h3>Plots</h3>")
    for p in report["periodic"]:
        out.append(_histogram_plot(p))
        out.append(_series_plot(p, t0))
    out.append(_gap_plot(report, t0, span))
    out.append(_latency_plot(report))
    out.append(_retransmission_plot(report))
    restarts = [(r["time"], s["id"]) for s in report["senders"] for r in s["serial"]["restart_events"]
                if r["time"] is not None]
    for st in report["state"]:
        out.append(_state_plot(st, t0, span, restarts))
        if st["episodes_relays_open"]:
            out.append("<h3>ES-Link relays open</h3>" + _table(
                ["start (s)", "duration (s)", "BU states", "still open at end"],
                [[f"{e['start'] - t0:.3f}", _num(e["duration_s"], 3), "/".join(e["states"]), e["open_at_end"]]
                 for e in st["episodes_relays_open"]]))
    out.append("<details><summary>Terminal summary</summary><pre>" + _e(summary.render(report)) + "</pre></details>")
    return "\n".join(out)


def render(reports: list[dict], combined: Optional[dict] = None, errors: Sequence[dict] = ()) -> str:
    ok = all(r["verdict"]["ok"] for r in reports) and not errors
    parts = [page_head("VM-110 EG-Link capture analysis"),
             ("<h1>VM-110 EG-Link capture analysis "
              f'<span class="{"ok" if ok else "fail"}">{"OK" if ok else "FAIL"}</span></h1>'),
             f"<p>vm110 {_e(__version__)}, engine {_e(reports[0]['tool']['engine'])}</p>"]
    if errors:
        parts.append("<h2>Captures that could not be read</h2><ul>"
                     + "".join(f'<li class="error">{_e(escaped(e["error"]))}</li>' for e in errors) + "</ul>")
    if combined:
        parts.append("<pre>" + _e(summary.render_combined(combined)) + "</pre>")
    parts += [_section(r) for r in reports]
    parts.append("</body></html>")
    return "\n".join(parts)


def write(path: str, reports: list[dict], combined: Optional[dict] = None, errors: Sequence[dict] = ()) -> None:
    """The HTML file, written atomically."""
    write_text(path, render(reports, combined, errors))
