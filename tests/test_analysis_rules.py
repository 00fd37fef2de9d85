"""The revised serial, restart, periodic and command rules (docs/rules.md) through `analyze`, on
crafted captures whose expected numbers are worked out by hand from the rules."""
from __future__ import annotations

import html
import re

import pytest

from vm110 import constants as C
from vm110.analysis import analyze
from vm110.analysis.report import Options
from vm110.layers import VRAI, VRAO, VRCI, VRCO, VRPO

import tshark_runner as T
from test_analysis_craft import BU, BU_ORIGIN, CTRL, T0, Traffic, payload, vrpi

OUT = C.OUTPUT_PORT


def _report(tr: Traffic, tmp_path, **options) -> dict:
    tr.write(tmp_path / "t.pcap")
    return analyze(str(tmp_path / "t.pcap"), options=Options(serial_scope="sender", **options))


def _sender(report: dict, src: str) -> dict:
    return next(s for s in report["senders"] if s["src"] == src)


def _stream(report: dict, ptype: str, src: str) -> dict:
    return next(p for p in report["periodic"] if p["type"] == ptype and p["sender"].endswith(f"{src} origin 0x"
                                                                                           + p["sender"][-4:]))


def _finding(report: dict, rule: str) -> dict:
    return next(f for f in report["verdict"]["findings"] if f["rule"] == rule)


def test_two_overlapping_commands_acked_in_reverse_order(tmp_path):
    tr = Traffic()
    serial = 0
    for k in range(8):                       # VRPI keeps the link alive
        tr.add(k * 0.125, vrpi(serial))
        serial += 1
    # Commands 5 and 6 pressed 30 ms apart, each resent every 100 ms; 6 acked first.
    for t, cid in ((0.01, 5), (0.04, 6), (0.11, 5), (0.14, 6), (0.21, 5)):
        tr.add(t, payload(VRCI, serial, BU_ORIGIN, command_id=cid))
        serial += 1
    tr.add(0.16, payload(VRAO, 0, command_id=6), src=CTRL, sport=OUT)
    tr.add(0.23, payload(VRAO, 1, command_id=5), src=CTRL, sport=OUT)
    tr.frames.sort(key=lambda f: f[0])
    cmd = _report(tr, tmp_path)["commands"]["VRCI"]
    assert (cmd["commands"], cmd["transmissions"], cmd["retransmissions"], cmd["acked"], cmd["unacked"],
            cmd["duplicate_acks"], cmd["acks_without_command"]) == (2, 5, 3, 2, 0, 0, 0)
    assert sorted((c["command_id"], c["retransmissions"], c["latency_first_ms"]) for c in cmd["list"]) == [
        (5, 2, 220.0), (6, 1, 120.0)]


def test_the_same_id_after_the_reuse_gap_is_a_new_command(tmp_path):
    tr = Traffic()
    tr.add(0.0, payload(VRCO, 0, command_id=9), src=CTRL, sport=OUT)
    tr.add(0.1, payload(VRCO, 1, command_id=9), src=CTRL, sport=OUT)        # retransmission
    tr.add(0.105, payload(VRAI, 0, BU_ORIGIN, command_id=9))
    tr.add(2.7, payload(VRCO, 2, command_id=9), src=CTRL, sport=OUT)        # 2.6 s later: a new command
    tr.add(2.71, payload(VRAI, 1, BU_ORIGIN, command_id=9))
    cmd = _report(tr, tmp_path)["commands"]["VRCO"]
    assert (cmd["commands"], cmd["retransmissions"], cmd["acked"], cmd["spurious_retransmissions"],
            cmd["duplicate_acks"]) == (2, 1, 2, 0, 0)
    shorter = _report(tr, tmp_path, reuse_gap_ms=3000.0)["commands"]["VRCO"]
    assert (shorter["commands"], shorter["spurious_retransmissions"], shorter["duplicate_acks"]) == (1, 1, 1)


def test_a_mirror_copy_is_no_arrival(tmp_path):
    tr = Traffic()
    for k in range(10):
        tr.add(k * 0.125, vrpi(k))
        if k == 4:
            tr.add(k * 0.125 + 0.001, vrpi(k))          # the mirror port's copy, 1 ms later
    report = _report(tr, tmp_path)
    p = report["periodic"][0]
    assert _sender(report, f"{BU}:5825")["serial"]["duplicates"] == 1
    assert (p["count"], p["interval_ms"]["min"], p["jitter_ms"]["max"]) == (10, 125.0, 0.0)
    item = _finding(report, "duplicates")["items"][0]
    assert (item["frame"], item["serial"], item["filter"]) == (6, 4, "frame.number == 6")


def test_a_serial_seen_long_ago_is_no_duplicate(tmp_path):
    tr = Traffic()
    for k in range(5):
        tr.add(k * 0.125, vrpi(k))
    tr.add(2.0, vrpi(2))             # serial 2 last accepted 1.75 s ago: a restart candidate,
    tr.add(2.125, vrpi(9))           # not confirmed by 9: out of order
    ser = _sender(_report(tr, tmp_path), f"{BU}:5825")["serial"]
    assert (ser["duplicates"], ser["out_of_order"], ser["restarts"], ser["lost"]) == (0, 1, 0, 4)


def test_silence_to_the_end_is_a_watchdog_violation(tmp_path):
    tr = Traffic()
    for k in range(80):                                    # BU stops at 1.0 s
        if k * 0.125 <= 1.0:
            tr.add(k * 0.125, vrpi(k))
        tr.add(k * 0.1 + 0.05, payload(VRPO, k, packet_number=0, periodic_data=b"d" * 8), src=CTRL, sport=OUT)
    tr.frames.sort(key=lambda f: f[0])
    report = _report(tr, tmp_path)
    vrpi_stream = next(p for p in report["periodic"] if p["type"] == "VRPI")
    vrpo_stream = next(p for p in report["periodic"] if p["type"] == "VRPO")
    assert vrpi_stream["watchdog"]["violations"] == [
        {"start": T0 + 1.0, "gap_ms": 6950.0, "until_end": True, "frame": 19}]
    assert vrpo_stream["watchdog"]["violations"] == []
    item = _finding(report, "watchdog")["items"][0]
    assert (item["frame"], item["until_end"], item["type"]) == (19, True, "VRPI") and not report["verdict"]["ok"]


def _counter(tr: Traffic, times, serials, **kw) -> None:
    for t, s in zip(times, serials):
        tr.add(t, vrpi(s), **kw)


def test_a_confirmed_restart_starts_the_counter_afresh_and_interrupts_commands(tmp_path):
    tr = Traffic()
    _counter(tr, [k * 0.125 for k in range(20)], range(40000, 40020))       # above 32767
    tr.add(2.4, payload(VRCI, 40020, BU_ORIGIN, command_id=77))             # outstanding at the reboot
    _counter(tr, [3.5 + k * 0.125 for k in range(10)], [0, *range(2, 11)])  # rebooted: counter from 0
    tr.add(3.6, payload(VRCI, 1, BU_ORIGIN, command_id=77))                 # a new command, same ID
    tr.add(3.61, payload(VRAO, 0, command_id=77), src=CTRL, sport=OUT)
    tr.frames.sort(key=lambda f: f[0])
    report = _report(tr, tmp_path)
    ser = _sender(report, f"{BU}:5825")["serial"]
    assert (ser["restarts"], ser["duplicates"], ser["out_of_order"], ser["lost"]) == (1, 0, 0, 0)
    assert ser["restart_events"] == [{"time": T0 + 3.5, "frame": 22, "from": 40020, "to": 0}]
    cmd = report["commands"]["VRCI"]
    assert (cmd["commands"], cmd["interrupted"], cmd["acked"], cmd["unacked"], cmd["failed"]) == (2, 1, 1, 0, 0)
    assert [c["interrupted_frame"] for c in cmd["list"]] == [22, None]
    vrpi_stream = report["periodic"][0]
    assert [v["gap_ms"] for v in vrpi_stream["watchdog"]["violations"]] == [1125.0]   # the reboot's silence
    rules = {f["rule"] for f in report["verdict"]["findings"]}
    assert {"restarts", "interrupted"} <= rules and "unacked" not in rules


def test_a_long_outage_with_real_loss_is_loss(tmp_path):
    tr = Traffic()
    _counter(tr, [k * 0.125 for k in range(80)], range(80))                 # 8 packets/s for 10 s
    _counter(tr, [70.0 + k * 0.125 for k in range(5)], range(560, 565))     # 60 s later, 480 missed
    ser = _sender(_report(tr, tmp_path), f"{BU}:5825")["serial"]
    assert (ser["restarts"], ser["lost"], len(ser["gaps"])) == (0, 480, 1)


def test_a_jump_the_silence_cannot_explain_is_a_restart_when_confirmed(tmp_path):
    tr = Traffic()
    _counter(tr, [k * 0.125 for k in range(80)], range(80))
    _counter(tr, [13.0 + k * 0.125 for k in range(5)], range(25000, 25005))  # 3 s silent, 24,920 ahead
    ser = _sender(_report(tr, tmp_path), f"{BU}:5825")["serial"]
    assert (ser["restarts"], ser["lost"], ser["restart_events"][0]["from"], ser["restart_events"][0]["to"]) == (
        1, 0, 79, 25000)


def test_a_restart_on_a_new_port(tmp_path):
    tr = Traffic()
    for k in range(30):                                     # the BU's VRPI throughout
        tr.add(k * 0.125, vrpi(k))
    for k in range(8):                                      # controller on port 40001 until 0.75 s
        tr.add(0.05 + k * 0.1, payload(VRPO, 100 + k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40001)
    tr.add(0.7, payload(VRCO, 108, command_id=3), src=CTRL, sport=40001)     # never acked: interrupted
    for k in range(10):                                     # the restarted program, new port, from 1.25 s
        tr.add(1.25 + k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40777)
    tr.frames.sort(key=lambda f: f[0])
    report = _report(tr, tmp_path)
    new = _sender(report, f"{CTRL}:40777")["serial"]
    first = next(i for i, f in enumerate(tr.frames, 1) if f[2] == 40777)
    assert new["restart_events"] == [{"time": T0 + 1.25, "frame": first, "from": 108, "to": 0,
                                      "port_from": 40001, "port_to": 40777}]
    assert _sender(report, f"{CTRL}:40001")["serial"]["restarts"] == 0
    old_stream = next(p for p in report["periodic"] if p["sender"].startswith(f"Output {CTRL}:40001"))
    new_stream = next(p for p in report["periodic"] if p["sender"].startswith(f"Output {CTRL}:40777"))
    assert old_stream["watchdog"]["violations"] == []                        # taken over: no silence to the end
    assert (new_stream["count"], new_stream["interval_ms"]["max"]) == (10, 500.0)   # from 0.75 s to 1.25 s
    cmd = report["commands"]["VRCO"]
    assert (cmd["commands"], cmd["interrupted"], cmd["unacked"]) == (1, 1, 0)


def _moves(tr: Traffic, second_move: float) -> list[int]:
    """A controller on port 5827 until 9.9 s, restarted on port 40001 at 10.3 s (one packet), then
    on port 40002 at `second_move`; returns the first frame on each port."""
    for k in range(100):
        tr.add(k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=OUT)
    tr.add(10.3, payload(VRPO, 0, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40001)
    for k in range(30):
        tr.add(second_move + k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40002)
    return [1, 101, 102]


def test_a_sender_that_moves_on_links_to_the_port_it_moved_from(tmp_path):
    """Moved 5827 -> 40001 -> 40002, each port silent at least 250 ms before the next begins: two
    restarts, each from the port before (interpretation.md, "A new source port")."""
    tr = Traffic()
    _, second, third = _moves(tr, 10.7)
    report = _report(tr, tmp_path)
    events = {s["src"]: [(e["frame"], e["port_from"], e["port_to"]) for e in s["serial"]["restart_events"]]
              for s in report["senders"]}
    assert events == {f"{CTRL}:{OUT}": [], f"{CTRL}:40001": [(second, OUT, 40001)],
                      f"{CTRL}:40002": [(third, 40001, 40002)]}


def test_a_port_already_moved_from_is_never_restarted_again(tmp_path):
    """Moved 5827 -> 40001, and 150 ms after the one packet on 40001 a sender on 40002 begins:
    40001 has not been silent 250 ms, so 40002 is no restart of it (interpretation.md), and 5827
    (silent 450 ms) moved on to 40001 already and lives on there: no restart of it either (a trial
    linked 40002 back to 5827, past the port it came from). 40001 then falls silent to the end."""
    tr = Traffic()
    _, second, _ = _moves(tr, 10.45)
    report = _report(tr, tmp_path)
    events = {s["src"]: [(e["frame"], e["port_from"], e["port_to"]) for e in s["serial"]["restart_events"]]
              for s in report["senders"]}
    assert events == {f"{CTRL}:{OUT}": [], f"{CTRL}:40001": [(second, OUT, 40001)], f"{CTRL}:40002": []}
    silent = _stream(report, "VRPO", f"{CTRL}:40001")["watchdog"]["violations"]
    assert [(v["frame"], v["until_end"]) for v in silent] == [(second, True)]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_the_dissector_never_restarts_a_port_already_moved_from(tshark, tmp_path):
    """Where analyze and the dissector count the same thing they agree: in Wireshark too, the only
    restart is 5827 -> 40001."""
    tr = Traffic()
    _, second, _ = _moves(tr, 10.45)
    with tshark.workspace(tmp_path / "ws") as ws:
        tr.write(ws.dir / "t.pcap")
        done = ws.run(["-r", str(ws.dir / "t.pcap"), "-Y", "vm110.analysis.restart_port_from", "-T", "fields",
                       "-e", "frame.number", "-e", "vm110.analysis.restart_port_from"])
    assert [line.split("\t") for line in done.stdout.splitlines()] == [[str(second), str(OUT)]]


def test_a_new_sender_beside_a_live_one_is_no_restart(tmp_path):
    tr = Traffic()
    for k in range(10):
        tr.add(k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40001)
        tr.add(0.5 + k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"a"), src=CTRL, sport=40002)
    tr.frames.sort(key=lambda f: f[0])
    report = _report(tr, tmp_path)
    assert [s["serial"]["restarts"] for s in report["senders"]] == [0, 0]


def test_findings_are_located_and_capped(tmp_path):
    tr = Traffic()
    serial = 0
    for k in range(300):
        tr.add(k * 0.125, vrpi(serial))
        serial += 2                                          # every other serial lost: 299 gaps
    report = _report(tr, tmp_path)
    lost = _finding(report, "lost")
    assert (lost["count"], len(lost["items"]), lost["more"]) == (299, 100, 199)
    first = lost["items"][0]
    assert {k: first[k] for k in ("frame", "after", "count", "serial", "filter")} == {
        "frame": 2, "after": 0, "count": 1, "serial": 2, "filter": "frame.number == 2"}
    assert first["sender"] == report["senders"][0]["id"] and first["time"] == T0 + 0.125


def test_a_count_of_one_reads_in_the_singular(tmp_path):
    """"1 packets lost", "1 duplicated packets" (trial): one of a kind reads in the singular."""
    tr = Traffic()
    for k in (0, 1, 2, 4, 5, 5, 6, 7):                       # serial 3 lost, 5 twice
        tr.add(k * 0.125 + (0.001 if k == 5 and len(tr.frames) == 6 else 0), vrpi(k))
    from vm110.analysis import summary
    report = _report(tr, tmp_path)
    messages = {f["rule"]: f["message"] for f in report["verdict"]["findings"]}
    assert messages["lost"] == "1 packet lost (serial gaps)" and messages["duplicates"] == "1 duplicated packet"
    severities = sorted(f["severity"] for f in report["verdict"]["findings"])
    assert severities == ["error", "warning"]
    assert "VERDICT: FAIL (1 error, 1 warning)" in summary.render(report)


def test_a_finding_beyond_the_kept_items_says_where_all_of_them_are(tmp_path):
    from vm110.analysis import report_html, summary
    tr = Traffic()
    for k in range(150):
        tr.add(k * 0.125, vrpi(k))
        tr.add(k * 0.125 + 0.001, vrpi(k))                  # each packet twice: 150 duplicates
    tr.add(150 * 0.125, vrpi(152))                           # and 2 lost
    report = _report(tr, tmp_path)
    dup = _finding(report, "duplicates")
    assert (dup["count"], len(dup["items"]), dup["more"], dup["filter"]) == (
        150, 100, 50, "vm110.expert.serial_duplicate")
    assert "filter" not in _finding(report, "lost"), "the dissector also marks gaps filled later"
    text = summary.render(report)
    assert ("... 147 more (--list, or the JSON report: the first 100; all of them in Wireshark: "
            "[vm110.expert.serial_duplicate])") in text
    assert "... 50 more (all of them in Wireshark: [vm110.expert.serial_duplicate])" in summary.render(report, True)
    assert ('… 50 more (all of them in Wireshark: <code class="filter">vm110.expert.serial_duplicate</code>)'
            in report_html.render([report]))
    # Options the dissector's defaults do not share: the filter goes with the preferences that do.
    other = _report(tr, tmp_path, dup_window_ms=500.0)
    assert _finding(other, "duplicates")["filter"] and other["verdict"]["wireshark_prefs"] == ["vm110.dup_window_ms:500"]
    assert ("... 50 more (all of them in Wireshark (with -o vm110.dup_window_ms:500): "
            "[vm110.expert.serial_duplicate])") in summary.render(other, True)
    # A window no preference takes (they are whole milliseconds): no filter.
    fraction = _report(tr, tmp_path, dup_window_ms=500.5)
    assert "filter" not in _finding(fraction, "duplicates") and "wireshark_prefs" not in fraction["verdict"]
    assert "... 50 more (the report keeps the first 100)" in summary.render(fraction, True)
    # (without --list the first 100 are named once: it said "...: the first 100; the report keeps the first 100")
    assert "            ... 147 more (--list, or the JSON report: the first 100)" in summary.render(fraction).splitlines()
    why = "dup_window_ms is 500.5, and the dissector's vm110.dup_window_ms takes whole milliseconds"
    assert fraction["verdict"]["no_filters"] == why and "no_filters" not in other["verdict"]
    assert f"  No Wireshark filter for the rules: {why}" in summary.render(fraction).splitlines()
    assert f"<p>No Wireshark filter for the rules: {html.escape(why)}</p>" in report_html.render([fraction])
    # Other ports: the dissector's input port preference.
    moved = Traffic()
    for t, _, sport, _, data in tr.frames:
        moved.add(t - T0, data, sport=sport + 1000)
    moved.write(tmp_path / "moved.pcap")
    report = analyze(str(tmp_path / "moved.pcap"), port=C.INPUT_PORT + 1000, options=Options(serial_scope="sender"))
    assert _finding(report, "duplicates")["count"] == 150 and _finding(report, "duplicates")["filter"]
    assert report["verdict"]["wireshark_prefs"] == [f"vm110.input_port:{C.INPUT_PORT + 1000}"]


def test_html_and_terminal_show_where_findings_lie(tmp_path):
    from vm110.analysis import report_html, summary
    tr = Traffic()
    for k in range(20):
        tr.add(k * 0.125, vrpi(k if k < 10 else k + 3))          # 3 lost before frame 11
    report = _report(tr, tmp_path)
    page = report_html.render([report])
    row = re.search(r'<tr><td class="error">lost</td><td>11</td><td>\+1\.250000</td>.*?</tr>', page)
    assert row and '<code class="filter">frame.number == 11</code>' in row.group(0) and "count 3" in row.group(0)
    assert "restarts" in page and "interrupted" in page
    text = summary.render(report)
    assert "frame 11 at +1.250000 s:" in text and "count 3" in text and "[frame.number == 11]" in text


def test_a_restart_to_serial_0_shows_its_to(tmp_path):
    from vm110.analysis import report_html, summary
    tr = Traffic()
    _counter(tr, [k * 0.125 for k in range(8)], range(500, 508))
    _counter(tr, [3.0 + k * 0.125 for k in range(4)], range(4))
    report = _report(tr, tmp_path)
    assert "serial 507 -> 0" in summary.render(report)
    assert "from 507, to 0" in summary.render(report) and "from 507, to 0" in report_html.render([report])


def test_findings_with_a_damaged_timestamp_still_render(tmp_path):
    """A non-finite time is null in the report (self-fuzz found the summary failing on it)."""
    from vm110.analysis import report_html, summary
    tr = Traffic()
    _counter(tr, [0.0, 0.125, 0.25], [0, 5, 6])
    report = _report(tr, tmp_path)
    _finding(report, "lost")["items"][0]["time"] = None
    assert "frame 2 at - s:" in summary.render(report)
    assert "<td>-</td>" in report_html.render([report])


def test_copies_of_an_undecided_candidate_cost_no_memory(tmp_path):
    """A restart candidate waits for its next packet; copies of it within its duplicate window
    are duplicates whatever it turns out to be: judged at once, not held, so a flood of them
    stays cheap and flat."""
    tr = Traffic()
    _counter(tr, [k * 0.125 for k in range(8)], range(500, 508))
    copies = 3_000
    _counter(tr, [3.0 + k * 0.0002 for k in range(copies + 1)], [0] * (copies + 1))     # 0.6 s of copies
    _counter(tr, [3.7, 3.8], [1, 2])                                                    # confirmed
    report = _report(tr, tmp_path)
    ser = _sender(report, f"{BU}:5825")["serial"]
    assert (ser["restarts"], ser["duplicates"], ser["out_of_order"]) == (1, copies, 0)
    assert ser["restart_events"][0]["frame"] == 9 and report["periodic"][0]["count"] == 11


def test_a_long_command_acked_late_is_a_report_its_schema_admits(tmp_path):
    """A VRCI resent 70 times, then acknowledged: its `failed` item's filter (once a narrowed range
    in parentheses, which the schema's filter pattern refused: trial) validates against `vm110
    analyze --schema`; its consecutive frames are one range."""
    tr = Traffic()
    for k in range(70):
        tr.add(k * 0.1, payload(VRCI, k, BU_ORIGIN, command_id=7))
    ack = tr.add(7.0, payload(VRAO, 0, command_id=7), src=CTRL, sport=OUT)
    [item] = _finding(_report(tr, tmp_path), "failed")["items"]     # conftest holds it to the schema
    assert item["filter"] == f"frame.number in {{1..{ack}}}"


@pytest.mark.parametrize("window", [1000.0, 2000.0])
def test_a_long_command_s_filter_shows_exactly_its_frames_in_wireshark(tmp_path, window):
    """A VRCI resent 70 times, then acknowledged; a mirror copies three transmissions 1.55 s
    late, and one copy arrives with a bad CRC. The item's filter, in Wireshark with its
    default preferences, shows exactly the item's frames: the transmissions the analysis accepted
    (the late copies too, unless a duplicate window of 2 s makes them duplicates) and the ack. It
    once narrowed a frame range by `!vm110.analysis.serial_duplicate`, which depends on Wireshark's
    duplicate window, and showed the illegal copy besides (a packet the analysis never took)."""
    sent = [(k * 0.1, k, {}) for k in range(70)] + [(k * 0.1 + 1.55, k, {}) for k in (0, 3, 6)]
    sent.append((3.05, 30, {"crc": 0}))
    tr = Traffic()
    frames = {"sent": [], "late": []}
    for t, k, force in sorted(sent, key=lambda x: x[0]):
        frame = tr.add(t, payload(VRCI, k, BU_ORIGIN, command_id=7, **force))
        if not force:
            frames["sent" if len(frames["sent"]) == k else "late"].append(frame)
    ack = tr.add(7.0, payload(VRAO, 0, command_id=7), src=CTRL, sport=OUT)
    [item] = _finding(_report(tr, tmp_path, dup_window_ms=window), "failed")["items"]
    want = frames["sent"] + (frames["late"] if window == 1000.0 else []) + [ack]
    assert sorted(item["frames"]) == sorted(want)
    runner = next(r for r in T.RUNNERS if r.root is None)
    with runner.workspace(tmp_path / "ws") as ws:
        tr.write(ws.dir / "t.pcap")
        done = ws.run(["-r", str(ws.dir / "t.pcap"), "-Y", item["filter"], "-T", "fields", "-e", "frame.number"])
    assert [int(f) for f in done.stdout.split()] == sorted(want)


def test_a_watchdog_item_says_its_frame_ends_the_silence(tmp_path):
    """The item names the packet after the silence and the time the silence began: "frame 9 at
    +1.000 s" read as one event, and frame 9 is at +3.5 s (trials, twice)."""
    from vm110.analysis import summary
    tr = Traffic()
    for k, t in enumerate([i * 0.125 for i in range(9)] + [3.5 + i * 0.125 for i in range(8)]):
        tr.add(t, vrpi(k))
    report = _report(tr, tmp_path)
    [item] = [i for f in report["verdict"]["findings"] if f["rule"] == "watchdog" for i in f["items"]]
    assert (item["frame"], item["time"] - T0, item["until_end"]) == (10, 1.0, False)
    assert "frame 10 ends a silence from +1.000000 s:" in summary.render(report)


def test_a_command_still_in_flight_at_the_end_has_not_failed(tmp_path):
    """Two VRCI never acknowledged: one sent 2.5 s before the capture ends (past the 2000 ms limit:
    failed), one 5 ms before (unacked, not failed: the capture cannot tell; it was failed)."""
    tr = Traffic()
    for k in range(41):
        tr.add(k * 0.125, vrpi(k))
    tr.add(2.5, payload(VRCI, 100, BU_ORIGIN, command_id=1))
    tr.add(4.995, payload(VRCI, 101, BU_ORIGIN, command_id=2))
    tr.frames.sort(key=lambda f: f[0])
    report = _report(tr, tmp_path)
    vrci = report["commands"]["VRCI"]
    assert (vrci["commands"], vrci["unacked"], vrci["failed"]) == (2, 2, 1)
    assert [(c["command_id"], c["failed"]) for c in vrci["list"]] == [(1, True), (2, False)]
    assert [i["command_id"] for i in _finding(report, "failed")["items"]] == [1]
    assert report["totals"]["failed"] == 1
