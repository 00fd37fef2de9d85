"""The reference machine controller: correct in every point of TS-0006 section 5 and interpretation.md.

- VRPO every `period_ms` (default 100 ms); periodic data above 488 bytes goes out as a burst of
  back-to-back packets numbered from 0 (section 4.2, 5.1.2).
- Every VRCI is acknowledged with a VRAO, retransmissions too, in the order they arrive; each
  command is executed once (a command ID heard again within the reuse gap is a retransmission,
  unless the BU rebooted in between: its serials tell, `sim.peers`), and only while the last VRPI
  of the BU that sent it (its origin) showed an armed RU (section 4.3). A VRCI heard while no VRPI
  of its BU tells the RU's state (none since start-up or a restart, or none within the VRPI
  timeout) is left unacknowledged, logged `deferred`: the BU's next retransmission after a VRPI is
  decided on it (section 4.4, 5.1.3).
- Own commands (VRCO), several in flight at once, are each resent every 100 ms until the VRAI, and
  given up after `vrco_timeout_ms`.
- Restarts (`sim.lifecycle`): back with VRPO from cycle 0, serials and command IDs afresh.
- No VRPI for 500 ms is flagged (and logged) until VRPI comes back (section 5.1.1), for each BU
  (origin) on its own, and before any BU is heard, for the link.
- Two BUs of one origin (a misconfiguration: their serials interleave, their states alternate)
  are told apart where they can be, by source: VRPI of one origin from a source heard within the
  VRPI timeout, after another source was heard, is logged `origin_shared` (once per origin). A BU
  restarted on a new port leaves its old one for good and is no such pair. (Two on one machine
  send from one address; `sim.claim` refuses the second of them.)
- Illegal packets are ignored and counted by reason (section 5.1.5).

Subclasses (the fuzzer's planted bugs) override the hooks: `on_vrci`, `on_vrai`, `on_vrpi`,
`on_illegal`, `acknowledge`, `execute`, `periodic_data`, `vrpo_payloads`, `transmit`.
"""
from __future__ import annotations

import heapq
import itertools
import struct
from dataclasses import dataclass, field
from typing import Any, Optional

from .. import constants as C
from .. import protocol as P
from .. import encode
from .clock import log_seconds, ms, seconds
from .ledger import PeerCommands
from .lifecycle import Life, Restart
from .node import Node, Rx, source_text
from .outbox import NEVER, CommandOutbox, OutboxEvents

_CMD_ID = struct.Struct("<" + P.FIELDS["command_id"].code)
_DATA = P.PACKETS[C.PacketType.VRCI].span("command_data")
_VRPO = C.PacketType.VRPO
_CYCLE = struct.Struct("<I")
_VRPO_NUMBER = struct.Struct("<H")
_BU_ARMED = int(C.BuState.ARMED)
_RU_ARMED = frozenset((int(C.RuState.ARMED), int(C.RuState.ENABLED)))
_VRPI_STATE = struct.Struct("<B5xHB")  # bu_state, (vlaps..c_link), armed_ru, ru_state
_VRPO_HEADER_SIZE, _VRPO_MAX_DATA = P.PAYLOAD_BOUNDS[C.PacketType.VRPO][0], C.VRPO_MAX_DATA


class HeardBu:
    """What the controller knows of one BU from its VRPI: its watchdog (TS-0006 5.1.1) and its RU's
    state (4.3). Also the link's watchdog until a BU is heard."""

    __slots__ = ("alarm", "armed", "last", "shared", "since", "sources", "src")

    def __init__(self, since: int) -> None:
        self.since = since                  # the watchdog counts from here (the last VRPI, start-up, a resume)
        self.last: Optional[int] = None     # when the last VRPI arrived; None: none
        self.alarm = False
        self.armed = False                  # its last VRPI showed an armed RU
        self.src: Any = None                # where its last VRPI came from
        self.sources: dict[Any, int] = {}   # the sources its VRPI came from lately: the last VRPI of each
        self.shared = False                 # `origin_shared` logged


def _origin(origin: Optional[int]) -> dict[str, str]:
    """The BU a watchdog event is about, for the log (none for the link's)."""
    return {} if origin is None else {"origin": f"0x{origin:04x}"}


@dataclass
class ControllerConfig(Life):
    period_ms: float = 100.0
    data_size: int = 64                       # periodic data bytes per cycle (split above 488)
    first_packet_number: int = 0
    vrpi_timeout_ms: float = C.VRPI_WATCHDOG_MS
    vrco_resend_ms: float = C.COMMAND_RESEND_MS
    vrco_timeout_ms: float = C.VRCO_GIVE_UP_MS
    command_id_start: int = 0
    commands: tuple[tuple[Any, ...], ...] = ()   # VRCO to send: (time s, data[, command ID])
    command_every_s: float = 0.0              # and one every N s (0: none)
    command_until_s: float = 0.0              # no periodic VRCO from then on (0: no end)
    require_armed: bool = True                # execute commands only for an armed RU (4.3)
    glink: tuple[tuple[float, float], ...] = ()      # G-Link fallback windows (s): slower VRPO
    glink_period_ms: float = 400.0
    extra: dict[str, Any] = field(default_factory=dict)  # free room for subclasses


class Controller(CommandOutbox, Node):
    """Reference controller. Sends Output packets with origin 0."""

    direction = C.Direction.OUTPUT
    command_type = C.PacketType.VRCO
    command_events = OutboxEvents("vrco_sent", "vrco_acked", "vrco_gave_up", "vrai_ignored", "vrco_dropped")
    command_label = "ALARM"

    def __init__(self, config: Optional[ControllerConfig] = None, name: str = "controller", **node: Any) -> None:
        self.config = cfg = config or ControllerConfig()
        node.setdefault("windows", cfg.windows())
        super().__init__(name, origin=0, **node)
        self._period, self._glink_period = ms(cfg.period_ms), ms(cfg.glink_period_ms)
        self._vrpi_timeout_us = ms(cfg.vrpi_timeout_ms)
        self._vrpi_alarm_after = self._vrpi_timeout_us + 1
        self._glink = tuple((seconds(a), seconds(b)) for a, b in cfg.glink)
        self._next_vrpo = 0
        self.cycle = 0
        # The BUs heard, by origin: each has its own watchdog and RU (one BU's VRPI hid another gone
        # silent, and a disarmed BU's had an armed one's commands refused). Key None until a BU is
        # heard (since start-up or a restart): no VRPI at all is an error too.
        self.bus: dict[Optional[int], HeardBu] = {}
        self._vrpi_due = NEVER              # the first µs past the timeout of one not tripped yet
        self._watches: list[tuple[int, int, Optional[int]]] = []    # (due, order, origin): `_watch`
        self._watch_order = itertools.count()
        # operator commands heard, to execute each once; the BU numbers as this node does
        self.handled = PeerCommands(self.type_serials is not None)
        self._outbox_init(cfg.command_id_start, ms(cfg.vrco_resend_ms), ms(cfg.vrco_timeout_ms))
        self._data_tail = bytes(i & 0xFF for i in range(4, cfg.data_size))

    # --- schedule -----------------------------------------------------------------------------
    def start(self, now: int) -> None:
        self._next_vrpo = now
        self._watch_afresh(now)
        cfg = self.config
        every = seconds(cfg.command_every_s)
        self._outbox_start(((seconds(c[0]) + now, c[1], c[2] if len(c) > 2 else None) for c in cfg.commands),
                           every + now if cfg.command_every_s > 0 else None, every,
                           now + seconds(cfg.command_until_s) if cfg.command_until_s else None)

    def _due(self) -> Optional[int]:
        due = self._next_vrpo
        if self._vrpi_due < due:  # noqa: PLR1730 (per packet: an if is cheaper than min())
            due = self._vrpi_due
        return self._command_due if self._command_due < due else due

    def _tick(self, now: int) -> None:
        if now >= self._vrpi_due:
            self._trip_watchdogs(now)
        if now >= self._command_due:
            self._tick_commands(now)
        if now >= self._next_vrpo:
            first = self.config.first_packet_number
            for index, chunk in enumerate(self.vrpo_payloads(now)):
                self.send(_VRPO, chunk, now, first + index, len(chunk) - _VRPO_HEADER_SIZE)   # key, data_len
            self.cycle += 1
            self._next_vrpo += self._vrpo_period(now) if self._glink else self._period
            if self._next_vrpo <= now:     # after a stall: carry on from now, no catch-up burst
                self._next_vrpo = now + self._vrpo_period(now)

    def _vrpo_period(self, now: int) -> int:
        if self._glink and any(a <= now < b for a, b in self._glink):
            return self._glink_period
        return self._period

    def on_resume(self, now: int) -> None:
        for origin, watch in self.bus.items():
            watch.since = now    # it was not listening: judge VRPI from here on
            if not watch.alarm:
                self._watch(origin, watch)

    def on_restart(self, now: int, restart: Restart) -> None:
        self._next_vrpo, self.cycle = now, 0
        self._watch_afresh(now)
        self.handled = PeerCommands(self.type_serials is not None)
        self._outbox_restart(now, restart.command_id)

    # --- VRPI watchdogs ------------------------------------------------------------------------
    # Each watch's due time (the first µs past its timeout) waits in a heap, an entry going stale
    # when its BU's VRPI comes again or its watchdog trips: the cost per VRPI stays flat however
    # many origins a network or a fuzzer makes up.
    def _watch_afresh(self, now: int) -> None:
        """From start-up or a restart: no BU known, the link's watchdog running from `now`."""
        self.bus = {None: HeardBu(now)}
        self._watches = []
        self._watch(None, self.bus[None])

    def _watch(self, origin: Optional[int], watch: HeardBu) -> None:
        heapq.heappush(self._watches, (watch.since + self._vrpi_alarm_after, next(self._watch_order), origin))
        self._rewatch()

    def _rewatch(self) -> None:
        heap, after = self._watches, self._vrpi_alarm_after
        while heap:
            due, _, origin = heap[0]
            watch = self.bus.get(origin)
            if watch is not None and not watch.alarm and watch.since + after == due:
                self._vrpi_due = due
                return
            heapq.heappop(heap)
        self._vrpi_due = NEVER

    def _trip_watchdogs(self, now: int) -> None:
        while self._vrpi_due <= now:
            origin = heapq.heappop(self._watches)[2]
            watch = self.bus[origin]
            watch.alarm = True
            self.event(watch.since + self._vrpi_timeout_us, "vrpi_timeout", **_origin(origin),
                       last_vrpi=log_seconds(watch.last))
            self._rewatch()

    def _vrpi_heard(self, origin: int, now: int) -> HeardBu:
        """A VRPI of BU `origin`: its watchdog starts afresh."""
        heard = self.bus.get(origin)
        if heard is None or heard.alarm:
            heard = self._vrpi_back(origin, now)
        heard.since = heard.last = now
        self._watch(origin, heard)
        return heard

    def _vrpi_back(self, origin: int, now: int) -> HeardBu:
        """The first VRPI of BU `origin` since start-up or a restart, or its first after its timeout:
        restored when its watchdog (for a BU's first, the link's) had tripped."""
        link = self.bus.pop(None, None)
        heard = self.bus.get(origin)
        if heard is None:
            heard = self.bus[origin] = HeardBu(now)
            heard.alarm = link is not None and link.alarm
        if heard.alarm:
            gap = None if heard.last is None else (now - heard.last) / 1000
            self.event(now, "vrpi_restored", **_origin(origin), gap_ms=gap)
            heard.alarm = False
        return heard

    # --- VRPO ---------------------------------------------------------------------------------
    def periodic_data(self, now: int) -> bytes:
        """This cycle's periodic data: the cycle counter, then a fixed pattern."""
        return (_CYCLE.pack(self.cycle & 0xFFFFFFFF) + self._data_tail)[:self.config.data_size]

    def vrpo_payloads(self, now: int) -> list[bytes]:
        """The VRPO payloads of one cycle: full 488-byte chunks, the last one shorter."""
        data = self.periodic_data(now)
        if len(data) < _VRPO_MAX_DATA:
            return [_VRPO_NUMBER.pack(self.config.first_packet_number & 0xFFFF) + data]
        chunks = [data[i:i + C.VRPO_MAX_DATA] for i in range(0, len(data), C.VRPO_MAX_DATA)] or [b""]
        first = self.config.first_packet_number
        return [encode.vrpo_payload((first + n) & 0xFFFF, chunk) for n, chunk in enumerate(chunks)]

    # --- input handling -----------------------------------------------------------------------
    def follow(self, rx: Rx, now: int) -> None:
        """Every legal packet of the BU, first: a BU that rebooted begins a new command stream (an
        ID it reuses within the reuse gap was a repeat, never executed: interpretation.md)."""
        restart, held, new = self.handled.follow(rx, now)
        if restart is not None:
            # (logged when the next packet confirms it: the restart's own time and first serial)
            self.event(now, "bu_restart", origin=f"0x{rx.origin:04x}", src=source_text(rx.src),
                       at=log_seconds(restart[1]), serial=restart[0])
        if held is not None:
            if new:
                self.execute(held.origin, held.command_id, held.data, now)
            else:
                self.event(held.heard, "repeat", command_id=held.command_id)

    def on_vrpi(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        bu = self._vrpi_heard(rx.origin, now)
        if rx.src != bu.src:
            self._source_changed(rx.origin, bu, rx.src, now)
        bu.sources[rx.src] = now
        bu_state, armed_ru, ru_state = _VRPI_STATE.unpack_from(rx.payload)
        bu.armed = bu_state == _BU_ARMED and armed_ru != 0 and ru_state in _RU_ARMED

    def _source_changed(self, origin: int, bu: HeardBu, src: Any, now: int) -> None:
        """A VRPI of BU `origin` from another source than its last: back to one heard within the
        VRPI timeout is a second BU of the origin (a restarted BU does not go back)."""
        timeout = self._vrpi_timeout_us
        back = bu.sources.get(src)
        if back is not None and now - back <= timeout and not bu.shared:
            bu.shared = True
            self.event(now, "origin_shared", **_origin(origin), src=source_text(src), other=source_text(bu.src))
        bu.sources = {s: t for s, t in bu.sources.items() if now - t <= timeout}   # (a BU's old ports go)
        bu.src = src

    def ru_state_known(self, origin: int, now: int) -> bool:
        """Does a VRPI of BU `origin` within the VRPI timeout tell its RU's state? Not after start-up
        or a restart before its first one, nor after a silence of its VRPI longer than the timeout."""
        last = self.last_vrpi(origin)
        return last is not None and now - last <= self._vrpi_timeout_us

    def ru_armed(self, origin: int) -> bool:
        """Did the last VRPI of BU `origin` show an armed RU?"""
        heard = self.bus.get(origin)
        return heard is not None and heard.armed

    def last_vrpi(self, origin: int) -> Optional[int]:
        """When the last VRPI of BU `origin` arrived; None: none since start-up or a restart."""
        heard = self.bus.get(origin)
        return None if heard is None else heard.last

    def on_vrci(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        command_id = _CMD_ID.unpack_from(rx.payload)[0]
        if self.config.require_armed and not self.ru_state_known(rx.origin, now):
            # It cannot be checked against the RU's state (4.3), so it is not processed and not
            # acknowledged (4.4): the BU resends it every 100 ms (5.1.3), and the first copy after a
            # VRPI is decided on that VRPI. Refused and acknowledged, a command of an armed RU was
            # lost while the operator was told it went through; with no VRPI for 2000 ms, the BU
            # tells the operator it failed.
            self.event(now, "deferred", command_id=command_id, origin=f"0x{rx.origin:04x}", serial=rx.serial,
                       last_vrpi=log_seconds(self.last_vrpi(rx.origin)))
            return
        self.acknowledge(command_id, now)
        new = self.handled.command(rx, command_id, rx.payload[_DATA], now)
        if new:
            self.execute(rx.origin, command_id, rx.payload[_DATA], now)
        elif new is not None:      # (None: it waits for the BU's next packet, `follow`)
            self.event(now, "repeat", command_id=command_id)

    def acknowledge(self, command_id: int, now: int) -> None:
        self.send(C.PacketType.VRAO, encode.ack_payload(command_id), now, key=command_id)

    def execute(self, origin: int, command_id: int, data: bytes, now: int) -> None:
        """Carry out an operator command (here: log it); refused while no RU is armed."""
        text = data.rstrip(b"\0").decode("ascii", "replace")
        if self.config.require_armed and not self.ru_armed(origin):
            self.event(now, "refused", command_id=command_id, origin=f"0x{origin:04x}", data=text)
        else:
            self.event(now, "executed", command_id=command_id, origin=f"0x{origin:04x}", data=text)

    # --- own commands (VRCO): `CommandOutbox` -------------------------------------------------
    def on_vrai(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        self.on_command_ack(rx, now)           # completes the VRCO in flight with its ID

    def summary(self) -> dict[str, Any]:
        """Counters for logs and tests."""
        counts = self.counts
        return {**self.traffic_summary(),
                "executed": counts["executed"], "refused": counts["refused"],
                "deferred": counts["deferred"], "repeats": counts["repeat"], "vrpi_timeouts": counts["vrpi_timeout"],
                "origin_shared": counts["origin_shared"],
                # its own commands' outcomes, as the base unit's summary has them (they were missing)
                **self.outbox_summary("commands_gave_up")}
