"""The fast engine on a crafted capture whose every impairment the test put there itself."""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from scapy.packet import Raw

from test_analysis_craft import BU, BU_ORIGIN, CTRL, T0, Traffic, payload, vrpi
from vm110 import constants as C
from vm110.analysis import analyze
from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPO

BU_ID = f"Input {BU}:{C.INPUT_PORT} origin 0x{BU_ORIGIN:04x}"
CTRL_ID = f"Output {CTRL}:{C.OUTPUT_PORT} origin 0x0000"
OTHER_BU, OTHER_PORT, OTHER_ORIGIN = "10.0.0.11", 6000, 0x0202


def jitter_reference(times: list, period_ms: float) -> tuple:
    """RFC 3550 form, written out plainly: J += (|D| - J)/16 per pair of consecutive packets."""
    j, history = 0.0, []
    for a, b in itertools.pairwise(times):
        delta = (b - a) * 1000.0
        k = max(1, math.floor(delta / period_ms + 0.5))
        j += (abs(delta - k * period_ms) - j) / 16.0
        history.append(j)
    return j, sum(history) / len(history), max(history)


def build_mixed(path) -> dict:
    """The scenario; returns facts the test checks against (serials, times)."""
    tr = Traffic()
    bu = {"serial": 0}
    ctrl = {"serial": 0}
    facts = {"vrpi_times": [], "bu_lost": [], "bu_gap_after": []}

    def bu_next() -> int:
        s = bu["serial"]
        bu["serial"] += 1
        return s

    def ctrl_next() -> int:
        s = ctrl["serial"]
        ctrl["serial"] += 1
        return s

    events = []   # (time, kind, args): built first, serials assigned in time order
    for i in range(80):
        if 40 <= i <= 44:
            continue                                  # base unit stalls: VRPI watchdog
        events.append((0.125 * i, "vrpi", i))
    for k in range(3):
        events.append((1.01 + 0.1 * k, "vrci", 7))
    events.append((1.24, "vrao", 7))
    events.append((1.31, "vrci", 7))                  # spurious: after the ack
    events.append((1.35, "vrao", 7))                  # duplicate ack
    for k in range(21):
        events.append((2.01 + 0.1 * k, "vrci", 8))    # never acknowledged
    for k in range(21):
        events.append((6.01 + 0.1 * k, "vrci", 9))    # acknowledged after 2040 ms: failed
    events.append((8.05, "vrao", 9))
    events.append((9.0, "vrao", 50))                  # nothing to acknowledge
    events += [(3.0, "vrco", 65535), (3.1, "vrco", 65535), (3.15, "vrai", 65535),
               (3.5, "vrco", 0), (3.52, "vrai", 0)]
    for i in range(100):
        t = 0.05 + 0.1 * i
        if i == 50:
            events += [(t, "vrpo", (0, 488)), (t + 0.001, "vrpo", (1, 488)), (t + 0.002, "vrpo", (2, 100))]
        elif i == 60:
            events += [(t, "vrpo", (0, 488)), (t + 0.001, "vrpo_bad", (1, 488)), (t + 0.002, "vrpo", (2, 100))]
        else:
            events.append((t, "vrpo", (0, 20)))
    events.sort(key=lambda e: e[0])

    swapped = {}
    for t, kind, arg in events:
        if kind == "vrpi":
            i = arg
            s = bu_next()
            state = C.BuState.STOPPED if 50 <= i <= 55 else C.BuState.ARMED
            if i == 10:
                facts["bu_lost"].append(s)
                continue                              # lost on the way
            if i == 70:
                facts["bu_lost"].append(s)
                tr.add(t, vrpi(s, revision=1, bu_state=state))   # illegal: revision
                continue
            if i == 36:
                swapped[36] = (t, s, state)
                continue                              # sent after i = 37: out of order
            data = vrpi(s, bu_state=state, ru_battery=80 - i // 10)
            if i == 37:
                t30, s30, st30 = swapped[36]
                tr.add(t30, data)                     # serial s arrives first, at i = 36's time
                tr.add(t, vrpi(s30, bu_state=st30, ru_battery=80 - 3))
                facts["vrpi_times"] += [T0 + t30, T0 + t]
                continue
            tr.add(t, data)
            facts["vrpi_times"].append(T0 + t)
            if i == 20:
                tr.add(t + 0.0002, data)              # the network duplicated it: no arrival
        elif kind == "vrci":
            tr.add(t, payload(VRCI, bu_next(), BU_ORIGIN, command_id=arg))
        elif kind == "vrai":
            tr.add(t, payload(VRAI, bu_next(), BU_ORIGIN, command_id=arg))
        elif kind == "vrao":
            tr.add(t, payload(VRAO, ctrl_next(), command_id=arg), src=CTRL, sport=C.OUTPUT_PORT)
        elif kind == "vrco":
            tr.add(t, payload(VRCO, ctrl_next(), command_id=arg), src=CTRL, sport=C.OUTPUT_PORT)
        else:
            number, size = arg
            data = payload(VRPO, ctrl_next(), packet_number=number, periodic_data=bytes(size))
            if kind == "vrpo_bad":
                data = data[:-1] + bytes([data[-1] ^ 0xFF])      # corrupted CRC
            tr.add(t, data, src=CTRL, sport=C.OUTPUT_PORT)
    # Illegal packets that belong to no counter, another base unit on another port, other traffic.
    with_raw = VM110(type=b"VRXX", serial=999, origin=BU_ORIGIN) / Raw(b"\0" * 4)
    tr.add(7.0, bytes(with_raw))
    tr.add(7.1, payload(VRAI, 998, BU_ORIGIN, size=3, command_id=1))
    for i in range(10):
        tr.add(0.02 + 0.125 * i, vrpi(i, OTHER_ORIGIN), src=OTHER_BU, sport=OTHER_PORT)
    tr.add(0.5, b"\x12\x34" + bytes(30), src="10.0.0.30", sport=53)
    tr.frames.sort(key=lambda f: f[0])
    tr.write(path)
    facts["frames"] = len(tr.frames)
    return facts


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    path = tmp_path_factory.mktemp("mixed") / "mixed.pcap"
    facts = build_mixed(path)
    return analyze(str(path)), facts


def _sender(report, sid):
    return next(s for s in report["senders"] if s["id"] == sid)


def _periodic(report, ptype, sid):
    return next(p for p in report["periodic"] if p["type"] == ptype and p["sender"] == sid)


def test_capture_and_crc(mixed):
    report, facts = mixed
    cap = report["capture"]
    assert cap["packets"] == facts["frames"]
    assert cap["other_udp_packets"] == 1
    assert cap["eglink_packets"] == facts["frames"] - 1
    assert report["crc"] == {**report["crc"], "variant": "mpeg2", "byte_order": "little",
                             "invalid": 1, "valid": facts["frames"] - 1 - 1}
    assert report["illegal"]["total"] == 4
    assert report["illegal"]["by_reason"] == {"bad_crc": 1, "revision": 1, "size_mismatch": 1, "unknown_id": 1}


def test_serials_of_the_base_unit(mixed):
    report, facts = mixed
    snd = _sender(report, BU_ID)
    assert snd["by_type"] == {"VRAI": 2, "VRCI": 46, "VRPI": 74}
    ser = snd["serial"]
    assert ser["scope"] == "sender"
    assert (ser["received"], ser["lost"], ser["duplicates"], ser["out_of_order"]) == (122, 2, 1, 1)
    assert sorted(ser["lost_serials"]) == sorted(facts["bu_lost"])
    assert [g["count"] for g in ser["gaps"]] == [1, 1, 1]
    assert ser["gaps"][0]["after"] == facts["bu_lost"][0] - 1


def test_other_senders(mixed):
    report, _ = mixed
    ids = [s["id"] for s in report["senders"]]
    assert ids == sorted(ids) and len(ids) == 3
    other = _sender(report, f"Input {OTHER_BU}:{OTHER_PORT} origin 0x{OTHER_ORIGIN:04x}")
    assert other["by_type"] == {"VRPI": 10} and other["serial"]["lost"] == 0
    ctrl = _sender(report, CTRL_ID)
    assert ctrl["by_type"] == {"VRAO": 4, "VRCO": 3, "VRPO": 103}
    assert ctrl["serial"]["lost"] == 1     # the corrupted VRPO's serial


def test_periodic_streams(mixed):
    report, facts = mixed
    p = _periodic(report, "VRPI", BU_ID)
    assert p["count"] == 73                           # the duplicate is no arrival (docs/rules.md)
    assert [{k: v[k] for k in ("start", "gap_ms", "until_end")} for v in p["watchdog"]["violations"]] == [
        {"start": T0 + 4.875, "gap_ms": 750.0, "until_end": False}]
    assert p["interval_ms"]["max"] == 750.0 and p["interval_ms"]["min"] == 125.0
    final, mean, peak = jitter_reference(facts["vrpi_times"], C.VRPI_PERIOD_MS)
    assert p["jitter_ms"]["final"] == pytest.approx(final, abs=1e-3)
    assert p["jitter_ms"]["mean"] == pytest.approx(mean, abs=1e-3)
    assert p["jitter_ms"]["max"] == pytest.approx(peak, abs=1e-3)
    vrpo = _periodic(report, "VRPO", CTRL_ID)
    assert vrpo["watchdog"]["violations"] == [] and vrpo["count"] == 103
    assert vrpo["nominal_ms"] == 100 and vrpo["outside_recommended"]["count"] == 0
    assert report["vrpo_bursts"]["complete"] == 99 and report["vrpo_bursts"]["incomplete"] == 1


def test_commands(mixed):
    report, _ = mixed
    vrci = report["commands"]["VRCI"]
    expect = {"commands": 3, "transmissions": 46, "retransmissions": 43, "acked": 2, "unacked": 1,
              "failed": 2, "spurious_retransmissions": 1, "acks_without_command": 1, "duplicate_acks": 1}
    assert {k: vrci[k] for k in expect} == expect
    assert vrci["ack_latency_ms"] == {"min": 230.0, "p50": 1135.0, "p95": 1949.5, "max": 2040.0}
    assert [c["latency_last_ms"] for c in vrci["list"]] == [30.0, None, 40.0]
    assert [len(c["frames"]) for c in vrci["list"]] == [4, 21, 21]
    assert vrci["retransmission_histogram"] == {"3": 1, "20": 2}
    vrco = report["commands"]["VRCO"]
    assert {k: vrco[k] for k in ("commands", "transmissions", "retransmissions", "acked", "unacked", "failed",
                                 "command_id_wraps")} == {
        "commands": 2, "transmissions": 3, "retransmissions": 1, "acked": 2, "unacked": 0, "failed": 0,
        "command_id_wraps": 1}
    assert vrco["ack_latency_ms"]["min"] == 20.0 and vrco["ack_latency_ms"]["max"] == 150.0


def test_state_timeline_and_verdict(mixed):
    report, _ = mixed
    st = next(s for s in report["state"] if s["sender"] == BU_ID)
    episodes = st["episodes_relays_open"]
    assert [(e["start"], e["end"], e["states"]) for e in episodes] == [(T0 + 6.25, T0 + 7.0, ["Stopped"])]
    assert st["ru_battery"]["min"] == 73 and st["ru_battery"]["max"] == 80
    assert [s["name"] for s in st["segments"]["bu_state"]] == ["Armed", "Stopped", "Armed"]
    rules = {f["rule"] for f in report["verdict"]["findings"]}
    assert {"lost", "illegal", "watchdog", "failed", "unacked", "relays_open", "duplicates"} <= rules
    assert report["verdict"]["ok"] is False
    # The base unit's stall, and the other base unit silent from 1.145 s to the end of the capture.
    assert report["totals"]["watchdog"] == 2 and report["totals"]["lost"] == 3
    other = next(p for p in report["periodic"] if p["sender"].startswith(f"Input {OTHER_BU}"))
    assert [v["until_end"] for v in other["watchdog"]["violations"]] == [True]


def test_pcapng_gives_the_same_report(mixed, tmp_path):
    report, _ = mixed
    path = tmp_path / "mixed.pcapng"
    tr_path = tmp_path / "again.pcap"
    build_mixed(tr_path)
    # Same frames rewritten as pcapng by scapy (independent writer).
    from scapy.utils import PcapNgWriter, rdpcap
    frames = rdpcap(str(tr_path))
    with PcapNgWriter(str(path)) as out:
        for f in frames:
            out.write(f)
    again = analyze(str(path))
    strip = ("capture", "tool")
    assert {k: v for k, v in again.items() if k not in strip} == {k: v for k, v in report.items() if k not in strip}
    assert again["capture"]["format"] == "pcapng" and again["capture"]["packets"] == report["capture"]["packets"]


def test_crc_candidates_are_counted_alike_on_ipv6(tmp_path):
    """A packet valid under the chosen CRC counts for it only, on IPv6 (off the hot path) as on
    IPv4: restart.pcapng has one that a second variant validates too (frame 750, bzip2/big)."""
    from scapy.layers.inet import IP, UDP
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import Ether
    from scapy.utils import rdpcap, wrpcap
    original = Path(__file__).resolve().parents[1] / "captures" / "restart.pcapng"
    moved = []
    for pkt in rdpcap(str(original)):
        udp = pkt[UDP]
        again = Ether() / IPv6(src="fd00::" + pkt[IP].src.rsplit(".", 1)[1], dst="ff02::1") / UDP(
            sport=udp.sport, dport=udp.dport) / bytes(udp.payload)[:udp.len - 8]
        again.time = pkt.time
        moved.append(again)
    wrpcap(str(tmp_path / "v6.pcap"), moved)
    v4, v6 = analyze(str(original)), analyze(str(tmp_path / "v6.pcap"))
    assert v6["crc"] == v4["crc"] and v4["crc"]["candidates"] == {"mpeg2/little": v4["crc"]["valid"]}
