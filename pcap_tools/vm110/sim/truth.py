"""Ground truth of a synthesised capture, from the tap's event log, by the rules of docs/rules.md.

The input is what the tap saw (`sim.virtual.Arrival`): the sender's own record of each packet
(type, serial, command ID, VRPO packet number and data length) and the illegal reasons the
impairments put in by construction. No packet bytes are decoded here. Where docs/rules.md leaves
a detail open the choice is written next to the code and in captures/README.md.
"""
from __future__ import annotations

import collections
from collections import Counter
from typing import Any, Callable, Optional, Sequence

from .. import constants as C
from .clock import US_PER_S, ms
from .ledger import REUSE_GAP_MS
from .peers import (CANDIDATE_WAIT_US, CONFIRM, DUP_WINDOW_US, MIN_RATE, NEW_PORT_SILENCE_US, PLAUSIBLE_BASE,
                    PLAUSIBLE_FACTOR, RATE_WINDOW_US)
from .reading import Reading
from .virtual import Arrival, Station, endpoints

SCHEMA_VERSION = 6           # the report's (docs/report.md): the truth is in its shape
_WATCHDOG_MS = {C.PacketType.VRPI: C.VRPI_WATCHDOG_MS, C.PacketType.VRPO: C.VRPO_WATCHDOG_MS}
_WATCHDOG_US = {ptype: ms(limit) for ptype, limit in _WATCHDOG_MS.items()}
_FAIL_US = {C.PacketType.VRCI: ms(C.VRCI_FAIL_MS), C.PacketType.VRCO: ms(C.VRCO_GIVE_UP_MS)}
_COMMAND_TYPES = (C.PacketType.VRCI, C.PacketType.VRCO)
_VRPO = C.PacketType.VRPO
_BAD_CRC = C.Problem.BAD_CRC.value
_NAMES = {t: t.value for t in C.PacketType}
_TYPE_ORDER = {t: i for i, t in enumerate(C.PacketType)}    # the analysis' order of per-type counters
_MODULUS, _HALF, _VRPO_MAX_DATA = C.SERIAL_MODULUS, C.SERIAL_HALF, C.VRPO_MAX_DATA
REUSE_GAP_US = ms(REUSE_GAP_MS)     # a command ID within this of its previous transmission: a retransmission


def _time(t_us: int) -> float:
    return round(t_us / US_PER_S, 6)


def _ms(delta_us: int) -> float:
    return round(delta_us / 1000, 3)


class _Candidate:
    """A packet that may start a restart of its counter, until the counter's next other serial decides."""

    __slots__ = ("commands", "frame", "restart", "serial", "t")

    def __init__(self, serial: int, t: int, frame: int) -> None:
        self.serial, self.t, self.frame = serial, t, frame
        self.restart: Optional[bool] = None          # the decision, once made
        self.commands = False                        # a restart that changes commands (rules.md rule 5)


class _Counter:
    """The serial counter of one sender (scope `sender`), by docs/rules.md "Serial numbers"."""

    def __init__(self, epoch_us: int) -> None:
        self.epoch_us = epoch_us
        self.h: Optional[int] = None
        self.start = self.prev = 0                   # counter start (first packet, last restart); previous accepted
        self.accepted: dict[int, int] = {}           # serial -> when last accepted
        self.missing: dict[int, tuple[int, dict]] = {}   # serials in open gaps -> when it opened, the gap (in order)
        self.recent: collections.deque[int] = collections.deque()    # accepted times, for the rate
        self.lost_for_good: list[int] = []           # missing when the counter restarted or came round
        self.wraps = 0
        self.duplicates: list[int] = []
        self.out_of_order: list[int] = []
        self.gaps: list[dict[str, Any]] = []
        self.restarts: list[dict[str, Any]] = []
        self.candidate: Optional[_Candidate] = None

    def add(self, s: int, t: int, frame: int) -> tuple[bool, Optional[_Candidate]]:
        """Classify a legal packet: (accepted, the candidate it opened if any). A pending candidate
        is decided first by any other serial."""
        cand = self.candidate
        if cand is not None:
            if s == cand.serial:
                self.duplicates.append(s)            # copies of the candidate confirm nothing
                return False, None
            self._decide(cand, s, t)
        if self.h is None:
            self._restart_state(s, t)
            return True, None
        last = self.accepted.get(s)
        if last is not None and t - last < DUP_WINDOW_US:
            self.duplicates.append(s)
            return False, None
        d = (s - self.h) % _MODULUS
        if d == 1:
            if not s:
                self.wraps += 1
            self._came_round(s)
            self.h = s
        elif s in self.missing and t - self.missing[s][0] < DUP_WINDOW_US:
            gap = self.missing.pop(s)[1]
            gap["late"] = gap.get("late", 0) + 1     # late: fills its gap
            self.out_of_order.append(s)
        elif 1 < d < _HALF and self._plausible(d - 1, t):
            gap = {"after": self.h, "count": d - 1, "time": _time(self.epoch_us + t), "frame": frame}
            self.gaps.append(gap)
            for k in range(1, d):
                lost = (self.h + k) % _MODULUS
                self._came_round(lost)
                self.missing[lost] = (t, gap)
            self._came_round(s)
            if s < self.h:
                self.wraps += 1
            self.h = s
        else:
            cand = self.candidate = _Candidate(s, t, frame)
            self._accept(s, t)
            return True, cand
        self._accept(s, t)
        return True, None

    def _accept(self, s: int, t: int) -> None:
        self.accepted[s] = self.prev = t
        recent = self.recent
        recent.append(t)
        if recent[0] < t - RATE_WINDOW_US:         # older than any rate window: one out per one in
            recent.popleft()

    def _came_round(self, s: int) -> None:
        """A serial reached again while still missing: its number came round, it stays lost."""
        if self.missing and s in self.missing:
            del self.missing[s]
            self.lost_for_good.append(s)

    def _plausible(self, missing: int, t: int) -> bool:
        dt = (t - self.prev) / US_PER_S
        if missing <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * MIN_RATE * dt:
            return True
        return missing <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * max(self._rate(t), MIN_RATE) * dt

    def _rate(self, t: int) -> float:
        """Accepted packets in [t - W, t) per second, W = min(10 s, t - start)."""
        window = min(RATE_WINDOW_US, t - self.start)
        if window <= 0:
            return 0.0
        recent = self.recent
        while recent and recent[0] < t - window:
            recent.popleft()
        count = len(recent)
        for x in reversed(recent):
            if x < t:
                break
            count -= 1
        return count / (window / US_PER_S)

    def _decide(self, cand: _Candidate, s: int, t: int) -> None:
        self.candidate = None
        cand.restart = 1 <= (s - cand.serial) % _MODULUS <= CONFIRM
        cand.commands = cand.restart and t - cand.t < CANDIDATE_WAIT_US
        if not cand.restart:
            self.out_of_order.append(cand.serial)    # unconfirmed: accepted, moves nothing
            return
        self.restarts.append({"time": _time(self.epoch_us + cand.t), "frame": cand.frame,
                              "from": self.h, "to": cand.serial})
        self._restart_state(cand.serial, cand.t)

    def _restart_state(self, s: int, t: int) -> None:
        self.lost_for_good.extend(self.missing)      # serials lost before stay lost
        self.missing = {}
        self.accepted = {}
        self.recent.clear()
        self.h, self.start = s, t
        self._accept(s, t)

    def finish(self) -> None:
        """The capture ended: a pending candidate stays unconfirmed."""
        if self.candidate is not None:
            self.candidate.restart = False
            self.out_of_order.append(self.candidate.serial)
            self.candidate = None

    def lost(self) -> list[int]:
        return self.lost_for_good + list(self.missing)


def _serial_report(scope: str, counters: list[_Counter], link: Optional[dict[str, Any]],
                   received: int) -> dict[str, Any]:
    """The counters of a sender (one, or one per packet type in the analysis' order) as one:
    serials listed counter by counter, gaps and restarts by frame, a new-port restart first."""
    lost = [s for c in counters for s in c.lost()]
    duplicates = [s for c in counters for s in c.duplicates]
    out_of_order = [s for c in counters for s in c.out_of_order]
    gaps = sorted((g for c in counters for g in c.gaps), key=lambda g: g["frame"])
    restarts = ([link] if link else []) + sorted((r for c in counters for r in c.restarts), key=lambda r: r["frame"])
    return {"scope": scope, "received": received, "lost": len(lost), "duplicates": len(duplicates),
            "out_of_order": len(out_of_order), "wraps": sum(c.wraps for c in counters),
            "lost_serials": lost, "duplicate_serials": duplicates, "out_of_order_serials": out_of_order,
            "gaps": gaps, "restarts": len(restarts), "restart_events": restarts}


class _Commands:
    """Commands of one kind (VRCI or VRCO) and their acknowledgements, in capture order
    (docs/rules.md "Commands")."""

    def __init__(self, kind: C.PacketType) -> None:
        self.kind, self.fail_us = kind, _FAIL_US[kind]
        self.open: dict[tuple[str, int], dict[str, Any]] = {}    # (sender, ID) -> its latest command
        self.by_id: dict[int, list[dict[str, Any]]] = {}         # ID -> commands not interrupted, by start
        self.list: list[dict[str, Any]] = []
        self.spurious = self.acks_without_command = self.duplicate_acks = self.interrupted = 0

    def command(self, sender: str, command_id: int, frame: int, t: int) -> None:
        cmd = self.open.get((sender, command_id))
        if cmd is not None and t - cmd["_times"][-1] < REUSE_GAP_US:
            cmd["frames"].append(frame)
            cmd["_times"].append(t)
            if cmd["ack_frame"] is not None:
                self.spurious += 1
            return
        cmd = {"sender": sender, "command_id": command_id, "frames": [frame], "ack_frame": None,
               "latency_first_ms": None, "latency_last_ms": None, "_times": [t], "_ack_t": None}
        self.open[(sender, command_id)] = cmd
        self.by_id.setdefault(command_id, []).append(cmd)
        self.list.append(cmd)

    def ack(self, command_id: int, frame: int, t: int) -> None:
        live = self.by_id.get(command_id)
        if not live:
            self.acks_without_command += 1
            return
        cmd = live[-1]
        if cmd["ack_frame"] is not None:
            self.duplicate_acks += 1
            return
        cmd["ack_frame"], cmd["_ack_t"] = frame, t
        cmd["latency_first_ms"] = _ms(t - cmd["_times"][0])
        cmd["latency_last_ms"] = _ms(t - cmd["_times"][-1])

    def restart(self, sender: str, t: int) -> None:
        """The sender restarted at t: its commands neither acknowledged nor past their fail limit
        end as interrupted; its IDs start new commands from here."""
        for key in [k for k in self.open if k[0] == sender]:
            cmd = self.open.pop(key)
            if cmd["ack_frame"] is None and t - cmd["_times"][0] <= self.fail_us:
                cmd["_interrupted"] = True
                self.interrupted += 1
                self.by_id[key[1]].remove(cmd)

    def report(self, end: int) -> dict[str, Any]:
        """`end`: the capture's last record (a command still within its limit then has not failed)."""
        transmissions = sum(len(c["frames"]) for c in self.list)
        acked = sum(c["ack_frame"] is not None for c in self.list)
        failed = sum(not c.get("_interrupted") and ((end if c["_ack_t"] is None else c["_ack_t"]) - c["_times"][0]
                                                    > self.fail_us) for c in self.list)
        return {"commands": len(self.list), "transmissions": transmissions,
                "retransmissions": transmissions - len(self.list), "acked": acked,
                "unacked": len(self.list) - acked - self.interrupted, "interrupted": self.interrupted,
                "failed": failed, "spurious_retransmissions": self.spurious,
                "acks_without_command": self.acks_without_command, "duplicate_acks": self.duplicate_acks,
                "list": [{k: v for k, v in c.items() if not k.startswith("_")} for c in self.list]}


def _burst_shape(burst: list[tuple[int, int]]) -> Optional[bool]:
    """A VRPO burst of (packet number, counted from the first's, data length) numbered 0..n-1 each
    once with every packet but the last by number carrying 488 data bytes: whether the last carries fewer (it ended the
    burst); None for any other burst (interpretation.md, 'VRPO split')."""
    if len(burst) == 1:                            # most bursts: one packet
        number, size = burst[0]
        return None if number else size < _VRPO_MAX_DATA
    ordered = sorted(burst)
    if [n for n, _ in ordered] != list(range(len(ordered))) or \
            any(n != _VRPO_MAX_DATA for _, n in ordered[:-1]):
        return None
    return ordered[-1][1] < _VRPO_MAX_DATA


class _Sender:
    """What the truth keeps per sender (one endpoint of a station), updated packet by packet."""

    def __init__(self, sid: str, station: Station, port: int, epoch_us: int, reading: Reading) -> None:
        self.id, self.station, self.port = sid, station, port
        self.by_type: dict[C.PacketType, int] = {}     # legal packets (duplicates too), by type
        self.scope, self.epoch_us = reading.serial_scope, epoch_us
        self.counters: dict[Optional[C.PacketType], _Counter] = {}   # None (scope sender) or type -> counter
        self.link: Optional[dict[str, Any]] = None     # the restart of an earlier sender on another port
        self.vrpo_start = reading.vrpo_start
        self.last_legal = 0
        self.last_type: Optional[C.PacketType] = None  # of the latest legal packet (duplicates too)
        self.streams: dict[C.PacketType, int] = {}     # periodic type -> accepted packets
        # periodic type -> (time, frame) of its latest accepted packet
        self.last: dict[C.PacketType, tuple[int, int]] = {}
        self.inherited: dict[C.PacketType, tuple[int, int]] = {}   # the same of the sender it took over (new port)
        self.taken_over = False                        # a later sender on a new port took over
        self.violations: dict[C.PacketType, list[tuple[int, int, bool, int]]] = {}   # (start, end, until end, frame)
        self.burst: list[tuple[int, int]] = []         # the VRPO burst being received (`_burst_shape`)
        self.burst_zero = False                        # it holds a packet numbered 0
        self.burst_t = 0
        self.complete = self.incomplete = 0
        # The data size inferred (docs/rules.md, "VRPO bursts"): a VRPO packet of fewer than 488
        # bytes seen before the burst; the most packets of a complete burst of 488-byte packets.
        self.short_before = False
        self.full_most = 0

    def counter(self, ptype: C.PacketType) -> _Counter:
        """The counter of a packet of this type, started at its first packet."""
        key = ptype if self.scope == "type" else None
        counter = self.counters.get(key)
        if counter is None:
            counter = self.counters[key] = _Counter(self.epoch_us)
        return counter

    def periodic(self, ptype: C.PacketType, t: int, frame: int) -> None:
        self.streams[ptype] = self.streams.get(ptype, 0) + 1
        last = self.last.get(ptype, self.inherited.get(ptype))
        if last is not None and t - last[0] > _WATCHDOG_US[ptype]:
            self.violations.setdefault(ptype, []).append((last[0], t, False, frame))
        self.last[ptype] = (t, frame)

    def burst_over(self, number: int) -> bool:
        """The burst ended with a short last packet; or packet `number` restarts the numbering (a
        second 0); or the burst has the inferred size (full packets, as many as the longest
        complete such burst) and `number` does not go on from it."""
        if number == 0 and self.burst_zero:
            return True
        shape = _burst_shape(self.burst)
        return shape is True or (shape is False and not self.short_before and 0 < self.full_most <= len(self.burst)
                                 and number != len(self.burst))

    def close_burst(self) -> None:
        if not self.burst:
            return
        parts = self.burst
        shape = _burst_shape(parts)
        full = shape is False and not self.short_before and len(parts) >= self.full_most
        if shape or full:
            self.complete += 1
        else:
            self.incomplete += 1
        if full:
            self.full_most = len(parts)
        self.short_before = self.short_before or any(size < _VRPO_MAX_DATA for _, size in parts)
        self.burst, self.burst_zero = [], False

    def report(self) -> dict[str, Any]:
        station = self.station
        return {"id": self.id, "direction": station.node.direction.value, "origin": station.node.origin,
                "src": f"{station.ip}:{self.port}",
                "by_type": {_NAMES[t]: n for t, n in sorted(self.by_type.items())},
                "serial": _serial_report(self.scope, [self.counters[k] for k in sorted(
                    self.counters, key=lambda k: -1 if k is None else _TYPE_ORDER[k])], self.link,
                    sum(self.by_type.values()))}


class GroundTruth:
    """The truth of a capture, fed with the tap's arrivals in file order (`add`, batch by batch);
    an arrival whose endpoint index is past the last endpoint is a frame that is not EG-Link."""

    def __init__(self, stations: Sequence[Station], epoch_us: int, reading: Optional[Reading] = None) -> None:
        self.stations, self.epoch_us = stations, epoch_us
        self.reading = reading or Reading()      # as every station speaks it, and analyze reads it
        self._endpoints = endpoints(list(stations))
        self._ids = [sid for s in stations for sid in s.sender_ids()]
        self._senders: dict[str, _Sender] = {}                   # by id, from the first legal packet
        self._by_endpoint: list[Optional[_Sender]] = [None] * len(self._ids)
        self.illegal: Counter[str] = Counter()
        self.frames = self.other = self.illegal_total = self.crc_bad = 0
        self.first_t: Optional[int] = None
        self.last_t = 0
        self.commands = {kind: _Commands(kind) for kind in _COMMAND_TYPES}
        # Command events wait here while a restart candidate is undecided: its restart (if it is
        # one) interrupts commands at the candidate's place in the capture.
        self._held: list[tuple[Callable[..., None], tuple[Any, ...]]] = []
        self._undecided: list[_Candidate] = []

    def _sender(self, endpoint: int, t: int, frame: int, serial: int, ptype: C.PacketType) -> _Sender:
        sid = self._ids[endpoint]
        station, port = self._endpoints[endpoint]
        sender = self._senders[sid] = _Sender(sid, self.stations[station], port, self.epoch_us, self.reading)
        self._by_endpoint[endpoint] = sender
        self._new_port(sender, t, frame, serial, ptype)
        return sender

    def _new_port(self, sender: _Sender, t: int, frame: int, serial: int, ptype: C.PacketType) -> None:
        """A sender's first legal packet (of type `ptype`): the restart of an earlier sender of the
        same direction, origin and address on another port, silent at least 250 ms (the one heard
        last). `from` is the highest serial of the earlier sender's counter of that type, if it
        had one, else of its last packet's type (per-type counters)."""
        node, ip = sender.station.node, sender.station.ip
        earlier = [s for s in self._senders.values() if s is not sender and s.station.ip == ip
                   and s.station.node.direction is node.direction and s.station.node.origin == node.origin
                   and s.port != sender.port and t - s.last_legal >= NEW_PORT_SILENCE_US]
        if not earlier:
            return
        old = max(earlier, key=lambda s: s.last_legal)
        old.taken_over = True
        sender.inherited = dict(old.last)
        key = None if old.scope == "sender" else ptype if ptype in old.counters else old.last_type
        counter = old.counters.get(key)
        sender.link = {"time": _time(self.epoch_us + t), "frame": frame, "from": counter.h if counter else 0,
                       "to": serial, "port_from": old.port, "port_to": sender.port}
        self._command_event(self._restart, old.id, t)

    def _restart(self, sender: str, t: int) -> None:
        for commands in self.commands.values():
            commands.restart(sender, t)

    def _maybe_restart(self, cand: _Candidate, sender: str) -> None:
        if cand.commands:
            self._restart(sender, cand.t)

    def _command_event(self, fn: Callable[..., None], *args: Any) -> None:
        if self._undecided:
            self._held.append((fn, args))
        else:
            fn(*args)

    def _release(self) -> None:
        """Run the held command events once every candidate is decided."""
        self._undecided = [c for c in self._undecided if c.restart is None]
        if not self._undecided and self._held:
            held, self._held = self._held, []
            for fn, args in held:
                fn(*args)

    def add(self, arrivals: Sequence[Arrival]) -> None:
        if not arrivals:
            return
        if self.first_t is None:
            self.first_t = arrivals[0][0]
        self.last_t = arrivals[-1][0]
        by_endpoint, count = self._by_endpoint, len(self._by_endpoint)
        commands, watchdogs, acks = self.commands, _WATCHDOG_US, C.ACK_OF
        burst_gap = C.VRPO_BURST_GAP_MS * 1000
        frame = self.frames
        for t, _, endpoint, _, problems, meta, _ in arrivals:
            frame += 1
            if endpoint >= count:
                self.other += 1
                continue
            assert meta is not None      # every EG-Link sender's packet carries its Meta
            if problems:
                self.illegal_total += 1
                self.illegal.update(problems)
                self.crc_bad += _BAD_CRC in problems
                continue
            ptype = meta.ptype
            sender = by_endpoint[endpoint] or self._sender(endpoint, t, frame, meta.serial, ptype)
            sender.last_legal, sender.last_type = t, ptype
            sender.by_type[ptype] = sender.by_type.get(ptype, 0) + 1
            accepted, cand = sender.counter(ptype).add(meta.serial, t, frame)
            if self._undecided:
                self._release()
            if not accepted:
                continue      # a duplicate: no arrival, no transmission, no ack, no burst part
            if cand is not None:
                self._undecided.append(cand)
                self._held.append((self._maybe_restart, (cand, sender.id)))
            if ptype in watchdogs:
                sender.periodic(ptype, t, frame)
            if ptype is _VRPO:
                burst, number = sender.burst, meta.key - sender.vrpo_start
                # (a burst that is over takes no more, even within the gap)
                if burst and (t - sender.burst_t >= burst_gap or sender.burst_over(number)):
                    sender.close_burst()
                    burst = sender.burst
                burst.append((number, meta.data_len))
                sender.burst_zero = sender.burst_zero or number == 0
                sender.burst_t = t
            elif ptype in commands:
                self._command_event(commands[ptype].command, sender.id, meta.key, frame, t)
            elif ptype in acks:
                self._command_event(commands[acks[ptype]].ack, meta.key, frame, t)
        self.frames = frame

    def report(self) -> dict[str, Any]:
        """The truth dict (docs/report.md, the keys marked ✓)."""
        senders = [self._senders[sid] for sid in sorted(self._senders)]
        for sender in senders:
            for counter in sender.counters.values():
                counter.finish()
            sender.close_burst()
        self._release()
        periodic = sorted(((ptype, sender) for sender in senders for ptype in sender.last),
                          key=lambda item: (_NAMES[item[0]], item[1].id))
        eglink = self.frames - self.other
        first, duration = self.first_t, self.last_t - self.first_t if self.first_t is not None else 0
        return {
            "schema_version": SCHEMA_VERSION,
            "capture": {"packets": self.frames, "eglink_packets": eglink,
                        "first_time": None if first is None else _time(self.epoch_us + first),
                        "last_time": None if first is None else _time(self.epoch_us + self.last_t),
                        "duration_s": _time(duration)},
            "crc": {"variant": self.reading.crc, "byte_order": self.reading.crc_order,
                    "valid": eglink - self.crc_bad, "invalid": self.crc_bad},
            "illegal": {"total": self.illegal_total, "by_reason": dict(sorted(self.illegal.items()))},
            "senders": [sender.report() for sender in senders],
            "periodic": [self._periodic(ptype, sender) for ptype, sender in periodic],
            "commands": {kind.value: c.report(self.last_t) for kind, c in self.commands.items()},
            "vrpo_bursts": {"complete": sum(s.complete for s in senders),
                            "incomplete": sum(s.incomplete for s in senders)},
        }

    def _periodic(self, ptype: C.PacketType, sender: _Sender) -> dict[str, Any]:
        epoch, (last, frame) = self.epoch_us, sender.last[ptype]
        violations = list(sender.violations.get(ptype, ()))
        if not sender.taken_over and self.last_t - last > _WATCHDOG_US[ptype]:
            violations.append((last, self.last_t, True, frame))     # silent until the end of the capture
        return {"type": ptype.value, "sender": sender.id, "count": sender.streams[ptype],
                "watchdog": {"limit_ms": _WATCHDOG_MS[ptype],
                             "violations": [{"start": _time(epoch + a), "gap_ms": _ms(b - a), "until_end": end,
                                             "frame": f} for a, b, end, f in violations]}}
