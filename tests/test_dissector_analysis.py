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

import json
import random
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import pytest
from scapy.layers.inet import UDP
from scapy.utils import rdpcap

import tshark_runner as T
from vm110 import constants as C
from vm110.decode import decode

pytestmark = pytest.mark.tshark

CAPTURES = T.REPO / "captures"
TRUTH_CAPTURES = sorted(p for p in CAPTURES.iterdir()
                        if p.suffix in (".pcap", ".pcapng") and Path(f"{p}.truth.json").exists())
ANALYSIS_FIELDS = (
    "analysis.serial_missing", "analysis.serial_duplicate", "analysis.serial_out_of_order", "analysis.interval",
    "analysis.retransmission_of", "analysis.retransmission_number", "analysis.since_first",
    "analysis.ack_in", "analysis.ack_to", "analysis.ack_time", "analysis.ack_time_last",
    "burst.packets", "burst.frame", "burst.complete", "reassembled")
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


def run_fields(ws: T.Workspace, capture: Path, extra=(), prefs=ON, fields=FIELDS) -> tuple[list[Row], str]:
    local = ws.dir / capture.name
    if not local.exists():
        local.write_bytes(capture.read_bytes())
    proc = ws.run(["-r", str(local), *T.pref_args(prefs), *extra, *field_args(fields)])
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
                _CACHE[key] = run_fields(ws, capture, ["-2"])[0]
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
    generated fields alone (a late packet removes its serial from the lost ones)."""
    out = defaultdict(lambda: {"gaps": [], "duplicate_serials": [], "out_of_order_serials": [], "missing": Counter()})
    for r in legal_rows(rows):
        missing = r.int("vm110.analysis.serial_missing")
        v, serial = out[r.sender], r.int("vm110.serial")
        if missing:
            after = (serial - missing - 1) % C.SERIAL_MODULUS
            v["gaps"].append({"after": after, "count": missing, "time": round(r.time, 6)})
            for k in range(1, missing + 1):
                v["missing"][(after + k) % C.SERIAL_MODULUS] += 1
            assert r.has("serial_gap")
        if r.get("vm110.analysis.serial_duplicate"):
            v["duplicate_serials"].append(serial)
            assert r.has("serial_duplicate")
        if r.get("vm110.analysis.serial_out_of_order"):
            v["out_of_order_serials"].append(serial)
            assert r.has("serial_out_of_order")
            if v["missing"][serial]:
                v["missing"][serial] -= 1
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_serials(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    view = serial_view(dissected(tshark, capture, tmp_path))
    assert sorted(view) == sorted(s["id"] for s in truth["senders"])
    for sender in truth["senders"]:
        want, got = sender["serial"], view[sender["id"]]
        assert got["gaps"] == want["gaps"], sender["id"]
        assert got["duplicate_serials"] == want["duplicate_serials"], sender["id"]
        assert got["out_of_order_serials"] == want["out_of_order_serials"], sender["id"]
        lost = sorted(got["missing"].elements())
        assert len(lost) == want["lost"], sender["id"]
        assert lost == sorted(s % C.SERIAL_MODULUS for s in want["lost_serials"]), sender["id"]


# --- Timing -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_watchdog(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    rows = dissected(tshark, capture, tmp_path)
    got = defaultdict(list)
    counts = Counter()
    for r in legal_rows(rows):
        kind = r.get("vm110.type")
        if kind not in ("VRPI", "VRPO"):
            continue
        interval = r.float("vm110.analysis.interval")
        assert (interval is None) == (counts[(kind, r.sender)] == 0), r.number
        counts[(kind, r.sender)] += 1
        limit = C.VRPI_WATCHDOG_MS if kind == "VRPI" else C.VRPO_WATCHDOG_MS
        tripped = r.has(f"watchdog_{kind.lower()}")
        assert tripped == (interval is not None and interval > limit), r.number
        if tripped:
            got[(kind, r.sender)].append({"start": round(r.time - interval / 1000, 6), "gap_ms": round(interval, 3)})
    for p in truth["periodic"]:
        key = (p["type"], p["sender"])
        assert got[key] == p["watchdog"]["violations"], key
        assert counts[key] == p["count"], key


# --- Commands and acknowledgements -------------------------------------------------------------------
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", TRUTH_CAPTURES, ids=lambda p: p.name)
def test_commands(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    rows = {r.number: r for r in eg_rows(dissected(tshark, capture, tmp_path))}
    linked_retransmissions, linked_acks = set(), set()
    for kind, ack_kind in ((C.PacketType.VRCI.value, "VRAO"), (C.PacketType.VRCO.value, "VRAI")):
        want = truth["commands"][kind]
        never = late = 0
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
        if kind == "VRCI":
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
            full, full_text = run_fields(ws, capture, ["-2"])
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


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_readme_analysis_filters(tshark, tmp_path):
    """The stream analysis filters the README shows compile and match frames of the captures."""
    readme = (T.REPO / "README.md").read_text()
    block = readme.split("**Stream analysis filters**", 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
    filters = [line.split("  ")[0].strip() for line in block.splitlines() if line.strip()]
    assert len(filters) >= 5
    try:
        with tshark.workspace(tmp_path) as ws:
            for capture in ("loss.pcapng", "bu-watchdog.pcap", "vrpo-split.pcapng"):
                (ws.dir / capture).write_bytes((CAPTURES / capture).read_bytes())
            for expression in filters:
                matched = 0
                for capture in ("loss.pcapng", "bu-watchdog.pcap", "vrpo-split.pcapng"):
                    proc = ws.run(["-r", str(ws.dir / capture), "-2", "-Y", expression], check=False)
                    assert proc.returncode == 0, f"{expression!r}: {proc.stderr.strip()}"
                    matched += len(proc.stdout.splitlines())
                    if matched:
                        break
                assert matched, f"{expression!r} matches nothing"
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_preferences_type_scope_and_thresholds(tshark, tmp_path):
    """Per-type serial scope equals vm110.analysis.serials (the Python analysis) run per sender and
    type; a watchdog preference moves the threshold."""
    from vm110.analysis.serials import classify
    capture = CAPTURES / "loss.pcapng"
    try:
        with tshark.workspace(tmp_path) as ws:
            rows, _ = run_fields(ws, capture, ["-2"], prefs={**ON, "vm110.serial_scope": "type",
                                                            "vm110.vrpi_watchdog_ms": "100"})
            relaxed, _ = run_fields(ws, CAPTURES / "bu-watchdog.pcap", ["-2"],
                                    prefs={**ON, "vm110.vrpo_watchdog_ms": "3200"})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    streams = defaultdict(list)
    for r in legal_rows(rows):
        streams[(r.sender, r.get("vm110.type"))].append(r)
    assert len(streams) > 2
    seen = Counter()
    for key, stream in streams.items():
        want = classify([r.int("vm110.serial") for r in stream], [r.time for r in stream])
        gaps = [(r.int("vm110.serial"), r.int("vm110.analysis.serial_missing")) for r in stream
                if r.get("vm110.analysis.serial_missing")]
        assert gaps == [((after + count + 1) % C.SERIAL_MODULUS, count) for after, count, _ in want.gaps], key
        assert [r.int("vm110.serial") for r in stream if r.get("vm110.analysis.serial_duplicate")] \
            == want.duplicate_serials, key
        assert [r.int("vm110.serial") for r in stream if r.get("vm110.analysis.serial_out_of_order")] \
            == want.out_of_order_serials, key
        seen.update(gaps=len(want.gaps), duplicates=want.duplicates, late=want.out_of_order)
    assert min(seen["gaps"], seen["duplicates"], seen["late"]) > 0
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
