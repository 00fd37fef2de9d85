"""`vm110 analyze`: summary, JSON and HTML files, several captures, --jobs, --fail-on, exit codes."""
from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import pytest

from test_analysis_craft import Traffic, vrpi
from vm110.errors import EXIT_FINDINGS, EXIT_OK, EXIT_USAGE

REPO = Path(__file__).resolve().parents[1]


def vm110(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", "analyze", *args], capture_output=True, text=True,
                          env=env)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    base = tmp_path_factory.mktemp("cli")
    clean, lossy = Traffic(), Traffic()
    for i in range(16):
        clean.add(i * 0.125, vrpi(i))
        if i != 7:
            lossy.add(i * 0.125, vrpi(i))
    clean.write(base / "clean.pcap")
    lossy.write(base / "lossy.pcapng", "pcapng")
    (base / "text.pcap").write_text("this is not a capture\n")
    Traffic().write(base / "empty.pcap")
    return base


def one_line_error(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == EXIT_USAGE
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_clean_capture_summary_and_exit_zero(files):
    result = vm110(str(files / "clean.pcap"), "--fail-on", "lost>0,watchdog>0,unacked>0,illegal>0")
    assert result.returncode == EXIT_OK, result.stderr
    assert "VERDICT: OK" in result.stdout and "VRPI 16" in result.stdout
    assert result.stderr == ""                     # no progress bar when stderr is not a terminal


def test_fail_on_violation_exits_one(files):
    result = vm110(str(files / "lossy.pcapng"), "--fail-on", "lost>0")
    assert result.returncode == EXIT_FINDINGS
    assert "VERDICT: FAIL" in result.stdout and "lost=1 (rule lost>0)" in result.stderr
    assert vm110(str(files / "lossy.pcapng"), "--fail-on", "lost>1,watchdog").returncode == EXIT_OK


def test_a_violation_gives_its_numbers_in_full(tmp_path):
    """VRPI silent for 1000 s: `interval_max_ms=1.00012e+06 (rule interval_max_ms>1e+06)` read as a
    rule broken by a rounded value and a threshold the user did not give (999999.5)."""
    tr = Traffic()
    for i, t in enumerate((0.0, 0.125, 1000.25)):
        tr.add(t, vrpi(i))
    tr.write(tmp_path / "silent.pcap")
    result = vm110(str(tmp_path / "silent.pcap"), "--quiet", "--fail-on", "interval_max_ms>999999.5,packets>=3")
    assert result.returncode == EXIT_FINDINGS
    assert result.stderr.splitlines() == [
        f"fail-on: {tmp_path / 'silent.pcap'}: interval_max_ms=1000125 (rule interval_max_ms>999999.5)",
        f"fail-on: {tmp_path / 'silent.pcap'}: packets=3 (rule packets>=3)"]


def test_notes_are_counted_and_fail_only_a_rule_that_names_them():
    """captures/glink.pcapng (README of captures/: a G-Link fallback, VRPO every 400 ms, duplicate
    VRAI) has nothing lost, duplicated, illegal or late: only duplicate acknowledgements and VRPO
    intervals outside the recommended range, which Wireshark's experts call notes (as TCP's duplicate
    ACKs). Analyze said "VERDICT: OK (0 errors, 2 warnings)": a capture of notes warned."""
    capture = str(REPO / "captures" / "glink.pcapng")
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    result = vm110(capture)
    assert result.returncode == EXIT_OK, result.stderr
    assert "VERDICT: OK (0 errors, 0 warnings, 2 notes)" in result.stdout
    assert f"  note    {sum(c['duplicate_acks'] for c in truth['commands'].values())} duplicate acknowledgements" \
        in result.stdout
    assert vm110(capture, "--quiet", "--fail-on", "duplicate_acks").returncode == EXIT_FINDINGS
    html = vm110(capture, "--quiet", "--html", "-").stdout
    assert "OK</span> (0 errors, 0 warnings, 2 notes)" in html and '<li class="note">note: ' in html


@pytest.mark.parametrize("args", [
    ["--fail-on", "lost>>0"], ["--fail-on", "nonsense>1"], ["--fail-on", ""], ["--fail-on", "lost>\uff11"], ["--jobs", "0"], ["--port", "70000"],
])
def test_bad_arguments(files, args):
    one_line_error(vm110(str(files / "clean.pcap"), *args))


def test_a_report_file_that_cannot_be_written_is_said_before_the_analysis(files, tmp_path):
    result = vm110(str(files / "clean.pcap"), "--json", str(tmp_path / "no" / "such" / "r.json"))
    one_line_error(result)
    assert "no folder" in result.stderr and "VERDICT" not in result.stdout     # (nothing analysed first)


def test_fail_on_name_in_capitals_is_named_as_unknown(files):
    result = vm110(str(files / "clean.pcap"), "--fail-on", "LOST>0")
    one_line_error(result)
    assert "unknown --fail-on name 'LOST'" in result.stderr and "'lost'" in result.stderr


def test_report_on_standard_output_stands_alone(files):
    """--json - (or --html -): standard output is the report alone, to pipe into a parser; the
    summary goes to standard error. Both on standard output would be neither."""
    result = vm110(str(files / "lossy.pcapng"), "--json", "-")
    assert result.returncode == EXIT_OK, result.stderr
    assert json.loads(result.stdout)["totals"]["lost"] == 1
    assert "VERDICT: FAIL" in result.stderr
    html = vm110(str(files / "lossy.pcapng"), "--html", "-")
    assert html.stdout.lstrip().lower().startswith("<!doctype html") and "VERDICT: FAIL" in html.stderr
    quiet = vm110(str(files / "lossy.pcapng"), "--json", "-", "--quiet")
    assert json.loads(quiet.stdout) and quiet.stderr == ""
    one_line_error(vm110(str(files / "lossy.pcapng"), "--json", "-", "--html", "-"))


def test_unreadable_inputs(files):
    one_line_error(vm110(str(files / "text.pcap")))
    one_line_error(vm110(str(files / "missing.pcap")))


def test_gzip_compressed_captures(files, tmp_path):
    """A `.pcapng.gz` (tcpdump -z gzip, dumpcap --compress gzip), which Wireshark opens as it is:
    analyze said "not a pcap or pcapng capture (magic 0x1f8b0800)", exit 2 (trial). It gives the
    plain file's report; one cut short is analysed up to the cut, said, and exits 2."""
    data = (files / "lossy.pcapng").read_bytes()
    packed = tmp_path / "lossy.pcapng.gz"
    packed.write_bytes(gzip.compress(data))
    plain = vm110(str(files / "lossy.pcapng"), "--json", str(tmp_path / "p.json"), "--quiet")
    unpacked = vm110(str(packed), "--json", str(tmp_path / "g.json"), "--quiet")
    assert plain.returncode == unpacked.returncode == EXIT_OK and unpacked.stderr == ""
    want, got = (json.loads((tmp_path / n).read_text()) for n in ("p.json", "g.json"))
    assert got["capture"].pop("file") == str(packed)
    del want["capture"]["file"]
    assert got == want
    packed.write_bytes(gzip.compress(data)[:-40])
    cut = vm110(str(packed), "--json", str(tmp_path / "c.json"))
    one_line_error(subprocess.CompletedProcess(cut.args, cut.returncode, "", cut.stderr))
    assert "gzip data cut short" in cut.stderr and "VERDICT: FAIL" in cut.stdout
    report = json.loads((tmp_path / "c.json").read_text())
    assert report["verdict"]["findings"][0]["rule"] == "damaged"
    assert 0 < report["capture"]["packets"] < want["capture"]["packets"]


def test_tshark_engine_without_its_dissector(files, tmp_path):
    import os
    env = {**os.environ, "VM110_DISSECTOR": str(tmp_path / "nope.lua")}
    one_line_error(vm110(str(files / "clean.pcap"), "--engine", "tshark", env=env))


def test_empty_capture(files, tmp_path):
    result = vm110(str(files / "empty.pcap"), "--json", str(tmp_path / "e.json"))
    assert result.returncode == EXIT_OK
    report = json.loads((tmp_path / "e.json").read_text())
    assert report["capture"]["packets"] == 0 and report["verdict"]["findings"][0]["rule"] == "no_eglink"
    # no EG-Link at all is no clean verdict (a link dead from the start), and a rule can fail on it
    assert "VERDICT: FAIL" in result.stdout
    assert vm110(str(files / "empty.pcap"), "--fail-on", "eglink_packets<1").returncode == EXIT_FINDINGS


def test_json_and_html_of_several_captures_in_parallel(files, tmp_path):
    caps = [str(files / "clean.pcap"), str(files / "lossy.pcapng")]
    serial = vm110(*caps, "--json", str(tmp_path / "a.json"), "--html", str(tmp_path / "a.html"))
    parallel = vm110(*caps, "--json", str(tmp_path / "b.json"), "--jobs", "2")
    assert serial.returncode == parallel.returncode == EXIT_OK
    assert "Combined: 2 captures, FAIL" in serial.stdout
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    assert a["schema_version"] == 6 and a["errors"] == [] and [r["capture"]["file"] for r in a["reports"]] == caps
    assert a["combined"]["totals"]["lost"] == 1 and a["combined"]["ok"] is False
    assert a == b
    page = (tmp_path / "a.html").read_text()
    assert page.count('data-plot="interval-histogram"') == 2 and "http" not in page.replace(
        "http://www.w3.org/2000/svg", "")


def test_progress_bar_only_on_a_terminal(files):
    import os
    import pty
    main, sub = pty.openpty()
    done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(files / "clean.pcap"), "--quiet"],
                          stdout=subprocess.PIPE, stderr=sub, timeout=120)
    os.close(sub)
    shown = os.read(main, 65536).decode(errors="replace")
    os.close(main)
    assert done.returncode == EXIT_OK
    assert "100%" in shown and "clean.pcap" in shown


def test_thresholds_are_options(files, tmp_path):
    out = tmp_path / "t.json"
    assert vm110(str(files / "lossy.pcapng"), "--vrpi-watchdog", "200", "--json", str(out), "--quiet").returncode == 0
    p = json.loads(out.read_text())["periodic"][0]
    assert p["watchdog"]["limit_ms"] == 200 and [round(v["gap_ms"]) for v in p["watchdog"]["violations"]] == [250]


_KILLER = """
import os, signal, sys
import vm110.commands.analyze as analyze
real = analyze._one

def one(job):                          # the worker given poison.pcap dies as the OOM killer ends it
    if job[0].endswith("poison.pcap"):
        os.kill(os.getpid(), signal.SIGKILL)
    return real(job)

analyze._one = one
from vm110.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_worker_that_dies_costs_its_capture_only(tmp_path):
    """`--jobs`: a worker process killed while it analysed a capture (the out-of-memory killer)
    left the process pool waiting for its result for ever: the command hung, with no line. That
    capture is an error entry that says why, every other capture is reported, exit 2."""
    names = ["normal.pcap", "poison.pcap", "loss.pcapng", "vrco.pcap"]
    for name in names:
        source = REPO / "captures" / ("restart.pcapng" if name == "poison.pcap" else name)
        (tmp_path / name).write_bytes(source.read_bytes())
    command = [sys.executable, "-c", _KILLER, "analyze", *(str(tmp_path / n) for n in names), "--jobs", "2",
               "--quiet", "--json", str(tmp_path / "r.json")]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)    # (a few s when well)
    except subprocess.TimeoutExpired:
        pytest.fail("vm110 analyze --jobs 2 hung after a worker died")
    said = (f"{tmp_path / 'poison.pcap'}: the process analysing it ended before it was done: killed (SIGKILL: "
            "what the kernel's out-of-memory killer sends)")
    assert done.returncode == EXIT_USAGE and done.stderr.splitlines() == [f"vm110 analyze: {said}"]
    report = json.loads((tmp_path / "r.json").read_text())
    assert [Path(r["capture"]["file"]).name for r in report["reports"]] == [n for n in names if n != "poison.pcap"]
    assert report["errors"] == [{"file": str(tmp_path / "poison.pcap"), "error": said}]
