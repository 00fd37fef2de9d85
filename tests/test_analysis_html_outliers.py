"""The interval histogram of a stream whose clock stepped back: the negative interval stands in a
grey bar of its own left of the axis (as the far longer ones do right of it), the axis is scaled
to the real intervals, and no two labels of a histogram overlap as headless Chromium lays them
out. The captures are crafted with known intervals; the expectations come from those."""
from __future__ import annotations

import html
import json
import re
import subprocess
from pathlib import Path

import pytest
import tshark_runner as T
from test_analysis_html import FLAGS, browser
from vm110.analysis import analyze
from vm110.analysis import report_html as R
from vm110.layers import VM110, VRPI

FIGURE = re.compile(r'<figure data-plot="interval-histogram">.*?</figure>', re.DOTALL)
TICK = re.compile(r'<text x="([\d.]+)" y="(\d+)" text-anchor="middle">(-?[\d.]+)</text>')
RECT = re.compile(r'<rect class="([^"]+)" x="([\d.]+)" y="[\d.]+" width="([\d.]+)"[^>]*>(?:<title>([^<]*)</title>)?')
PERIOD_US = 125_000
STEP_BACK_US = 20_000_000
JITTER_US = 5_000
# 40 VRPI 125 ms apart (each 5 ms late or not: intervals of 120 and 130 ms), the clock steps back
# 20 s, 40 more: one interval of -19875 ms (or 5 ms either side of it).
STEPPED_BACK = [PERIOD_US * i + JITTER_US * (i % 2) for i in range(40)] + \
    [PERIOD_US * (40 + i) + JITTER_US * (i % 2) - STEP_BACK_US for i in range(40)]
# Intervals spread from 100 ms to 3 s: the nominal (125 ms) and watchdog (500 ms) lines close on the axis.
SPREAD = [sum(100_000 + 2_900_000 * k // 39 for k in range(i)) for i in range(41)]
# A script that writes each histogram's text boxes (as drawn) into the page for --dump-dom.
MEASURE = """<script>
document.getElementById("boxes").textContent = JSON.stringify([...document.querySelectorAll("figure")].map(
  f => [...f.querySelectorAll("svg text")].filter(t => t.textContent).map(t => {
    const r = t.getBoundingClientRect(); return [t.textContent, r.left, r.top, r.right, r.bottom]; })));
</script>"""


def vrpi_capture(path: Path, times: list[int]) -> Path:
    T.write_pcap(path, [bytes(VM110(origin=0x0101, serial=i) / VRPI(bu_state=0x11, armed_ru=0x0C07, ru_state=3))
                        for i in range(len(times))], times)
    return path


def histogram(tmp_path: Path, name: str, times: list[int]) -> tuple[dict, str]:
    report = analyze(str(vrpi_capture(tmp_path / name, times)))
    (stream,) = report["periodic"]
    (figure,) = FIGURE.findall(R.render([report]))
    return stream, figure


def x_of(figure: str) -> tuple[float, float, list[float]]:
    """(a, b) with x = a + b * value, from the x axis' numeric tick labels, and the tick values."""
    ticks = [(float(x), float(v)) for x, y, v in TICK.findall(figure) if int(y) == R.H - R.MB + 14]
    assert len(ticks) >= 2, ticks
    (xa, va), (xb, vb) = ticks[0], ticks[-1]
    scale = (xb - xa) / (vb - va)
    return xa - scale * va, scale, [v for _, v in ticks]


def text_boxes(figures: list[str], tmp_path: Path) -> list[list[tuple[str, float, float, float, float]]]:
    """Per figure, the boxes (text, left, top, right, bottom) of its non-empty labels in Chromium."""
    page = tmp_path / "boxes.html"
    page.write_text(f"<!DOCTYPE html><html><head><meta charset='utf-8'><style>{R.CSS}</style></head><body>"
                    + "".join(figures) + f'<pre id="boxes"></pre>{MEASURE}</body></html>')
    done = subprocess.run([browser(), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--dump-dom",
                           page.as_uri()], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    found = re.search(r'<pre id="boxes">(.*?)</pre>', done.stdout, re.DOTALL)
    assert found and found.group(1), done.stdout[-2000:]
    return json.loads(html.unescape(found.group(1)))


def overlapping(boxes: list) -> list[tuple[str, str]]:
    return [(a[0], b[0]) for i, a in enumerate(boxes) for b in boxes[i + 1:]
            if a[1] < b[3] and b[1] < a[3] and a[2] < b[4] and b[2] < a[4]]


def test_a_step_back_stands_apart_left_of_an_axis_scaled_to_the_real_intervals(tmp_path):
    stream, figure = histogram(tmp_path, "stepped-back.pcap", STEPPED_BACK)
    back_ms = (PERIOD_US - JITTER_US - STEP_BACK_US) / 1000      # -19880 ms
    assert stream["time_backwards"] == 1 and stream["interval_ms"]["min"] == pytest.approx(back_ms)
    a, b, ticks = x_of(figure)
    # The axis covers the 120 and 130 ms intervals (and the 500 ms watchdog at most), not -20000 ms.
    assert min(ticks) >= 0 and max(ticks) <= 600, ticks
    rects = [(cls, float(x), float(w), html.unescape(title or "")) for cls, x, w, title in RECT.findall(figure)]
    blue = [(x, w) for cls, x, w, _ in rects if cls == "bar"]
    grey = [(x, w, title) for cls, x, w, title in rects if cls == "bar underflow"]
    low, high = a + b * 118, a + b * 132          # (the real intervals, and a bin's width around them)
    assert blue and all(low - 2 <= x and x + w <= high + 2 for x, w in blue), (a, b, blue)
    # One grey bar left of the blue ones, named on hover and in a key below the plot.
    (gx, gw, title), = grey
    assert gx + gw <= min(x for x, _ in blue) and gx < a + b * min(ticks)
    name = f"1 interval < 0 (clock stepped back), min {back_ms:.0f} ms"
    assert title.startswith("1 interval < 0 (clock stepped back)") and name in html.unescape(figure)


def test_no_two_labels_of_a_histogram_overlap(tmp_path):
    """The step back (its lines were 15 px apart on a -20000 ms axis) and lines close together on
    an axis to 3 s: every label (ticks, lines, slots, axis names, key) stands clear of the others."""
    figures = [histogram(tmp_path, name, times)[1]
               for name, times in (("stepped-back.pcap", STEPPED_BACK), ("spread.pcap", SPREAD))]
    assert "nominal 125 ms" in figures[1] and "watchdog 500 ms" in figures[1]
    for boxes in text_boxes(figures, tmp_path):
        texts = [t for t, *_ in boxes]
        assert any(t.startswith("nominal") for t in texts) and any("watchdog" in t for t in texts), texts
        assert overlapping(boxes) == [], boxes
