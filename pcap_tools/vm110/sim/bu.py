"""The simulated base unit (BU), TS-0006 section 5 as the BU sees it.

- VRPI every 125 ms with the remote's state (`sim.remote`).
- Operator commands as VRCI, several in flight at once (two keys pressed within 100 ms): each
  resent every 100 ms until its VRAO, failed (logged, no more resends) after 2000 ms without one.
- Every VRCO is acknowledged with a VRAI (retransmissions too) and handed to the RU application
  once per command (a command ID heard again within the reuse gap is a retransmission, unless the
  controller restarted in between: its serials tell, `sim.peers`).
- VRPO bursts (a VRPO split into several packets, TS-0006 4.2, 5.1.2) are judged by the rule of
  `vrpo_burst` as they arrive: an incomplete one (a packet missing, numbers out of sequence) is
  logged `vrpo_incomplete` and counted, as the analysis reports it (its data cannot be reassembled).
- VRPO watchdog: no VRPO for 2000 ms shows in VRPI as EG-Link "No link" and, with an RU armed,
  BU state "External link error" (ES-Link relays open) until VRPO comes back.
- G-Link fallback windows: the RU application answers over the slower C-Link, so each VRAI leaves
  later (`glink_ack_delay_ms`), and the reported C-Link RSSI drops.
- Restarts (`sim.lifecycle`): a reboot, back with VRPI, serials and command IDs afresh. The reboot
  loses the arming: VRPI say BU state "Initial" for `boot_ms`, then "Disarmed" with the RU among the
  unarmed ones until the operator arms it again `rearm_ms` after the BU came back (the script's
  state from then on; the script's commands go out as scripted, refused while no RU is armed).
One serial counter for everything it sends (interpretation.md).
"""
from __future__ import annotations

import random
import struct
from dataclasses import dataclass
from typing import Any, Optional

from .. import constants as C
from .. import encode
from .. import protocol as P
from ..vrpo_burst import DATA_OFFSET, BurstWatch
from .clock import log_seconds, ms, seconds
from .ledger import PeerCommands
from .lifecycle import Life, Restart
from .node import Node, Rx, source_text
from .outbox import CommandOutbox, OutboxEvents
from .remote import VRPI_INDEX, Remote, rebooted_values

_CMD_ID = struct.Struct("<" + P.FIELDS["command_id"].code)
_VRPO_NUMBER = struct.Struct("<" + P.FIELDS["packet_number"].code)
_SHOWN_NUMBERS = 16      # of an incomplete burst's packet numbers, in its log line
_DATA = P.PACKETS[C.PacketType.VRCO].span("command_data")
_VRPI = C.PacketType.VRPI
_VRPI_STRUCT = P.PACKETS[_VRPI].struct
_ARMED_RU, _BU_STATE = VRPI_INDEX["armed_ru"], VRPI_INDEX["bu_state"]
_EG_LINK, _RSSI = VRPI_INDEX["eg_link"], VRPI_INDEX["ru_rssi"]
DEFAULT_ORIGIN = 0x0101


@dataclass
class BaseUnitConfig(Life):
    origin: int = DEFAULT_ORIGIN
    vrpi_period_ms: float = C.VRPI_PERIOD_MS
    vrci_resend_ms: float = C.COMMAND_RESEND_MS
    vrci_fail_ms: float = C.VRCI_FAIL_MS
    vrpo_watchdog_ms: float = C.VRPO_WATCHDOG_MS
    command_id_start: int = 0
    glink: tuple[tuple[float, float], ...] = ()          # G-Link fallback windows (s)
    glink_ack_delay_ms: tuple[float, float] = (250.0, 650.0)
    glink_rssi: int = 25
    boot_ms: float = 1000.0          # after a reboot: "Initial", not fully operative yet (TS-0006 4.1.1)
    rearm_ms: float = 5000.0         # after a reboot: no RU armed until the operator arms it again
    seed: int = 0
    vrpo_start: int = 0              # the controller's first VRPO packet number (interpretation.md: 0, or 1)


class BaseUnit(CommandOutbox, Node):
    """Simulated BU. Sends Input packets with its origin."""

    direction = C.Direction.INPUT
    command_type = C.PacketType.VRCI
    command_events = OutboxEvents("command_sent", "command_acked", "command_failed", "vrao_ignored",
                                  "command_dropped")
    command_label = "OP CMD"

    def __init__(self, remote: Optional[Remote] = None, config: Optional[BaseUnitConfig] = None,
                 name: str = "bu", **node: Any) -> None:
        self.config = cfg = config or BaseUnitConfig()
        node.setdefault("windows", cfg.windows())
        super().__init__(name, origin=cfg.origin, **node)
        self.remote = remote or Remote.simple()
        self._rng = random.Random(f"bu:{cfg.seed}")
        self._glink = tuple((seconds(a), seconds(b)) for a, b in cfg.glink)
        self._period_us, self._watchdog_us = ms(cfg.vrpi_period_ms), ms(cfg.vrpo_watchdog_ms)
        self._t0 = 0
        self._next_vrpi = 0
        self.last_vrpo: Optional[int] = None     # when the last VRPO arrived; None: none since start-up
        self._vrpo_since: Optional[int] = None   # the watchdog counts from here (last VRPO, start, resume)
        self.watchdog_tripped = False
        self._rebooted: Optional[tuple[int, int]] = None   # after a reboot: (operative at, rearmed at)
        self._outbox_init(cfg.command_id_start, ms(cfg.vrci_resend_ms), ms(cfg.vrci_fail_ms))
        self._acks: list[tuple[int, int]] = []            # delayed VRAI: (due, command ID)
        # VRCO heard, to hand each to the RU app once; the controller numbers as this node does
        self.delivered = PeerCommands(self.type_serials is not None)
        self.bursts = BurstWatch(cfg.vrpo_start)     # (the data size inferred, as the analysis does by default)

    def start(self, now: int) -> None:
        self._t0 = self._next_vrpi = now
        self._vrpo_since = now    # grace period from start-up
        every, until = self.remote.command_every, self.remote.command_until
        self._outbox_start(((now + t, d, i) for t, d, i in self.remote.commands), now + every if every else None,
                           every, now + until if until else None)

    def _due(self) -> Optional[int]:
        due = self._next_vrpi
        if self._command_due < due:  # noqa: PLR1730 (per tick: an if is cheaper than min())
            due = self._command_due
        if self._acks and self._acks[0][0] < due:
            due = self._acks[0][0]
        return due

    def _tick(self, now: int) -> None:
        if now >= self._command_due:
            self._tick_commands(now)
        while self._acks and self._acks[0][0] <= now:
            self.send(C.PacketType.VRAI, encode.ack_payload(self._acks[0][1]), now, key=self._acks[0][1])
            self._acks.pop(0)
        if now >= self._next_vrpi:
            self.send(_VRPI, _VRPI_STRUCT.pack(*self.vrpi_values(now)), now)
            self._next_vrpi += self._period_us
            if self._next_vrpi <= now:      # after a stall: no catch-up burst
                self._next_vrpi = now + self._period_us

    def in_glink_fallback(self, now: int) -> bool:
        return any(a <= now < b for a, b in self._glink)

    # --- VRPI and the VRPO watchdog -----------------------------------------------------------
    def vrpi_values(self, now: int) -> list[Any]:
        """This VRPI's payload values (payload order): the remote's, with the BU's own state on top."""
        values = self._remote_values(now)
        armed = values[_ARMED_RU]
        if self._vrpo_since is not None and now - self._vrpo_since > self._watchdog_us:
            self._check_watchdog(now, bool(armed))
        if self.watchdog_tripped:
            values[_EG_LINK] = C.LinkStatus.NO_LINK
            if armed:
                values[_BU_STATE] = C.BuState.EXTERNAL_LINK_ERROR
        if armed and self._glink and self.in_glink_fallback(now):
            values[_RSSI] = self.config.glink_rssi
        return values

    def _remote_values(self, now: int) -> list[Any]:
        """The remote's state as this BU knows it: the script's, unless a reboot lost the arming."""
        values = self.remote.values(now - self._t0)
        if self._rebooted is None:
            return values
        operative, rearmed = self._rebooted
        if now >= rearmed:
            self._rebooted = None
            return values
        return rebooted_values(values, now >= operative)

    def _check_watchdog(self, now: int, armed: bool) -> None:
        since = self._vrpo_since
        if not self.watchdog_tripped and since is not None and now - since > self._watchdog_us:
            self.watchdog_tripped = True
            self.event(since + self._watchdog_us, "vrpo_watchdog", last_vrpo=log_seconds(self.last_vrpo),
                       es_relays_open=armed)

    def follow(self, rx: Rx, now: int) -> None:
        """Every legal packet of the controller, first: a controller restarted begins a new command
        stream (an ID it reuses within the reuse gap was a repeat, never delivered: interpretation.md)."""
        restart, held, new = self.delivered.follow(rx, now)
        if restart is not None:
            self.event(now, "controller_restart", src=source_text(rx.src), at=log_seconds(restart[1]),
                       serial=restart[0])
        if held is not None and new:
            self.deliver(held.command_id, held.data, now)

    def deliver(self, command_id: int, data: bytes, now: int) -> None:
        """Hand a controller command to the RU application (here: log it)."""
        self.event(now, "vrco_delivered", command_id=command_id, data=data.rstrip(b"\0").decode("ascii", "replace"))

    def on_vrpo(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        ended = self.bursts.add(now, _VRPO_NUMBER.unpack_from(rx.payload)[0], len(rx.payload) - DATA_OFFSET)
        if ended is not None:
            numbers = ",".join(map(str, ended.numbers[:_SHOWN_NUMBERS])) + (
                ",..." if len(ended.numbers) > _SHOWN_NUMBERS else "")
            self.event(now, "vrpo_incomplete", at=log_seconds(ended.first_us), packets=ended.packets,
                       numbers=numbers, data=ended.data)
        if self._vrpo_since is not None and now - self._vrpo_since > self._watchdog_us:
            self._check_watchdog(now, bool(self._remote_values(now)[_ARMED_RU]))
        if self.watchdog_tripped:
            self.watchdog_tripped = False
            self.event(now, "vrpo_restored")
        self.last_vrpo = self._vrpo_since = now

    def on_resume(self, now: int) -> None:
        self._vrpo_since = now   # it was not listening: judge VRPO from here on

    def on_restart(self, now: int, restart: Restart) -> None:
        self._next_vrpi = self._vrpo_since = now
        self.last_vrpo = None
        self.watchdog_tripped = False
        self._rebooted = (now + ms(self.config.boot_ms), now + ms(self.config.rearm_ms))
        self._acks.clear()
        self.delivered = PeerCommands(self.type_serials is not None)
        self.bursts = BurstWatch(self.config.vrpo_start)
        self._outbox_restart(now, restart.command_id)

    # --- operator commands (VRCI): `CommandOutbox` ---------------------------------------------
    def on_vrao(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        self.on_command_ack(rx, now)

    # --- controller commands (VRCO) -----------------------------------------------------------
    def on_vrco(self, rx: Rx, now: int) -> None:
        self.follow(rx, now)
        command_id = _CMD_ID.unpack_from(rx.payload)[0]
        if self.delivered.command(rx, command_id, rx.payload[_DATA], now):
            self.deliver(command_id, rx.payload[_DATA], now)
        if self.in_glink_fallback(now):
            low, high = self.config.glink_ack_delay_ms
            self._acks.append((now + ms(self._rng.uniform(low, high)), command_id))
            self._acks.sort()
        else:
            self.send(C.PacketType.VRAI, encode.ack_payload(command_id), now, key=command_id)

    def summary(self) -> dict[str, Any]:
        counts = self.counts
        return {**self.traffic_summary(),
                **self.outbox_summary("commands_failed"), "vrco_delivered": counts["vrco_delivered"],
                "vrpo_watchdog": counts["vrpo_watchdog"], "vrpo_incomplete": counts["vrpo_incomplete"]}
