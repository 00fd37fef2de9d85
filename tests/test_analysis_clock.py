"""Captures whose clock steps back (two captures appended with `mergecap -a`, a clock set back
mid-way): the rules run on the analysis clock (docs/rules.md), but what the report names is each
frame's own time, as Wireshark shows it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from scapy.all import rdpcap, wrpcap, wrpcapng

import report_schema
import tshark_runner as T
from test_analysis_craft import BU, BU_ORIGIN, CTRL, Traffic, payload, vrpi
from vm110 import constants as C
from vm110.analysis import analyze, summary
from vm110.analysis import report_html
from vm110.layers import VRPO
from vm110.timefmt import utc_iso

CAPTURES = Path(__file__).resolve().parent.parent / "captures"


@pytest.fixture(scope="module")
def appended(tmp_path_factory) -> tuple[Path, list[float]]:
    """loss.pcapng (gaps, duplicates, late packets) with retransmit.pcap (retransmissions, a failed
    command) after it: the second one's timestamps begin 30 s before the first one's end. Returns
    the file and every frame's own time (scapy's reading, frame 1 first)."""
    packets = [*rdpcap(str(CAPTURES / "loss.pcapng")), *rdpcap(str(CAPTURES / "retransmit.pcap"))]
    path = tmp_path_factory.mktemp("clock") / "appended.pcap"
    wrpcap(str(path), packets)
    return path, [float(p.time) for p in packets]


# Items that name a moment other than their frame's: a watchdog violation names the start of the
# silence, its frame the packet after it.
OTHER_MOMENT = frozenset({"watchdog"})


@pytest.mark.parametrize("engine", ["fast", "tshark"])
def test_items_name_each_frames_own_time(appended, engine):
    """Every located item of the findings, and every time of the senders' and commands' lists,
    is the time of its frame as the capture stores it (a trial: after the seam they showed the
    first capture's last time, +29.9 s, for frames Wireshark shows at +0.1 s ... +20 s)."""
    path, own = appended
    report = analyze(str(path), engine=engine)
    named = [(f["rule"], i["frame"], i["time"]) for f in report["verdict"]["findings"] if f["rule"] not in OTHER_MOMENT
             for i in f["items"] if "time" in i]
    for s in report["senders"]:
        named += [("gap", g["frame"], g["time"]) for g in s["serial"]["gaps"]]
        named += [("restart", r["frame"], r["time"]) for r in s["serial"]["restart_events"]]
    for kind, c in report["commands"].items():
        named += [(kind, e["frames"][0], e["time"]) for e in c["list"]]
        named += [(kind, e["frame"], e["time"]) for e in c["acks_without_command_list"] + c["duplicate_acks_list"]]
    seam = len(rdpcap(str(CAPTURES / "loss.pcapng")))
    assert sum(frame > seam for _, frame, _ in named) > 20          # the second capture has its findings
    wrong = [(rule, frame, time, own[frame - 1]) for rule, frame, time in named
             if time != pytest.approx(own[frame - 1], abs=1e-6)]
    assert wrong == []


def _first_late(folder: Path, name: str, write) -> tuple[Path, list[float]]:
    """normal.pcap with its first record stamped 100 s late (a clock set right after one packet):
    the last record lies 80 s before the first. Returns the file and every frame's own time."""
    packets = rdpcap(str(CAPTURES / "normal.pcap"))
    packets[0].time += 100
    write(str(folder / name), packets)
    return folder / name, [float(p.time) for p in packets]


@pytest.fixture(scope="module")
def first_late(tmp_path_factory) -> tuple[Path, list[float]]:
    return _first_late(tmp_path_factory.mktemp("clock"), "first-late.pcap", wrpcap)


@pytest.fixture(scope="module")
def first_late_ng(tmp_path_factory) -> tuple[Path, list[float]]:
    return _first_late(tmp_path_factory.mktemp("clock"), "first-late.pcapng", wrpcapng)


def test_the_monitor_names_each_frames_own_time(appended, tmp_path):
    """The monitor's findings too (it named the analysis clock's time for gaps, restarts and
    commands after the seam, as analyze did)."""
    path, own = appended
    lines = tmp_path / "lines.jsonl"
    done = subprocess.run([sys.executable, "-m", "vm110", "monitor", "--read", str(path), "--idle", "0",
                           "--no-dashboard", "--quiet", "--json-lines", str(lines)], capture_output=True, text=True)
    assert done.returncode in (0, 1), done.stderr
    found = [json.loads(line) for line in lines.read_text().splitlines()]
    named = [(f["rule"], f["item"]["frame"], f["item"]["time"]) for f in found
             if f.get("type") == "finding" and f["rule"] not in OTHER_MOMENT and "time" in f.get("item", {})]
    seam = len(rdpcap(str(CAPTURES / "loss.pcapng")))
    assert sum(frame > seam for _, frame, _ in named) > 5, named[-10:]
    wrong = [(rule, frame, time, own[frame - 1]) for rule, frame, time in named
             if time != pytest.approx(own[frame - 1], abs=1e-6)]
    assert wrong == []


@pytest.mark.parametrize("engine", ["fast", "tshark"])
@pytest.mark.parametrize("capture", ["first_late", "first_late_ng", "appended"])
def test_duration_is_the_span_of_the_records(capture, engine, request):
    """The capture's duration is the span from its earliest record to its latest, as capinfos
    gives it, never the last record minus the first (a trial printed -80.0 s); the summary and the
    HTML say that the records are not in time order and what they span."""
    path, own = request.getfixturevalue(capture)
    report = analyze(str(path), engine=engine)
    report_schema.check(report)
    cap = report["capture"]
    assert cap["duration_s"] == pytest.approx(max(own) - min(own), abs=1e-6)
    assert (cap["first_time"], cap["last_time"]) == pytest.approx((own[0], own[-1]))
    assert (cap["earliest_time"], cap["latest_time"]) == pytest.approx((min(own), max(own)))
    text = summary.render(report)
    assert f" EG-Link, {max(own) - min(own):.1f} s;" in text.splitlines()[0]
    if capture != "appended":
        assert f"not in time order, they span {utc_iso(min(own))} to {utc_iso(max(own))}" in text
        assert "not in time order, they span" in report_html.render([report])


def vrpo_set_back(path: Path) -> Path:
    """A VRPO stream every 100 ms whose clock is set back 10 s after 40 packets (at frame 41)."""
    tr = Traffic()
    for n in range(80):
        t = n * 0.1 - (10.0 if n >= 40 else 0.0)
        tr.add(t, payload(VRPO, n, packet_number=0, periodic_data=b"x" * 10), src=CTRL, sport=C.OUTPUT_PORT)
    tr.write(path)
    return path


def test_a_vrpo_step_back_is_time_backwards_and_nothing_else(tmp_path):
    """One step back of the time (rules.md, "the analysis clock": a negative interval, counted as
    time_backwards), not also an interval outside the recommended 50-200 ms (a trial counted the
    one cause twice) and no jitter: every interval the capture's own clock measures forward is
    exactly the period."""
    report = analyze(str(vrpo_set_back(tmp_path / "back.pcap")))
    [p] = report["periodic"]
    assert (p["type"], p["time_backwards"], p["outside_recommended"]["count"]) == ("VRPO", 1, 0)
    assert p["jitter_ms"] == {"final": 0.0, "mean": 0.0, "max": 0.0}
    rules = {f["rule"]: [i["frame"] for i in f["items"]] for f in report["verdict"]["findings"]}
    assert rules == {"time_backwards": [41]}


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_the_dissector_marks_a_vrpo_step_back_once(tshark, tmp_path):
    """Where analyze and the dissector count the same thing they agree: the step back is one
    finding, Time Backwards, in Wireshark too."""
    with tshark.workspace(tmp_path / "ws") as ws:
        path = vrpo_set_back(ws.dir / "back.pcap")
        done = ws.run(["-r", str(path), "-Y", "vm110.analysis.flags", "-T", "fields", "-e", "frame.number",
                       "-e", "vm110.analysis.flags"])
    assert [line.split("\t") for line in done.stdout.splitlines()] == [["41", "Time Backwards"]]


@pytest.mark.parametrize("engine", ["fast", "tshark"])
def test_two_taps_appended_are_said_to_be_out_of_time_order(tmp_path, engine):
    """The base unit's tap and the controller's appended one after the other (mergecap -a): each
    stream in time order, so no time_backwards, the first and last records the earliest and latest,
    and a VRCI acknowledged 20 ms after its first copy came out failed with a latency of 3.9 s, the
    analysis clock's (docs/rules.md), with nothing to say why (trial). The report now warns and
    counts the packets behind; the same traffic in time order gives no warning and 20 ms."""
    from vm110.layers import VRAO, VRCI
    bu, ctl = [], []
    serial = 0
    for i in range(40):
        bu.append((i * 0.125, vrpi(serial)))
        serial += 1
        if i == 8:
            bu.append((1.01, payload(VRCI, serial, BU_ORIGIN, command_id=5)))
            serial += 1
    for i in range(50):
        ctl.append((0.05 + i * 0.1, payload(VRPO, i, packet_number=0, periodic_data=b"x" * 10)))
    ctl.append((1.03, payload(VRAO, 50, command_id=5)))
    ctl.sort()
    behind = sum(t < bu[-1][0] for t, _ in ctl)
    reports = {}
    for name, order in (("appended", [(t, d, C.INPUT_PORT) for t, d in bu] + [(t, d, C.OUTPUT_PORT) for t, d in ctl]),
                        ("sorted", sorted([(t, d, C.INPUT_PORT) for t, d in bu] + [(t, d, C.OUTPUT_PORT) for t, d in ctl]))):
        traffic = Traffic()
        for t, data, port in order:
            traffic.add(t, data, src=CTRL if port == C.OUTPUT_PORT else BU, sport=port)
        traffic.write(tmp_path / f"{name}.pcap")
        reports[name] = report_schema.validating(analyze)(str(tmp_path / f"{name}.pcap"), engine=engine)
    appended, in_order = reports["appended"], reports["sorted"]
    assert appended["capture"]["time_backwards"] == 0 and behind == 50
    assert appended["capture"]["behind_clock"] == behind
    [warning] = [f for f in appended["verdict"]["findings"] if f["rule"] == "not_in_time_order"]
    assert warning["severity"] == "warning" and warning["count"] == behind and warning["items"] == []
    assert "frame.time_delta < 0" in warning["message"] and "reordercap" in warning["message"]
    assert appended["commands"]["VRCI"]["list"][0]["latency_first_ms"] == pytest.approx((bu[-1][0] - 1.01) * 1000)
    assert in_order["capture"]["behind_clock"] == 0
    assert "not_in_time_order" not in {f["rule"] for f in in_order["verdict"]["findings"]}
    assert in_order["commands"]["VRCI"]["list"][0]["latency_first_ms"] == pytest.approx(20.0)
