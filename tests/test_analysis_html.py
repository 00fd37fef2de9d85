"""The HTML report renders in headless Chromium (Debian's package) with no console message, and
every plot is there with something drawn in it."""
from __future__ import annotations

import re
import subprocess
from html.parser import HTMLParser

import pytest

from test_analysis_engine import build_mixed
from vm110.analysis import analyze, report_html

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run",
         "--disable-component-update", "--disable-sync", "--enable-logging=stderr", "--v=0"]
CONSOLE = re.compile(r":CONSOLE[:(]")
PLOTS = {"interval-histogram": "bar", "interval-time": "series", "serial-gaps": "point",
         "ack-latency": "bar", "retransmissions": "bar", "state-timeline": "segment"}


def chromium(page, tmp_path) -> tuple[str, list[str]]:
    """(DOM after loading, console lines) of a page."""
    done = subprocess.run(["chromium", *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--dump-dom",
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
