"""What the stream analysis must say of each packet, worked out here from TS-0006 and
interpretation.md (docs/rules.md's precise form) with nothing taken from vm110: own framing checks,
one serial counter per sender, the duplicate window, late packets, plausible gaps, restart
candidates confirmed by s + 1 .. s + 4, restarts on a new port, commands by (kind, sender, ID)
with retransmissions within the reuse gap, acks to the latest command of their ID, spurious
retransmissions and interrupted commands. Only for captures whose timestamps never go back."""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Optional

from own_capture import PAYLOAD_SIZE, Frame, crc_mpeg2

DUP_WINDOW, REUSE_GAP, FAIL, NEW_PORT_SILENCE, RATE_WINDOW, CANDIDATE_WAIT = 1.0, 2.0, 2.0, 0.25, 10.0, 10.0
MOD = 65536


def legal(payload: bytes) -> bool:
    """interpretation.md, "Illegal packets" (default CRC)."""
    if len(payload) < 20 or payload[:4] not in (*PAYLOAD_SIZE, b"VRPO"):
        return False
    revision, _origin, _serial, size = struct.unpack_from("<HHHH", payload, 4)
    if revision or size > 492 or len(payload) != 20 + size:
        return False
    if size < PAYLOAD_SIZE.get(payload[:4], 2):
        return False
    return struct.unpack_from("<I", payload, 16 + size)[0] == crc_mpeg2(payload[:16 + size])


@dataclass
class Expect:
    duplicate: bool = False
    out_of_order: bool = False
    missing: int = 0
    restart: Optional[int] = None           # the highest serial before
    port_from: Optional[int] = None
    retransmission_of: Optional[int] = None
    retransmission_number: Optional[int] = None
    spurious: bool = False
    ack_to: Optional[int] = None
    ack_time_ms: Optional[float] = None
    ack_time_last_ms: Optional[float] = None
    ack_in: Optional[int] = None
    interrupted_by: Optional[int] = None
    ack_without_command: bool = False
    duplicate_ack: bool = False


@dataclass
class Counter:
    h: int
    start: float
    accepted: dict = field(default_factory=dict)     # serial -> time last accepted
    gaps: dict = field(default_factory=dict)         # missing serial -> time its gap opened
    times: list = field(default_factory=list)        # times of accepted packets
    candidate: Optional[tuple] = None                # (serial, time, frame, [confirmed?])

    def accept(self, s: int, t: float) -> None:
        self.accepted[s] = t
        self.times.append(t)

    def rate(self, t: float) -> float:
        w = min(RATE_WINDOW, t - self.start)
        if w <= 0:
            return 0.0
        return sum(1 for x in self.times if t - w <= x < t) / w


@dataclass
class Command:
    kind: bytes
    sender: tuple
    cid: int
    frames: list
    times: list
    ack_frame: Optional[int] = None
    interrupted: bool = False
    restarted_after: bool = False


@dataclass
class Sender:
    key: tuple
    counter: Optional[Counter] = None
    last: float = 0.0
    taken_over: bool = False


class Model:
    def __init__(self) -> None:
        self.out: dict[int, Expect] = {}
        self.senders: dict[tuple, Sender] = {}
        self.commands: list[Command] = []
        self.waiting: dict[int, tuple] = {}          # counters with an undecided restart candidate: (time, decision)
        self.queue: list = []                        # command events behind them, in order

    def run(self, frames: list[Frame]) -> dict[int, Expect]:
        for number, f in enumerate(frames, start=1):
            if legal(f.payload):
                self.packet(number, f)
        self.waiting.clear()
        self.later(None)
        return self.out

    def release(self, t: float) -> None:
        """A candidate holds the command events 10 s at most: then they run as if it were none."""
        for key, (since, decision) in list(self.waiting.items()):
            if t - since >= CANDIDATE_WAIT:
                decision[0] = "released"
                del self.waiting[key]
        self.later(None)

    def later(self, event) -> None:
        """Command events wait while a restart candidate is undecided (it may interrupt commands)."""
        if event is not None:
            self.queue.append(event)
        if not self.waiting:
            queued, self.queue = self.queue, []
            for ev in queued:
                ev()

    def _sender(self, number: int, f: Frame, direction: str, origin: int, t: float) -> Sender:
        key = (direction, origin, f.src, f.sport)
        snd = self.senders.get(key)
        if snd is not None:
            return snd
        snd = self.senders[key] = Sender(key)
        silent = [o for o in self.senders.values() if o is not snd and o.key[:3] == key[:3]
                  and not o.taken_over and t - o.last >= NEW_PORT_SILENCE]
        if silent:
            pred = max(silent, key=lambda o: o.last)
            pred.taken_over = True
            e = self.out[number]
            e.restart, e.port_from = pred.counter.h, pred.key[3]
            self.later(lambda: self.interrupt(pred.key, t, number))
        return snd

    def interrupt(self, key: tuple, t: float, number: int) -> None:
        """A restart ends the sender's commands neither acknowledged nor past their fail limit."""
        for c in self.commands:
            if c.sender == key and c.ack_frame is None and not c.interrupted and t - c.times[0] < FAIL:
                c.interrupted = True
                self.out[c.frames[0]].interrupted_by = number
        for c in self.commands:
            if c.sender == key:
                c.restarted_after = True

    def packet(self, number: int, f: Frame) -> None:
        kind = f.payload[:4]
        _rev, origin, s, _size = struct.unpack_from("<HHHH", f.payload, 4)
        t = f.time_us / 1e6
        direction = "Input" if kind.endswith(b"I") else "Output"
        self.out[number] = e = Expect()
        self.release(t)
        snd = self._sender(number, f, direction, origin, t)
        snd.last = t
        c = snd.counter
        if c is None:
            snd.counter = c = Counter(s, t)
            c.accept(s, t)
        else:
            if c.candidate is not None and s != c.candidate[0]:
                cs, ct, cframe, decision = c.candidate
                c.candidate = None
                self.waiting.pop(id(c), None)
                if 1 <= (s - cs) % MOD <= 4:             # confirmed: a restart at the candidate
                    ce = self.out[cframe]
                    ce.out_of_order, ce.restart = False, c.h
                    decision[0] = decision[0] or "restart"   # (released: it changes no command)
                    snd.counter = c = Counter(cs, ct)
                    c.accept(cs, ct)
                self.later(None)
            if not self.serial(c, s, t, e, number):
                return                                    # a duplicate takes no further part
            if c.candidate is not None:                   # the commands from here on wait for it
                decision = c.candidate[3]
                self.waiting[id(c)] = (t, decision)
                self.later(lambda: decision[0] == "restart" and self.interrupt(snd.key, t, number))
        if kind in (b"VRCI", b"VRCO"):
            cid = struct.unpack_from("<H", f.payload, 16)[0]
            self.later(lambda: self.command(kind, snd.key, cid, number, t, e))
        elif kind in (b"VRAO", b"VRAI"):
            cid = struct.unpack_from("<H", f.payload, 16)[0]
            self.later(lambda: self.ack(b"VRCI" if kind == b"VRAO" else b"VRCO", cid, number, t, e))

    @staticmethod
    def serial(c: Counter, s: int, t: float, e: Expect, number: int) -> bool:
        """Classifies s; False for a duplicate."""
        if s in c.accepted and t - c.accepted[s] < DUP_WINDOW:
            e.duplicate = True
            return False
        d = (s - c.h) % MOD
        dt = t - c.times[-1]
        if d == 1:
            c.h = s
        elif s in c.gaps and t - c.gaps[s] < DUP_WINDOW:
            del c.gaps[s]
            e.out_of_order = True
        elif 1 < d < 32768 and d - 1 <= 64 + 4 * max(c.rate(t), 20) * dt:
            e.missing = d - 1
            for k in range(1, d):
                c.gaps[(c.h + k) % MOD] = t
            c.h = s
        else:
            e.out_of_order = True                         # until a next packet confirms it
            c.candidate = (s, t, number, [None])
        c.accept(s, t)
        return True

    def command(self, kind: bytes, key: tuple, cid: int, number: int, t: float, e: Expect) -> None:
        same = [c for c in self.commands if (c.kind, c.sender, c.cid) == (kind, key, cid)]
        if same and t - same[-1].times[-1] < REUSE_GAP and not same[-1].restarted_after:
            c = same[-1]
            e.retransmission_of, e.retransmission_number = c.frames[0], len(c.frames)
            e.spurious = c.ack_frame is not None
            c.frames.append(number)
            c.times.append(t)
            if c.ack_frame is not None:
                e.ack_in = c.ack_frame
        else:
            self.commands.append(Command(kind, key, cid, [number], [t]))

    def ack(self, kind: bytes, cid: int, number: int, t: float, e: Expect) -> None:
        mine = [c for c in self.commands if c.kind == kind and c.cid == cid and not c.interrupted]
        if not mine:
            e.ack_without_command = True
            return
        c = max(mine, key=lambda c: c.times[0])
        if c.ack_frame is not None:          # (it names its command and the time from its first transmission)
            e.duplicate_ack, e.ack_to, e.ack_time_ms = True, c.frames[0], (t - c.times[0]) * 1000
            return
        c.ack_frame = number
        e.ack_to = c.frames[0]
        e.ack_time_ms = (t - c.times[0]) * 1000
        e.ack_time_last_ms = (t - c.times[-1]) * 1000
        for fr in c.frames:
            self.out[fr].ack_in = number
