"""A node's own commands (BU: VRCI, controller: VRCO), which both ends handle alike (TS-0006 5.1.3-5.1.4).

Several commands may be in flight at once (an operator presses two keys within 100 ms; a
controller raises an alarm while a setting is still being resent, interpretation.md "Commands").
Each is sent when it is due, resent every resend interval until its acknowledgement, and given
up after the give-up time, on its own. Command IDs count up from the configured start (wrapping
65535 -> 0); a scripted command may carry its own ID (a device reusing an ID after a pause).
A restart (`_outbox_restart`) drops every command in flight and starts the IDs afresh.
"""
from __future__ import annotations

import collections
import struct
from typing import Any, Callable, Iterable, NamedTuple, Optional

from .. import constants as C
from .. import encode
from .. import protocol as P
from .node import Rx

_CMD_ID = struct.Struct("<" + P.FIELDS["command_id"].code)
NEVER = 1 << 62      # a due time later than any run (µs)


class OutboxEvents(NamedTuple):
    """The node's event names for its own commands."""

    sent: str
    acked: str
    gave_up: str
    ignored: str        # an acknowledgement that matches no command in flight
    dropped: str        # in flight when the node restarted


# A scripted command: (due µs, data, its own command ID or None for the next one).
Scheduled = tuple[int, bytes, Optional[int]]


class CommandOutbox:
    """Mixin for a `Node` (put it before `Node` in the bases). The node class sets `command_type`,
    `command_events` and `command_label` (text of the generated commands), calls `_outbox_init`
    in `__init__` and `_outbox_start` in `start`, wakes up by `_command_due` and then calls
    `_tick_commands`, and routes its acknowledgement packet to `on_command_ack`.
    `_command_due` is kept up to date here rather than worked out in `_due` (the runners ask
    `next_due` after every packet)."""

    command_type: C.PacketType
    command_events: OutboxEvents
    command_label: str
    send: Callable[..., bytes]          # Node's
    event: Callable[..., None]          # Node's
    counts: collections.Counter[str]    # Node's

    def _outbox_init(self, command_id_start: int, resend_us: int, give_up_us: int) -> None:
        self.next_command_id = command_id_start & 0xFFFF
        self.in_flight: dict[int, dict[str, Any]] = {}     # command ID -> its state, oldest first
        self._commands: collections.deque[Scheduled] = collections.deque()
        self._next_periodic_command: Optional[int] = None
        self._command_every = 0
        self._command_until: Optional[int] = None
        self._resend_us, self._give_up_us = resend_us, give_up_us
        self._command_due = NEVER           # when `_tick_commands` has something to do

    def _outbox_start(self, commands: Iterable[Scheduled], first: Optional[int], every: int,
                      until: Optional[int]) -> None:
        """Scripted commands, the first periodic one, its interval and end (all µs, absolute)."""
        self._commands = collections.deque(sorted(commands, key=lambda c: c[0]))
        self._next_periodic_command, self._command_every, self._command_until = first, every, until
        self._reschedule()

    def _outbox_restart(self, now: int, command_id_start: int) -> None:
        """The node restarted at `now`: commands in flight are lost with its memory, the IDs start
        afresh, and commands that fell due while it was down are not sent."""
        for command in self.in_flight.values():
            self.event(now, self.command_events.dropped, command_id=command["id"], transmissions=command["count"])
        self.in_flight.clear()
        self.next_command_id = command_id_start & 0xFFFF
        while self._commands and self._commands[0][0] < now:
            self._commands.popleft()
        t = self._next_periodic_command
        while t is not None and t < now:
            t += self._command_every
            if self._command_until is not None and t >= self._command_until:
                t = None
        self._next_periodic_command = t
        self._reschedule()

    def _reschedule(self) -> None:
        """The earliest resend or give-up of a command in flight, or the next new command."""
        due = NEVER if self._next_periodic_command is None else self._next_periodic_command
        if self._commands and self._commands[0][0] < due:
            due = self._commands[0][0]
        give_up = self._give_up_us
        for command in self.in_flight.values():
            t = min(command["next"], command["first"] + give_up)
            if t < due:  # noqa: PLR1730 (per transmission: an if is cheaper than min())
                due = t
        self._command_due = due

    def _tick_commands(self, now: int) -> None:
        """Give up expired commands, resend the due ones, then send every new command now due."""
        events = self.command_events
        for command in list(self.in_flight.values()):
            if now - command["first"] >= self._give_up_us:
                self.event(now, events.gave_up, command_id=command["id"], transmissions=command["count"])
                del self.in_flight[command["id"]]
            elif now >= command["next"]:
                self._send_command(command, now)
        for given_data, given_id in self._new_commands(now):
            command_id = given_id
            if command_id is None:
                command_id = self.next_command_id
                self.next_command_id = (command_id + 1) & 0xFFFF
            data = f"{self.command_label} {command_id}".encode() if given_data is None else given_data
            command = {"id": command_id, "data": data, "first": now, "next": now, "count": 0}
            self.in_flight.pop(command_id, None)      # an ID reused while in flight: the old one is forgotten
            self.in_flight[command_id] = command
            self._send_command(command, now)
        self._reschedule()

    def _new_commands(self, now: int) -> list[tuple[Optional[bytes], Optional[int]]]:
        """The queued commands due, then a generated one (data None) if due."""
        new: list[tuple[Optional[bytes], Optional[int]]] = []
        while self._commands and self._commands[0][0] <= now:
            _, data, command_id = self._commands.popleft()
            new.append((data, command_id))
        t = self._next_periodic_command
        if t is not None and t <= now:
            t += self._command_every
            self._next_periodic_command = None if self._command_until is not None and t >= self._command_until else t
            new.append((None, None))
        return new

    def _send_command(self, command: dict[str, Any], now: int) -> None:
        self.send(self.command_type, encode.command_payload(command["id"], command["data"]), now, key=command["id"])
        command["count"] += 1          # after sending: `transmit` hooks see the count before this one
        command["next"] = now + self._resend_us
        if command["count"] == 1:
            self.event(now, self.command_events.sent, command_id=command["id"])

    def outbox_summary(self, gave_up: str) -> dict[str, int]:
        """The node's own commands for its summary, `gave_up` naming that outcome: how many were sent,
        and how each ended (acknowledged, given up, dropped at a restart) or is still in flight: the
        four add up to the first (a summary of acknowledged and failed alone did not say how many
        were sent and were still unanswered when the run ended)."""
        counts, events = self.counts, self.command_events
        return {"commands_sent": counts[events.sent], "commands_acked": counts[events.acked],
                gave_up: counts[events.gave_up], "commands_dropped": counts[events.dropped],
                "commands_in_flight": len(self.in_flight)}

    def on_command_ack(self, rx: Rx, now: int) -> None:
        """An acknowledgement (BU: VRAO, controller: VRAI): completes the command in flight with its ID."""
        command_id = _CMD_ID.unpack_from(rx.payload)[0]
        command = self.in_flight.pop(command_id, None)
        if command is not None:
            self.event(now, self.command_events.acked, command_id=command_id,
                       latency_ms=(now - command["first"]) / 1000, transmissions=command["count"])
            self._reschedule()
        else:
            self.event(now, self.command_events.ignored, command_id=command_id)
