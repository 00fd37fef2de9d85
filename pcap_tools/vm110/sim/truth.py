"""Ground truth of a synthesised capture, from the tap's event log (/work/notes/truth-contract.md).

The input is what the tap saw (`sim.virtual.Arrival`): the sender's own record of each packet
(type, serial, command ID, VRPO packet number and data length) and the illegal reasons the
impairments put in by construction. No packet bytes are decoded here. The rules are those of
interpretation.md; where it leaves a detail open the choice is written next to the code and in
captures/README.md.
"""
from __future__ import annotations

from collections import Counter, defaultdict
from typing import Any, Iterable, Optional, Sequence

from .. import constants as C
from ..crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT
from .clock import US_PER_S
from .virtual import Arrival, Station

SCHEMA_VERSION = 1
_WATCHDOG_MS = {C.PacketType.VRPI: C.VRPI_WATCHDOG_MS, C.PacketType.VRPO: C.VRPO_WATCHDOG_MS}
_COMMAND_TYPES = (C.PacketType.VRCI, C.PacketType.VRCO)
_VRPO = C.PacketType.VRPO
_BAD_CRC = C.Problem.BAD_CRC.value
_NAMES = {t: t.value for t in C.PacketType}


def _time(t_us: int) -> float:
    return round(t_us / US_PER_S, 6)


def _ms(delta_us: int) -> float:
    return round(delta_us / 1000, 3)


class _SerialTrack:
    """Serial classification of one sender: interpretation.md, 'Serial numbers'.

    Serials are unwrapped against the highest one seen (forward distance below 32768 is ahead),
    so "already seen" means seen in this cycle of the counter.
    """

    def __init__(self) -> None:
        self.high: Optional[int] = None          # unwrapped highest serial
        self.seen: set[int] = set()
        self.lost: set[int] = set()
        self.received = self.wraps = 0
        self.duplicates: list[int] = []
        self.out_of_order: list[int] = []
        self.gaps: list[dict[str, Any]] = []

    def add(self, serial: int, t: int) -> bool:
        """Classify one received serial; False when it is a duplicate."""
        self.received += 1
        if self.high is None:
            self.high = serial
            self.seen.add(serial)
            return True
        d = (serial - self.high) % C.SERIAL_MODULUS
        if 0 < d < C.SERIAL_HALF:
            unwrapped = self.high + d
            if d > 1:
                self.lost.update(range(self.high + 1, unwrapped))
                self.gaps.append({"after": self.high % C.SERIAL_MODULUS, "count": d - 1, "time": _time(t)})
            self.wraps += unwrapped // C.SERIAL_MODULUS - self.high // C.SERIAL_MODULUS
            self.high = unwrapped
        else:
            unwrapped = self.high - (C.SERIAL_MODULUS - d) % C.SERIAL_MODULUS
            if d == 0 or unwrapped in self.seen:
                self.duplicates.append(serial)
                return False
            self.out_of_order.append(serial)
            self.lost.discard(unwrapped)
        self.seen.add(unwrapped)
        if len(self.seen) > C.SERIAL_MODULUS:      # only the last half cycle can be "already seen"
            floor = self.high - C.SERIAL_HALF
            self.seen = {u for u in self.seen if u >= floor}
        return True

    def report(self) -> dict[str, Any]:
        return {"scope": "sender", "received": self.received, "lost": len(self.lost),
                "duplicates": len(self.duplicates), "out_of_order": len(self.out_of_order), "wraps": self.wraps,
                "lost_serials": [s % C.SERIAL_MODULUS for s in sorted(self.lost)],
                "duplicate_serials": self.duplicates, "out_of_order_serials": self.out_of_order,
                "gaps": self.gaps}


class _Commands:
    """Commands of one kind (VRCI or VRCO) and their acknowledgements, in capture order."""

    def __init__(self, kind: C.PacketType) -> None:
        self.kind = kind
        self.current: dict[str, dict[str, Any]] = {}     # sender -> its latest (not superseded) command
        self.list: list[dict[str, Any]] = []
        self.spurious = self.acks_without_command = self.duplicate_acks = 0

    def command(self, sender: str, command_id: int, frame: int, t: int) -> None:
        cmd = self.current.get(sender)
        if cmd is not None and cmd["command_id"] == command_id:
            cmd["frames"].append(frame)
            cmd["_times"].append(t)
            if cmd["ack_frame"] is not None:
                self.spurious += 1
            return
        cmd = {"sender": sender, "command_id": command_id, "frames": [frame], "ack_frame": None,
               "latency_first_ms": None, "latency_last_ms": None, "_times": [t], "_ack_t": None}
        self.current[sender] = cmd
        self.list.append(cmd)

    def ack(self, command_id: int, frame: int, t: int) -> None:
        matches = [c for c in self.current.values() if c["command_id"] == command_id]
        if not matches:
            self.acks_without_command += 1
            return
        cmd = max(matches, key=lambda c: c["frames"][0])
        if cmd["ack_frame"] is not None:
            self.duplicate_acks += 1
            return
        cmd["ack_frame"], cmd["_ack_t"] = frame, t
        cmd["latency_first_ms"] = _ms(t - cmd["_times"][0])
        cmd["latency_last_ms"] = _ms(t - cmd["_times"][-1])

    def report(self) -> dict[str, Any]:
        transmissions = sum(len(c["frames"]) for c in self.list)
        acked = sum(c["ack_frame"] is not None for c in self.list)
        limit = C.VRCI_FAIL_MS * 1000
        failed = 0
        if self.kind is C.PacketType.VRCI:
            failed = sum(c["_ack_t"] is None or c["_ack_t"] - c["_times"][0] > limit for c in self.list)
        return {"commands": len(self.list), "transmissions": transmissions,
                "retransmissions": transmissions - len(self.list), "acked": acked,
                "unacked": len(self.list) - acked, "failed": failed, "spurious_retransmissions": self.spurious,
                "acks_without_command": self.acks_without_command, "duplicate_acks": self.duplicate_acks,
                "list": [{k: v for k, v in c.items() if not k.startswith("_")} for c in self.list]}


def _bursts(packets: Sequence[tuple[int, int, int]]) -> tuple[int, int]:
    """(complete, incomplete) VRPO bursts of one sender from (time, packet number, data length).

    A burst: packets less than 20 ms apart. Complete: numbers 0..n-1 each once, every packet but
    the last 488 data bytes, the last fewer (interpretation.md, 'VRPO split').
    """
    complete = incomplete = 0
    gap = C.VRPO_BURST_GAP_MS * 1000
    burst: list[tuple[int, int]] = []
    last_t: Optional[int] = None
    for t, number, length in list(packets) + [(-1, 0, 0)]:
        if burst and last_t is not None and (t < 0 or t - last_t >= gap):
            ordered = sorted(burst)
            numbers = [n for n, _ in ordered]
            ok = (numbers == list(range(len(numbers)))
                  and all(n == C.VRPO_MAX_DATA for _, n in ordered[:-1]) and ordered[-1][1] < C.VRPO_MAX_DATA)
            complete += ok
            incomplete += not ok
            burst = []
        burst.append((number, length))
        last_t = t
    return complete, incomplete


def ground_truth(frames: Iterable[tuple[int, Optional[Arrival]]], stations: Sequence[Station],
                 epoch_us: int) -> dict[str, Any]:
    """The truth dict for a capture: `frames` are (time µs, arrival) in file order, arrival None
    for a frame that is not EG-Link."""
    ids = [s.sender_id for s in stations]
    illegal: Counter[str] = Counter()
    illegal_total = crc_bad = eglink = frame = 0
    serials: dict[str, _SerialTrack] = defaultdict(_SerialTrack)
    by_type: dict[str, Counter[str]] = defaultdict(Counter)
    periodic: dict[tuple[str, str], list[int]] = defaultdict(list)
    commands = {kind: _Commands(kind) for kind in _COMMAND_TYPES}
    vrpo: dict[str, list[tuple[int, int, int]]] = defaultdict(list)
    first_t = last_t = 0
    for t, a in frames:
        frame += 1
        if frame == 1:
            first_t = t
        last_t = t
        if a is None:
            continue
        eglink += 1
        if a.problems:
            illegal_total += 1
            illegal.update(a.problems)
            crc_bad += _BAD_CRC in a.problems
            continue
        sender, meta = ids[a.station], a.meta
        ptype = meta.ptype
        name = _NAMES[ptype]
        by_type[sender][name] += 1
        if ptype in _WATCHDOG_MS:
            periodic[(name, sender)].append(t)
        if not serials[sender].add(meta.serial, epoch_us + t):
            continue      # a repeated serial is a duplicate, not a transmission or an ack
        if ptype in _COMMAND_TYPES:
            commands[ptype].command(sender, meta.key, frame, t)
        elif ptype in C.ACK_OF:
            commands[C.ACK_OF[ptype]].ack(meta.key, frame, t)
        elif ptype is _VRPO:
            vrpo[sender].append((t, meta.key, meta.data_len))
    bursts = [_bursts(packets) for packets in vrpo.values()]
    return {
        "schema_version": SCHEMA_VERSION,
        "capture": {"packets": frame, "eglink_packets": eglink, "duration_s": _time(last_t - first_t)},
        "crc": {"variant": DEFAULT_VARIANT, "byte_order": DEFAULT_BYTE_ORDER,
                "valid": eglink - crc_bad, "invalid": crc_bad},
        "illegal": {"total": illegal_total, "by_reason": dict(sorted(illegal.items()))},
        "senders": [_sender(sid, stations[ids.index(sid)], by_type[sid], serials[sid]) for sid in sorted(serials)],
        "periodic": [_periodic(ptype, sender, times, epoch_us) for (ptype, sender), times in sorted(periodic.items())],
        "commands": {kind.value: c.report() for kind, c in commands.items()},
        "vrpo_bursts": {"complete": sum(c for c, _ in bursts), "incomplete": sum(i for _, i in bursts)},
    }


def _sender(sid: str, station: Station, types: Counter[str], track: _SerialTrack) -> dict[str, Any]:
    return {"id": sid, "direction": station.node.direction.value, "origin": station.node.origin,
            "src": f"{station.ip}:{station.port}", "by_type": dict(sorted(types.items())), "serial": track.report()}


def _periodic(ptype: str, sender: str, times: list[int], epoch_us: int) -> dict[str, Any]:
    limit = _WATCHDOG_MS[C.PacketType(ptype)]
    violations = [{"start": _time(epoch_us + a), "gap_ms": _ms(b - a)}
                  for a, b in zip(times, times[1:]) if b - a > limit * 1000]
    return {"type": ptype, "sender": sender, "count": len(times),
            "watchdog": {"limit_ms": limit, "violations": violations}}
