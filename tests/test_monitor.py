"""`vm110 monitor` on files and pipes: the same report as `analyze`, findings and evidence as
they come, and bad input (one line, exit 2, the report of what was seen)."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from reference.generator import stepped_scenarios, write_scenario

from vm110 import constants as C

from vm110.analysis.periodic import Floats, SpilledFloats
from vm110.capture.reader import CaptureReader
from vm110.cli import main
from vm110.synth import synthesize

ROOT = Path(__file__).resolve().parent.parent
CAPTURES = sorted(p for p in (ROOT / "captures").iterdir() if p.suffix in (".pcap", ".pcapng"))
VM110 = [sys.executable, "-m", "vm110"]


def _reports(capture: str, tmp_path: Path, *extra: str) -> tuple[bytes, bytes]:
    a, m = tmp_path / "analyze.json", tmp_path / "monitor.json"
    assert main(["analyze", capture, "--quiet", "--json", str(a), *extra]) in (0, 1)
    assert main(["monitor", "--read", capture, "--idle", "0", "--quiet", "--no-dashboard", "--json", str(m),
                 *extra]) in (0, 1)
    return a.read_bytes(), m.read_bytes()


@pytest.mark.parametrize("capture", CAPTURES, ids=lambda p: p.name)
def test_monitor_ends_with_the_report_of_analyze(capture, tmp_path, capsys):
    a, m = _reports(str(capture), tmp_path)
    assert a == m


@pytest.mark.parametrize("scenario,fmt,extra", [("day", "pcap", ()), ("restart", "pcapng", ("--serial-scope", "type")),
                                                ("overlap", "pcap", ("--crc", "mpeg2", "--vrpi-watchdog", "200"))])
def test_monitor_matches_analyze_on_generated_captures(scenario, fmt, extra, tmp_path, capsys):
    capture = tmp_path / f"{scenario}.{fmt}"
    synthesize(scenario, str(capture), seed=7, duration_s=40.0, fmt=fmt)
    a, m = _reports(str(capture), tmp_path, *extra)
    assert a == m


def _appended_shorter_capture(path: Path) -> None:
    """A 9.9 s capture with a VRCI sent 3 times from 7.01 s and never acknowledged, then a 2.9 s
    capture appended (mergecap -a) whose senders start their serials afresh (trial)."""
    from test_analysis_craft import CTRL, Traffic, payload, vrpi
    from vm110.layers import VRCI, VRPO
    tr = Traffic()
    for start, length, serial in ((0.0, 9.9, 100), (0.0, 2.9, 5000)):
        events = [(i * 0.125, "VRPI") for i in range(int(length / 0.125) + 1)]
        events += [(i * 0.1 + 0.003, "VRPO") for i in range(int(length / 0.1))]
        if length > 9:
            events += [(7.01 + 0.1 * k, "VRCI") for k in range(3)]
        bu, ctrl = serial, serial
        for t, kind in sorted(events):
            if kind == "VRPO":
                tr.add(start + t, payload(VRPO, ctrl), src=CTRL, sport=C.OUTPUT_PORT)
                ctrl += 1
            else:
                tr.add(start + t, vrpi(bu) if kind == "VRPI" else payload(VRCI, bu, 0x0101, command_id=5))
                bu += 1
    tr.write(path)


def test_appended_shorter_capture_judges_commands_on_the_clock_and_silence_on_records(tmp_path):
    """Trial: after `mergecap -a` of a shorter capture, analyze said the unacknowledged VRCI had not
    failed (its last record is earlier than the command), and the monitor reported both streams silent
    to the end (it measured to the latest time, not the last record). rules.md: a command fails once
    the capture went on past its limit on the analysis clock; silence to the end is measured to the
    last record. The independent reference agrees."""
    from reference.analyser import analyse
    capture = tmp_path / "ab.pcap"
    _appended_shorter_capture(capture)
    a, m = _reports(str(capture), tmp_path)
    assert a == m
    report, ref = json.loads(a), analyse(str(capture))
    assert report["commands"]["VRCI"]["failed"] == ref["commands"]["VRCI"]["failed"] == 1
    assert report["commands"]["VRCI"]["unacked"] == 1
    assert not [v for p in report["periodic"] for v in p["watchdog"]["violations"]]
    assert report["capture"]["last_time"] == pytest.approx(1_700_000_002.903)


@given(stepped_scenarios())
@settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck), print_blob=True)
def test_monitor_matches_analyze_when_the_clock_steps_back(sc):
    """A capture whose time steps back, or captures appended (also a shorter one after a longer):
    the monitor's report is analyze's."""
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "gen.pcapng" if sc["format"] == "pcapng" else "gen.pcap")
        write_scenario(path, sc)
        a, m = _reports(path, Path(d), "--crc", "mpeg2", "--crc-order", "little")
    assert a == m


def test_the_dashboard_gives_each_latest_finding_its_filter(tmp_path):
    from vm110.monitor import dashboard
    lines = tmp_path / "live.jsonl"
    assert main(["monitor", "--read", str(ROOT / "captures" / "loss.pcapng"), "--idle", "0", "--no-dashboard",
                 "--quiet", "--json-lines", str(lines)]) == 0
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    findings = [o for o in objects if o["type"] == "finding"]
    header = {"source": "loss.pcapng", "now": findings[-1]["at"], "status": "done", "packets": 612, "rate": 0.0,
              "eglink": 612, "illegal": 0, "alarms": []}
    shown = dashboard.render(header, [o for o in objects if o["type"] == "snapshot"][-1], findings, 200, 40)
    last = [line for line in shown if line.endswith(f"[{findings[-1]['item']['filter']}]")]
    assert last and f"#{findings[-1]['frame']} " in last[0]


def test_the_live_view_says_each_sender_s_serial_scope(tmp_path):
    """A base unit numbering VRPI and VRCI on counters of their own: the live view gave its serial
    verdicts with no word of the scope they were judged in (only the end's report had it). Each
    snapshot now names it, null while `auto` has not chosen it (with `serial_choosing` while it
    chooses, from the first VRCI; a VRPI-only unit beside it has one type, no choice to make), and
    the dashboard says it; at the end, the report's."""
    from test_analysis_craft import BU_ORIGIN, Traffic, payload, vrpi
    from vm110.layers import VRCI
    from vm110.monitor import dashboard
    tr = Traffic()
    for i in range(160):                                                  # 20 s of VRPI
        tr.add(i * 0.125, vrpi(i))
        if i % 8 == 1:
            tr.add(i * 0.125 + 0.01, payload(VRCI, i // 8, BU_ORIGIN, command_id=i // 8))   # its own counter
        tr.add(i * 0.125 + 0.05, vrpi(7000 + i, origin=0x0202), src="10.0.0.11")
    tr.write(tmp_path / "t.pcap")
    lines, report = tmp_path / "live.jsonl", tmp_path / "m.json"
    main(["monitor", "--read", str(tmp_path / "t.pcap"), "--idle", "0", "--no-dashboard", "--quiet",
          "--crc", "mpeg2", "--crc-order", "little", "--json-lines", str(lines), "--json", str(report)])
    snapshots = [o for o in map(json.loads, lines.read_text().splitlines()) if o["type"] == "snapshot"]
    assert [s["serial"]["scope"] for s in json.loads(report.read_text())["senders"]] == ["type", "sender"]
    per_type, one_type = ([(s["serial_scope"], s["serial_choosing"]) for o in snapshots for s in o["senders"]
                           if s["sender"].split()[1].startswith(host)] for host in ("10.0.0.10:", "10.0.0.11:"))
    assert per_type[0] == (None, True) and per_type[-1] == ("type", False)
    assert set(per_type) == {(None, True), ("type", False)}
    assert set(one_type) == {(None, False)}
    header = {"source": "t.pcap", "now": 0.0, "status": "done", "packets": 0, "rate": 0.0, "eglink": 0,
              "illegal": 0, "alarms": []}
    last, first = (dashboard.render(header, snapshots[k], [], 100, 40) for k in (-1, 0))
    assert any("serials per type" in line for line in last)
    assert any("serials choosing" in line for line in first)
    assert sum("serials one type so far" in line for line in last + first) == 2


def test_the_dashboard_says_the_day_and_the_zone_of_its_times():
    """Field trial: a dashboard left running for days said '09:48:13.001' alone: which day, and
    in which zone (the times are UTC, as analyze's)? Its first line now gives the UTC date too,
    before the source (a long path is cut at the terminal's width, not the status)."""
    from vm110.monitor import dashboard
    header = {"source": "interface eth1", "now": 1_700_000_000.25, "status": "running", "packets": 0, "rate": 0.0,
              "eglink": 0, "illegal": 0, "alarms": []}
    view = {"senders": [], "senders_dropped": 0, "commands": {"commands": 0, "in_flight": 0, "unacked": 0,
                                                               "failed": 0, "ack_latency_ms": {"last": None,
                                                                                              "max_1m": None}}}
    first = dashboard.render(header, view, [], 80, 24)[0]
    assert first == "vm110 monitor  running  2023-11-14 22:13:20.250 UTC  interface eth1"
    header["source"] = "/a/path/longer/than/the/room/left/on/an/80/column/terminal/capture.pcapng"
    assert dashboard.render(header, view, [], 80, 24)[0].startswith(first[:-len("interface eth1")])


def test_finding_lines_give_the_date_of_their_time(tmp_path, capsys):
    """Trial: a monitor left running for days printed its finding lines as '15:06:42.700 #56 ERROR
    lost ...': which day? Each line (and each line of findings held back by the rate limit, and the
    dashboard's) now gives its capture time in ISO 8601 UTC with its date, as `vm110 decode` gives
    each packet's."""
    import datetime
    from vm110.monitor import dashboard
    lines = tmp_path / "live.jsonl"
    assert main(["monitor", "--read", str(ROOT / "captures" / "loss.pcapng"), "--idle", "0", "--no-dashboard",
                 "--json-lines", str(lines), "--crc", "mpeg2", "--crc-order", "little"]) == 0
    out = [line for line in capsys.readouterr().out.splitlines() if line.startswith("20")]
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    told = [o for o in objects if o["type"] in ("finding", "suppressed")]
    assert len(out) == len(told) and any(o["type"] == "suppressed" for o in told)

    def iso(t: float) -> str:
        return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    assert [line.split()[0] for line in out] == [iso(o["time"] if o["type"] == "finding" else o["at"]) for o in told]
    # A day later at the same time of day, a line says so. The dashboard, whose first line gives
    # the date, gives it again only for what is of another day (an 80-column line keeps room).
    f = next(o for o in told if o["type"] == "finding")
    later = {**f, "time": f["time"] + 86400, "item": {**f["item"], "time": f["time"] + 86400}}
    assert dashboard.finding_line(later).startswith(iso(f["time"] + 86400) + f" #{f['frame']} ")
    assert dashboard.finding_line(later)[10:] == dashboard.finding_line(f)[10:]
    header = {"source": "eth1", "now": later["time"] + 1, "status": "running", "packets": 0, "rate": 0.0,
              "eglink": 0, "illegal": 0, "alarms": [f["item"] | {"rule": "watchdog"}]}
    shown = dashboard.render(header, [o for o in objects if o["type"] == "snapshot"][-1], [f, later], 200, 40)
    assert shown[0].startswith(f"vm110 monitor  running  {iso(later['time'] + 1)[:10]} ")
    assert f"  ALARM watchdog {dashboard.short(f['sender'])} since {iso(f['time'])} #{f['frame']}" in shown
    assert shown[-2:] == [dashboard.finding_line(f), dashboard.finding_line(later)[11:]]


def test_findings_json_lines_and_evidence_of_a_silent_base_unit(tmp_path, capsys):
    capture = str(ROOT / "captures" / "bu-stops.pcap")
    lines, evidence = tmp_path / "live.jsonl", tmp_path / "evidence"
    evidence.mkdir()
    # A given CRC variant: nothing is held back while it is chosen from the first 256 packets.
    code = main(["monitor", "--read", capture, "--idle", "0", "--no-dashboard", "--quiet", "--json-lines", str(lines),
                 "--evidence", str(evidence), "--before", "2", "--after", "1", "--crc", "mpeg2", "--crc-order", "little"])
    assert code == 0
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    snapshots = [o for o in objects if o["type"] == "snapshot"]
    findings = [o for o in objects if o["type"] == "finding"]
    # One snapshot per second of capture time.
    times = [s["time"] for s in snapshots]
    assert times == [times[0] + i for i in range(len(times))] and len(times) >= 13
    alarm = [f for f in findings if f["rule"] == "watchdog" and f["event"] == "raised"]
    assert len(alarm) == 1 and alarm[0]["item"]["type"] == "VRPI" and alarm[0]["severity"] == "error"
    # Raised while the BU is still silent: within a second of the 500 ms limit, never cleared.
    silent_from = alarm[0]["item"]["time"]
    assert 0.5 < alarm[0]["at"] - silent_from <= 1.5
    assert not [f for f in findings if f["rule"] == "watchdog" and f["event"] == "cleared"]
    bu = next(s for s in snapshots[-1]["senders"] if s["role"] == "BU")
    ctl = next(s for s in snapshots[-1]["senders"] if s["role"] == "controller")
    assert bu["state"] == "watchdog" and bu["age_ms"] > 4000 and ctl["state"] == "alive"
    assert snapshots[-1]["alarms"][0]["rule"] == "watchdog" and bu["bu_state"] == "Armed"
    # The evidence: the frames of [alarm - 2 s, alarm + 1 s], named by time and rule, JSON beside.
    files = sorted(p for p in evidence.iterdir() if "-watchdog" in p.name)
    assert [f.suffix for f in files] == [".json", ".pcapng"]
    # The controller's last two commands, never acknowledged by the stopped BU, are failed (as in
    # the report's `failed` 2), each with its evidence. The first is told once its give-up time has
    # passed, while the capture runs (it waited for the end of the input while the BU, silent
    # before its first 10 s were over, had not chosen its serial scope), the second at the end.
    failed = [f for f in findings if f["rule"] == "failed"]
    assert [(f["item"]["type"], f["event"]) for f in failed] == [("VRCO", "raised")] * 2
    end = snapshots[-1]["time"]
    assert failed[0]["at"] - failed[0]["item"]["time"] <= C.VRCO_GIVE_UP_MS / 1000 + 1 < end - failed[0]["item"]["time"]
    assert len([p for p in evidence.iterdir() if "-failed" in p.name]) == 4      # .json and .pcapng each
    meta = json.loads(files[0].read_text())
    frames = list(CaptureReader(str(files[1])))
    assert meta["frames"]["count"] == len(frames) > 0 and meta["findings"][0]["rule"] == "watchdog"
    everything = {f[5]: f for f in CaptureReader(capture)}
    start, end = meta["window"]["start"], meta["window"]["end"]
    expected = [n for n, f in everything.items() if start <= f[0] <= end]
    assert meta["frames"]["numbers"] == expected
    assert [f[4] for f in frames] == [everything[n][4] for n in expected]     # the very payloads
    # ... at their very times (trial: written in ns from a float, 1750000007.875 became ...875000064).
    from reference.analyser import read_records
    original = read_records(capture)
    assert [r["t"] for r in read_records(str(files[1]))] == [original[n - 1]["t"] for n in expected]
    # The finding's filter names the capture's frames; `evidence_filter` the same ones in this file.
    item = meta["findings"][0]["item"]
    assert [frames[n - 1][4] for n in item["evidence_frames"]] == [everything[item["frame"]][4]]
    assert item["evidence_filter"] == f"frame.number == {item['evidence_frames'][0]}" != item["filter"]


def test_the_live_view_counts_each_sender_s_serials_as_the_report(tmp_path):
    """Trial: the dashboard showed a base unit's lost, duplicated and out-of-order packets as 0
    (the controller's were right): the live view named the BU by a key the analysis no longer
    used (its source index had grown to 30 bits), so nothing of the BU was found, nor its restart
    on a new port. Each sender's numbers at the end are now the report's."""
    lines, report = tmp_path / "live.jsonl", tmp_path / "m.json"
    assert main(["monitor", "--read", str(ROOT / "captures" / "loss.pcapng"), "--idle", "0", "--no-dashboard",
                 "--quiet", "--json-lines", str(lines), "--json", str(report)]) == 0
    last = [json.loads(line) for line in lines.read_text().splitlines()
            if json.loads(line)["type"] == "snapshot"][-1]
    shown = {s["sender"]: (s["lost"], s["duplicates"], s["out_of_order"]) for s in last["senders"]}
    told = {s["id"]: (s["serial"]["lost"], s["serial"]["duplicates"], s["serial"]["out_of_order"])
            for s in json.loads(report.read_text())["senders"]}
    assert {s.split()[0] for s in shown} == {"Input", "Output"}
    assert all(lost for lost, _, _ in told.values())
    for sender, (lost, dups, late) in shown.items():     # (the last snapshot: the last whole second)
        assert 0 < lost <= told[sender][0] and dups <= told[sender][1] and late <= told[sender][2], sender


def test_live_lost_findings_are_analyze_s_items(tmp_path, capsys):
    """A gap is reported live once no late packet can fill it (a duplicate window after it
    opened), with what analyze's `lost` items say of it: gaps filled later are out of order, not
    lost. The live stream keeps one line a second per sender and counts the rest."""
    capture, lines = str(ROOT / "captures" / "loss.pcapng"), tmp_path / "live.jsonl"
    # A given CRC variant and serial scope: nothing is held back while they are chosen.
    given = ["--crc", "mpeg2", "--crc-order", "little", "--serial-scope", "sender"]
    assert main(["monitor", "--read", capture, "--idle", "0", "--no-dashboard", "--quiet", "--json-lines",
                 str(lines), *given]) == 0
    live = [o for o in map(json.loads, lines.read_text().splitlines()) if o["type"] == "finding" and o["rule"] == "lost"]
    assert main(["analyze", capture, "--quiet", "--json", str(tmp_path / "a.json"), *given]) == 0
    report = json.loads((tmp_path / "a.json").read_text())
    [lost] = [f for f in report["verdict"]["findings"] if f["rule"] == "lost"]
    items = {i["frame"]: i for i in lost["items"]}
    window, end = report["options"]["dup_window_ms"] / 1000, report["capture"]["last_time"]
    for f in live:
        assert f["item"] == items[f["item"]["frame"]]
        # (told in the capture second after the window: `at` is the last packet before that tick)
        assert window - 1 <= f["at"] - f["item"]["time"] <= window + 2 or f["at"] == end
    # every item: a line, counted in a later line's suppressed_before, or in the closing count
    held = [o for o in map(json.loads, lines.read_text().splitlines()) if o["type"] == "suppressed"]
    assert all(o["rule"] == "lost" and o["count"] > 0 and o["at"] == end for o in held)
    assert len({o["sender"] for o in held}) == len(held)
    assert len(live) + sum(f.get("suppressed_before", 0) for f in live) + sum(o["count"] for o in held) == len(items)
    assert any("late" in i for i in items.values())


def test_a_sender_heard_only_briefly_does_not_hold_the_live_commands(tmp_path):
    """Field trial: a BU restarted on a new port 5 s after the monitor started (or any sender heard
    for less than 10 s: a stray packet) left the live view at 'commands 0' and told no failed
    command for the whole run: its old sender never chose its serial scope, so no command event
    after its first packet was ever applied before the end (and they all stayed in memory). The
    choice now ends once the analysis clock passes its look. Here one stray VRPO and VRCO, then a BU whose VRCIs
    are acknowledged: the live view counts them once the BU and the controller have chosen their scope."""
    from test_analysis_craft import CTRL, Traffic, payload, vrpi
    from vm110.layers import VRAO, VRCI, VRCO, VRPO
    tr = Traffic()
    tr.add(0.0, payload(VRPO, 1), src="10.0.0.99", sport=C.OUTPUT_PORT)        # heard once, never again
    tr.add(0.001, payload(VRCO, 2, command_id=1), src="10.0.0.99", sport=C.OUTPUT_PORT)
    for k in range(int(20 / 0.125)):
        tr.add(0.01 + k * 0.125, vrpi(100 + k))
        tr.add(0.02 + k * 0.125, payload(VRPO, 100 + k), src=CTRL, sport=C.OUTPUT_PORT)
    for k in range(10):                       # a VRCI every 2 s, acknowledged 5 ms later
        tr.add(0.5 + 2 * k, payload(VRCI, 1000 + k, 0x0101, command_id=k + 1))
        tr.add(0.505 + 2 * k, payload(VRAO, 1000 + k, command_id=k + 1), src=CTRL, sport=C.OUTPUT_PORT)
    tr.frames.sort(key=lambda f: f[0])
    capture = tmp_path / "stray.pcap"
    tr.write(capture)
    lines = tmp_path / "live.jsonl"
    assert main(["monitor", "--read", str(capture), "--idle", "0", "--no-dashboard", "--quiet", "--crc", "mpeg2",
                 "--crc-order", "little", "--json-lines", str(lines)]) == 0
    shown = [o["commands"]["commands"] for o in map(json.loads, lines.read_text().splitlines())
             if o["type"] == "snapshot"]
    assert shown[-1] >= 8                     # (the BU chose 10 s after its first VRCI, by 10.5 s)


def test_a_capture_ended_before_the_serial_scope_was_chosen_tells_its_findings(tmp_path):
    """Default options on a 6 s capture: its senders are still choosing their serial scope (10 s)
    when it ends. They choose then, as in the report, and every lost and restart item of the report
    is told: a line, or counted in a later line or the closing count (none was told before)."""
    capture, lines = tmp_path / "short.pcap", tmp_path / "live.jsonl"
    synthesize("loss", str(capture), 3, 6, "pcap")
    assert main(["monitor", "--read", str(capture), "--idle", "0", "--no-dashboard", "--quiet", "--json-lines",
                 str(lines), "--json", str(tmp_path / "r.json")]) == 0
    told = [o for o in map(json.loads, lines.read_text().splitlines()) if o.get("rule") in ("lost", "restarts")]
    report = json.loads((tmp_path / "r.json").read_text())
    items = [i for f in report["verdict"]["findings"] if f["rule"] in ("lost", "restarts") for i in f["items"]]
    assert len(items) >= 3
    assert {o["item"]["frame"] for o in told if o["type"] == "finding"} <= {i["frame"] for i in items}
    assert sum(o.get("count", 1) + o.get("suppressed_before", 0) for o in told) == len(items)


def test_a_report_on_standard_output_stands_alone(tmp_path):
    """--json -: standard output is the report alone; the finding lines go to standard error."""
    capture = str(ROOT / "captures" / "loss.pcapng")
    done = _run(["monitor", "--read", capture, "--idle", "0", "--json", "-"])
    assert done.returncode == 0 and json.loads(done.stdout)["totals"]["lost"] == 34
    assert b"ERROR lost" in done.stderr and b"VERDICT: FAIL" in done.stderr
    lines = _run(["monitor", "--read", capture, "--idle", "0", "--json-lines", "-"])
    assert lines.returncode == 0 and all(json.loads(line) for line in lines.stdout.splitlines())
    assert b"VERDICT: FAIL" in lines.stderr
    both = _run(["monitor", "--read", capture, "--idle", "0", "--json", "-", "--json-lines", "-"])
    assert both.returncode == 2 and both.stderr.count(b"\n") == 1 and not both.stdout


def _run(args: list[str], stdin: bytes = b"", timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(VM110 + args, input=stdin, capture_output=True, timeout=timeout)


def test_garbage_on_stdin_is_one_line_and_exit_2(tmp_path):
    out = _run(["monitor", "--read", "-", "--no-dashboard", "--json", str(tmp_path / "r.json")], b"this is no capture\n")
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    assert err == ["vm110 monitor: standard input: not a pcap or pcapng capture (magic 0x74686973)"]
    assert not (tmp_path / "r.json").exists()      # (as analyze: no report of what is not a capture)


@pytest.mark.parametrize("content", [b"this is no capture\n", "gzip"])
def test_a_file_that_is_no_capture_is_one_line_and_exit_2(tmp_path, content):
    """--read FILE of a text file, or of a gzip-compressed capture (which analyze reads): a first
    line said that the capture's header was cut short at byte 0, still being written (trial-readme),
    before the one that says what it is (a gzip file's only by its magic). That one line alone, exit 2."""
    path = tmp_path / "file"
    path.write_bytes(content if content != "gzip" else
                     subprocess.run(["gzip", "-c", str(ROOT / "captures" / "normal.pcap")], capture_output=True,
                                    check=True).stdout)
    out = _run(["monitor", "--read", str(path), "--idle", "0", "--no-dashboard"])
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    said = "compressed with gzip, which is not read here" if content == "gzip" else "not a pcap or pcapng capture"
    assert len(err) == 1 and err[0].startswith(f"vm110 monitor: {path}: {said}"), err


def test_a_pipe_that_closes_mid_record_keeps_what_was_seen(tmp_path):
    data = (ROOT / "captures" / "normal.pcap").read_bytes()
    cut = data[:5000]
    out = _run(["monitor", "--read", "-", "--no-dashboard", "--json", str(tmp_path / "r.json")], cut)
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vm110 monitor: standard input: file cut in the middle of a record at byte")
    report = json.loads((tmp_path / "r.json").read_text())
    whole = sum(1 for _ in CaptureReader(str(ROOT / "captures" / "normal.pcap")))
    assert 0 < report["capture"]["packets"] < whole
    assert "VERDICT" in out.stdout.decode()              # the summary of what was seen
    # The same bytes as a file give the same report (but for its name).
    part = tmp_path / "part.pcap"
    part.write_bytes(cut)
    assert main(["analyze", str(part), "--quiet", "--json", str(tmp_path / "a.json")]) == 2     # (damaged: as the monitor)
    a = json.loads((tmp_path / "a.json").read_text())
    a["capture"]["file"] = "-"
    assert a == report


def test_garbage_after_a_good_start_is_damage(tmp_path):
    data = (ROOT / "captures" / "loss.pcapng").read_bytes()[:20000] + b"\xff" * 64
    out = _run(["monitor", "--read", "-", "--no-dashboard", "--quiet", "--json", str(tmp_path / "r.json")], data)
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    assert len(err) == 1 and "corrupt pcapng block" in err[0]
    assert json.loads((tmp_path / "r.json").read_text())["capture"]["packets"] > 0


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
def test_no_such_interface():
    out = _run(["monitor", "-i", "vm110-nosuch0", "--no-dashboard", "--duration", "5"])
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    assert len(err) == 1 and "no device named" in err[0] and "vm110-nosuch0" in err[0]
    assert not out.stdout.strip()          # (no report of a capture that never began)


@pytest.mark.skipif(shutil.which("dumpcap") is None or shutil.which("setpriv") is None or os.geteuid() != 0,
                    reason="needs root (to drop to nobody), setpriv and dumpcap")
def test_no_permission_to_capture():
    if subprocess.run(["getcap", shutil.which("dumpcap")], capture_output=True, text=True).stdout.strip():
        pytest.skip("dumpcap has capture capabilities: everyone may capture here")
    drop = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups"]
    out = subprocess.run(drop + VM110 + ["monitor", "-i", "lo", "--no-dashboard", "--quiet", "--duration", "5"],
                         capture_output=True, timeout=60, cwd="/")
    if b"No module named" in out.stderr:
        pytest.skip("nobody cannot read this checkout")
    assert out.returncode == 2
    err = out.stderr.decode().strip().splitlines()
    assert len(err) == 1 and "permission" in err[0] and "dumpcap" in err[0]


def test_options_are_validated(capsys):
    for args in (["--read", "x", "--before", "nan"], ["--read", "x", "--duration", "0"], ["-i", "lo", "--realtime"],
                 ["--read", "-", "--idle", "1"], ["--read", "x", "--evidence", "/nonexistent/dir"], []):
        try:
            code = main(["monitor", *args])
        except SystemExit as exc:              # argparse's own refusals
            code = exc.code
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith("vm110 monitor: "), args


def test_follows_a_growing_file(tmp_path):
    """--read FILE reads on as the file grows (tail -f): the report is that of the whole file."""
    data = (ROOT / "captures" / "loss.pcapng").read_bytes()
    growing = tmp_path / "growing.pcapng"
    growing.write_bytes(data[:7001])                     # in the middle of a block
    proc = subprocess.Popen(VM110 + ["monitor", "--read", str(growing), "--idle", "2", "--no-dashboard", "--quiet",
                                     "--json", str(tmp_path / "m.json")], stderr=subprocess.PIPE)
    for cut in (7001, 30000, len(data)):
        time.sleep(0.4)
        with open(growing, "ab") as f:
            f.write(data[growing.stat().st_size:cut])
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert main(["analyze", str(growing), "--quiet", "--json", str(tmp_path / "a.json")]) == 0
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "m.json").read_bytes()


def test_sigterm_ends_with_the_report_of_what_was_seen(tmp_path):
    data = (ROOT / "captures" / "normal.pcap").read_bytes()
    lines = tmp_path / "live.jsonl"
    proc = subprocess.Popen(VM110 + ["monitor", "--read", "-", "--no-dashboard", "--quiet", "--fail-on", "packets>0",
                                     "--json", str(tmp_path / "r.json"), "--json-lines", str(lines)],
                            stdin=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdin is not None
    proc.stdin.write(data[:12000])          # the pipe stays open: only the signal ends the run
    proc.stdin.flush()
    for _ in range(200):                    # running (and its handlers in place) once it logs
        time.sleep(0.1)
        if lines.exists() and lines.stat().st_size:
            break
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)                   # before the pipe closes
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 1, err        # --fail-on holds for what was seen
    report = json.loads((tmp_path / "r.json").read_text())
    seen = report["capture"]["packets"]
    assert 0 < seen < sum(1 for _ in CaptureReader(str(ROOT / "captures" / "normal.pcap")))
    assert report["capture"]["problem"] is None      # a stream stopped between records is not damage


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_full_standard_output_leaves_the_watch_and_its_report(tmp_path):
    """Trial: `vm110 monitor ... > lines.txt` on a disk that filled: the first finding line that
    could not be written ended the run, exit 2, without the --json report. Now it is said once,
    the lines end and the watch goes on (as --json-lines on a full disk): the report is analyze's,
    the --fail-on verdict said, and exit 2 (the output is incomplete)."""
    capture = ROOT / "captures" / "loss.pcapng"
    with open("/dev/full", "w") as full:
        done = subprocess.run(VM110 + ["monitor", "--read", str(capture), "--idle", "0", "--no-dashboard", "--json",
                                       str(tmp_path / "m.json"), "--fail-on", "lost>0"], stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=120, check=False)
    assert main(["analyze", str(capture), "--quiet", "--json", str(tmp_path / "a.json")]) == 0
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "m.json").read_bytes()
    lost = json.loads((tmp_path / "a.json").read_text())["totals"]["lost"]
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == ["vm110 monitor: cannot write standard output: No space left on device",
                                        f"fail-on: {capture}: lost={lost} (rule lost>0)"]


@pytest.mark.skipif(shutil.which("nohup") is None, reason="nohup not installed")
def test_a_monitor_started_under_nohup_outlives_its_terminal(tmp_path):
    """Trial: `nohup vm110 monitor ... &`, then the SSH session closed: the monitor put its own
    handler over the SIGHUP that nohup had ignored, and ended with the session. A signal ignored
    at the start stays ignored: the watch goes on to the end of its input (here: the whole capture,
    analyze's report)."""
    capture = ROOT / "captures" / "normal.pcap"
    data = capture.read_bytes()
    lines = tmp_path / "live.jsonl"
    proc = subprocess.Popen(["nohup", *VM110, "monitor", "--read", "-", "--no-dashboard", "--quiet", "--json",
                             str(tmp_path / "m.json"), "--json-lines", str(lines)],
                            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stdin is not None
    proc.stdin.write(data[:12000])
    proc.stdin.flush()
    for _ in range(200):                    # running (its handlers in place) once it logs
        time.sleep(0.1)
        if lines.exists() and lines.stat().st_size:
            break
    proc.send_signal(signal.SIGHUP)         # the session closed
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(timeout=3)                # (it ended within a second of the signal)
    proc.stdin.write(data[12000:])
    proc.stdin.close()
    assert proc.wait(timeout=30) == 0
    with proc.stderr:
        assert proc.stderr.read() == b""
    assert main(["analyze", str(capture), "--quiet", "--json", str(tmp_path / "a.json")]) == 0
    whole, seen = (json.loads((tmp_path / name).read_text()) for name in ("a.json", "m.json"))
    assert seen["capture"].pop("file") == "-"
    del whole["capture"]["file"]
    assert seen == whole


def test_spilled_times_stay_exact_and_out_of_memory():
    block = SpilledFloats.BLOCK
    values = np.cumsum(np.random.default_rng(1).uniform(0.05, 0.2, 3 * block + 123)) + 1.75e9
    with tempfile.TemporaryFile() as spool:
        spilled, plain = SpilledFloats(spool), Floats()
        for part in np.array_split(values, 7):
            spilled.extend(part)
            plain.extend(part)
        assert len(spilled.blocks.where) == 3 and os.fstat(spool.fileno()).st_size == 3 * block * 8
        assert spilled.used == 123 and len(spilled.blocks.tail) == 128     # (the last block grows as it fills)
        assert np.array_equal(spilled.intervals_ms(), plain.intervals_ms())
        assert np.array_equal(spilled.intervals_ms(1.7e9), plain.intervals_ms(1.7e9))
        assert spilled.last() == plain.last() == values[-1]
        assert [spilled[i] for i in (0, block - 1, block + 5, 3 * block)] == [values[i] for i in (0, block - 1, block + 5,
                                                                                               3 * block)]


def test_a_replay_stopped_by_duration_reports_exactly_what_it_judged(tmp_path):
    capture = ROOT / "captures" / "normal.pcap"            # 20 s of traffic
    out = _run(["monitor", "--read", str(capture), "--realtime", "--duration", "3", "--no-dashboard", "--quiet",
                "--json", str(tmp_path / "m.json")])
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "m.json").read_text())
    seen = report["capture"]["packets"]
    assert 0 < seen < 300
    # The same packets as a file: the same report.
    data, pos = capture.read_bytes(), 24
    for _ in range(seen):
        pos += 16 + int.from_bytes(data[pos + 8:pos + 12], "little")
    prefix = tmp_path / "prefix.pcap"
    prefix.write_bytes(data[:pos])
    assert main(["analyze", str(prefix), "--quiet", "--json", str(tmp_path / "a.json")]) in (0, 1)
    expected = json.loads((tmp_path / "a.json").read_text())
    expected["capture"]["file"] = str(capture)
    assert report == expected


def test_waiting_at_the_end_of_a_file_is_not_silence(tmp_path):
    """--read FILE runs on capture time: a clean capture raises no watchdog while the monitor waits
    for the file to grow (it once took wall-clock waiting for a silent link)."""
    lines = tmp_path / "lines.jsonl"
    done = _run(["monitor", "--read", str(ROOT / "captures" / "normal.pcap"), "--idle", "1.5", "--no-dashboard",
                 "--json-lines", str(lines)])
    assert done.returncode == 0, done.stderr
    findings = [json.loads(line) for line in lines.read_text().splitlines()]
    assert [f for f in findings if f["type"] == "finding" and f["rule"] == "watchdog"] == []
    assert any(f["type"] == "snapshot" for f in findings)


def test_a_long_command_s_evidence_filter_is_in_the_file_s_numbers():
    """A command item of 70 transmissions and its ack: its filter in the evidence file names
    exactly those frames in the file's own numbers (ranges where they are consecutive)."""
    from vm110.analysis.findings import located_item
    from vm110.monitor.evidence import _in_file
    frames = list(range(101, 241, 2))                       # 70 transmissions, every other frame
    ack = 300
    item = located_item(frames + [ack], 1.0, "Input 10.0.0.10:5825 origin 0x0101", type="VRCI", command_id=7,
                        latency_ms=2500.0, ack_frame=ack)
    numbers = list(range(90, 301))                          # the evidence file holds frames 90..300
    [told] = _in_file([{"rule": "failed", "item": item}], numbers)
    here = told["item"]["evidence_frames"]
    assert here == [n - 89 for n in frames + [ack]]
    assert told["item"]["evidence_filter"] == "frame.number in {" + ", ".join(map(str, here)) + "}"


def test_live_vrpo_bursts_end_where_analyze_s_do(tmp_path):
    """interpretation.md: "a burst ends with a packet of fewer than 488 bytes". Unsplit VRPO
    packets 15 ms apart (closer than the 20 ms burst gap) are bursts of their own, 15 ms apart:
    the live view counts their intervals outside the recommended 50-200 ms as analyze does (9); a
    split burst (488 + 100 bytes, 1 ms apart) is one, so its parts add no interval."""
    from test_analysis_craft import CTRL, Traffic
    from vm110.analysis import analyze
    from vm110.analysis.report import Options
    from vm110.encode import packet, vrpo_payload
    from vm110.monitor.live import LiveSender
    sends = [(i * 0.015, 0, 100) for i in range(10)]
    sends += [(1.0 + k * 0.1 + j * 0.001, j, 488 if j == 0 else 100) for k in range(3) for j in range(2)]
    tr = Traffic()
    snd = LiveSender((False, b"", 5827, 0), "controller", "Output", Options())
    for serial, (t, number, size) in enumerate(sends):
        data = packet("VRPO", vrpo_payload(number, bytes(size)), serial=serial)
        tr.add(t, data, src=CTRL, sport=5827)
        snd.periodic(t, serial + 1, data, lambda _: None)
    path = tmp_path / "bursts.pcap"
    tr.write(path)
    report = analyze(str(path))
    [vrpo] = [p for p in report["periodic"] if p["type"] == "VRPO"]
    assert vrpo["outside_recommended"]["count"] == snd.outside == 9 + 1   # 15 ms x 9; 0.135 s -> 1.0 s
    assert report["vrpo_bursts"] == {**report["vrpo_bursts"], "complete": 13, "incomplete": 0}


def test_each_finding_line_gives_its_filter_once(tmp_path, capsys):
    """Trial: every finding line ended with its display filter twice (`[frame.number == 7]  [frame.number == 7]`)."""
    capture = str(ROOT / "captures" / "loss.pcapng")
    assert main(["monitor", "--read", capture, "--idle", "0", "--no-dashboard", "--crc", "mpeg2", "--crc-order",
                 "little", "--serial-scope", "sender"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if " ERROR lost " in line]
    assert lines
    for line in lines:
        frame = line.split(" #", 1)[1].split()[0]
        assert line.endswith(f"  [frame.number == {frame}]") and line.count("[frame.number") == 1


def test_evidence_that_cannot_be_written_leaves_the_watch_and_its_report(tmp_path, monkeypatch, capsys):
    """Trial: a disk full (or read-only) under --evidence ended the run at the first alarm's file,
    exit 2, with no report and no verdict. Now each window not written is said and counted, and the
    run ends with analyze's report and the --fail-on verdict."""
    from vm110.errors import CliError
    from vm110.monitor import evidence as ev

    def full(path, data):
        raise CliError(f"cannot write {path}: No space left on device")
    monkeypatch.setattr(ev, "write_bytes", full)
    capture, folder = str(ROOT / "captures" / "bu-stops.pcap"), tmp_path / "evidence"
    folder.mkdir()
    assert main(["analyze", capture, "--quiet", "--json", str(tmp_path / "a.json")]) == 0
    capsys.readouterr()
    assert main(["monitor", "--read", capture, "--idle", "0", "--quiet", "--no-dashboard", "--evidence", str(folder),
                 "--json", str(tmp_path / "m.json"), "--fail-on", "watchdog>0"]) == 1
    assert (tmp_path / "m.json").read_bytes() == (tmp_path / "a.json").read_bytes()
    err = capsys.readouterr().err.splitlines()
    # the watchdog's window, and one that the two failed commands (one sender, 1.5 s apart) share
    said = [line for line in err if line.startswith("vm110 monitor: evidence not written: cannot write")]
    assert [line.rsplit("Z-", 1)[1] for line in said] == ["watchdog.pcapng: No space left on device",
                                                           "failed.pcapng: No space left on device"]
    assert "vm110 monitor: evidence: 2 alarm window(s) not written, the last: " + said[-1].split(": ", 2)[2] in err
    assert not list(folder.iterdir())


def test_json_lines_that_cannot_be_written_leave_the_watch_and_its_report(tmp_path):
    """Trial: a --json-lines file on a full disk ended the run with a traceback, no report and no
    verdict. Now the lines end (said once) and the watch goes on to the report and the verdict.
    (The file size limit stands in for the full disk: writes beyond it fail, EFBIG.)"""
    import resource
    limit, lines = 16 << 10, tmp_path / "live.jsonl"

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    done = subprocess.run(VM110 + ["monitor", "--read", str(ROOT / "captures" / "loss.pcapng"), "--idle", "0",
                                   "--no-dashboard", "--json-lines", str(lines), "--fail-on", "lost>0"],
                          capture_output=True, timeout=60, preexec_fn=small_files)
    assert done.returncode == 1, done.stderr
    assert done.stderr.decode().splitlines() == [
        f"vm110 monitor: --json-lines {lines}: cannot write: File too large; no more lines are written",
        f"fail-on: {ROOT / 'captures' / 'loss.pcapng'}: lost=34 (rule lost>0)"]
    assert b"VERDICT: FAIL" in done.stdout and b"error   34 packets lost" in done.stdout
    # Whole lines only: the one that did not fit is taken back (a torn last line broke every reader).
    written = lines.read_bytes()
    assert limit - 2000 < len(written) < limit and written.endswith(b"\n")
    assert all(json.loads(line)["type"] in ("snapshot", "finding") for line in written.splitlines())


def test_a_closed_standard_output_ends_the_run_with_its_report_and_verdict(tmp_path):
    """Trial: `vm110 monitor ... | head -1` exited 0 at the next line, without the --json report
    and without the --fail-on verdict (analyze keeps both). Now the reader's going ends the run as
    Ctrl-C does: the report of what was seen is written and the exit code is the verdict's."""
    report = tmp_path / "r.json"
    proc = subprocess.Popen(VM110 + ["monitor", "--read", str(ROOT / "captures" / "loss.pcapng"), "--realtime",
                                     "--no-dashboard", "--json", str(report), "--fail-on", "lost>0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    first = proc.stdout.readline()
    proc.stdout.close()                                         # head -1
    assert b" ERROR lost " in first
    assert proc.wait(timeout=40) == 1
    with proc.stderr:
        err = proc.stderr.read().decode()
    seen = json.loads(report.read_text())
    assert 0 < seen["totals"]["lost"] < 34 and seen["capture"]["packets"] < 612      # stopped, not read to its end
    assert err.splitlines()[-1].endswith(f"lost={seen['totals']['lost']} (rule lost>0)")


def _wait_read_to_its_end(proc: subprocess.Popen, path: Path, timeout: float = 60) -> None:
    """Until `proc` has `path` open and has read all of it (a busy machine starts a monitor slowly)."""
    size, deadline = path.stat().st_size, time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        for fd in os.listdir(f"/proc/{proc.pid}/fd"):
            with contextlib.suppress(OSError):
                if os.readlink(f"/proc/{proc.pid}/fd/{fd}") == str(path):
                    pos = int(Path(f"/proc/{proc.pid}/fdinfo/{fd}").read_text().split()[1])
                    if pos >= size:
                        return
        time.sleep(0.05)
    raise AssertionError(f"the monitor did not read {path} to its end within {timeout} s")


@pytest.mark.parametrize("how", ["replaced", "cut"])
def test_a_followed_file_replaced_or_cut_shorter_ends_the_input(how, tmp_path):
    """Trial: a followed capture renamed over by another (a capture re-recorded, a rotation) was
    still read through the old file: the monitor waited on it in silence, its report that of the
    old file, exit 0. Now the input ends there, with the report of what was read and exit 2, as for
    any input not read to its end; likewise a file cut shorter than what was read."""
    followed, other = tmp_path / "live.pcapng", tmp_path / "other.pcapng"
    shutil.copy(ROOT / "captures" / "normal.pcap", followed)
    shutil.copy(ROOT / "captures" / "loss.pcapng", other)
    proc = subprocess.Popen(VM110 + ["monitor", "--read", str(followed), "--no-dashboard", "--quiet",
                                     "--json", str(tmp_path / "m.json")], stderr=subprocess.PIPE)
    _wait_read_to_its_end(proc, followed)          # (no --idle: followed for ever)
    if how == "replaced":
        other.replace(followed)
        said = f"{followed} was replaced by another file while followed"
    else:
        os.truncate(followed, 1000)
        said = f"{followed} was cut shorter (1000 bytes) than what was read ({(ROOT / 'captures' / 'normal.pcap').stat().st_size})"
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()                                # (the old monitor followed the old file for ever)
        proc.communicate()
    assert proc.returncode == 2
    assert err.decode().splitlines() == [f"vm110 monitor: {said}: the report is of what was read before"]
    assert main(["analyze", str(ROOT / "captures" / "normal.pcap"), "--quiet", "--json", str(tmp_path / "a.json")]) == 0
    a, m = json.loads((tmp_path / "a.json").read_text()), json.loads((tmp_path / "m.json").read_text())
    assert m == {**a, "capture": {**a["capture"], "file": str(followed)}}


def test_a_link_gone_silent_after_a_restart_candidate_holds_no_failed_command(tmp_path):
    """On a live link (and with --realtime) the analysis clock moves only with packets: when the
    whole link fell silent just after a base unit's restart candidate, the command events behind
    the candidate waited until traffic came back, so the controller's VRCO that failed at +2.6 s
    was told only at the end (+15 s), though the watchdogs came on time. The wait ends on the
    wall clock too (rules.md rule 5: 10 s after the candidate; 2 s later, for packets in flight)."""
    from test_analysis_craft import CTRL, T0, Traffic, payload, vrpi
    from vm110.layers import VRCO, VRPO
    tr = Traffic()
    for i in range(8):
        tr.add(i * 0.125, vrpi(100 + i))
    tr.add(1.0, vrpi(5000))                                     # the candidate; then the link is silent
    for i in range(11):
        tr.add(0.01 + i * 0.1, payload(VRPO, i, packet_number=0, periodic_data=b"x" * 10), src=CTRL,
               sport=C.OUTPUT_PORT)
    tr.add(0.6, payload(VRCO, 11, command_id=4), src=CTRL, sport=C.OUTPUT_PORT)       # never acknowledged
    tr.frames.sort(key=lambda f: f[0])
    tr.write(tmp_path / "silent.pcap")
    lines = tmp_path / "lines.jsonl"
    out = _run(["monitor", "--read", str(tmp_path / "silent.pcap"), "--realtime", "--duration", "15",
                "--no-dashboard", "--quiet", "--json-lines", str(lines), "--crc", "mpeg2", "--crc-order", "little",
                "--serial-scope", "sender"])
    assert out.returncode in (0, 1), out.stderr
    [failed] = [o for o in map(json.loads, lines.read_text().splitlines())
                if o["type"] == "finding" and o["rule"] == "failed"]
    assert failed["at"] - T0 < 14.0                              # released at +13 s (the end: +15 s)


def test_a_live_watch_stopped_after_its_last_record_spans_until_it_stopped(tmp_path):
    """Trial: every live run stopped by a signal (the link watched on past its last packet) had its
    report say "first record ..., last ...: not in time order, they span ..." of records in time
    order, and a duration that ended at the last packet, not when the watch did. The span watched
    ends where the watch ended: last and latest time alike, the duration between first and last."""
    data = (ROOT / "captures" / "normal.pcap").read_bytes()
    lines = tmp_path / "live.jsonl"
    proc = subprocess.Popen(VM110 + ["monitor", "--read", "-", "--no-dashboard", "--json", str(tmp_path / "r.json"),
                                     "--json-lines", str(lines)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdin is not None
    proc.stdin.write(data[:12000])          # the pipe stays open: the link is watched on
    proc.stdin.flush()
    for _ in range(200):
        time.sleep(0.1)
        if lines.exists() and lines.stat().st_size:
            break
    time.sleep(0.5)                         # watched past the last record
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    cap = json.loads((tmp_path / "r.json").read_text())["capture"]
    records = [ts for ts, *_ in CaptureReader(str(ROOT / "captures" / "normal.pcap"))]
    assert cap["first_time"] == cap["earliest_time"] == records[0]
    assert cap["last_time"] == cap["latest_time"] > records[cap["packets"] - 1] + 0.4
    assert cap["duration_s"] == pytest.approx(cap["last_time"] - cap["first_time"])
    assert b"not in time order" not in out and b"Time: 20" in out


def _illegal_from_many_ports(n: int) -> bytes:
    """A pcap of `n` datagrams on the input port that are no EG-Link packet (an ID and nothing
    else), each from another source port: `n` illegal findings no rate limit holds back."""
    import io

    from vm110.capture.writer import PcapWriter, UdpFlow
    out = io.BytesIO()
    with PcapWriter(out) as w:
        w.write_many((1_750_000_000_000_000 + i * 1000, UdpFlow("10.0.0.10", 20000 + i, "239.255.42.20", 5825)
                      .frame(b"VRPI" + bytes(30))) for i in range(n))
    return out.getvalue()


def test_a_reader_that_stops_reading_stops_neither_the_watch_nor_its_end(tmp_path):
    """Trial: `vm110 monitor ... | less` left at a full screen (or a terminal paused by Ctrl-S):
    once the pipe was full the monitor stood still in a finding line, its watch with it, and
    SIGTERM did not end it (no report, no exit code) until the reader read. Now what the reader does
    not take waits in a bounded backlog and the watch goes on: every finding is in --json-lines,
    SIGTERM gives the report, and a reader still stalled at the end is left as one gone away."""
    n = 2000                                # some 300 kB of finding lines: more than a pipe holds
    capture, lines, report = tmp_path / "many.pcap", tmp_path / "live.jsonl", tmp_path / "r.json"
    capture.write_bytes(_illegal_from_many_ports(n))
    stalled_r, stalled_w = os.pipe()       # read by no one until the end
    proc = subprocess.Popen(VM110 + ["monitor", "--read", str(capture), "--no-dashboard", "--crc", "mpeg2",
                                     "--crc-order", "little", "--json", str(report), "--json-lines", str(lines),
                                     "--fail-on", "illegal>0"],      # (followed until the signal)
                            stdout=stalled_w, stderr=subprocess.PIPE)
    os.close(stalled_w)
    try:
        for _ in range(100):
            time.sleep(0.1)
            if lines.exists() and lines.read_text().count('"rule": "illegal"') == n:
                break
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=30)[1].decode()
        assert proc.returncode == 1, err                     # the verdict of what was seen
        assert json.loads(report.read_text())["totals"]["illegal"] == n
        assert lines.read_text().count('"rule": "illegal"') == n
        assert "vm110 monitor: standard output not read for 5 s: the rest of it is left out" in err
        os.set_blocking(stalled_r, False)
        told = b""
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(stalled_r, 1 << 16):
                told += chunk
        text = told.decode()
        assert text.count(" illegal ") > 100 and text.endswith("\n")     # what it took: whole lines
    finally:
        os.close(stalled_r)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_packet_ids_off_the_network_reach_no_terminal_as_escape_sequences(tmp_path, capsys):
    """Trial: a datagram on the input port whose first bytes were ESC [ 2 J (any host on the link
    can send one) was told as `illegal \\x1b[2J: ...` with the ESC itself: the terminal of the
    finding lines cleared its screen, the dashboard's likewise (and ESC ] 0 ; set its title).
    The lines give such characters as their escapes."""
    from vm110.capture.writer import PcapWriter, UdpFlow
    from vm110.monitor import dashboard as dash
    capture = tmp_path / "esc.pcap"
    flow = UdpFlow("10.0.0.10", 5825, "239.255.42.20", 5825)
    with open(capture, "wb") as f, PcapWriter(f) as w:
        w.write_many([(1_750_000_000_000_000, flow.frame(b"\x1b[2J" + bytes(30))),
                      (1_750_000_002_000_000, flow.frame(b"\x1b]0;" + bytes(30)))])
    assert main(["monitor", "--read", str(capture), "--idle", "0", "--no-dashboard", "--crc", "mpeg2",
                 "--crc-order", "little", "--json-lines", str(tmp_path / "l.jsonl")]) == 0
    told = [ln for ln in capsys.readouterr().out.splitlines() if " ERROR illegal " in ln]
    assert [ln.split(": ")[1] for ln in told] == ["illegal \\x1b[2J", "illegal \\x1b]0;"]
    findings = [json.loads(ln) for ln in (tmp_path / "l.jsonl").read_text().splitlines()]
    findings = [f for f in findings if f["type"] == "finding"]
    assert [f["item"]["type"] for f in findings] == ["\x1b[2J", "\x1b]0;"]      # (the JSON keeps them as they came)
    view = {"commands": {"commands": 0, "in_flight": 0, "unacked": 0, "failed": 0,
                         "ack_latency_ms": {"last": None, "max_1m": None}}, "senders": []}
    header = {"now": findings[0]["time"], "status": "running", "source": "cap\x1b[2J.pcap", "packets": 2,
              "rate": 0.0, "eglink": 2, "illegal": 2, "alarms": []}
    screen = dash.render(header, view, findings, 120, 24)
    assert all(ln.isprintable() for ln in screen) and "\\x1b[2J" in screen[0]
    assert "illegal \\x1b[2J" in screen[-2] and "illegal \\x1b]0;" in screen[-1]


def test_a_followed_file_of_dumpcap_s_ring_buffer_goes_on_in_the_next_one(tmp_path):
    """Trial: `dumpcap -b filesize:... -w ring/r.pcapng` with `vm110 monitor --read
    ring/r_00001_...pcapng`: once dumpcap went on in r_00002_..., the monitor sat on the first file
    for ever, its dashboard saying the link alive. It reads on in the ring's next file (made once
    the one before is closed), as one stream: the report is analyze's of the files one after the
    other. A BU losing every 20th VRPI, over three ring files."""
    from vm110 import encode as E
    from vm110.capture.writer import PcapngWriter, UdpFlow
    flow = UdpFlow("10.0.0.10", 5825, "239.255.42.20", 5825)
    vrpi = E.vrpi_payload({"bu_state": 0x10})
    stamps = ["20250615150640", "20250615150643", "20250615150647"]
    names = [tmp_path / f"r_{i + 1:05d}_{stamp}.pcapng" for i, stamp in enumerate(stamps)]
    for i, name in enumerate(names):
        with open(name, "wb") as f, PcapngWriter(f) as w:
            w.write_many((1_750_000_000_000_000 + serial * 125_000,
                          flow.frame(E.packet(C.PacketType.VRPI, vrpi, origin=0x101, serial=serial)))
                         for serial in range(i * 30, (i + 1) * 30) if serial % 20 != 7)
    (tmp_path / "all.pcapng").write_bytes(b"".join(n.read_bytes() for n in names))
    expected, seen = tmp_path / "a.json", tmp_path / "m.json"
    assert main(["analyze", str(tmp_path / "all.pcapng"), "--quiet", "--json", str(expected)]) == 0
    assert main(["monitor", "--read", str(names[0]), "--idle", "0", "--quiet", "--json", str(seen)]) == 0
    a, m = json.loads(expected.read_text()), json.loads(seen.read_text())
    assert m["totals"]["packets"] == 85 and m["totals"]["lost"] == 5
    assert m["capture"].pop("file") == str(names[0])
    del a["capture"]["file"]
    assert m == a


@pytest.mark.parametrize("cut_in", ["record", "header"])
def test_a_followed_file_whose_writer_stopped_mid_record_is_said_to_have(cut_in, tmp_path, monkeypatch, capsys):
    """Trial: a followed capture whose writer died (the file no longer grows, cut in the middle of
    a record) was waited on in silence for ever, and at Ctrl-C the record cut short was dropped
    without a word. Now, once the file has not grown for a while, the monitor says so and where the
    record cut short begins (standard error, --json-lines), and at the end that it was not read."""
    from vm110.monitor import session
    monkeypatch.setattr(session, "STALL_S", 0.2, raising=False)     # (60 s: a tcpdump without -U writes in blocks)
    data = (ROOT / "captures" / "normal.pcap").read_bytes()
    starts, pos = [], 24                               # pcap: a 24-byte header, records of 16 + incl_len
    while pos < len(data):
        starts.append(pos)
        pos += 16 + int.from_bytes(data[pos + 8:pos + 12], "little")
    cut = tmp_path / "died.pcap"
    # The writer died 20 bytes into the last record, or into the capture's header (24 bytes).
    at, what = (starts[-1], "a record") if cut_in == "record" else (0, "the capture's header")
    cut.write_bytes(data[:at + 20])
    lines = tmp_path / "l.jsonl"
    assert main(["monitor", "--read", str(cut), "--duration", "1", "--no-dashboard", "--quiet",
                 "--json-lines", str(lines)]) == 0
    where = f"{what} cut short at byte {at} (20 bytes)"
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith(f"vm110 monitor: {cut} has not grown for ") and err[0].endswith(f"it ends in {where}")
    assert err[1] == f"vm110 monitor: {cut}: {where}, not read (still being written, or its writer stopped there)"
    said = [json.loads(ln) for ln in lines.read_text().splitlines() if '"input"' in ln]
    assert [(s["event"], s["message"]) for s in said] == [("stalled", err[0].removeprefix("vm110 monitor: "))]
