"""What both ends of the EG-Link share: one serial counter, sending, receiving, ignoring illegal packets.

A node is a passive state machine on integer microseconds. A runner (virtual clock in
`sim.virtual`, sockets and wall clock in `sim.realtime`) calls `start`, `tick` when `next_due`
has come, and `receive` for every datagram; the node sends through the callable the runner
attached. Subclasses override the `on_*` hooks.
"""
from __future__ import annotations

import itertools
import struct
from collections import Counter
from typing import Any, Callable, NamedTuple, Optional, Sequence

from .. import constants as C
from .. import protocol as P
from ..crc import (BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, VARIANTS, ByteOrder, check_byte_order,
                   crc_function, crc_matches, trailer_function)
from ..decode import crc_span, decode
from ..printable import escaped
from .clock import US_PER_S
from .lifecycle import NEVER, Restart, Window

_HEADER = P.HEADER
_RX_HEADER = struct.Struct("<4s2xHHH4x")      # what a receiver needs: ID, origin, serial, size
_TYPES = {t.value.encode(): t for t in C.PacketType}
_RAW_IDS = {t: t.value.encode() for t in C.PacketType}
_NAMES = {t: t.value for t in C.PacketType}
_RAW_NAMES = {raw: t.value for raw, t in _TYPES.items()}
_HANDLERS = {t: f"on_{t.value.lower()}" for t in C.PacketType}
_new = tuple.__new__     # builds a NamedTuple without its Python-level __new__
_PREFIX_LEN, _REVISION = C.PREFIX_LEN, C.SUPPORTED_REVISION    # hot paths
SERIAL_SCOPES = ("sender", "type")


class Rx(NamedTuple):
    """A legal packet as a node receives it; decode `data` with `vm110.decode` for every field."""

    ptype: C.PacketType
    origin: int
    serial: int
    payload: bytes
    data: bytes
    src: Any


class Meta(NamedTuple):
    """What the sender knows about a packet it sent: the event log of the ground truth."""

    sender: str        # node name
    ptype: C.PacketType
    serial: int
    key: int           # command ID (commands, acks), packet number (VRPO), else 0
    data_len: int      # VRPO periodic data bytes, else 0


Send = Callable[[bytes, int, Meta], None]


def inspect(data: bytes, crc_fn: Callable[[bytes], int],
            order: ByteOrder) -> tuple[list[str], Optional[C.PacketType]]:
    """Illegal reasons (as `vm110.decode` gives them) and the type, without decoding the fields."""
    n = len(data)
    if n < C.OVERHEAD:
        return decode(data)["problems"], None   # rare: let the full decoder sort it out
    raw_id, revision, _origin, _serial, size, _spare = _HEADER.unpack_from(data)
    ptype = _TYPES.get(raw_id)
    problems = [] if ptype else [C.Problem.UNKNOWN_ID.value]
    end = crc_span(data, size)
    if int.from_bytes(data[end:end + C.CRC_LEN], order) != crc_fn(data[:end]):
        problems.append(C.Problem.BAD_CRC.value)
    if revision != C.SUPPORTED_REVISION:
        problems.append(C.Problem.REVISION.value)
    if n != C.OVERHEAD + size:
        problems.append(C.Problem.SIZE_MISMATCH.value)
    if size > C.MAX_PAYLOAD:
        problems.append(C.Problem.SIZE_TOO_LARGE.value)
    if ptype and revision == C.SUPPORTED_REVISION and end - C.PREFIX_LEN < P.PAYLOAD_BOUNDS[ptype][0]:
        problems.append(C.Problem.TRUNCATED.value)
    return problems, ptype


def source_text(src: Any) -> Any:
    """A packet's source as a log names it: "HOST:PORT" (as given when not an address pair)."""
    return f"{src[0]}:{src[1]}" if isinstance(src, tuple) else src


_TABLES: dict[type, Optional[dict[C.PacketType, Optional[Callable[..., None]]]]] = {}


def _handler_table(cls: type["Node"]) -> Optional[dict[C.PacketType, Optional[Callable[..., None]]]]:
    """The `on_<type>` function of `cls` for each type, or None when `cls` overrides `on_packet`
    (then every packet goes through it). Hooks are looked up on the class, once."""
    if cls not in _TABLES:
        _TABLES[cls] = (None if cls.on_packet is not Node.on_packet
                        else {t: getattr(cls, name, None) for t, name in _HANDLERS.items()})
    return _TABLES[cls]


class Node:
    """One end of the link. `name` identifies it in logs and in the ground truth."""

    direction: C.Direction = C.Direction.INPUT

    def __init__(self, name: str, *, origin: int = 0, serial_start: int = 0,
                 windows: tuple[Window, ...] = (), crc: str = DEFAULT_VARIANT,
                 crc_order: str = DEFAULT_BYTE_ORDER, serial_scope: str = "sender",
                 printer: Optional[Callable[[int, str], None]] = None) -> None:
        self.name = name
        self.origin = origin
        self.serial = serial_start & 0xFFFF
        if serial_scope not in SERIAL_SCOPES:
            raise ValueError(f"unknown serial scope {serial_scope!r}; choose from {', '.join(SERIAL_SCOPES)}")
        # One counter for everything sent (interpretation.md), or, for devices that number that
        # way, one per packet type, each from `serial`: the next serial of each type sent so far.
        self.type_serials: Optional[dict[C.PacketType, int]] = {} if serial_scope == "type" else None
        # (start, end, restart or None) in µs: neither sends nor receives (`sim.lifecycle`)
        self.stalls = tuple(sorted(windows, key=lambda w: (w[0], w[1])))
        self.restarts = tuple(r for _, _, r in self.stalls if r is not None)
        # Asked at each restart with its new port (None: the same one; the runner reopens the
        # socket for a new one): the ports sent from before and after, for the log.
        self.restart_source: Optional[Callable[[Optional[int]], tuple[int, int]]] = None
        self.crc, self.crc_order = crc, check_byte_order(crc_order)
        self._crc_fn = crc_function(crc)
        self._trailer = trailer_function(crc, self.crc_order)
        self._send: Optional[Send] = None
        self.printer = printer
        self.listeners: list[Callable[[dict[str, Any]], None]] = []   # called with every log entry
        self.log: list[dict[str, Any]] = []
        # False: entries go to the printer and listeners only (a run of days kept every one of
        # them, some 400 bytes each); `counts` has them by kind either way, for summaries.
        self.keep_log = True
        self.counts: Counter[str] = Counter()
        self._sent: dict[C.PacketType, int] = {}         # counted per packet: plain dicts, see `sent`
        self._received: dict[bytes, int] = {}
        self.illegal: Counter[str] = Counter()      # by reason; each packet counts once per reason
        self.illegal_packets = 0
        self.send_errors: Counter[str] = Counter()   # packets the network refused, by reason
        # What the node's own impairment (`simulate --loss` ...) did to what it sent, by type name:
        # packets dropped on purpose (never on the wire) and extra copies (duplicates, mirror copies).
        self.impaired_dropped: Counter[str] = Counter()
        self.impaired_copies: Counter[str] = Counter()
        self.impaired_held: Counter[str] = Counter()   # copies delayed past the end of the run: never sent
        self._stall_index = 0
        self._stall_told = False  # the window at `_stall_index` has been logged (it has begun)
        self._stall_passed = 0    # the end of the last window passed: nothing overdue runs before it
        self.stopped = False      # for good (a window without end)
        self._stalls_ahead = bool(self.stalls)
        if not self._stalls_ahead:
            self._bind_direct()
        # Set just before `receive` by a caller that built the packet and knows its illegal reasons
        # (the virtual network; tests hold `impair.mangle` to `inspect`): `receive` skips `inspect`.
        self.vouched: Optional[tuple[str, ...]] = None
        self._handlers = _handler_table(type(self))

    @property
    def sent(self) -> Counter[str]:
        """Packets sent, by type name: each once (its extra copies are `impaired_copies`), none
        that the node's own impairment dropped on purpose (`impaired_dropped`)."""
        sent = Counter({_NAMES[ptype]: n for ptype, n in self._sent.items()})
        sent.subtract(self.impaired_dropped)
        return +sent

    @property
    def received(self) -> Counter[str]:
        """Legal packets received, by type name."""
        return Counter({_RAW_NAMES[raw_id]: n for raw_id, n in self._received.items()})

    # --- wiring -------------------------------------------------------------------------------
    def attach(self, send: Send) -> None:
        """The runner's send function: takes (bytes, now µs, Meta)."""
        self._send = send
        if type(self).transmit is Node.transmit:
            self.transmit = send      # type: ignore[method-assign,assignment]  # no hook overridden: to the runner

    def _bind_direct(self) -> None:
        """Without stalls ahead, `tick` and `next_due` are `_tick` and `_due` themselves, bound on
        the instance (unless a subclass overrides them): one call less per packet for the runners."""
        cls = type(self)
        if cls.tick is Node.tick:
            self.tick = self._tick    # type: ignore[method-assign]
        if cls.next_due is Node.next_due:
            self.next_due = self._due   # type: ignore[method-assign]

    def start(self, now: int) -> None:
        """Called once by the runner before the first tick."""

    def next_due(self) -> Optional[int]:
        """When `tick` must run next (µs), None for nothing scheduled. Stalls postpone it; the
        start of the next one is due too, to be logged when it begins."""
        due = self._due()
        if not self._stalls_ahead:
            return due
        if due is not None:
            # An overdue event runs when the node runs again, at the end of the window it left:
            # read at its own time, it lay in that window, whose end was `now`, and a window
            # beginning there then kept the runners ticking at `now` for ever.
            stall_end = self._stall_end(due if due > self._stall_passed else self._stall_passed)
            if stall_end is not None:
                due = stall_end
        if not self._stall_told:
            start = self.stalls[self._stall_index][0]
            if due is None or start < due:
                return start
        return due

    def tick(self, now: int) -> None:
        if self._stalls_ahead and self._stall_check(now):
            return
        self._tick(now)

    def receive(self, data: bytes, now: int, src: Any = None) -> None:
        """A datagram arrived. Illegal packets are counted and otherwise ignored (TS-0006 5.1.5)."""
        if self._stalls_ahead and self._stall_check(now):
            return
        problems: Sequence[str] | None = self.vouched
        if problems is None:
            problems = inspect(data, self._crc_fn, self.crc_order)[0]
        else:
            self.vouched = None
        if problems:
            self.illegal_packets += 1
            self.illegal.update(problems)
            self.on_illegal(data, list(problems), now, src)
            return
        raw_id, origin, serial, size = _RX_HEADER.unpack_from(data)
        ptype = _TYPES[raw_id]
        try:
            self._received[raw_id] += 1
        except KeyError:
            self._received[raw_id] = 1
        rx = _new(Rx, (ptype, origin, serial, data[_PREFIX_LEN:_PREFIX_LEN + size], data, src))
        handlers = self._handlers
        if handlers is None:
            self.on_packet(rx, now)
        else:                     # on_packet not overridden: the class's on_<type>, looked up once
            handler = handlers[ptype]
            if handler is not None:
                handler(self, rx, now)

    # --- sending ------------------------------------------------------------------------------
    def send(self, ptype: C.PacketType, payload: bytes, now: int, key: int = 0, data_len: int = 0) -> bytes:
        """Frame `payload` with the next serial of this node's counter (of its type's, per type) and send it."""
        counters = self.type_serials
        if counters is None:
            serial = self.serial
            self.serial = (serial + 1) & 0xFFFF
        else:
            serial = counters.get(ptype, self.serial)
            counters[ptype] = (serial + 1) & 0xFFFF
        body = _HEADER.pack(_RAW_IDS[ptype], _REVISION, self.origin, serial, len(payload), 0) + payload
        data = body + self._trailer(body)
        try:
            self._sent[ptype] += 1
        except KeyError:
            self._sent[ptype] = 1
        self.transmit(data, now, _new(Meta, (self.name, ptype, serial, key, data_len)))
        return data

    def traffic_summary(self) -> dict[str, Any]:
        """What every node's summary begins with: packets sent, dropped on purpose by the impairment,
        its extra copies and the copies it still held back when the run ended, by type (the summary
        counted the dropped ones as sent: they never reached the peer, whose received count fell
        short of it); received by type, illegal ones by reason, and packets the network refused."""
        return {"sent": dict(self.sent), "impaired_dropped": dict(self.impaired_dropped),
                "impaired_copies": dict(self.impaired_copies), "impaired_held": dict(self.impaired_held),
                "received": dict(self.received), "illegal_packets": self.illegal_packets,
                "illegal": dict(self.illegal), "send_errors": dict(self.send_errors)}

    def impaired(self, ptype: str, copies: int) -> None:
        """The node's impairment let `copies` copies of a packet of type `ptype` go (0: dropped)."""
        if copies == 0:
            self.impaired_dropped[ptype] += 1
        elif copies > 1:
            self.impaired_copies[ptype] += copies - 1

    def send_failed(self, reason: str, now: int, dest: Any = None) -> None:
        """The network refused a packet (no route to the peer, a full buffer): lost, as UDP loses
        it. The first of each reason is logged and all are counted: a --peer out of reach was sent
        to for the whole run with nothing said, and its packets counted as sent."""
        self.send_errors[reason] += 1
        if self.send_errors[reason] == 1:
            self.event(now, "send_failed", error=reason, to=source_text(dest))

    def transmit(self, data: bytes, now: int, meta: Meta) -> None:
        """Last hook before the wire (override to alter bytes on purpose)."""
        if self._send is None:
            raise RuntimeError(f"{self.name}: not attached to a runner")
        self._send(data, now, meta)

    # --- hooks and helpers for subclasses -----------------------------------------------------
    def on_packet(self, rx: Rx, now: int) -> None:
        """A legal packet; dispatches to `on_<type>` (e.g. `on_vrci`)."""
        handler = getattr(self, _HANDLERS[rx.ptype], None)
        if handler is not None:
            handler(rx, now)

    def on_illegal(self, data: bytes, problems: list[str], now: int, src: Any) -> None:
        """An illegal packet, already counted; the specification says: ignore it. The first of each
        reason is logged: a peer given another --crc had every packet ignored with nothing in the
        log but a watchdog. With its packet ID and serial when its header is there: a peer wrong
        on one packet type only was otherwise left to be found in a capture. A bad CRC that is right
        under another reading of TS-0006 says which (`valid_crc=VARIANT/ORDER`): the peer's, to give
        this node (a user saw "bad_crc" and had to guess among the eight)."""
        first = [p for p in problems if self.illegal[p] == 1]
        if first:
            where = source_text(src)
            header: dict[str, Any] = {}
            if len(data) >= _PREFIX_LEN:
                raw_id, _origin, serial, size = _RX_HEADER.unpack_from(data)
                header = {"packet": raw_id.decode("latin-1"), "serial": serial}
                if C.Problem.BAD_CRC.value in first and len(data) >= C.OVERHEAD:
                    readings = crc_matches(data, crc_span(data, size))
                    if readings:
                        header["valid_crc"] = ",".join(f"{v}/{o}" for v in VARIANTS for o in BYTE_ORDERS
                                                       if (v, o) in readings)
            self.event(now, "illegal_first", reasons=",".join(first), src=where, **header)

    def _due(self) -> Optional[int]:
        return None

    def _tick(self, now: int) -> None:
        pass

    def event(self, now: int, kind: str, **details: Any) -> None:
        """Record (and, with a printer, print) something the node did or detected."""
        entry = {"t": now / US_PER_S, "node": self.name, "event": kind, **details}
        self.counts[kind] += 1
        if self.keep_log:
            self.log.append(entry)
        for listener in self.listeners:
            listener(entry)
        if self.printer is not None:
            # (command data comes off the network: a newline in it forged a log line of its own)
            extra = " ".join(f"{k}={escaped(str(v))}" for k, v in details.items())
            self.printer(now, f"{now / US_PER_S:10.3f} {self.name} {kind} {extra}".rstrip())

    def events(self, kind: str) -> list[dict[str, Any]]:
        """The entries of one kind (none kept without `keep_log`)."""
        return [e for e in self.log if e["event"] == kind]

    def _stall_end(self, now: int) -> Optional[int]:
        """The end of the window ahead that `now` lies in, if any."""
        for start, end, _ in itertools.islice(self.stalls, self._stall_index, None):
            if start <= now < end:
                return end
        return None

    def _stall_check(self, now: int) -> bool:
        """True while stalled; logs each window as it begins and ends (a window logged only when
        it was over went unlogged in a run that ended within it, or that stopped with a silent
        peer) and lets subclasses resynchronise after it."""
        while self._stall_index < len(self.stalls):
            start, end, restart = self.stalls[self._stall_index]
            if now < start:
                return False
            if not self._stall_told:
                self._stall_told = True
                self.stopped = end == NEVER
                self.event(start, "stopped" if self.stopped else "stall_start" if restart is None else "down")
            if now < end:
                return True
            self._stall_index += 1
            self._stall_told = False
            self._stall_passed = end
            self._stalls_ahead = self._stall_index < len(self.stalls)
            if not self._stalls_ahead:
                self._bind_direct()
            if restart is None:
                self.event(end, "stall_end")
                self.on_resume(end)
            else:
                self._restart(end, restart)
        return False

    def on_resume(self, now: int) -> None:
        """The node runs again after a stall."""

    def _restart(self, now: int, restart: Restart) -> None:
        """Back from a restart: the counter afresh, maybe a new source port, then the subclass's state."""
        self.serial = restart.serial & 0xFFFF
        if self.type_serials is not None:
            self.type_serials.clear()
        # The port it sends from now (asked for 0: the free one it took), and the one before when
        # it changed: a restart on the same port logged "port=None".
        ports: dict[str, int] = {}
        if self.restart_source is not None:
            before, after = self.restart_source(restart.port)
            ports = {"port": after} if after == before else {"port": after, "port_from": before}
        self.event(now, "restart", serial=self.serial, **ports)
        self.on_restart(now, restart)

    def on_restart(self, now: int, restart: Restart) -> None:
        """The node starts afresh after a restart (subclasses reset their state)."""
