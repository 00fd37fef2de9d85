"""Ground truth of a synthesised capture, from the tap's event log (/work/notes/truth-contract.md).

The input is what the tap saw (`sim.virtual.Arrival`): the sender's own record of each packet
(type, serial, command ID, VRPO packet number and data length) and the illegal reasons the
impairments put in by construction. No packet bytes are decoded here. The rules are those of
interpretation.md; where it leaves a detail open the choice is written next to the code and in
captures/README.md.
"""
from __future__ import annotations

from collections import Counter
from typing import Any, Optional, Sequence

from .. import constants as C
from ..crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT
from .clock import US_PER_S
from .node import Meta
from .virtual import Arrival, Station

SCHEMA_VERSION = 1
_WATCHDOG_MS = {C.PacketType.VRPI: C.VRPI_WATCHDOG_MS, C.PacketType.VRPO: C.VRPO_WATCHDOG_MS}
_WATCHDOG_US = {ptype: limit * 1000 for ptype, limit in _WATCHDOG_MS.items()}
_COMMAND_TYPES = (C.PacketType.VRCI, C.PacketType.VRCO)
_VRPO = C.PacketType.VRPO
_BAD_CRC = C.Problem.BAD_CRC.value
_NAMES = {t: t.value for t in C.PacketType}
_MODULUS, _HALF, _VRPO_MAX_DATA = C.SERIAL_MODULUS, C.SERIAL_HALF, C.VRPO_MAX_DATA


def _time(t_us: int) -> float:
    return round(t_us / US_PER_S, 6)


def _ms(delta_us: int) -> float:
    return round(delta_us / 1000, 3)


class _SerialTrack:
    """Serial classification of one sender: interpretation.md, 'Serial numbers'.

    Serials are unwrapped against the highest one seen (forward distance below 32768 is ahead),
    so "already seen" means seen in this cycle of the counter. Between the first serial and the
    highest one, a serial has been seen exactly when it is not lost (a gap puts it in `lost`, its
    late arrival takes it out): no set of every serial is kept.
    """

    __slots__ = ("epoch_us", "first", "high", "early", "lost", "wraps", "duplicates", "out_of_order", "gaps")

    def __init__(self, epoch_us: int) -> None:
        self.epoch_us = epoch_us                 # added to times (µs) when reported
        self.first = 0                           # unwrapped first serial
        self.high: Optional[int] = None          # unwrapped highest serial
        self.early: set[int] = set()             # seen late, from before the first serial
        self.lost: set[int] = set()
        self.wraps = 0
        self.duplicates: list[int] = []
        self.out_of_order: list[int] = []
        self.gaps: list[dict[str, Any]] = []

    def add(self, serial: int, t: int) -> bool:
        """Classify one received serial; False when it is a duplicate."""
        high = self.high
        if high is None:
            self.first = self.high = serial
            return True
        d = (serial - high) % _MODULUS
        if d == 1:                                 # the next one: most packets
            self.high = high + 1
            if not serial:
                self.wraps += 1
        elif 0 < d < _HALF:
            unwrapped = self.high = high + d
            self.lost.update(range(high + 1, unwrapped))
            self.gaps.append({"after": high % _MODULUS, "count": d - 1, "time": _time(self.epoch_us + t)})
            self.wraps += unwrapped // _MODULUS - high // _MODULUS
        else:
            unwrapped = high - (_MODULUS - d) % _MODULUS
            early = unwrapped < self.first
            if d == 0 or (unwrapped in self.early if early else unwrapped not in self.lost):
                self.duplicates.append(serial)
                return False
            self.out_of_order.append(serial)
            if early:
                self.early.add(unwrapped)
            else:
                self.lost.discard(unwrapped)
        return True

    def report(self, received: int) -> dict[str, Any]:
        return {"scope": "sender", "received": received, "lost": len(self.lost),
                "duplicates": len(self.duplicates), "out_of_order": len(self.out_of_order), "wraps": self.wraps,
                "lost_serials": [s % _MODULUS for s in sorted(self.lost)],
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


def _complete_burst(burst: list[tuple[int, int]]) -> bool:
    """A VRPO burst of (packet number, data length): complete when the numbers are 0..n-1 each
    once, every packet but the last carries 488 data bytes and the last fewer (interpretation.md,
    'VRPO split'). A burst: packets less than 20 ms apart."""
    ordered = sorted(burst)
    numbers = [n for n, _ in ordered]
    return (numbers == list(range(len(numbers)))
            and all(n == C.VRPO_MAX_DATA for _, n in ordered[:-1]) and ordered[-1][1] < C.VRPO_MAX_DATA)


class _Sender:
    """What the truth keeps per sender, updated packet by packet."""

    __slots__ = ("id", "station", "by_type", "serial", "last", "violations", "burst", "burst_t", "complete",
                 "incomplete")

    def __init__(self, sid: str, station: Station, epoch_us: int) -> None:
        self.id, self.station = sid, station
        self.by_type: dict[C.PacketType, int] = {}     # legal packets (duplicates too), by type
        self.serial = _SerialTrack(epoch_us)
        self.last: dict[C.PacketType, int] = {}        # periodic type -> time of its latest packet
        self.violations: dict[C.PacketType, list[tuple[int, int]]] = {}   # -> gaps over its limit
        self.burst: list[Meta] = []                    # the VRPO burst being received
        self.burst_t = 0
        self.complete = self.incomplete = 0

    def close_burst(self) -> None:
        burst = self.burst
        if not burst:
            return
        if len(burst) == 1:                        # most bursts: one packet
            meta = burst[0]
            complete = meta.key == 0 and meta.data_len < _VRPO_MAX_DATA
        else:
            complete = _complete_burst([(meta.key, meta.data_len) for meta in burst])
        if complete:
            self.complete += 1
        else:
            self.incomplete += 1
        self.burst = []

    def report(self) -> dict[str, Any]:
        station = self.station
        return {"id": self.id, "direction": station.node.direction.value, "origin": station.node.origin,
                "src": f"{station.ip}:{station.port}",
                "by_type": {_NAMES[t]: n for t, n in sorted(self.by_type.items())},
                "serial": self.serial.report(sum(self.by_type.values()))}


class GroundTruth:
    """The truth of a capture, fed with the tap's arrivals in file order (`add`, batch by batch);
    an arrival whose station index is past the last station is a frame that is not EG-Link."""

    def __init__(self, stations: Sequence[Station], epoch_us: int) -> None:
        self.stations, self.epoch_us = stations, epoch_us
        self._ids = [s.sender_id for s in stations]
        self._senders: dict[str, _Sender] = {}                   # by id, from the first legal packet
        self._by_station: list[Optional[_Sender]] = [None] * len(stations)
        self.illegal: Counter[str] = Counter()
        self.frames = self.other = self.illegal_total = self.crc_bad = 0
        self.first_t: Optional[int] = None
        self.last_t = 0
        self.commands = {kind: _Commands(kind) for kind in _COMMAND_TYPES}

    def _sender(self, station: int) -> _Sender:
        sid = self._ids[station]
        sender = self._senders.get(sid)
        if sender is None:
            sender = self._senders[sid] = _Sender(sid, self.stations[station], self.epoch_us)
        self._by_station[station] = sender
        return sender

    def add(self, arrivals: Sequence[Arrival]) -> None:
        if not arrivals:
            return
        if self.first_t is None:
            self.first_t = arrivals[0][0]
        self.last_t = arrivals[-1][0]
        by_station, count = self._by_station, len(self._by_station)
        commands, watchdogs, acks = self.commands, _WATCHDOG_US, C.ACK_OF
        burst_gap = C.VRPO_BURST_GAP_MS * 1000
        frame = self.frames
        for t, _, station, _, problems, meta in arrivals:
            frame += 1
            if station >= count:
                self.other += 1
                continue
            if problems:
                self.illegal_total += 1
                self.illegal.update(problems)
                self.crc_bad += _BAD_CRC in problems
                continue
            sender = by_station[station] or self._sender(station)
            ptype = meta.ptype
            try:
                sender.by_type[ptype] += 1
            except KeyError:
                sender.by_type[ptype] = 1
            limit = watchdogs.get(ptype)
            if limit is not None:
                last = sender.last.get(ptype)
                if last is not None and t - last > limit:
                    sender.violations.setdefault(ptype, []).append((last, t))
                sender.last[ptype] = t
            track, serial = sender.serial, meta.serial
            high = track.high
            if high is not None and serial and serial - high % _MODULUS == 1:    # next, no wrap: most packets
                track.high = high + 1
            elif not track.add(serial, t):
                continue      # a repeated serial is a duplicate, not a transmission or an ack
            if ptype is _VRPO:
                burst = sender.burst
                if burst and t - sender.burst_t >= burst_gap:
                    sender.close_burst()
                    burst = sender.burst
                burst.append(meta)
                sender.burst_t = t
            elif ptype in commands:
                commands[ptype].command(sender.id, meta.key, frame, t)
            elif ptype in acks:
                commands[acks[ptype]].ack(meta.key, frame, t)
        self.frames = frame

    def report(self) -> dict[str, Any]:
        """The truth dict (truth-contract.md)."""
        senders = [self._senders[sid] for sid in sorted(self._senders)]
        for sender in senders:
            sender.close_burst()
        periodic = sorted(((ptype, sender) for sender in senders for ptype in sender.last),
                          key=lambda item: (_NAMES[item[0]], item[1].id))
        eglink = self.frames - self.other
        duration = self.last_t - self.first_t if self.first_t is not None else 0
        return {
            "schema_version": SCHEMA_VERSION,
            "capture": {"packets": self.frames, "eglink_packets": eglink, "duration_s": _time(duration)},
            "crc": {"variant": DEFAULT_VARIANT, "byte_order": DEFAULT_BYTE_ORDER,
                    "valid": eglink - self.crc_bad, "invalid": self.crc_bad},
            "illegal": {"total": self.illegal_total, "by_reason": dict(sorted(self.illegal.items()))},
            "senders": [sender.report() for sender in senders],
            "periodic": [self._periodic(ptype, sender) for ptype, sender in periodic],
            "commands": {kind.value: c.report() for kind, c in self.commands.items()},
            "vrpo_bursts": {"complete": sum(s.complete for s in senders),
                            "incomplete": sum(s.incomplete for s in senders)},
        }

    def _periodic(self, ptype: C.PacketType, sender: _Sender) -> dict[str, Any]:
        epoch = self.epoch_us
        return {"type": ptype.value, "sender": sender.id, "count": sender.by_type[ptype],
                "watchdog": {"limit_ms": _WATCHDOG_MS[ptype],
                             "violations": [{"start": _time(epoch + a), "gap_ms": _ms(b - a)}
                                            for a, b in sender.violations.get(ptype, ())]}}
