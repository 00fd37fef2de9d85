"""The HTML report's plots as a reader sees them: headless Chromium draws every plot of the report
(the report's own markup and CSS, each figure at a known place on one page), takes a screenshot,
and the test reads the pixels (pypng). Each interval histogram has bars of the bar colour inside its
plot area, at least a few pixels wide, the tallest as high as the y axis says (max count x 1.1 on
top), standing where the axis puts the stream's median interval (tick labels read from the SVG), and
an interval far longer than the rest in a grey bar of its own right of them; the
state timeline's legend shows a swatch of every colour its rows use; every axis label has a unit.
Captures: all intervals alike (bu-watchdog's VRPI, 124.991-125.009 ms: one bin of 0.0003 ms, which
the report rounds to 0), one watchdog gap among 120 (bu-watchdog's VRPO), restarts, loss with jitter,
a crafted stream with a single 100 s outlier, and one of a single interval."""
from __future__ import annotations

import html
import re
import subprocess
from pathlib import Path

import png
import pytest
import tshark_runner as T
from test_analysis_html import CONSOLE, FLAGS, browser
from vm110.analysis import analyze
from vm110.analysis import report_html as R
from vm110.layers import VM110, VRPI

CAPTURES = Path(__file__).resolve().parent.parent / "captures"
FIGURE = re.compile(r'<figure data-plot="([^"]+)">.*?</figure>', re.DOTALL)
SVG_HEIGHT = re.compile(r'<svg [^>]*height="(\d+)"')
TICK = re.compile(r'<text x="([\d.]+)" y="(\d+)" text-anchor="middle">([^<]*)</text>')
AXIS_LABEL = re.compile(r'<text x="[\d.]+" y="[\d.]+" text-anchor="middle"(?: transform="[^"]*")?>([^<]*)</text>')
SLOT = 40          # px between figures on the page


def rgb(color: str) -> tuple[int, int, int]:
    return int(color[1:3], 16), int(color[3:5], 16), int(color[5:7], 16)


BAR, OVER = rgb(R.COLORS[0]), rgb(R.OVERFLOW)
PLOT_HEIGHT = R.H - R.MT - R.MB


def vrpi_capture(path: Path, times: list[int]) -> Path:
    T.write_pcap(path, [bytes(VM110(origin=0x0101, serial=i) / VRPI(bu_state=0x11, armed_ru=0x0C07, ru_state=3))
                        for i in range(len(times))], times)
    return path


# 40 VRPI exactly 125 ms apart, 100 s of silence, 5 more: 44 intervals, one of 100 000 ms.
OUTLIER = [125_000 * i for i in range(40)] + [125_000 * 39 + 100_000_000 + 125_000 * i for i in range(5)]
ONE_INTERVAL = [0, 130_000]      # two packets: a histogram of one interval


def screenshot(figures: list[str], tmp_path: Path) -> tuple[list[list[tuple[int, int, int]]], list[int]]:
    """The page's pixels (rows of RGB) and each figure's top; no console message allowed."""
    tops, y = [], 0
    for f in figures:
        tops.append(y)
        y += int(SVG_HEIGHT.search(f).group(1)) + SLOT
    body = "".join(f'<div style="position:absolute;left:0;top:{top}px">{f}</div>' for top, f in zip(tops, figures))
    page = tmp_path / "plots.html"
    page.write_text(f"<!DOCTYPE html><html><head><meta charset='utf-8'><style>{R.CSS}"
                    "body{margin:0}figure{margin:0}figcaption{display:none}</style></head>"
                    f"<body>{body}</body></html>")
    shot = tmp_path / "plots.png"
    done = subprocess.run([browser(), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--hide-scrollbars",
                           "--force-device-scale-factor=1", f"--window-size={R.W},{y}", f"--screenshot={shot}",
                           page.as_uri()], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and shot.exists(), done.stderr[-2000:]
    assert not [line for line in done.stderr.splitlines() if CONSOLE.search(line)]
    width, height, rows, _ = png.Reader(bytes=shot.read_bytes()).asRGB8()
    assert (width, height) == (R.W, y)
    return [[tuple(r[i:i + 3]) for i in range(0, 3 * width, 3)] for r in rows], tops


def columns(pixels, top: int, color: tuple[int, int, int]) -> dict[int, int]:
    """x -> pixels of `color` in that column of the plot area of the figure at `top`."""
    out = {}
    for x in range(R.ML + 1, R.W - R.MR):
        n = sum(1 for y in range(top + R.MT + 1, top + R.H - R.MB) if pixels[y][x] == color)
        if n:
            out[x] = n
    return out


def runs(xs: list[int]) -> list[tuple[int, int]]:
    """Consecutive x positions as (first, last)."""
    out: list[tuple[int, int]] = []
    for x in sorted(xs):
        if out and x == out[-1][1] + 1:
            out[-1] = (out[-1][0], x)
        else:
            out.append((x, x))
    return out


def value_to_x(figure: str) -> tuple[float, float]:
    """(a, b) with x = a + b * value, from the x axis' numeric tick labels."""
    ticks = [(float(x), float(v)) for x, y, v in TICK.findall(figure)
             if int(y) == R.H - R.MB + 14 and re.fullmatch(r"-?[\d.]+(e[-+]?\d+)?", v)]
    assert len(ticks) >= 2, ticks
    (xa, va), (xb, vb) = ticks[0], ticks[-1]
    scale = (xb - xa) / (vb - va)
    return xa - scale * va, scale


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> list[dict]:
    crafted = tmp_path_factory.mktemp("crafted")
    paths = [CAPTURES / name for name in ("bu-watchdog.pcap", "restart.pcapng", "loss.pcapng", "glink.pcapng")]
    paths += [vrpi_capture(crafted / "outlier.pcap", OUTLIER), vrpi_capture(crafted / "one.pcap", ONE_INTERVAL)]
    return [analyze(str(p)) for p in paths]


def test_every_histogram_shows_its_bars_where_the_data_lie(reports, tmp_path):
    figures, streams = [], []
    for report in reports:
        page = R.render([report])
        hist = [m.group(0) for m in FIGURE.finditer(page) if m.group(1) == "interval-histogram"]
        assert len(hist) == len(report["periodic"])
        figures += hist
        streams += [(report["capture"]["file"], p) for p in report["periodic"]]
    pixels, tops = screenshot(figures, tmp_path)
    checked = 0
    for figure, top, (name, p) in zip(figures, tops, streams):
        where = f"{Path(name).name} {p['type']} {p['sender']}"
        if p["count"] < 2:
            continue
        blue, grey = columns(pixels, top, BAR), columns(pixels, top, OVER)
        assert blue, f"{where}: no bar drawn"
        # As high as the axis says: the highest bar is the largest count, the axis goes to 1.1 times it.
        tallest = max([*blue.values(), *grey.values()])
        assert abs(tallest - PLOT_HEIGHT / 1.1) <= 3, (where, tallest)
        assert max(last - first + 1 for first, last in runs(list(blue))) >= R.MIN_BAR, where
        # The median interval (from the report's statistics) lies under a bar, read off the axis.
        a, b = value_to_x(figure)
        median_x = a + b * p["interval_ms"]["p50"]
        near = [x for x in blue if abs(x - median_x) <= max(R.HIST_BAR_PX, 2)]
        assert near, (where, median_x, runs(list(blue)))
        assert max(blue[x] for x in near) >= min(PLOT_HEIGHT / 1.1 * 0.25, 20), where
        # An interval far beyond the rest (a watchdog gap): a grey bar right of the blue ones, not
        # an axis stretched to it.
        if p["interval_ms"]["max"] > 4 * max(p["interval_ms"]["p95"], p["interval_ms"]["p50"]):
            assert grey and min(grey) > max(blue), where
        checked += 1
    assert checked >= 9


def test_the_state_timeline_has_a_legend_and_every_axis_a_unit(reports, tmp_path):
    figures = []
    for report in reports[:2]:
        page = R.render([report])
        for m in FIGURE.finditer(page):
            # Axis labels: the middle-anchored texts that are not tick values (nor the overflow slot's "≥500", "max 3100").
            labels = [t for t in map(html.unescape, AXIS_LABEL.findall(m.group(0)))
                      if not re.fullmatch(r"-?[\d.]+(e[-+]?\d+)?|≥\d+|max \d+", t)]
            if m.group(1) == "state-timeline":
                figures.append(m.group(0))
                assert labels == ["time since capture start (s)"]     # the rows are named beside them
            elif labels:                                                # not a "no data" placeholder
                assert len(labels) == 2 and all(re.search(r"\((ms|s|count)[,)]", t) for t in labels), \
                    (m.group(1), labels)
    pixels, tops = screenshot(figures, tmp_path)
    for figure, top in zip(figures, tops):
        height = int(SVG_HEIGHT.search(figure).group(1))
        assert height > R.H + 4 * R.KEY_ROW                   # room for a row per field
        used = {rgb(c) for c in re.findall(r'class="segment"[^>]*fill="(#[0-9a-f]{6})"', figure)}
        plot = {pixels[y][x] for y in range(top + R.MT, top + R.H - R.MB) for x in range(R.ML, R.W - R.MR)}
        legend = {pixels[y][x] for y in range(top + R.H, top + height) for x in range(R.ML, R.W)}
        assert used and used <= plot, "segments drawn"
        assert used <= legend, f"colours without a legend swatch: {used - legend}"
        names = [html.unescape(n) for n in re.findall(r'class="swatch"[^>]*/><text [^>]*>([^<]*)</text>', figure)]
        assert "ES-Link relays open" in names and "Armed" in names
