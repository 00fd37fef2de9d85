"""Capture synthesis: deterministic bytes, and a ground truth that an independent decode of the
written capture (scapy for the frames, vm110.decode for the EG-Link payloads) agrees with."""
from __future__ import annotations

import json
import pathlib
import struct
import subprocess
import sys
from collections import Counter, defaultdict

import pytest
from scapy.layers.inet import IP, UDP
from scapy.packet import Raw
from scapy.utils import RawPcapNgReader, RawPcapReader

from vm110 import constants as C
from vm110.decode import decode
from vm110.sim.scenario import SCENARIOS
from vm110.synth import synthesize, truth_path

LIBRARY = [name for name in SCENARIOS if name != "day"]


def read_capture(path: str, ng: bool = False) -> list[tuple[float, str, dict]]:
    """(time, sender id, decoded fields) per frame, checking the frame's own checksums on the way.

    The UDP payload is cut from the raw frame by the UDP length (scapy may dissect it as VM110
    when vm110.layers is loaded, and rebuilding an illegal packet need not give its bytes back).
    """
    rows = []
    with (RawPcapNgReader if ng else RawPcapReader)(path) as reader:
        for raw, meta in reader:
            if ng:
                when = (meta.tshigh << 32 | meta.tslow) / meta.tsresol
            else:
                when = meta.sec + meta.usec / 1e6
            ip = IP(raw[14:])
            start = 14 + ip.ihl * 4
            sport, dport, udp_len, udp_sum = struct.unpack_from("!HHHH", raw, start)
            if sport not in (C.INPUT_PORT, C.OUTPUT_PORT):
                rows.append((when, None, None))          # other traffic on the tap
                continue
            assert raw[:6] == bytes.fromhex("01005e7f2a14") and raw[12:14] == b"\x08\x00"
            assert ip.dst == C.MULTICAST_GROUP and ip.ttl == C.MULTICAST_TTL
            payload = raw[start + 8:start + udp_len]
            rebuilt = IP(bytes(IP(src=ip.src, dst=ip.dst, ttl=ip.ttl, id=ip.id, flags=ip.flags)
                               / UDP(sport=sport, dport=dport) / Raw(payload)))
            assert (rebuilt.chksum, rebuilt[UDP].chksum) == (ip.chksum, udp_sum)
            fields = decode(payload)
            sender = f"{fields.get('direction')} {ip.src}:{sport} origin 0x{fields.get('origin', 0):04x}"
            rows.append((when, sender, fields))
    return rows


def unwrap(serials: list[int]) -> list[int]:
    out, high = [], None
    for s in serials:
        if high is None:
            u = s
        else:
            d = (s - high % 65536) % 65536
            u = high + d if d < 32768 else high - (65536 - d)
        high = u if high is None else max(high, u)
        out.append(u)
    return out


def recount(rows: list[tuple[float, str, dict]]) -> dict:
    """The truth's figures, counted again from decoded packets with plain set arithmetic."""
    frames = len(rows)
    rows = [row for row in rows if row[2] is not None]
    legal = [(t, s, f) for t, s, f in rows if not f["problems"]]
    reasons = Counter(r for _, _, f in rows for r in f["problems"])
    per_sender = defaultdict(list)
    for t, s, f in legal:
        per_sender[s].append((t, f))
    senders, dup_frames = {}, set()
    for s, items in per_sender.items():
        unwrapped = unwrap([f["serial"] for _, f in items])
        seen, dups, late, high = set(), 0, 0, None
        for (t, f), u in zip(items, unwrapped):
            if u in seen:
                dups += 1
                dup_frames.add(id(f))
            elif high is not None and u < high:
                late += 1
            seen.add(u)
            high = u if high is None else max(high, u)
        lost = set(range(unwrapped[0], max(unwrapped) + 1)) - seen
        senders[s] = {"by_type": dict(Counter(f["type"] for _, f in items)), "lost": len(lost),
                      "duplicates": dups, "out_of_order": late, "received": len(items)}
    commands = {}
    for kind, ack in (("VRCI", "VRAO"), ("VRCO", "VRAI")):
        sends = [(t, f["command_id"]) for t, s, f in legal if f["type"] == kind and id(f) not in dup_frames]
        acks = [(t, f["command_id"]) for t, s, f in legal if f["type"] == ack and id(f) not in dup_frames]
        first = {}
        for t, cid in sends:
            first.setdefault(cid, t)
        first_ack = {cid: min(t for t, c in acks if c == cid and t >= first[cid]) for cid in first
                     if any(c == cid and t >= first[cid] for t, c in acks)}
        failed = sum(cid not in first_ack or first_ack[cid] - first[cid] > 2.0 for cid in first) if kind == "VRCI" else 0
        commands[kind] = {"commands": len(first), "transmissions": len(sends), "acked": len(first_ack), "failed": failed}
    violations = {}
    for ptype, limit in (("VRPI", 0.5), ("VRPO", 2.0)):
        for s, items in per_sender.items():
            times = [t for t, f in items if f["type"] == ptype]
            if times:
                violations[(ptype, s)] = sum(b - a > limit for a, b in zip(times, times[1:]))
    return {"frames": frames, "packets": len(rows), "illegal": sum(bool(f["problems"]) for _, _, f in rows), "reasons": dict(reasons),
            "crc_bad": sum(f.get("crc.status") == C.CRC_BAD for _, _, f in rows),
            "senders": senders, "commands": commands, "violations": violations}


def compare(truth: dict, counted: dict) -> None:
    assert truth["capture"]["packets"] == counted["frames"]
    assert truth["capture"]["eglink_packets"] == counted["packets"]
    assert truth["illegal"]["total"] == counted["illegal"]
    assert truth["illegal"]["by_reason"] == counted["reasons"]
    assert truth["crc"]["invalid"] == counted["crc_bad"]
    assert truth["crc"]["valid"] == counted["packets"] - counted["crc_bad"]
    assert {s["id"] for s in truth["senders"]} == set(counted["senders"])
    for s in truth["senders"]:
        mine = counted["senders"][s["id"]]
        assert s["by_type"] == mine["by_type"]
        for key in ("received", "lost", "duplicates", "out_of_order"):
            assert s["serial"][key] == mine[key], (s["id"], key)
        assert len(s["serial"]["lost_serials"]) == s["serial"]["lost"]
    for kind, mine in counted["commands"].items():
        theirs = truth["commands"][kind]
        assert {k: theirs[k] for k in mine} == mine, kind
        assert theirs["retransmissions"] == theirs["transmissions"] - theirs["commands"]
    for p in truth["periodic"]:
        assert len(p["watchdog"]["violations"]) == counted["violations"][(p["type"], p["sender"])]


@pytest.mark.parametrize("name", LIBRARY)
def test_truth_agrees_with_an_independent_decode(name, tmp_path):
    out = str(tmp_path / f"{name}.pcap")
    truth = synthesize(name, out, seed=11)
    assert json.loads(open(truth_path(out)).read()) == truth
    compare(truth, recount(read_capture(out)))


def test_long_run_with_wraps_agrees_too(tmp_path):
    out = str(tmp_path / "day.pcapng")
    truth = synthesize("day", out, seed=65000, duration_s=120.0, fmt="pcapng")
    compare(truth, recount(read_capture(out, ng=True)))
    assert any(s["serial"]["wraps"] for s in truth["senders"])


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path):
    paths = [str(tmp_path / f"{i}.pcapng") for i in range(3)]
    for path, seed in zip(paths, (5, 5, 6)):
        synthesize("loss", path, seed=seed, duration_s=8.0, fmt="pcapng")
    read = [(open(p, "rb").read(), open(truth_path(p), "rb").read()) for p in paths]
    assert read[0] == read[1]
    assert read[0][0] != read[2][0] and read[0][1] != read[2][1]


def test_scenarios_show_what_they_promise(tmp_path):
    def run(name):
        return synthesize(name, str(tmp_path / f"{name}.pcap"), seed=1)
    retransmit = run("retransmit")["commands"]["VRCI"]
    assert retransmit["failed"] == 1 and retransmit["retransmissions"] > 10
    assert {c["command_id"] for c in retransmit["list"]} >= {65534, 65535, 0}
    vrco = run("vrco")["commands"]["VRCO"]
    assert vrco["unacked"] == 1 and vrco["retransmissions"] > 10
    illegal = run("illegal")
    assert set(illegal["illegal"]["by_reason"]) == {p.value for p in C.Problem}
    assert illegal["capture"]["packets"] == illegal["capture"]["eglink_packets"] + 4     # the mDNS frames
    bu_wd = {p["type"]: p for p in run("bu-watchdog")["periodic"]}
    assert [round(v["gap_ms"]) for v in bu_wd["VRPO"]["watchdog"]["violations"]] == [3100]
    ctl_wd = {p["type"]: p for p in run("controller-watchdog")["periodic"]}
    assert len(ctl_wd["VRPI"]["watchdog"]["violations"]) == 2
    split = run("vrpo-split")["vrpo_bursts"]
    assert split["complete"] > 100 and split["incomplete"] > 0
    glink = run("glink")
    assert glink["commands"]["VRCO"]["duplicate_acks"] > 0 and glink["commands"]["VRCO"]["unacked"] == 0
    normal = run("normal")
    assert [s["serial"]["wraps"] for s in normal["senders"]] == [1, 0]
    assert all(s["serial"]["lost"] == 0 for s in normal["senders"])


def vm110(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=60)


def test_cli_lists_writes_and_rejects(tmp_path):
    listing = vm110("synth", "--list")
    assert listing.returncode == 0 and all(name in listing.stdout for name in SCENARIOS)
    out = tmp_path / "x.pcapng"
    done = vm110("synth", "normal", "--out", str(out), "--duration", "3", "--seed", "2")
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:4] == b"\x0a\x0d\x0d\x0a"            # pcapng from the extension
    assert json.loads((tmp_path / "x.pcapng.truth.json").read_text())["schema_version"] == 1
    bad = vm110("synth", "nonsense", "--out", str(tmp_path / "y.pcap"))
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "unknown scenario" in bad.stderr
    unwritable = vm110("synth", "normal", "--out", str(tmp_path / "missing" / "z.pcap"))
    assert unwritable.returncode == 2 and "Traceback" not in unwritable.stderr


@pytest.mark.tshark
def test_tshark_reads_the_synthesised_captures(tmp_path):
    for fmt in ("pcap", "pcapng"):
        out = str(tmp_path / f"c.{fmt}")
        truth = synthesize("illegal", out, seed=3, duration_s=6.0, fmt=fmt)
        fields = subprocess.run(["tshark", "-r", out, "-o", "ip.check_checksum:TRUE", "-o", "udp.check_checksum:TRUE",
                                 "-T", "fields", "-e", "ip.checksum.status", "-e", "udp.checksum.status"],
                                capture_output=True, text=True, timeout=60)
        lines = fields.stdout.splitlines()
        assert len(lines) == truth["capture"]["packets"]
        assert all(line.split("\t")[:2] == ["1", "1"] for line in lines)     # 1 = Good

LIBRARY_DIR = pathlib.Path(__file__).resolve().parent.parent / "captures"


@pytest.mark.parametrize("path", sorted(LIBRARY_DIR.glob("*.truth.json")), ids=lambda p: p.name)
def test_library_is_what_make_captures_writes(path, tmp_path):
    capture = path.with_name(path.name[:-len(".truth.json")])
    name = capture.name.split(".")[0]
    out = tmp_path / capture.name
    synthesize(name, str(out), seed=1, fmt="pcapng" if capture.suffix == ".pcapng" else "pcap")
    assert out.read_bytes() == capture.read_bytes(), f"run `make captures`: {capture.name} is stale"
    assert (tmp_path / path.name).read_bytes() == path.read_bytes()

