"""Stream analysis of dissector/vm110.lua (issue 4) against the synthesizer's ground truth.

Every capture of captures/ with a `.truth.json` (computed by `vm110 synth` from its own event log,
not by decoding) goes through real tshark once per tshark version, in two passes (`-2`, as the GUI
shows a loaded file); each generated field and expert is checked against the truth: serial gaps
at detection time, duplicates, late packets and the resulting lost serials per sender, watchdog
violations, every retransmission linked to its first transmission, every ack to its command,
unacknowledged and failed commands, VRPO bursts, and the reassembled data byte for byte (the
expected bytes re-derived from the capture with `vm110.decode`).
"""
from __future__ import annotations

import functools
import json
import random
import re
import subprocess
import sys
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import pytest
from scapy.layers.inet import UDP
from scapy.utils import rdpcap

import tshark_runner as T
from vm110 import constants as C
from vm110.analysis import analyze
from vm110.analysis.report import Options
from vm110.analysis.findings import FINDINGS, RULE_FILTERS
from vm110.decode import decode

pytestmark = pytest.mark.tshark

CAPTURES = T.REPO / "captures"
TRUTH_CAPTURES = sorted(p for p in CAPTURES.iterdir()
                        if p.suffix in (".pcap", ".pcapng") and Path(f"{p}.truth.json").exists())
ANALYSIS_FIELDS = (
    "analysis.serial_missing", "analysis.serial_duplicate", "analysis.serial_out_of_order", "analysis.interval",
    "analysis.retransmission_of", "analysis.retransmission_number", "analysis.since_first",
    "analysis.ack_in", "analysis.ack_to", "analysis.ack_time", "analysis.ack_time_last",
    "analysis.restart", "analysis.restart_port_from", "analysis.silent_until_end", "analysis.interrupted_by",
    "analysis.burst_interval", "burst.packets", "burst.frame", "burst.complete", "reassembled")
FIELDS = ("frame.number", "frame.time_epoch", "ip.src", "udp.srcport", "vm110.type", "vm110.origin",
          "vm110.serial", "vm110.command_id", "vm110.packet_number",
          *(f"vm110.{f}" for f in ANALYSIS_FIELDS), *(f"vm110.expert.{c}" for c in sorted(T.ANALYSIS_EXPERTS)),
          *(f"vm110.expert.{c}" for c in sorted(T.PROBLEM_CODES)))
ON = {"vm110.analysis": "TRUE"}


@dataclass
class Row:
    values: dict

    def get(self, name: str) -> str:
        return self.values.get(name, "")

    def int(self, name: str) -> Optional[int]:
        text = self.get(name).split("|")[0]
        return int(text, 0) if text else None

    def float(self, name: str) -> Optional[float]:
        text = self.get(name)
        return float(text) if text else None

    def has(self, expert: str) -> bool:
        return bool(self.get(f"vm110.expert.{expert}"))

    @property
    def legal(self) -> bool:
        return bool(self.get("vm110.type")) and not any(self.has(c) for c in T.PROBLEM_CODES)

    @property
    def number(self) -> int:
        return int(self.get("frame.number"))

    @property
    def time(self) -> float:
        return float(self.get("frame.time_epoch"))

    @property
    def sender(self) -> str:
        direction = "Input" if self.get("vm110.type").endswith("I") else "Output"
        return f"{direction} {self.get('ip.src')}:{self.get('udp.srcport')} origin 0x{self.int('vm110.origin'):04x}"


def field_args(fields=FIELDS) -> list[str]:
    return ["-T", "fields", "-E", "aggregator=|", "-E", "occurrence=a", *(a for f in fields for a in ("-e", f))]


def run_fields(ws: T.Workspace, capture: Path, extra=(), prefs=ON, fields=FIELDS,
               shared: bool = False) -> tuple[list[Row], str]:
    local = ws.dir / capture.name
    if not local.exists():
        local.write_bytes(capture.read_bytes())
    proc = ws.run(["-r", str(local), *T.pref_args(prefs), *extra, *field_args(fields)], shared=shared)
    assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-2000:]
    rows = []
    for line in proc.stdout.splitlines():
        rows.append(Row(dict(zip(fields, line.split("\t")))))
    return rows, proc.stdout


_CACHE: dict = {}


def dissected(runner: T.Tshark, capture: Path, base: Path) -> list[Row]:
    key = (runner.name, capture.name)
    if key not in _CACHE:
        try:
            with runner.workspace(base) as ws:
                _CACHE[key] = run_fields(ws, capture, ["-2"], shared=True)[0]
        except T.TsharkUnavailable as exc:
            pytest.fail(str(exc))
    return _CACHE[key]


def eg_rows(rows: list[Row]) -> list[Row]:
    return [r for r in rows if r.get("vm110.type")]


def legal_rows(rows: list[Row]) -> list[Row]:
    return [r for r in rows if r.legal]


# --- Serial numbers -------------------------------------------------------------------------------
def serial_view(rows: list[Row]) -> dict:
    """Per sender: gaps at detection, duplicates, late serials and the serials still lost, from the
    generated fields alone (a late packet removes its serial from the lost ones and counts as late
    on the latest gap that left it missing)."""
    out = defaultdict(lambda: {"gaps": [], "duplicate_serials": [], "out_of_order_serials": [], "missing": Counter(),
                               "restart_events": [], "gap_of": {}})
    for r in legal_rows(rows):
        missing = r.int("vm110.analysis.serial_missing")
        v, serial = out[r.sender], r.int("vm110.serial")
        if r.get("vm110.analysis.restart"):
            event = {"time": round(r.time, 6), "frame": r.number, "from": r.int("vm110.analysis.restart"),
                     "to": serial}
            if r.get("vm110.analysis.restart_port_from"):
                event.update(port_from=r.int("vm110.analysis.restart_port_from"), port_to=int(r.get("udp.srcport")))
            v["restart_events"].append(event)
            assert r.has("restart")
        if missing:
            after = (serial - missing - 1) % C.SERIAL_MODULUS
            gap = {"after": after, "count": missing, "time": round(r.time, 6), "frame": r.number}
            v["gaps"].append(gap)
            for k in range(1, missing + 1):
                v["missing"][(after + k) % C.SERIAL_MODULUS] += 1
                v["gap_of"][(after + k) % C.SERIAL_MODULUS] = gap
            assert r.has("serial_gap")
        if r.get("vm110.analysis.serial_duplicate"):
            v["duplicate_serials"].append(serial)
            assert r.has("serial_duplicate")
        if r.get("vm110.analysis.serial_out_of_order"):
            v["out_of_order_serials"].append(serial)
            assert r.has("serial_out_of_order")
            if v["missing"][serial]:
                v["missing"][serial] -= 1
                gap = v["gap_of"].pop(serial, None)   # (None: its number came round since: lost for good)
                if gap is not None:
                    gap["late"] = gap.get("late", 0) + 1
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_serials(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    view = serial_view(dissected(tshark, capture, tmp_path))
    assert sorted(view) == sorted(s["id"] for s in truth["senders"])
    for sender in truth["senders"]:
        want, got = sender["serial"], view[sender["id"]]
        assert like(got["gaps"], want["gaps"]), sender["id"]
        assert got["duplicate_serials"] == want["duplicate_serials"], sender["id"]
        assert got["out_of_order_serials"] == want["out_of_order_serials"], sender["id"]
        lost = sorted(got["missing"].elements())
        assert len(lost) == want["lost"], sender["id"]
        if "lost_serials" in want:
            assert lost == sorted(s % C.SERIAL_MODULUS for s in want["lost_serials"]), sender["id"]
        events = [{**e, "time": round(e["time"], 6)} for e in want.get("restart_events", [])]
        assert like(got["restart_events"], events), sender["id"]


def like(got: list[dict], want: list[dict]) -> bool:
    """The same entries, compared on the keys the truth has (its schema grows: a frame, say)."""
    return [{k: g.get(k) for k in w} for g, w in zip(got, want)] == want and len(got) == len(want)


# --- Timing -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_watchdog(tshark, capture, tmp_path):
    """Intervals between accepted packets (a duplicate has none; only a stream's first packet has
    none, unless a sender on a new port continues its predecessor's stream), the watchdog on the
    packet after an over-limit interval, and the silence to the end on the stream's last packet."""
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    rows = dissected(tshark, capture, tmp_path)
    got = defaultdict(list)
    counts, accepted = Counter(), Counter()
    for r in legal_rows(rows):
        kind = r.get("vm110.type")
        if kind not in ("VRPI", "VRPO"):
            continue
        key = (kind, r.sender)
        interval = r.float("vm110.analysis.interval")
        counts[key] += 1
        if r.get("vm110.analysis.serial_duplicate"):
            assert interval is None and not r.get("vm110.analysis.silent_until_end"), r.number
            continue
        assert interval is not None or accepted[key] == 0, r.number
        accepted[key] += 1
        limit = C.VRPI_WATCHDOG_MS if kind == "VRPI" else C.VRPO_WATCHDOG_MS
        tripped = r.has(f"watchdog_{kind.lower()}")
        assert tripped == (interval is not None and interval > limit), r.number
        if tripped:
            got[key].append({"start": round(r.time - interval / 1000, 6), "gap_ms": round(interval, 3),
                             "until_end": False, "frame": r.number})
        silent = r.float("vm110.analysis.silent_until_end")
        assert r.has("silent_until_end") == (silent is not None), r.number
        if silent is not None:
            assert silent > limit
            got[key].append({"start": round(r.time, 6), "gap_ms": round(silent, 3), "until_end": True,
                             "frame": r.number})
    for p in truth["periodic"]:
        key = (p["type"], p["sender"])
        want = [{"until_end": False, **v} for v in p["watchdog"]["violations"]]
        assert like(got[key], [{**v, "start": round(v["start"], 6)} for v in want]), key
        assert p["count"] in (accepted[key], counts[key]), key


# --- Commands and acknowledgements -------------------------------------------------------------------
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_commands(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    rows = {r.number: r for r in eg_rows(dissected(tshark, capture, tmp_path))}
    linked_retransmissions, linked_acks = set(), set()
    for kind, ack_kind in ((C.PacketType.VRCI.value, "VRAO"), (C.PacketType.VRCO.value, "VRAI")):
        want = truth["commands"][kind]
        never = late = interrupted = 0
        for cmd in want["list"]:
            first = rows[cmd["frames"][0]]
            assert first.get("vm110.type") == kind and first.int("vm110.command_id") == cmd["command_id"]
            assert first.sender == cmd["sender"]
            assert first.get("vm110.analysis.retransmission_of") == ""
            for number, frame in enumerate(cmd["frames"][1:], start=1):
                r = rows[frame]
                assert r.int("vm110.analysis.retransmission_of") == cmd["frames"][0], frame
                assert r.int("vm110.analysis.retransmission_number") == number, frame
                assert r.float("vm110.analysis.since_first") == pytest.approx(
                    (r.time - first.time) * 1000, abs=1e-3)
                assert r.has("retransmission")
                linked_retransmissions.add(frame)
            for frame in cmd["frames"]:
                assert rows[frame].int("vm110.analysis.ack_in") == cmd["ack_frame"], frame
            if cmd["ack_frame"] is None:
                if first.get("vm110.analysis.interrupted_by"):
                    assert first.has("command_interrupted") and not first.has("never_acked")
                    interrupted += 1
                    continue
                assert first.has("never_acked")
                never += 1
                continue
            assert not first.has("never_acked")
            ack = rows[cmd["ack_frame"]]
            assert ack.get("vm110.type") == ack_kind
            assert ack.int("vm110.analysis.ack_to") == cmd["frames"][0]
            assert round(ack.float("vm110.analysis.ack_time"), 3) == cmd["latency_first_ms"]
            assert round(ack.float("vm110.analysis.ack_time_last"), 3) == cmd["latency_last_ms"]
            linked_acks.add(cmd["ack_frame"])
            limit = C.VRCI_FAIL_MS if kind == "VRCI" else C.VRCO_GIVE_UP_MS
            assert first.has("ack_late") == (cmd["latency_first_ms"] > limit)
            late += cmd["latency_first_ms"] > limit
        assert interrupted == want.get("interrupted", 0)
        if kind == "VRCI" or truth["schema_version"] >= 2:   # (schema 1: a VRCO never failed)
            assert never + late == want["failed"]
        kinds = [r for r in rows.values() if r.get("vm110.type") == kind]
        acks = [r for r in rows.values() if r.get("vm110.type") == ack_kind]
        assert sum(r.has("spurious_retransmission") for r in kinds) == want["spurious_retransmissions"]
        assert sum(r.has("ack_without_command") for r in acks) == want["acks_without_command"]
        assert sum(r.has("duplicate_ack") for r in acks) == want["duplicate_acks"]
        assert sum(r.has("never_acked") for r in kinds) == want["unacked"]
    # No other frame claims to be a retransmission or a (first) acknowledgement.
    assert {n for n, r in rows.items() if r.get("vm110.analysis.retransmission_of")} == linked_retransmissions
    assert {n for n, r in rows.items() if r.get("vm110.analysis.ack_time_last")} == linked_acks


# --- VRPO bursts ---------------------------------------------------------------------------------------
def vrpo_data(capture: Path) -> dict[int, tuple[int, bytes]]:
    """frame -> (packet number, periodic data) of every legal VRPO, decoded by vm110.decode."""
    out = {}
    for number, pkt in enumerate(rdpcap(str(capture)), start=1):
        if UDP not in pkt:
            continue
        payload = bytes(pkt[UDP].payload)[:pkt[UDP].len - 8]
        d = decode(payload)
        if d.get("type") == "VRPO" and not d["problems"]:
            out[number] = (d["packet_number"], d["periodic_data"])
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_bursts(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    rows = eg_rows(dissected(tshark, capture, tmp_path))
    data = vrpo_data(capture)
    complete = incomplete = reassembled = 0
    for r in rows:
        if not r.get("vm110.burst.complete"):
            assert not r.get("vm110.reassembled")
            continue
        # A burst of one packet has no burst subtree: the packet itself is the burst.
        frames = [int(f) for f in r.get("vm110.burst.frame").split("|")] if r.get("vm110.burst.frame") else [r.number]
        assert frames[-1] == r.number and (r.int("vm110.burst.packets") or 1) == len(frames)
        if r.get("vm110.burst.complete") in ("1", "True"):
            complete += 1
            assert not r.has("burst_incomplete")
            if len(frames) > 1:
                expected = b"".join(d for _, d in sorted(data[f] for f in frames))
                assert bytes.fromhex(r.get("vm110.reassembled").replace(":", "")) == expected, r.number
                reassembled += 1
        else:
            incomplete += 1
            assert r.has("burst_incomplete") and not r.get("vm110.reassembled")
    assert {"complete": complete, "incomplete": incomplete} == truth["vrpo_bursts"]
    if "split" in capture.name:
        assert reassembled > 0


# --- Passes and re-dissection --------------------------------------------------------------------------
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_redissection_reads_stored_results(tshark, tmp_path):
    """A second pass over any subset of frames shows exactly what the full second pass shows (the GUI
    re-dissects single frames in any order); the first pass agrees on what it can know."""
    capture = CAPTURES / "loss.pcapng"
    try:
        with tshark.workspace(tmp_path) as ws:
            full, _full_text = run_fields(ws, capture, ["-2"])
            chosen = sorted(random.Random(4).sample(range(1, len(full) + 1), 150), reverse=True)
            subset, _ = run_fields(ws, capture, ["-2", "-Y", " || ".join(f"frame.number == {n}" for n in chosen)])
            single, _ = run_fields(ws, capture)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    by_number = {r.number: r.values for r in full}
    assert [r.values for r in subset] == [by_number[n] for n in sorted(chosen)]
    assert any(r.has("never_acked") or r.get("vm110.analysis.ack_in") for r in full)
    first_pass = ("vm110.analysis.serial_missing", "vm110.analysis.serial_duplicate",
                  "vm110.analysis.serial_out_of_order", "vm110.analysis.interval",
                  "vm110.analysis.retransmission_of", "vm110.analysis.ack_to", "vm110.analysis.ack_time")
    for one, two in zip(single, full):
        assert [one.get(f) for f in first_pass] == [two.get(f) for f in first_pass], one.number
        assert not one.has("never_acked")
    # Every field a single pass lacks is in the README's list of what it does not show (trial:
    # vm110.analysis.ack_in, on no command of a single pass, was not).
    readme = (T.REPO / "README.md").read_text()
    told = readme.split("What depends on later packets is known", 1)[1].split("`-z vm110,stat` is always", 1)[0]
    lacking = {f for one, two in zip(single, full) for f in ANALYSIS_FIELDS
               if two.get(f"vm110.{f}") and not one.get(f"vm110.{f}")}
    assert lacking and not {f for f in lacking if f"`{f.rsplit('.', 1)[-1]}`" not in told}


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_analysis_off_and_illegal_packets(tshark, tmp_path):
    """With the preference off nothing is analysed; illegal packets are never analysed."""
    capture = CAPTURES / "illegal.pcap"
    rows = dissected(tshark, capture, tmp_path)
    try:
        with tshark.workspace(tmp_path) as ws:
            off, _ = run_fields(ws, capture, ["-2"], prefs={"vm110.analysis": "FALSE"})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert all(not r.get(f"vm110.{f}") for r in off for f in ANALYSIS_FIELDS)
    assert any(r.get(f"vm110.{f}") for r in rows for f in ANALYSIS_FIELDS)
    illegal = {r.number for r in eg_rows(rows) if not r.legal}
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    assert len(illegal) == truth["illegal"]["total"]
    for r in rows:
        if r.number in illegal:
            assert not any(r.get(f"vm110.{f}") for f in ANALYSIS_FIELDS), r.number


# (restart.pcapng first: it has the most kinds of findings, so that most filters need one run)
README_CAPTURES = ("restart.pcapng", "vrpo-split.pcapng", "bu-stops.pcap", "loss.pcapng", "bu-watchdog.pcap")


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_readme_analysis_filters(tshark, tmp_path):
    """The stream analysis filters the README shows compile and match frames of the captures."""
    readme = (T.REPO / "README.md").read_text()
    block = readme.split("**Stream analysis filters**", 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
    filters = [line.split("  ")[0].strip() for line in block.splitlines() if line.strip()]
    assert len(filters) >= 5
    try:
        with tshark.workspace(tmp_path) as ws:
            for capture in README_CAPTURES:
                (ws.dir / capture).write_bytes((CAPTURES / capture).read_bytes())
            for expression in filters:
                matched = 0
                for capture in README_CAPTURES:
                    proc = ws.run(["-r", str(ws.dir / capture), "-2", "-Y", expression], check=False)
                    assert proc.returncode == 0, f"{expression!r}: {proc.stderr.strip()}"
                    matched += len(proc.stdout.splitlines())
                    if matched:
                        break
                assert matched, f"{expression!r} matches nothing"
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


def per_type_senders(source: Path, target: Path) -> None:
    """The capture with each packet type of a host moved to an address of its own: per-sender
    scope on it is per-type scope on the original (no two types share a host, so no new-port
    restarts either)."""
    from scapy.layers.inet import IP
    from scapy.utils import wrpcap
    kinds = [t.value.encode() for t in C.PacketType]
    packets = rdpcap(str(source))
    for pkt in packets:
        if IP in pkt and UDP in pkt and bytes(pkt[UDP].payload)[:4] in kinds:
            octets = pkt[IP].src.split(".")
            pkt[IP].src = f"10.{200 + kinds.index(bytes(pkt[UDP].payload)[:4])}.{octets[2]}.{octets[3]}"
            del pkt[IP].chksum
    wrpcap(str(target), packets)


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_preferences_type_scope_and_thresholds(tshark, tmp_path):
    """Per-type serial scope equals the independent reference (tests/reference) run on the capture
    with every type of a sender on its own address; a watchdog preference moves the threshold."""
    from reference.analyser import analyse as reference
    capture = CAPTURES / "loss.pcapng"
    split = tmp_path / "per-type.pcap"
    per_type_senders(capture, split)
    ref = reference(str(split))
    try:
        with tshark.workspace(tmp_path / "ws") as ws:
            rows, _ = run_fields(ws, capture, ["-2"], prefs={**ON, "vm110.serial_scope": "type",
                                                            "vm110.vrpi_watchdog_ms": "100"})
            relaxed, _ = run_fields(ws, CAPTURES / "bu-watchdog.pcap", ["-2"],
                                    prefs={**ON, "vm110.vrpo_watchdog_ms": "3200"})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    seen = Counter()
    for r in legal_rows(rows):
        want = ref["frames"].get(r.number, {})
        got = {}
        if r.get("vm110.analysis.serial_missing"):
            got["serial_missing"] = r.int("vm110.analysis.serial_missing")
        for key in ("serial_duplicate", "serial_out_of_order", "restart"):
            if r.get(f"vm110.analysis.{key}"):
                got[key] = r.int(f"vm110.analysis.{key}")
        assert got == {k: v for k, v in want.items() if k in ("serial_missing", "serial_duplicate",
                                                                 "serial_out_of_order", "restart")}, r.number
        seen.update(got.keys())
    assert min(seen["serial_missing"], seen["serial_duplicate"], seen["serial_out_of_order"]) > 0
    vrpi = [r for r in legal_rows(rows) if r.get("vm110.type") == "VRPI" and r.get("vm110.analysis.interval")]
    assert vrpi and all(r.has("watchdog_vrpi") == (r.float("vm110.analysis.interval") > 100) for r in vrpi)
    assert not any(r.has("watchdog_vrpo") for r in relaxed)


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_burst_preferences(tshark, tmp_path):
    """Numbering from 1 and a configured periodic data size: a crafted burst reassembles, one with a
    skipped packet number does not."""
    from vm110.layers import VM110, VRPO
    data = bytes(i % 251 for i in range(808))
    parts = [data[:C.VRPO_MAX_DATA], data[C.VRPO_MAX_DATA:]]
    packets = [bytes(VM110(serial=1) / VRPO(packet_number=1, periodic_data=parts[0])),
               bytes(VM110(serial=2) / VRPO(packet_number=2, periodic_data=parts[1])),
               bytes(VM110(serial=3) / VRPO(packet_number=1, periodic_data=parts[0])),
               bytes(VM110(serial=4) / VRPO(packet_number=3, periodic_data=parts[1]))]
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "bursts.pcap"
            T.write_pcap(pcap, packets, [0, 100, 100_000, 100_100])
            rows, _ = run_fields(ws, pcap, ["-2"], prefs={**ON, "vm110.vrpo_number_start": "1",
                                                        "vm110.vrpo_data_size": "808"})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert [r.get("vm110.burst.complete") in ("1", "True") for r in rows] == [False, True, False, False]
    assert bytes.fromhex(rows[1].get("vm110.reassembled").replace(":", "")) == data
    assert rows[3].get("vm110.burst.complete") in ("0", "False") and rows[3].has("burst_incomplete")
    assert rows[3].has("burst_missing") and not rows[3].get("vm110.reassembled")
    assert [r.get("vm110.burst.frame") for r in rows] == ["1|2", "1|2", "3|4", "3|4"]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_complete_burst_takes_no_more_packets(tshark, tmp_path):
    """interpretation.md: "a burst ends with a packet of fewer than 488 bytes". Packets 10 ms apart
    (closer than the 20 ms gap): two unsplit ones are two complete bursts; a 300-byte packet 0 is
    complete alone, so the packet 1 after it is a burst of its own, missing packet 0; a split burst
    whose short part 1 arrives before its part 0 is one burst, complete with its second packet."""
    from vm110.layers import VM110, VRPO
    sends = [(0, 100), (0, 100), (0, 300), (1, 100), (1, 100), (0, C.VRPO_MAX_DATA)]
    packets = [bytes(VM110(serial=i + 1) / VRPO(packet_number=n, periodic_data=bytes(size)))
               for i, (n, size) in enumerate(sends)]
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "bursts.pcap"
            T.write_pcap(pcap, packets, [0, 10_000, 100_000, 110_000, 200_000, 201_000])
            rows, _ = run_fields(ws, pcap, ["-2"], prefs=ON)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    shown = [(r.get("vm110.burst.frame") or str(r.number), r.get("vm110.burst.complete") in ("1", "True"))
             for r in rows]
    assert shown == [("1", True), ("2", True), ("3", True), ("4", False), ("5|6", False), ("5|6", True)]
    assert rows[3].has("burst_missing") and rows[3].has("burst_incomplete")
    assert not any(r.has("burst_incomplete") for r in rows[:3] + rows[4:])


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_bursts_of_full_packets_infer_the_data_size(tshark, tmp_path):
    """docs/rules.md, "VRPO bursts" (data size 0 = infer): a sender of 976 bytes a cycle sends
    bursts of two 488-byte packets, complete; the third lost its second packet and is incomplete.
    Then 488 bytes every 15 ms (closer than the gap): each packet restarts the numbering and is a
    complete burst of its own, as long as the sender's longest burst so far is not longer. A burst
    that has the size inferred takes no packet that does not go on from it."""
    from vm110.layers import VM110, VRPO
    sends = [(0, 0), (1, 1), (100, 0), (101, 1), (200, 0), (300, 0), (301, 1)]
    packets = [bytes(VM110(serial=i + 1) / VRPO(packet_number=n, periodic_data=bytes(C.VRPO_MAX_DATA)))
               for i, (_, n) in enumerate(sends)]
    quick = [bytes(VM110(serial=i + 1) / VRPO(packet_number=0, periodic_data=bytes(C.VRPO_MAX_DATA)))
             for i in range(3)]
    # the size reached (two packets): packet 1 of the next cycle, 14 ms after, arrives before its 0
    swapped = [bytes(VM110(serial=i + 1) / VRPO(packet_number=n, periodic_data=bytes(C.VRPO_MAX_DATA)))
               for i, n in enumerate([0, 1, 0, 1, 1, 0])]
    try:
        with tshark.workspace(tmp_path) as ws:
            T.write_pcap(ws.dir / "976.pcap", packets, [ms * 1000 for ms, _ in sends])
            T.write_pcap(ws.dir / "488.pcap", quick, [0, 15_000, 30_000])
            T.write_pcap(ws.dir / "swapped.pcap", swapped, [0, 1000, 100_000, 101_000, 115_000, 116_000])
            rows, _ = run_fields(ws, ws.dir / "976.pcap", ["-2"], prefs=ON)
            fast, _ = run_fields(ws, ws.dir / "488.pcap", ["-2"], prefs=ON)
            reached, _ = run_fields(ws, ws.dir / "swapped.pcap", ["-2"], prefs=ON)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert [(r.get("vm110.burst.frame"), r.get("vm110.burst.complete") in ("1", "True")) for r in reached] == [
        ("1|2", False), ("1|2", True), ("3|4", False), ("3|4", True), ("5|6", False), ("5|6", True)]
    assert not any(r.has("burst_incomplete") for r in reached)
    shown = [(r.get("vm110.burst.frame") or str(r.number), r.get("vm110.burst.complete")) for r in rows]
    assert [(f, c in ("1", "True") if c else None) for f, c in shown] == [
        ("1|2", None), ("1|2", True), ("3|4", None), ("3|4", True), ("5", False), ("6|7", None), ("6|7", True)]
    assert [r.number for r in rows if r.has("burst_incomplete")] == [5]
    assert [r.get("vm110.burst.complete") in ("1", "True") for r in fast] == [True] * 3
    assert not any(r.has("burst_incomplete") or r.get("vm110.burst.frame") for r in fast)


# --- docs/rules.md on hand-crafted captures (expected values worked out by hand) ------------------------
def _bu(serial: int, payload) -> bytes:
    from vm110.layers import VM110
    return bytes(VM110(origin=0x0101, serial=serial) / payload)


def _ctl(serial: int, payload) -> bytes:
    from vm110.layers import VM110
    return bytes(VM110(serial=serial) / payload)


def _crafted(tshark, tmp_path, timeline, passes=("-2",), extra=()) -> dict[int, Row]:
    """Frames 1.. of the timeline [(ms, payload or Datagram)], dissected with the analysis on."""
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "crafted.pcap"
            T.write_pcap(pcap, [p for _, p in timeline], [round(ms * 1000) for ms, _ in timeline])
            rows, _text = run_fields(ws, pcap, [*passes, *extra])
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    return {r.number: r for r in rows}


def _stat(tshark, tmp_path, timeline) -> str:
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "crafted-stat.pcap"
            T.write_pcap(pcap, [p for _, p in timeline], [round(ms * 1000) for ms, _ in timeline])
            return ws.run(["-r", str(pcap), "-q", "-z", "vm110,stat", *T.pref_args(ON)]).stdout
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


def _vrpi():
    from vm110.layers import VRPI
    return VRPI()


def _vrpo():
    from vm110.layers import VRPO
    return VRPO(packet_number=0, periodic_data=bytes(16))


def _cmd(kind: str, cid: int):
    from vm110 import layers
    return getattr(layers, kind)(command_id=cid)


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_overlapping_commands_acked_in_reverse_order(tshark, tmp_path):
    """Two commands of one sender open at once; a new ID ends nothing; each ack finds its own."""
    rows = _crafted(tshark, tmp_path, [
        (0, _bu(1, _vrpi())),
        (10, _bu(2, _cmd("VRCI", 5))),
        (20, _bu(3, _cmd("VRCI", 6))),
        (110, _bu(4, _cmd("VRCI", 5))),            # retransmission of frame 2 (command 6 is open too)
        (120, _ctl(1, _cmd("VRAO", 6))),           # acks frame 3
        (130, _ctl(2, _cmd("VRAO", 5))),           # acks frame 2
    ])
    assert rows[2].int("vm110.analysis.ack_in") == 6 and rows[4].int("vm110.analysis.ack_in") == 6
    assert rows[3].int("vm110.analysis.ack_in") == 5
    assert rows[4].int("vm110.analysis.retransmission_of") == 2
    assert rows[4].int("vm110.analysis.retransmission_number") == 1
    assert rows[4].float("vm110.analysis.since_first") == 100.0
    assert rows[5].int("vm110.analysis.ack_to") == 3 and rows[5].float("vm110.analysis.ack_time") == 100.0
    assert rows[6].int("vm110.analysis.ack_to") == 2 and rows[6].float("vm110.analysis.ack_time") == 120.0
    assert rows[6].float("vm110.analysis.ack_time_last") == 20.0
    assert not any(r.has(e) for r in rows.values() for e in ("never_acked", "duplicate_ack", "ack_without_command"))


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_command_id_reused_after_the_reuse_gap(tshark, tmp_path):
    """The same ID 2.5 s after its last transmission is a new command; within 2 s a retransmission
    (here after the ack: spurious). A shorter reuse gap preference makes the second one new too."""
    timeline = [
        (0, _bu(1, _cmd("VRCI", 7))),
        (5, _ctl(1, _cmd("VRAO", 7))),
        (2505, _bu(2, _cmd("VRCI", 7))),           # new command
        (2510, _ctl(2, _cmd("VRAO", 7))),          # acks frame 3, not a duplicate ack
        (4005, _bu(3, _cmd("VRCI", 7))),           # 1500 ms later: retransmission of frame 3
    ]
    rows = _crafted(tshark, tmp_path / "a", timeline)
    assert not rows[3].get("vm110.analysis.retransmission_of") and rows[3].int("vm110.analysis.ack_in") == 4
    assert rows[4].int("vm110.analysis.ack_to") == 3 and not rows[4].has("duplicate_ack")
    assert rows[5].int("vm110.analysis.retransmission_of") == 3 and rows[5].has("spurious_retransmission")
    short = _crafted(tshark, tmp_path / "b", timeline, extra=["-o", "vm110.reuse_gap_ms:1000"])
    assert not short[5].get("vm110.analysis.retransmission_of") and short[5].has("never_acked")


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_duplicates_take_no_part(tshark, tmp_path):
    """A mirror copy 1 ms later and a copy 300 ms later: duplicates, no interval, and they do not
    reset the watchdog; a copy of a command is no retransmission, a copy of an ack no duplicate ack."""
    rows = _crafted(tshark, tmp_path, [
        (0, _bu(1, _vrpi())),
        (1, _bu(1, _vrpi())),                      # mirror copy
        (125, _bu(2, _vrpi())),                    # interval 125 from frame 1
        (130, _bu(3, _cmd("VRCI", 9))),
        (131, _bu(3, _cmd("VRCI", 9))),            # copy of the command
        (140, _ctl(1, _cmd("VRAO", 9))),
        (141, _ctl(1, _cmd("VRAO", 9))),           # copy of the ack
        (300, _bu(2, _vrpi())),                    # late copy, still within the window
        (626, _bu(4, _vrpi())),                    # 501 ms after frame 3: watchdog
    ])
    for n in (2, 5, 7, 8):
        assert rows[n].int("vm110.analysis.serial_duplicate") == 1 and rows[n].has("serial_duplicate"), n
        assert not rows[n].get("vm110.analysis.interval") and not rows[n].get("vm110.analysis.retransmission_of")
        assert not rows[n].get("vm110.analysis.ack_to") and not rows[n].has("duplicate_ack"), n
    assert rows[3].float("vm110.analysis.interval") == 125.0
    assert rows[9].float("vm110.analysis.interval") == 501.0 and rows[9].has("watchdog_vrpi")
    assert rows[6].int("vm110.analysis.ack_to") == 4


def _bad_crc(packet: bytes) -> bytes:
    return packet[:-1] + bytes([packet[-1] ^ 0xFF])


# The capture's last record: another protocol's (which the dissector never sees: a tap filtered to
# frames without EG-Link does), or an illegal EG-Link packet (dissected, not analysed).
LAST_RECORDS = {"other-udp": T.Datagram(b"not EG-Link at all, just UDP", sport=9999, dport=9999),
                "illegal-eg-link": None}


@pytest.mark.parametrize("last", LAST_RECORDS)
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_silent_until_the_end(tshark, last, tmp_path):
    """The base unit stops at 375 ms; the capture's last record (not a legal EG-Link packet) is at
    2000 ms: the VRPI stream's last packet is silent until the end (1625 ms); the VRPO stream (last
    1500 ms) is not. Known on the second pass; the statistics say it too."""
    timeline = [(125 * k, _bu(k + 1, _vrpi())) for k in range(4)]
    timeline += [(100 * k + 50, _ctl(k + 1, _vrpo())) for k in range(15)]
    timeline.sort(key=lambda e: e[0])
    timeline.append((2000, LAST_RECORDS[last] or _bad_crc(_ctl(16, _vrpo()))))
    rows = _crafted(tshark, tmp_path / "two", timeline)
    silent = {n: r.float("vm110.analysis.silent_until_end") for n, r in rows.items()
              if r.get("vm110.analysis.silent_until_end")}
    last_vrpi = max(n for n, r in rows.items() if r.get("vm110.type") == "VRPI")
    assert silent == {last_vrpi: 1625.0} and rows[last_vrpi].has("silent_until_end")
    single = _crafted(tshark, tmp_path / "one", timeline, passes=())
    assert not any(r.get("vm110.analysis.silent_until_end") for r in single.values())
    assert "VRPI silent until the end: 1625.000 ms" in _stat(tshark, tmp_path / "stat", timeline)


def _restart_timeline():
    return [
        (0, _ctl(100, _vrpo())), (100, _ctl(101, _vrpo())), (200, _ctl(102, _vrpo())),
        (250, _ctl(103, _cmd("VRCO", 9))),         # outstanding at the restart: interrupted
        (300, _ctl(104, _vrpo())),
        (1800, _ctl(0, _vrpo())),                  # candidate (d = 65432): confirmed by serial 1
        (1900, _ctl(1, _vrpo())),
        (1950, _ctl(2, _cmd("VRCO", 9))),          # 1700 ms after the last one: new (restart since)
        (1960, _bu(1, _cmd("VRAI", 9))),           # acks frame 8, not the interrupted frame 4
    ]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_same_port_restart_confirmed(tshark, tmp_path):
    rows = _crafted(tshark, tmp_path / "two", _restart_timeline())
    assert rows[6].int("vm110.analysis.restart") == 104 and rows[6].has("restart")
    assert not rows[6].get("vm110.analysis.restart_port_from")
    assert not any(rows[6].get(f"vm110.analysis.serial_{k}") for k in ("missing", "duplicate", "out_of_order"))
    assert rows[6].float("vm110.analysis.interval") == 1500.0 and not rows[6].has("watchdog_vrpo")
    assert not rows[7].get("vm110.analysis.serial_missing")
    assert rows[4].int("vm110.analysis.interrupted_by") == 6 and rows[4].has("command_interrupted")
    assert not rows[4].has("never_acked") and not rows[4].get("vm110.analysis.ack_in")
    assert not rows[8].get("vm110.analysis.retransmission_of") and rows[8].int("vm110.analysis.ack_in") == 9
    assert rows[9].int("vm110.analysis.ack_to") == 8
    stat = _stat(tshark, tmp_path / "stat", _restart_timeline())
    assert "Restart in frame 6: serial 104 -> 0" in stat
    assert "Commands: 2, acked 1, unacknowledged 0, interrupted 1, retransmissions 0" in stat
    # One pass: the candidate is not decided when its frame is shown.
    single = _crafted(tshark, tmp_path / "one", _restart_timeline(), passes=())
    assert not single[6].get("vm110.analysis.restart") and not single[6].get("vm110.analysis.serial_out_of_order")


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_restart_info_marker(tshark, tmp_path):
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "restart.pcap"
            timeline = _restart_timeline()
            T.write_pcap(pcap, [p for _, p in timeline], [ms * 1000 for ms, _ in timeline])
            proc = ws.run(["-r", str(pcap), "-2", *T.pref_args(ON), "-T", "fields", "-e", "_ws.col.Info"])
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    info = proc.stdout.splitlines()
    assert info[5].startswith("[Restart] ") and sum("[Restart]" in line for line in info) == 1


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_unconfirmed_candidate_is_out_of_order(tshark, tmp_path):
    """Serial 500 after 13 (8/s, 125 ms later: at most 74 lost is plausible) is a candidate; the next
    serial 14 does not confirm it: out of order, nothing moved (14 is in order after 13)."""
    timeline = [(125 * k, _bu(10 + k, _vrpi())) for k in range(4)]
    timeline += [(500, _bu(500, _vrpi())), (625, _bu(14, _vrpi()))]
    rows = _crafted(tshark, tmp_path, timeline)
    assert rows[5].int("vm110.analysis.serial_out_of_order") == 1 and not rows[5].get("vm110.analysis.restart")
    assert not rows[5].get("vm110.analysis.serial_missing")
    assert not rows[6].get("vm110.analysis.serial_missing") and not rows[6].get("vm110.analysis.serial_out_of_order")
    assert rows[6].float("vm110.analysis.interval") == 125.0


def _candidate_timeline(*later):
    """VRPI 10-13 at 8/s, then serial 5000 at 500 ms (at most 74 lost is plausible: a candidate),
    then `later` [(ms, serial)]: 13 stays h while the candidate is undecided or out of order."""
    return [(125 * k, _bu(10 + k, _vrpi())) for k in range(4)] + [(500, _bu(5000, _vrpi()))] + [
        (ms, _bu(serial, _vrpi())) for ms, serial in later]


def _released_timeline(confirm_ms):
    """VRPI 10-13 at 8/s, the base unit's VRCI 5 (serial 14) at 450 ms, never acknowledged, then
    the candidate 5000 at 500 ms (at most 68 lost is plausible) and serial 5001 at `confirm_ms`."""
    return [(125 * k, _bu(10 + k, _vrpi())) for k in range(4)] + [
        (450, _bu(14, _cmd("VRCI", 5))), (500, _bu(5000, _vrpi())), (confirm_ms, _bu(5001, _vrpi()))]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_restart_confirmed_10_s_late_changes_no_command(tshark, tmp_path):
    """rules.md rule 5: 5001 confirms the candidate 5000 whenever it comes, a restart from 14 on
    frame 6. Confirmed 1 us less than 10 s after it, the restart interrupts the VRCI sent 50 ms
    before it (within its 2000 ms limit); exactly 10 s after it, the command events had stopped
    waiting for it: the VRCI is not interrupted but never acknowledged (failed)."""
    vrci, cand, confirm = 5, 6, 7
    rows = _crafted(tshark, tmp_path / "in-time", _released_timeline(10_499.999))
    assert rows[cand].int("vm110.analysis.restart") == 14 and rows[cand].has("restart")
    assert rows[vrci].int("vm110.analysis.interrupted_by") == cand and rows[vrci].has("command_interrupted")
    assert not rows[vrci].has("never_acked")
    timeline = _released_timeline(10_500)
    rows = _crafted(tshark, tmp_path / "late", timeline)
    assert rows[cand].int("vm110.analysis.restart") == 14 and rows[cand].has("restart")
    assert not rows[cand].get("vm110.analysis.serial_out_of_order")
    assert not any(rows[confirm].get(f"vm110.analysis.{k}") for k in ("restart", "serial_missing", "serial_out_of_order"))
    assert not rows[vrci].get("vm110.analysis.interrupted_by") and not rows[vrci].has("command_interrupted")
    assert rows[vrci].has("never_acked")
    stat = _stat(tshark, tmp_path / "stat", timeline)
    assert "restarts 1\n  Restart in frame 6: serial 14 -> 5000\n" in stat
    assert "Commands: 1, acked 0, unacknowledged 1, interrupted 0, retransmissions 0" in stat


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_copies_of_a_pending_candidate_are_duplicates(tshark, tmp_path):
    """Copies of the candidate 5 s and 11 s after it are duplicates (rule 5, beyond the 1 s window,
    whenever they come); the capture ending first, it is out of order; 5001 at 12 s confirms it."""
    copies = ((5500, 5000), (11_500, 5000))
    for name, later, restart in (("end", copies, False), ("confirmed", (*copies, (12_000, 5001)), True)):
        rows = _crafted(tshark, tmp_path / name, _candidate_timeline(*later))
        if restart:
            assert rows[5].int("vm110.analysis.restart") == 13 and not rows[5].get("vm110.analysis.serial_out_of_order")
            assert not any(rows[8].get(f"vm110.analysis.{k}") for k in ("restart", "serial_missing", "serial_out_of_order"))
        else:
            assert rows[5].int("vm110.analysis.serial_out_of_order") == 1 and not rows[5].get("vm110.analysis.restart")
        for n in (6, 7):
            assert rows[n].int("vm110.analysis.serial_duplicate") == 1 and rows[n].has("serial_duplicate"), (name, n)
            assert not rows[n].get("vm110.analysis.interval"), (name, n)


def _silent_candidate_timeline():
    """Frames 1-5: the base unit's serial 5000 is a candidate at 500 ms, and it falls silent for
    good. The controller: VRPO at 1000 ms (6), VRCO 9 at 1050 (7) resent at 1150 (8), VRPO each
    second from 2000 to 11000 ms (9-18), VRCO 7 at 11050 (19) resent at 11150 (20); none acked."""
    controller = [(1000, _vrpo()), (1050, _cmd("VRCO", 9)), (1150, _cmd("VRCO", 9))]
    controller += [(1000 * k, _vrpo()) for k in range(2, 12)] + [(11_050, _cmd("VRCO", 7)), (11_150, _cmd("VRCO", 7))]
    return _candidate_timeline() + [(ms, _ctl(serial, p)) for serial, (ms, p) in enumerate(controller, start=1)]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_silent_sender_candidate_holds_commands_for_10_s_only(tshark, tmp_path):
    """The controller's command events wait behind the base unit's candidate until the analysis
    clock (the controller's VRPO at 11 s) reaches 10 s after it: then they run past it (it is still
    pending, out of order at the capture's end), so a single pass links the VRCO 7 resent after
    that (before: held to the capture's end)."""
    timeline = _silent_candidate_timeline()
    vrco9, resent9, vrco7, resent7 = 7, 8, 19, 20
    rows = _crafted(tshark, tmp_path / "two", timeline)
    assert rows[5].int("vm110.analysis.serial_out_of_order") == 1
    assert rows[resent9].int("vm110.analysis.retransmission_of") == vrco9
    assert rows[resent7].int("vm110.analysis.retransmission_of") == vrco7
    assert rows[vrco9].has("never_acked") and rows[vrco7].has("never_acked")
    single = _crafted(tshark, tmp_path / "one", timeline, passes=())
    assert not single[resent9].get("vm110.analysis.retransmission_of")   # (held while the candidate was)
    assert single[resent7].int("vm110.analysis.retransmission_of") == vrco7 and single[resent7].has("retransmission")


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_long_outage_is_loss_and_restart_from_above_32767(tshark, tmp_path):
    """8/s for 10 s, then 60 s of silence and a jump of 481: 480 lost is plausible (up to
    64 + 4 * 20 * 60). A counter at 40003 that restarts at 0 after 2 s (a forward jump of 25533,
    at most 224 plausible) is a restart, not 25,532 lost."""
    timeline = [(125 * k, _bu(k + 1, _vrpi())) for k in range(80)]
    timeline.append((125 * 79 + 60_000, _bu(561, _vrpi())))
    rows = _crafted(tshark, tmp_path / "outage", timeline)
    assert rows[81].int("vm110.analysis.serial_missing") == 480 and rows[81].has("serial_gap")
    assert rows[81].float("vm110.analysis.interval") == 60_000.0 and rows[81].has("watchdog_vrpi")
    timeline = [(125 * k, _bu(40000 + k, _vrpi())) for k in range(4)]
    timeline += [(2375, _bu(0, _vrpi())), (2500, _bu(1, _vrpi()))]
    rows = _crafted(tshark, tmp_path / "restart", timeline)
    assert rows[5].int("vm110.analysis.restart") == 40003
    assert not any(r.get("vm110.analysis.serial_missing") for r in rows.values())
    assert rows[5].float("vm110.analysis.interval") == 2000.0 and rows[5].has("watchdog_vrpi")


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_rules_new_port_restart(tshark, tmp_path):
    """The controller reappears on port 50000 after 1400 ms of silence: a restart of the sender on
    5827 (from its highest serial 6), its open VRCO interrupted, the one past its give-up limit not;
    the new VRPO stream begins with the interval from the old one's last VRPO (2300 ms: watchdog);
    the old stream is not silent until the end."""
    new = 50000
    rows = _crafted(tshark, tmp_path, [
        (0, _ctl(1, _vrpo())), (100, _ctl(2, _vrpo())), (200, _ctl(3, _vrpo())),
        (250, _ctl(4, _cmd("VRCO", 4))),           # 2350 ms old at the restart: failed, not interrupted
        (300, _ctl(5, _vrpo())),
        (1200, _ctl(6, _cmd("VRCO", 5))),          # 1400 ms old: interrupted
        (2600, T.Datagram(_ctl(0, _vrpo()), sport=new)),
        (2700, T.Datagram(_ctl(1, _vrpo()), sport=new)),
        (2800, T.Datagram(_ctl(2, _vrpo()), sport=new)),
    ])
    first = rows[7]
    assert first.int("vm110.analysis.restart") == 6 and first.int("vm110.analysis.restart_port_from") == 5827
    assert first.has("restart") and first.float("vm110.analysis.interval") == 2300.0 and first.has("watchdog_vrpo")
    assert rows[6].int("vm110.analysis.interrupted_by") == 7 and not rows[6].has("never_acked")
    assert rows[4].has("never_acked") and not rows[4].get("vm110.analysis.interrupted_by")
    assert not any(r.get("vm110.analysis.silent_until_end") for r in rows.values())


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_limits_are_judged_to_the_microsecond_in_analyze_as_in_the_dissector(tshark, tmp_path):
    """Intervals exactly at a limit, on an epoch clock: a float difference there is off by some
    0.2 us, and analyze judged copies exactly the duplicate window apart duplicates and an ID
    exactly the reuse gap later a retransmission, where the dissector (to the microsecond) did not
    (a trial). Each limit here is met exactly and missed by 1 us; the rules' "less than" decides."""
    import subprocess
    import sys
    new = 40000
    timeline = [
        (0, _bu(1, _cmd("VRCI", 7))),              # 1
        (150, _bu(2, _cmd("VRCI", 7))),            # 2  the reuse gap (150) later: a new command
        (299.999, _bu(3, _cmd("VRCI", 7))),        # 3  149.999 later: retransmission of 2
        (400, _bu(4, _cmd("VRCI", 8))),            # 4
        (700, _ctl(1, _cmd("VRAO", 8))),           # 5  acks 4 at the fail limit (300): not late
        (800, _bu(5, _cmd("VRCI", 9))),            # 6
        (1100.001, _ctl(2, _cmd("VRAO", 9))),      # 7  acks 6 1 us past it: late, failed
        (1200, _ctl(3, _vrpo())),                  # 8
        (1450, T.Datagram(_ctl(0, _vrpo()), sport=new)),   # 9  the new-port silence (250) after 8: restart
        (2000, _bu(6, _vrpi())),                   # 10
        (2125, _bu(7, _vrpi())),                   # 11
        (2224.999, _bu(7, _vrpi())),               # 12 99.999 after 11: duplicate
        (2250, _bu(8, _vrpi())),                   # 13
        (2350, _bu(8, _vrpi())),                   # 14 the window (100) after 13: no copy, restart to 8
        (2375, _bu(9, _vrpi())),                   # 15 confirms it
    ]
    prefs = {"vm110.dup_window_ms": "100", "vm110.reuse_gap_ms": "150", "vm110.vrci_fail_ms": "300"}
    try:
        with tshark.workspace(tmp_path / "ws") as ws:
            pcap = ws.dir / "limits.pcap"
            T.write_pcap(pcap, [p for _, p in timeline], [round(ms * 1000) for ms, _ in timeline])
            rows, _ = run_fields(ws, pcap, ["-2"], prefs={**ON, **prefs})
            out = tmp_path / "limits.json"
            done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(pcap), "--json", str(out), "--quiet",
                                   "--dup-window", "100", "--reuse-gap", "150", "--vrci-fail", "300"],
                                  capture_output=True, text=True)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert done.returncode in (0, 1), done.stderr
    by = {r.number: r for r in rows}
    assert not by[2].get("vm110.analysis.retransmission_of") and by[3].int("vm110.analysis.retransmission_of") == 2
    assert by[5].int("vm110.analysis.ack_to") == 4 and not by[5].has("ack_late")
    assert by[7].int("vm110.analysis.ack_to") == 6 and by[7].has("ack_late")
    assert by[9].int("vm110.analysis.restart_port_from") == 5827
    assert by[12].has("serial_duplicate") and not by[14].has("serial_duplicate") and by[14].has("restart")
    report = json.loads(out.read_text())
    vrci = report["commands"]["VRCI"]
    assert (vrci["commands"], vrci["retransmissions"], vrci["failed"]) == (4, 1, 3)   # 1 and 2-3 never acked
    assert report["totals"]["duplicates"] == 1 and report["totals"]["restarts"] == 2


# --- The dissector and `vm110 analyze --json` count the same things -----------------------------------
ALL_CAPTURES = sorted(p for p in CAPTURES.iterdir() if p.suffix in (".pcap", ".pcapng"))


@functools.lru_cache(maxsize=None)
def report_of(capture: Path, scope: str = "auto") -> dict:
    """`vm110 analyze` of a bundled capture, once per capture and serial scope: `auto` (its
    default, as a user runs it) or `sender` (the dissector's default scope)."""
    return analyze(str(capture), options=Options(serial_scope=scope))


def dissector_counts(rows: list[Row]) -> dict:
    """Per sender and per (type, sender) / (kind, sender): what `vm110 analyze` counts, from the
    dissector's fields and experts alone."""
    c: Counter = Counter()
    for r in legal_rows(rows):
        s, kind = r.sender, r.get("vm110.type")
        missing = r.int("vm110.analysis.serial_missing")
        if missing:
            c[("gaps", s)] += 1
            c[("lost_at_detection", s)] += missing
        for key in ("duplicate", "out_of_order"):
            if r.get(f"vm110.analysis.serial_{key}"):
                c[(key, s)] += 1
        if r.get("vm110.analysis.restart"):
            c[("restarts", s)] += 1
        if kind in ("VRPI", "VRPO"):
            c[("watchdog", kind, s)] += r.has(f"watchdog_{kind.lower()}") + r.has("silent_until_end")
            c[("outside", kind, s)] += r.has("vrpo_interval")
        if kind in ("VRCI", "VRCO") and not r.get("vm110.analysis.serial_duplicate"):
            if r.get("vm110.analysis.retransmission_of"):
                c[("retransmissions", kind)] += 1
            else:
                c[("commands", kind)] += 1
            c[("unacked", kind)] += r.has("never_acked")
            c[("interrupted", kind)] += bool(r.get("vm110.analysis.interrupted_by"))
    return c


def report_counts(report: dict) -> dict:
    c: Counter = Counter()
    for sender in report["senders"]:
        s, serial = sender["id"], sender["serial"]
        c[("gaps", s)] += len(serial["gaps"])
        c[("lost_at_detection", s)] += sum(g["count"] for g in serial["gaps"])
        c[("duplicate", s)] += serial["duplicates"]
        c[("out_of_order", s)] += serial["out_of_order"]
        c[("restarts", s)] += serial["restarts"]
    for p in report["periodic"]:
        c[("watchdog", p["type"], p["sender"])] += len(p["watchdog"]["violations"])
        c[("outside", p["type"], p["sender"])] += (p.get("outside_recommended") or {}).get("count", 0)
    for kind in ("VRCI", "VRCO"):
        for key in ("commands", "retransmissions", "unacked", "interrupted"):
            c[(key, kind)] += report["commands"][kind][key]
    return c


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", ALL_CAPTURES, ids=lambda p: p.name)
def test_counts_equal_vm110_analyze(tshark, capture, tmp_path):
    """Issue 12, point 5: wherever the dissector (tshark -2) and `vm110 analyze --json` count the same
    thing they give the same number: serial gaps (events and serials), duplicates, out of order,
    restarts, watchdog violations (with the silences to the end), commands, retransmissions,
    unacknowledged and interrupted commands, VRPO burst intervals outside the recommended range."""
    rows = dissected(tshark, capture, tmp_path)
    got, want = dissector_counts(rows), report_counts(report_of(capture, "sender"))
    keys = sorted(set(got) | set(want), key=str)
    differ = [k for k in keys if got[k] != want[k]]
    assert {k: got[k] for k in differ} == {k: want[k] for k in differ}
    assert sum(want.values()) > 0


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", ALL_CAPTURES, ids=lambda p: p.name)
def test_a_findings_filter_shows_its_items_and_no_other_frame(tshark, capture, tmp_path):
    """A finding's `filter` (the report with default options, as a user runs it) is the dissector's
    experts that mark exactly the frames of its items, and beyond them as many as `more` says."""
    report = report_of(capture)
    rows = dissected(tshark, capture, tmp_path)
    per_sender = all(s["serial"]["scope"] == "sender" for s in report["senders"])
    for f in report["verdict"]["findings"]:
        assert ("filter" in f) == (f["rule"] in RULE_FILTERS and per_sender), f["rule"]
        if "filter" not in f:
            continue
        codes = [term.removeprefix("vm110.expert.") for term in f["filter"].split(" || ")]
        marked = {r.number for r in rows if any(r.has(code) for code in codes)}
        items = {item["frame"] for item in f["items"]}
        assert items <= marked and len(marked) == len(items) + f.get("more", 0), f["rule"]


def _rewritten(source: Path, target: Path, change) -> Path:
    """`source` with each EG-Link payload replaced by the payloads `change(payload, serials, frame)`
    gives (none: the frame is dropped; two: a copy follows), at the same times; `serials` counts
    per (sender, type) for a caller that renumbers."""
    from scapy.packet import Raw
    from scapy.utils import wrpcap
    frames, serials = [], Counter()
    for frame in rdpcap(str(source)):
        if UDP not in frame or not decode(bytes(frame[UDP].payload))["type"]:
            frames.append(frame)
            continue
        for data in change(bytes(frame[UDP].payload), serials, frame):
            copy = frame.copy()
            copy[UDP].remove_payload()
            copy[UDP].add_payload(Raw(data))
            copy[UDP].chksum = 0
            frames.append(copy)
    wrpcap(str(target), frames)
    return target


def _with_crc(data: bytes, variant: str, order: str) -> bytes:
    from vm110.crc import crc_function
    from vm110.decode import crc_span
    end = crc_span(data, decode(data)["size"])
    return data[:end] + crc_function(variant)(data[:end]).to_bytes(4, order) + data[end + 4:]


def _crc_iso_hdlc_big(data: bytes, serials, frame) -> list[bytes]:
    return [_with_crc(data, "iso-hdlc", "big")]


def _serials_per_type(data: bytes, serials, frame) -> list[bytes]:
    """Each sender's packet types counted on their own, with VRPI 30 and 31 lost and VRPO 12 twice."""
    from vm110.protocol import HEADER_OFFSETS
    key = (frame["IP"].src, data[:4])
    serial = serials[key]
    serials[key] += 1
    at = HEADER_OFFSETS["serial"]
    data = _with_crc(data[:at] + serial.to_bytes(2, "little") + data[at + 2:], "mpeg2", "little")
    if data[:4] == b"VRPI" and serial in (30, 31):
        return []
    return [data, data] if data[:4] == b"VRPO" and serial == 12 else [data]


_OPTION_REPORTS: dict = {}

# Options other than the defaults, each with the preferences the report must name for them.
OTHER_OPTIONS = [
    ("loss.pcapng", None, ["--dup-window", "500", "--vrpo-range", "90", "110", "--vrpi-watchdog", "300"],
     ["vm110.vrpi_watchdog_ms:300", "vm110.vrpo_min_ms:90", "vm110.vrpo_max_ms:110", "vm110.dup_window_ms:500"]),
    ("retransmit.pcap", None, ["--reuse-gap", "1000", "--vrci-fail", "1500", "--vrco-give-up", "1200"],
     ["vm110.vrci_fail_ms:1500", "vm110.vrco_give_up_ms:1200", "vm110.reuse_gap_ms:1000"]),
    ("loss.pcapng", _crc_iso_hdlc_big, [], ["vm110.crc_variant:iso-hdlc", "vm110.crc_byte_order:big"]),
    ("normal.pcap", _serials_per_type, [], ["vm110.serial_scope:type"]),
]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("name, change, options, prefs", OTHER_OPTIONS,
                         ids=[" ".join([o[0], *o[2][:2]]) + (f" {o[1].__name__}" if o[1] else "") for o in OTHER_OPTIONS])
def test_a_findings_filter_with_other_options_names_the_preferences_it_needs(tshark, name, change, options, prefs,
                                                                             tmp_path):
    """With options, CRC or serial scope other than the defaults a report gave no rule filters at
    all (trial): Wireshark at its defaults would mark other frames. It now names the preferences
    under which the dissector judges as it did, and under them each filter marks exactly its items."""
    capture = CAPTURES / name if change is None else _rewritten(CAPTURES / name, tmp_path / f"x-{name}", change)
    key = (name, change and change.__name__, tuple(options))     # (the same report for every tshark)
    if key not in _OPTION_REPORTS:
        done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(capture), "--json", "-", "--quiet",
                               *options], capture_output=True, text=True, timeout=300)
        _OPTION_REPORTS[key] = json.loads(done.stdout)
    report = _OPTION_REPORTS[key]
    assert report["verdict"]["wireshark_prefs"] == prefs
    filtered = [f for f in report["verdict"]["findings"] if "filter" in f]
    assert filtered and all(f["rule"] in RULE_FILTERS for f in filtered)
    try:
        with tshark.workspace(tmp_path) as ws:
            rows, _ = run_fields(ws, capture, ["-2"], prefs={**ON, **dict(p.split(":", 1) for p in prefs)})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    for f in filtered:
        codes = [term.removeprefix("vm110.expert.") for term in f["filter"].split(" || ") if "(" not in term]
        marked = {r.number for r in rows if any(r.has(code) for code in codes)}
        items = {item["frame"] for item in f["items"]}
        assert items <= marked and len(marked) == len(items) + f.get("more", 0), f["rule"]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_the_illegal_filter_finds_an_empty_datagram_on_the_ports_analysed(tshark, tmp_path):
    """`analyze --port 6825`: the illegal rule's filter found an empty datagram (which Wireshark
    gives no dissector) by the default ports 5825/5827, so it missed the one on 6827 and would
    have marked one on 5827. It names the analysis' ports, and under the report's preferences it
    shows exactly the illegal items."""
    from test_analysis_craft import CTRL, Traffic, payload, vrpi
    from vm110.layers import VRPO
    tr = Traffic()
    for k in range(40):
        tr.add(k * 0.125, vrpi(k), sport=6825)
        tr.add(0.01 + k * 0.1, payload(VRPO, k, packet_number=0, periodic_data=b"x" * 10), src=CTRL, sport=6827)
    tr.add(2.05, b"", src=CTRL, sport=6827)                       # empty: illegal on this port pair
    tr.add(2.06, b"", src=CTRL, sport=C.OUTPUT_PORT)              # empty on 5827: not EG-Link here
    tr.frames.sort(key=lambda f: f[0])
    capture = tmp_path / "ports.pcap"
    tr.write(capture)
    done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(capture), "--port", "6825", "--json", "-",
                           "--quiet"], capture_output=True, text=True, timeout=300)
    report = json.loads(done.stdout)
    [illegal] = [f for f in report["verdict"]["findings"] if f["rule"] == "illegal"]
    assert "udp.port in {6825, 6827}" in illegal["filter"] and len(illegal["items"]) == 1
    prefs = [arg for p in report["verdict"]["wireshark_prefs"] for arg in ("-o", p)]
    assert prefs == ["-o", "vm110.input_port:6825"]
    try:
        with tshark.workspace(tmp_path) as ws:
            (ws.dir / capture.name).write_bytes(capture.read_bytes())
            shown = ws.run(["-r", str(ws.dir / capture.name), "-2", *prefs, "-Y", illegal["filter"], "-T", "fields",
                            "-e", "frame.number"]).stdout.split()
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert [int(n) for n in shown] == [illegal["items"][0]["frame"]]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_the_findings_filters_are_wireshark_filters(tshark, tmp_path):
    """Each rule's filter compiles, and shows every duplicate of overlap.pcapng: 107, of which the
    report keeps 100."""
    capture = CAPTURES / "overlap.pcapng"
    report = report_of(capture)
    dup = next(f for f in report["verdict"]["findings"] if f["rule"] == "duplicates")
    assert (dup["count"], dup.get("more")) == (107, 7)
    try:
        with tshark.workspace(tmp_path) as ws:
            (ws.dir / capture.name).write_bytes(capture.read_bytes())
            every = " || ".join(f"({f})" for f in RULE_FILTERS.values())
            for expression, expected in ((dup["filter"], 107), (every, None)):
                proc = ws.run(["-r", str(ws.dir / capture.name), "-2", "-Y", expression], check=False)
                assert proc.returncode == 0, f"{expression!r}: {proc.stderr.strip()}"
                assert expected is None or len(proc.stdout.splitlines()) == expected
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_expert_summaries_are_constant(tshark, tmp_path):
    """Wireshark's expert statistics group by summary: one line per analysis expert, so its counts
    are the dissector's (on loss.pcapng 62 serial gaps, not the 58 distinct texts of old)."""
    capture = CAPTURES / "loss.pcapng"
    try:
        with tshark.workspace(tmp_path) as ws:
            (ws.dir / capture.name).write_bytes(capture.read_bytes())
            text = ws.run(["-r", str(ws.dir / capture.name), "-2", *T.pref_args(ON), "-q", "-z", "expert"]).stdout
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    lines = [line for line in text.splitlines() if "VM110" in line]
    summaries = [line.split("VM110", 1)[1].strip() for line in lines]
    assert len(summaries) == len(set(summaries)), lines
    rows = dissected(tshark, capture, tmp_path)
    gaps = sum(bool(r.get("vm110.analysis.serial_missing")) for r in rows)
    assert any(line.split()[0] == str(gaps) and "Serial gap" in line for line in lines), lines


def expert_severities(text: str, protocol: str) -> dict[str, str]:
    """Summary -> section ("Warns", "Notes", ...) of one protocol's lines in tshark -z expert."""
    out, section = {}, None
    for line in text.splitlines():
        words = line.split()
        if len(words) == 2 and words[1].startswith("("):
            section = words[0]
        elif len(words) > 3 and words[0].isdigit() and words[2] == protocol:
            out[" ".join(words[3:])] = section
    return out


def readme_analysis_severities() -> dict[str, str]:
    """Analysis expert code -> "Errors", "Notes" or "Warns", as README's list of the analysis
    experts says where it first names each (a code marked "(error" is an error, "(note" a note; the
    others are warnings)."""
    text = (T.REPO / "README.md").read_text()
    start = text.index("Experts (group sequence")
    paragraph = text[start:text.index("\n\n", start)]
    out: dict[str, str] = {}
    for code, marked in re.findall(r"`([a-z_]+)`(?: \((error|note))?", paragraph):
        out.setdefault(code, {"error": "Errors", "note": "Notes"}.get(marked, "Warns"))
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_analysis_expert_severities_as_readme_and_tcp(tshark, tmp_path):
    """A spurious retransmission (after the acknowledgement) is a note, as Wireshark's own
    tcp.analysis.spurious_retransmission (and its retransmissions and duplicate ACKs) are: the
    TCP severity read from this tshark, on a TCP segment sent again after its ACK. And README's
    list of the analysis experts gives each expert loss.pcapng and restart.pcapng raise the severity
    tshark shows (it called the spurious retransmission and the duplicate acknowledgement warnings)."""
    from scapy.layers.inet import IP, TCP
    from scapy.layers.l2 import Ether
    from scapy.packet import Raw
    from scapy.utils import wrpcap
    a, b = "10.0.0.1", "10.0.0.2"
    segment = IP(src=a, dst=b) / TCP(sport=1000, dport=80, flags="PA", seq=101, ack=501) / Raw(b"x" * 10)
    tcp = [Ether() / p for p in (IP(src=a, dst=b) / TCP(sport=1000, dport=80, flags="S", seq=100),
                                 IP(src=b, dst=a) / TCP(sport=80, dport=1000, flags="SA", seq=500, ack=101),
                                 IP(src=a, dst=b) / TCP(sport=1000, dport=80, flags="A", seq=101, ack=501), segment,
                                 IP(src=b, dst=a) / TCP(sport=80, dport=1000, flags="A", seq=501, ack=111), segment)]
    for i, p in enumerate(tcp):
        p.time = 1 + i / 100
    ours = {}
    try:
        with tshark.workspace(tmp_path) as ws:
            wrpcap(str(ws.dir / "tcp.pcap"), tcp)
            tcp_text = ws.run(["-r", str(ws.dir / "tcp.pcap"), "-q", "-z", "expert"], plugin=False).stdout
            for capture in (CAPTURES / "loss.pcapng", CAPTURES / "restart.pcapng"):
                (ws.dir / capture.name).write_bytes(capture.read_bytes())
                ours |= expert_severities(ws.run(["-r", str(ws.dir / capture.name), "-2", *T.pref_args(ON), "-q",
                                                  "-z", "expert"]).stdout, "VM110")
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    tcp_sev = expert_severities(tcp_text, "TCP")
    summaries = dict(re.findall(r'seq\("([a-z_]+)", "([^"]+)"', (T.REPO / "dissector" / "vm110.lua").read_text()))
    assert tcp_sev["This frame is a (suspected) spurious retransmission"] == \
        ours[summaries["spurious_retransmission"]] == "Notes", (tcp_sev, ours)
    readme = readme_analysis_severities()
    shown = {code: ours[summaries[code]] for code in summaries if summaries[code] in ours}
    assert len(shown) >= 12 and "Errors" in shown.values(), ours
    assert {code: readme[code] for code in shown} == shown


# `vm110 analyze`'s rule -> the dissector's experts of the same finding: those of the rule's filter,
# and the experts of the rules that have none. Two rules have no expert of their own: the dissector's
# serial gap is seen at detection, also when a later packet fills it (a warning, as TCP's "previous
# segment not captured"), where analyze's `lost` counts only serials never received; and a packet
# cut short by the snaplen is the `illegal` rule's `truncated`.
RULE_EXPERTS = {**{rule: tuple(re.findall(r"vm110\.expert\.([a-z_]+)", expression))
                   for rule, expression in RULE_FILTERS.items()},
                "failed": ("ack_late", "never_acked"), "vrpo_incomplete": ("burst_incomplete",), "relays_open": ("es_relays_open",)}
NO_EXPERT_OF_THEIR_OWN = {"lost", "snaplen_truncated"}
SEVERITY_LEVELS = {"Error": "error", "Warning": "warning", "Note": "note"}   # (PDML's "Severity level: ...")
# Between them, every rule of RULE_EXPERTS (the crafted capture: a timestamp going backwards, an ack
# without a command, a late one)
SEVERITY_CAPTURES = ("restart.pcapng", "loss.pcapng", "vrpo-split.pcapng", "illegal.pcap", "crafted.pcap")


def _crafted_severities(pcap: Path) -> None:
    bu = {"origin": 0x0101}
    from vm110.layers import VM110, VRAO, VRCI, VRPI
    timeline = [(ms, VM110(serial=s, **bu) / VRPI()) for s, ms in enumerate((0, 100, 200, 150, 250), start=1)]
    timeline += [(260, VM110(serial=1) / VRAO(command_id=7)), (300, VM110(serial=6, **bu) / VRCI(command_id=1)),
                 (300 + C.VRCI_FAIL_MS + 100, VM110(serial=2) / VRAO(command_id=1))]
    T.write_pcap(pcap, [bytes(p) for _, p in timeline], [ms * 1000 for ms, _ in timeline])


def expert_levels(ws: T.Workspace, pcap: Path, codes: set[str]) -> dict[str, set[str]]:
    """Expert code -> the severities tshark -2 gives it on this capture (those of `codes`)."""
    from lxml import etree
    shown = ws.run(["-r", str(pcap), "-2", *T.pref_args(ON), "-T", "pdml",
                    "-Y", " || ".join(f"vm110.expert.{c}" for c in sorted(codes))]).stdout
    out: dict[str, set[str]] = defaultdict(set)
    for expert in etree.fromstring(shown.encode(), parser=etree.XMLParser(huge_tree=True)).iter("field"):
        if expert.get("name") != "_ws.expert":
            continue
        children = {c.get("name"): c for c in expert}
        code = next((n[len("vm110.expert."):] for n in children if n and n.startswith("vm110.expert.")), None)
        level = children["_ws.expert.severity"].get("showname").split(": ", 1)[1]
        if code in codes:
            out[code].add(SEVERITY_LEVELS.get(level, level))
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_each_finding_has_the_severity_of_its_dissector_experts(tshark, tmp_path):
    """A finding is as severe in `vm110 analyze` as the dissector's experts of it are in Wireshark,
    read from tshark's own expert infos on captures that raise them (analyze called a spurious
    retransmission a warning, which the dissector and Wireshark's TCP call a note; the dissector
    called a watchdog violation, a late and a never acknowledged command warnings, which analyze
    and TS-0006 call errors)."""
    assert set(RULE_EXPERTS) | NO_EXPERT_OF_THEIR_OWN == {rule for rule, *_ in FINDINGS}
    codes = {c for experts in RULE_EXPERTS.values() for c in experts}
    ours: dict[str, set[str]] = defaultdict(set)       # rule -> analyze's severities of it
    theirs: dict[str, set[str]] = defaultdict(set)     # rule -> tshark's severities of its experts
    try:
        with tshark.workspace(tmp_path) as ws:
            for name in SEVERITY_CAPTURES:
                pcap = ws.dir / name
                if name == "crafted.pcap":
                    _crafted_severities(pcap)
                else:
                    pcap.write_bytes((CAPTURES / name).read_bytes())
                levels = expert_levels(ws, pcap, codes)
                for f in analyze(str(pcap))["verdict"]["findings"]:
                    shown = {lv for c in RULE_EXPERTS.get(f["rule"], ()) for lv in levels.get(c, ())}
                    if shown:
                        ours[f["rule"]].add(f["severity"])
                        theirs[f["rule"]] |= shown
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert set(ours) == set(RULE_EXPERTS), sorted(set(RULE_EXPERTS) - set(ours))
    assert ours == theirs
