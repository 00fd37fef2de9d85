"""The HTML report renders in headless Chromium (Debian's package) with no console message, and
every plot is there with something drawn in it."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

from test_analysis_engine import build_mixed
from vm110.analysis import analyze, report_html

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run",
         "--disable-component-update", "--disable-sync", "--enable-logging=stderr", "--v=0"]
CONSOLE = re.compile(r":CONSOLE[:(]")
CAPTURES = Path(__file__).resolve().parent.parent / "captures"
PLOTS = {"interval-histogram": "bar", "interval-time": "series", "serial-gaps": "point",
         "ack-latency": "bar", "retransmissions": "bar", "state-timeline": "segment"}


def browser() -> str:
    """The headless browser that renders the reports: chromium, which scripts/setup-system.sh
    installs where apt has it. Ubuntu ships it only as a snap: the test is skipped there."""
    found = shutil.which("chromium")
    if found is None:
        pytest.skip("chromium is not installed (apt has none here: Ubuntu ships it only as a snap)")
    return found


def chromium(page, tmp_path) -> tuple[str, list[str]]:
    """(DOM after loading, console lines) of a page."""
    done = subprocess.run([browser(), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--dump-dom",
                           page.as_uri()], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout, [line for line in done.stderr.splitlines() if CONSOLE.search(line)]


class Figures(HTMLParser):
    """figure[data-plot] -> classes of the shapes drawn inside its <svg>."""

    def __init__(self) -> None:
        super().__init__()
        self.plots: dict[str, list[str]] = {}
        self.current = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "figure" and "data-plot" in a:
            self.current = a["data-plot"]
            self.plots.setdefault(self.current, [])
        elif self.current and a.get("class"):
            self.plots[self.current].append(a["class"])

    def handle_endtag(self, tag):
        if tag == "figure":
            self.current = None


def test_console_errors_are_seen(tmp_path):
    page = tmp_path / "bad.html"
    page.write_text("<html><body><script>console.error('boom'); missing();</script></body></html>")
    _, console = chromium(page, tmp_path)
    assert len(console) == 2


@pytest.mark.slow
def test_report_renders_with_every_plot(tmp_path):
    build_mixed(tmp_path / "mixed.pcap")
    report = analyze(str(tmp_path / "mixed.pcap"))
    page = tmp_path / "report.html"
    report_html.write(str(page), [report])
    dom, console = chromium(page, tmp_path)
    assert console == []
    figures = Figures()
    figures.feed(dom)
    for name, shape in PLOTS.items():
        assert name in figures.plots, name
        assert shape in figures.plots[name], (name, figures.plots[name])
    assert "FAIL" in dom and "ES-Link relays open" in dom
    periodic = len(report["periodic"])
    assert sum(1 for cls in figures.plots["interval-histogram"] if cls == "marker") >= 2
    assert dom.count('data-plot="interval-time"') == periodic


def test_the_report_fits_a_phone_s_width(tmp_path):
    """Report trial: the report mailed to an engineer is read on a phone too; its plots (900 px)
    and wide tables made the page twice a phone's width, its text tiny once fitted. On a narrow
    screen it now lays out within it (plots scaled, tables scrolled on their own) and says so to a
    phone's browser (the viewport meta). The page's width is measured in the page itself."""
    build_mixed(tmp_path / "mixed.pcap")
    page = tmp_path / "report.html"
    report_html.write(str(page), [analyze(str(tmp_path / "mixed.pcap"))])
    text = page.read_text()
    assert '<meta name="viewport" content="width=device-width, initial-scale=1">' in text
    measured = tmp_path / "measured.html"
    measured.write_text(text.replace("</body>", "<script>document.title = 'width ' + document.documentElement"
                                     ".scrollWidth + ' of ' + window.innerWidth</script></body>"))
    done = subprocess.run([browser(), *FLAGS, "--window-size=390,844", f"--user-data-dir={tmp_path / 'profile'}",
                           "--dump-dom", measured.as_uri()], capture_output=True, text=True, timeout=120)
    # (a desktop Chromium keeps its window at least about 500 px wide: the window's width is the screen's)
    width, screen = map(int, re.search(r"<title>width (\d+) of (\d+)</title>", done.stdout).groups())
    assert screen < 600 and width <= screen, (width, screen)


class Tables(HTMLParser):
    """The page's tables as rows of cell texts (header row included)."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self.cell = []

    def handle_data(self, data):
        if self.cell is not None:
            self.cell.append(data)

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self.cell is not None:
            self.tables[-1][-1].append("".join(self.cell))
            self.cell = None


def test_the_commands_table_names_ms_for_ack_latency():
    """retransmit.pcap's VRCI are acknowledged up to 1599.991 ms after their first transmission
    (its truth file): the column that shows 1599.99 says it is in ms."""
    truth = json.loads((CAPTURES / "retransmit.pcap.truth.json").read_text())
    latencies = [c["latency_first_ms"] for c in truth["commands"]["VRCI"]["list"] if c["latency_first_ms"] is not None]
    tables = Tables()
    tables.feed(report_html.render([analyze(str(CAPTURES / "retransmit.pcap"))]))
    header, *rows = next(t for t in tables.tables if t[0][:2] == ["type", "commands"])
    assert header[-3:] == ["latency p50 (ms)", "latency p95 (ms)", "latency max (ms)"]
    vrci = dict(zip(header, next(r for r in rows if r[0] == "VRCI")))
    assert vrci["latency max (ms)"] == f"{max(latencies):.2f}" == "1599.99"


def test_a_vrpo_stream_without_a_nominal_period_still_renders(tmp_path):
    """VRPO packets all within one burst (5 ms apart): intervals, but no burst interval to take a
    nominal period from. The histogram formatted `nominal None` and the report had no HTML (the
    self-fuzzer's find)."""
    from test_analysis_craft import CTRL, VRPO, Traffic, payload, vrpi
    tr = Traffic()
    for k in range(8):
        tr.add(k * 0.125, vrpi(k))
        data = b"d" * (488 if k < 7 else 8)      # one split burst: parts 0..7, the last short
        tr.add(0.3 + k * 0.005, payload(VRPO, k, packet_number=k, periodic_data=data), src=CTRL, sport=5827)
    tr.frames.sort(key=lambda f: f[0])
    tr.write(tmp_path / "one-burst.pcap")
    report = analyze(str(tmp_path / "one-burst.pcap"))
    [vrpo] = [p for p in report["periodic"] if p["type"] == "VRPO"]
    assert vrpo.get("nominal_ms") is None and len(vrpo["plot"]["histogram"]) >= 2
    page = report_html.render([report])
    assert "watchdog 2000 ms" in page and "nominal None" not in page


def test_a_watchdog_row_says_its_frame_ends_the_silence(tmp_path):
    """The findings table put a watchdog item's frame (the packet after the silence) beside the time
    the silence began, `10 | +1.000000`, and frame 10 is at +3.5 s (trial: the terminal summary said
    "ends a silence from", the HTML did not)."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for k, t in enumerate([i * 0.125 for i in range(9)] + [3.5 + i * 0.125 for i in range(8)]):
        tr.add(t, vrpi(k))
    tr.write(tmp_path / "silence.pcap")
    tables = Tables()
    tables.feed(report_html.render([analyze(str(tmp_path / "silence.pcap"))]))
    header, *rows = next(t for t in tables.tables if t[0][:3] == ["finding", "frames", "time (s)"])
    [row] = [dict(zip(header, r)) for r in rows if r[0] == "watchdog"]
    assert (row["frames"], row["time (s)"]) == ("10", "silence from +1.000000")


def test_the_findings_table_reads_an_item_as_words_as_the_summary_does():
    """restart.pcapng's relays-open episodes and illegal.pcap's packets: the HTML's findings table
    showed Python's `states ['External link error']`, `reasons ['bad_crc']` and unrounded seconds
    (`duration_s 0.249991`) where the summary says `states External link error` and `0.250`, and it
    left out what the summary's items have in a different order. Both read every item alike."""
    for name, rule in (("restart.pcapng", "relays_open"), ("illegal.pcap", "illegal")):
        report = analyze(str(CAPTURES / name))
        tables = Tables()
        tables.feed(report_html.render([report]))
        header, *rows = next(t for t in tables.tables if t[0][:3] == ["finding", "frames", "time (s)"])
        shown = [dict(zip(header, r)) for r in rows if r[0] == rule]
        [finding] = [f for f in report["verdict"]["findings"] if f["rule"] == rule]
        assert len(shown) == len(finding["items"]) > 0
        for row, item in zip(shown, finding["items"]):
            if rule == "relays_open":
                assert row["what"] == f"duration_s {item['duration_s']:.3f}, states {'/'.join(item['states'])}"
            else:
                assert row["what"] == f"type {item['type']}, reasons {'/'.join(item['reasons'])}"
