"""Capture synthesis: deterministic bytes, and a ground truth that an independent decode of the
written capture (scapy for the frames, vm110.decode for the EG-Link payloads) agrees with."""
from __future__ import annotations

import itertools
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
from vm110.sim.bu import BaseUnit
from vm110.sim.clock import seconds
from vm110.sim.controller import Controller
from vm110.sim.node import Meta
from vm110.sim.scenario import CONTROLLER_NEW_PORT, EPOCH_US, SCENARIOS
from vm110.sim.truth import GroundTruth
from vm110.sim.virtual import Station, VirtualNetwork
from vm110.synth import synthesize, truth_path

LIBRARY = [name for name in SCENARIOS if name not in ("day", "restart")]     # restart: below, from the logs


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
    """The truth's figures, counted again from decoded packets with plain set arithmetic (for
    senders that do not restart: one cycle of the counter, repeats within the 1 s window)."""
    frames = len(rows)
    end = rows[-1][0] if rows else 0.0
    rows = [row for row in rows if row[2] is not None]
    legal = [(t, s, f) for t, s, f in rows if not f["problems"]]
    reasons = Counter(r for _, _, f in rows for r in f["problems"])
    per_sender = defaultdict(list)
    for t, s, f in legal:
        per_sender[s].append((t, f))
    senders, dup_frames = {}, set()
    for s, items in per_sender.items():
        unwrapped = unwrap([f["serial"] for _, f in items])
        seen, last_at, dups, late, high = set(), {}, 0, 0, None
        for (t, f), u in zip(items, unwrapped):
            if u in last_at and t - last_at[u] < 1.0:
                dups += 1
                dup_frames.add(id(f))
                continue
            if high is not None and u < high:
                late += 1
            seen.add(u)
            last_at[u] = t
            high = u if high is None else max(high, u)
        lost = set(range(unwrapped[0], max(unwrapped) + 1)) - seen
        senders[s] = {"by_type": dict(Counter(f["type"] for _, f in items)), "lost": len(lost),
                      "duplicates": dups, "out_of_order": late, "received": len(items)}
    accepted = [(t, s, f) for t, s, f in legal if id(f) not in dup_frames]
    commands = {}
    for kind, ack in (("VRCI", "VRAO"), ("VRCO", "VRAI")):
        cmds, last_tx = [], {}
        for t, s, f in accepted:
            if f["type"] == kind:
                key = (s, f["command_id"])
                if key not in last_tx or t - last_tx[key][0] >= 2.0:
                    cmds.append({"id": f["command_id"], "first": t, "tx": 0, "ack": None})
                    last_tx[key] = (t, cmds[-1])
                last_tx[key] = (t, last_tx[key][1])
                last_tx[key][1]["tx"] += 1
            elif f["type"] == ack:
                started = [c for c in cmds if c["id"] == f["command_id"]]
                if started and started[-1]["ack"] is None:
                    started[-1]["ack"] = t
        commands[kind] = {"commands": len(cmds), "transmissions": sum(c["tx"] for c in cmds),
                          "acked": sum(c["ack"] is not None for c in cmds),
                          "failed": sum(c["ack"] is None or c["ack"] - c["first"] > 2.0 for c in cmds)}
    periodic = {}
    for ptype, limit in (("VRPI", 0.5), ("VRPO", 2.0)):
        for s in per_sender:
            times = [t for t, s2, f in accepted if s2 == s and f["type"] == ptype]
            if times:
                gaps = [b - a > limit for a, b in itertools.pairwise(times)] + [end - times[-1] > limit]
                periodic[(ptype, s)] = (len(times), sum(gaps))
    return {"frames": frames, "packets": len(rows), "illegal": sum(bool(f["problems"]) for _, _, f in rows),
            "reasons": dict(reasons), "crc_bad": sum(f.get("crc.status") == C.CRC_BAD for _, _, f in rows),
            "senders": senders, "commands": commands, "periodic": periodic}


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
        assert s["serial"]["restarts"] == 0
    for kind, mine in counted["commands"].items():
        theirs = truth["commands"][kind]
        assert {k: theirs[k] for k in mine} == mine, kind
        assert theirs["retransmissions"] == theirs["transmissions"] - theirs["commands"]
        assert theirs["unacked"] == theirs["commands"] - theirs["acked"] and theirs["interrupted"] == 0
    for p in truth["periodic"]:
        assert (p["count"], len(p["watchdog"]["violations"])) == counted["periodic"][(p["type"], p["sender"])]


@pytest.mark.parametrize("name", LIBRARY)
def test_truth_agrees_with_an_independent_decode(name, tmp_path):
    out = str(tmp_path / f"{name}.pcap")
    truth = synthesize(name, out, seed=11)
    assert json.loads(pathlib.Path(truth_path(out)).read_text()) == truth
    compare(truth, recount(read_capture(out)))


def test_long_run_with_wraps_agrees_too(tmp_path):
    out = str(tmp_path / "day.pcapng")
    truth = synthesize("day", out, seed=65000, duration_s=120.0, fmt="pcapng")
    compare(truth, recount(read_capture(out, ng=True)))
    assert any(s["serial"]["wraps"] for s in truth["senders"])


@pytest.mark.parametrize("name", ["loss", "overlap"])
def test_same_seed_same_bytes_other_seed_other_bytes(name, tmp_path):
    paths = [str(tmp_path / f"{i}.pcapng") for i in range(3)]
    for path, seed in zip(paths, (5, 5, 6)):
        synthesize(name, path, seed=seed, duration_s=8.0, fmt="pcapng")
    read = [(pathlib.Path(p).read_bytes(), pathlib.Path(truth_path(p)).read_bytes()) for p in paths]
    assert read[0] == read[1]
    assert read[0][0] != read[2][0] and read[0][1] != read[2][1]


def test_restarts_on_a_new_port_are_reproducible(tmp_path):
    paths = [str(tmp_path / f"{i}.pcap") for i in range(2)]
    for path in paths:
        synthesize("restart", path, seed=3, duration_s=30.0)
    assert pathlib.Path(paths[0]).read_bytes() == pathlib.Path(paths[1]).read_bytes()
    assert pathlib.Path(truth_path(paths[0])).read_bytes() == pathlib.Path(truth_path(paths[1])).read_bytes()


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
    # The truth is in the report's shape (docs/report.md, the keys marked ✓): the same version.
    from vm110.analysis.report import SCHEMA_VERSION
    assert json.loads((tmp_path / "x.pcapng.truth.json").read_text())["schema_version"] == SCHEMA_VERSION
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


@pytest.mark.parametrize("path", sorted(p for p in LIBRARY_DIR.glob("*.truth.json") if p.name.split(".")[0] in SCENARIOS),
                         ids=lambda p: p.name)     # crane.pcapng: captures/crane.py (test_crane_capture)
def test_library_is_what_make_captures_writes(path, tmp_path):
    capture = path.with_name(path.name[:-len(".truth.json")])
    name = capture.name.split(".")[0]
    out = tmp_path / capture.name
    synthesize(name, str(out), seed=1, fmt="pcapng" if capture.suffix == ".pcapng" else "pcap")
    assert out.read_bytes() == capture.read_bytes(), f"run `make captures`: {capture.name} is stale"
    assert (tmp_path / path.name).read_bytes() == path.read_bytes()



# --- the new scenarios against what the simulators logged and sent ----------------------------
def run_scenario(name: str, seed: int = 1) -> tuple[list, list]:
    """The scenario's stations after a run on the virtual clock, and every arrival at the tap:
    the same run `synthesize` writes (same seed, same events)."""
    sc = SCENARIOS[name]
    stations = sc.stations(seed, sc.duration_s)
    arrivals = [a for batch in VirtualNetwork(stations).run(sc.duration_s) for a in batch]
    return stations, arrivals


def by_node(truth: dict, station) -> list[dict]:
    return [s for s in truth["senders"] if s["src"].split(":")[0] == station.ip]


def test_outcome_of_every_command_is_the_senders_own(tmp_path):
    """Commands, acks, failures and interruptions in the truth are what the nodes logged; serials
    lost are what the nodes sent and the tap did not see; duplicates are the mirror copies."""
    for name in ("overlap", "bu-stops", "restart"):
        truth = synthesize(name, str(tmp_path / f"{name}.pcap"), seed=1)
        stations, arrivals = run_scenario(name)
        mirror = sum(not a[6] for a in arrivals)
        assert sum(s["serial"]["duplicates"] for s in truth["senders"]) == mirror, name
        for station in stations:
            node, mine = station.node, by_node(truth, station)
            seen = sum(s["serial"]["received"] - s["serial"]["duplicates"] for s in mine)
            assert seen + sum(s["serial"]["lost"] for s in mine) == sum(node.sent.values()), (name, node.name)
            kind = node.command_type.value
            events = node.command_events
            cmds = truth["commands"][kind]
            assert cmds["commands"] == len(node.events(events.sent)), (name, kind)
            assert cmds["acked"] == len(node.events(events.acked)), (name, kind)
            # dropped at a restart: interrupted unless past the fail limit (then failed, as given up)
            sent_at, dropped = {}, []          # ages of the dropped commands
            for e in node.log:
                if e["event"] == events.sent:
                    sent_at[e["command_id"]] = e["t"]
                elif e["event"] == events.dropped:
                    dropped.append(e["t"] - sent_at[e["command_id"]])
            assert cmds["interrupted"] == sum(age <= 2.0 for age in dropped), (name, kind)
            assert cmds["failed"] == len(node.events(events.gave_up)) + sum(age > 2.0 for age in dropped)
            assert cmds["unacked"] == cmds["commands"] - cmds["acked"] - cmds["interrupted"]


def test_overlap_has_commands_in_flight_together_and_reused_ids(tmp_path):
    truth = synthesize("overlap", str(tmp_path / "o.pcapng"), seed=1, fmt="pcapng")
    compare(truth, recount(read_capture(str(tmp_path / "o.pcapng"), ng=True)))
    for kind in ("VRCI", "VRCO"):
        cmds = truth["commands"][kind]["list"]
        spans = [(c["frames"][0], c["ack_frame"] or c["frames"][-1]) for c in cmds]
        assert any(b[0] < a[1] for a, b in itertools.pairwise(spans)), f"no two {kind} in flight together"
        assert truth["commands"][kind]["retransmissions"] > 10
    ids = Counter(c["command_id"] for c in truth["commands"]["VRCI"]["list"])
    assert sum(n > 1 for n in ids.values()) > 10                  # IDs used again after the pause
    assert truth["commands"]["VRCI"]["failed"] == 1 and truth["commands"]["VRCI"]["acks_without_command"] == 0
    assert all(s["serial"]["duplicates"] > 20 for s in truth["senders"])
    assert all(not p["watchdog"]["violations"] for p in truth["periodic"])


def test_bu_stops_leaves_vrpi_silent_until_the_end(tmp_path):
    truth = synthesize("bu-stops", str(tmp_path / "b.pcap"), seed=1)
    stations, arrivals = run_scenario("bu-stops")
    bu = stations[0].node
    assert [e["t"] for e in bu.events("stopped")] == [10.0]
    frame, last_vrpi = max((n, a[0]) for n, a in enumerate(arrivals, 1) if a[5].ptype is C.PacketType.VRPI)
    periodic = {p["type"]: p for p in truth["periodic"]}
    assert periodic["VRPI"]["watchdog"]["violations"] == [
        {"start": round((EPOCH_US + last_vrpi) / 1e6, 6), "gap_ms": (arrivals[-1][0] - last_vrpi) / 1000,
         "until_end": True, "frame": frame}]
    assert periodic["VRPO"]["watchdog"]["violations"] == []
    assert truth["commands"]["VRCO"]["failed"] == 2 and truth["commands"]["VRCI"]["failed"] == 0


def test_restarts_are_where_the_nodes_restarted(tmp_path):
    truth = synthesize("restart", str(tmp_path / "r.pcap"), seed=1)
    stations, arrivals = run_scenario("restart")
    events = []
    for s in truth["senders"]:
        events += [(e["time"], s["src"], e) for e in s["serial"]["restart_events"]]
    logged = []
    for station in stations:
        port = station.port
        for e in station.node.events("restart"):
            before = [a[5].serial for a in arrivals if a[5].sender == station.node.name and a[0] < seconds(e["t"])]
            assert e.get("port_from", e["port"]) == port      # the port it sent from before
            port = e["port"]
            logged.append((round(EPOCH_US / 1e6 + e["t"], 6), f"{station.ip}:{port}", before[-1], e["serial"],
                           "port_from" in e))
    assert sorted((t, src, e["from"], e["to"], "port_to" in e) for t, src, e in events) == sorted(logged)
    assert [s["serial"]["restarts"] for s in truth["senders"]] == [1, 1, 1]
    bu = next(s for s in truth["senders"] if s["direction"] == "Input")
    assert bu["serial"]["restart_events"][0]["from"] > 32767 and bu["serial"]["lost"] < 5
    new_port = next(e for _, _, e in events if "port_to" in e)
    assert (new_port["port_from"], new_port["port_to"]) == (C.OUTPUT_PORT, CONTROLLER_NEW_PORT)
    assert all(s["serial"]["duplicates"] == s["serial"]["out_of_order"] == 0 for s in truth["senders"])
    assert truth["commands"]["VRCI"]["interrupted"] == truth["commands"]["VRCO"]["interrupted"] == 1
    vrpo = [p for p in truth["periodic"] if p["type"] == "VRPO"]
    # the old port's stream is taken over: no silence to the end; the 2.3 s to the new port is a violation
    assert [len(p["watchdog"]["violations"]) for p in vrpo] == [1, 0]
    assert vrpo[0]["sender"].endswith(f":{CONTROLLER_NEW_PORT} origin 0x0000")


def test_truth_rules_at_a_restart_candidate():
    """docs/rules.md by hand: an ack between a restart and the packet that confirms it finds its
    command interrupted; an unconfirmed candidate is out of order; copies of it are duplicates."""
    stations = [Station(BaseUnit(), "10.0.0.10", C.INPUT_PORT), Station(Controller(), "10.0.0.20", C.OUTPUT_PORT)]
    P = C.PacketType
    plan = [(0.0, 0, P.VRPI, 100, 0), (0.1, 0, P.VRCI, 101, 5), (0.2, 0, P.VRPI, 102, 0),
            (1.5, 0, P.VRPI, 0, 0),                        # a restart candidate ...
            (1.51, 1, P.VRAO, 0, 5),                       # ... an ack before it is confirmed ...
            (1.6, 0, P.VRPI, 1, 0),                        # ... and its confirmation
            (1.7, 0, P.VRPI, 2, 0), (1.8, 0, P.VRPI, 40000, 0), (1.8001, 0, P.VRPI, 40000, 0),
            (1.9, 0, P.VRPI, 3, 0)]                        # 40000: a candidate left unconfirmed
    truth = GroundTruth(stations, EPOCH_US)
    truth.add([(seconds(t), n, endpoint, b"", (), Meta(stations[endpoint].node.name, ptype, serial, key, 0), True)
               for n, (t, endpoint, ptype, serial, key) in enumerate(plan)])
    report = truth.report()
    bu = report["senders"][0]["serial"]
    assert bu["restart_events"] == [{"time": round(EPOCH_US / 1e6 + 1.5, 6), "frame": 4, "from": 102, "to": 0}]
    assert (bu["out_of_order_serials"], bu["duplicate_serials"], bu["lost"]) == ([40000], [40000], 0)
    vrci = report["commands"]["VRCI"]
    assert (vrci["interrupted"], vrci["acks_without_command"], vrci["unacked"], vrci["failed"]) == (1, 1, 0, 0)


READING = ["--crc", "bzip2", "--crc-order", "big", "--serial-scope", "type", "--vrpo-start", "1"]


@pytest.mark.parametrize("name", ["vrpo-split", "restart", "overlap"])
def test_a_capture_of_another_reading_has_the_truth_analyze_gives_under_the_same_options(tmp_path, name):
    """`synth` had none of the reading options `simulate` and `analyze` share: a capture of another
    reading of TS-0006 could not be synthesised with its ground truth. Now both devices speak it
    and `analyze` given the same options reports the truth; at its defaults (VRPO numbered from 0)
    it does not, nor under interpretation.md's CRC."""
    from test_analysis_truth import contract_diff
    from vm110 import cli

    out = tmp_path / "reading.pcap"
    assert cli.main(["synth", name, "--out", str(out), "--seed", "3", *READING]) == 0
    truth = json.loads(pathlib.Path(truth_path(str(out))).read_text())
    assert truth["crc"] == {"variant": "bzip2", "byte_order": "big", "valid": truth["capture"]["eglink_packets"],
                            "invalid": 0}
    assert {s["serial"]["scope"] for s in truth["senders"]} == {"type"}

    def report(*options: str) -> dict:
        path = tmp_path / "report.json"
        assert cli.main(["analyze", str(out), "--quiet", "--json", str(path), *options]) in (0, 1)
        return json.loads(path.read_text())
    assert contract_diff(truth, report(*READING)) == []     # every packet valid under bzip2/big among them
    different = contract_diff(truth, report())       # (auto finds the CRC, and may find the scope)
    assert any(d.startswith(".vrpo_bursts.complete: ") for d in different), different
    assert report("--crc", "mpeg2", "--crc-order", "little", *READING[4:])["crc"]["valid"] == 0


@pytest.mark.parametrize("name", [n for n in SCENARIOS if n != "day"])
def test_auto_finds_the_per_type_counters_of_every_scenario(tmp_path, name):
    """Devices numbering each packet type on its own (the simulators' `--serial-scope type`, no
    analysis code): `analyze` at its defaults must find the scope, and then the truth's serial
    verdicts. It counted lost serials, and asked per-type counters for half the anomalies: on
    `retransmit` (a burst of lost acks) and `vrpo-split` (lost burst parts, in both readings) it
    took one counter, with false out-of-order packets and the real losses missed."""
    from vm110 import cli

    out = tmp_path / "typed.pcap"
    assert cli.main(["synth", name, "--out", str(out), "--seed", "2", "--serial-scope", "type"]) == 0
    truth = json.loads(pathlib.Path(truth_path(str(out))).read_text())
    report = tmp_path / "report.json"
    assert cli.main(["analyze", str(out), "--quiet", "--json", str(report)]) in (0, 1)
    counts = ("lost", "duplicates", "out_of_order", "restarts")
    told = {s["id"]: (s["serial"]["scope"], [s["serial"][k] for k in counts])
            for s in json.loads(report.read_text())["senders"] if len(s["by_type"]) > 1}
    assert told and told == {s["id"]: ("type", [s["serial"][k] for k in counts])
                             for s in truth["senders"] if s["id"] in told}


def test_synth_keeps_no_node_log(tmp_path, monkeypatch):
    """Review: `vm110 synth` ran nodes that kept every log entry (about 16 MB per 18,000 s of
    'normal', for a log nothing reads); the truth and the capture are the same without it."""
    from vm110.sim import scenario as S
    built = []
    real = S.Scenario.stations

    def stations(self, *args, **kwargs):
        built.extend(real(self, *args, **kwargs))
        return built
    monkeypatch.setattr(S.Scenario, "stations", stations)
    truth = synthesize("normal", str(tmp_path / "n.pcap"), seed=1, duration_s=30.0)
    assert truth["capture"]["packets"] > 500
    assert built and all(station.node.log == [] for station in built)
