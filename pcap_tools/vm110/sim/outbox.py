"""A node's own commands (BU: VRCI, controller: VRCO), which both ends handle alike (TS-0006 5.1.3-5.1.4).

One command in flight at a time, each with the next sequential command ID: sent, resent every
resend interval until its acknowledgement, given up after the give-up time. The next one comes
from the queue of scripted commands (first) or the periodic generator, once the previous is done.
"""
from __future__ import annotations

import collections
import struct
from typing import Any, Callable, Iterable, NamedTuple, Optional

from .. import constants as C
from .. import encode
from .node import Rx

_CMD_ID = struct.Struct("<H")
NEVER = 1 << 62      # a due time later than any run (µs)


class OutboxEvents(NamedTuple):
    """The node's event names for its own commands."""

    sent: str
    acked: str
    gave_up: str
    ignored: str        # an acknowledgement that matches no command in flight


class CommandOutbox:
    """Mixin for a `Node` (put it before `Node` in the bases). The node class sets `command_type`,
    `command_events` and `command_label` (text of the generated commands), calls `_outbox_init`
    in `__init__` and `_outbox_start` in `start`, wakes up by `_command_due` and then calls
    `_tick_commands`, and routes its acknowledgement packet to `on_command_ack`.
    `_command_due` is kept up to date here rather than worked out in `_due` (the runners ask
    `next_due` after every packet): a subclass that sets `pending` or the queue itself calls
    `_reschedule()`."""

    command_type: C.PacketType
    command_events: OutboxEvents
    command_label: str
    send: Callable[..., bytes]          # Node's
    event: Callable[..., None]          # Node's

    def _outbox_init(self, command_id_start: int, resend_us: int, give_up_us: int) -> None:
        self.next_command_id = command_id_start & 0xFFFF
        self.pending: Optional[dict[str, Any]] = None      # the command in flight
        self._commands: collections.deque[tuple[int, bytes]] = collections.deque()
        self._next_periodic_command: Optional[int] = None
        self._command_every = 0
        self._command_until: Optional[int] = None
        self._resend_us, self._give_up_us = resend_us, give_up_us
        self._command_due = NEVER           # when `_tick_commands` has something to do

    def _outbox_start(self, commands: Iterable[tuple[int, bytes]], first: Optional[int], every: int,
                      until: Optional[int]) -> None:
        """Scripted commands (µs, data), the first periodic one, its interval and end (all µs, absolute)."""
        self._commands = collections.deque(commands)
        self._next_periodic_command, self._command_every, self._command_until = first, every, until
        self._reschedule()

    def queue_command(self, data: bytes, at: int) -> None:
        """Send a command with `data` at time `at` (µs) or as soon as the one in flight is done."""
        self._commands.append((at, data))
        self._reschedule()

    def _reschedule(self) -> None:
        """Resend or give-up time of the command in flight, else the next queued or periodic one."""
        p = self.pending
        if p is not None:
            self._command_due = min(p["next"], p["first"] + self._give_up_us)
            return
        due = NEVER if self._next_periodic_command is None else self._next_periodic_command
        if self._commands and self._commands[0][0] < due:
            due = self._commands[0][0]
        self._command_due = due

    def _tick_commands(self, now: int) -> None:
        """Resend the command in flight when due; or give it up, and send the next one due if any."""
        p = self.pending
        if p is not None and now - p["first"] < self._give_up_us:
            if now >= p["next"]:
                self._send_command(now)
        else:
            if p is not None:
                self.event(now, self.command_events.gave_up, command_id=p["id"], transmissions=p["count"])
                self.pending = None
            data = self._next_command_data(now)
            if data is not None:
                self.pending = {"id": self.next_command_id, "data": data, "first": now, "next": now, "count": 0}
                self.next_command_id = (self.next_command_id + 1) & 0xFFFF
                self._send_command(now)
        self._reschedule()

    def _next_command_data(self, now: int) -> Optional[bytes]:
        """The first queued command if due, else a generated one if due."""
        if self._commands and self._commands[0][0] <= now:
            return self._commands.popleft()[1]
        t = self._next_periodic_command
        if t is None or t > now:
            return None
        t += self._command_every
        self._next_periodic_command = None if self._command_until is not None and t >= self._command_until else t
        return f"{self.command_label} {self.next_command_id}".encode()

    def _send_command(self, now: int) -> None:
        p = self.pending
        assert p is not None
        self.send(self.command_type, encode.command_payload(p["id"], p["data"]), now, key=p["id"])
        p["count"] += 1          # after sending: `transmit` hooks see the count before this one
        p["next"] = now + self._resend_us
        if p["count"] == 1:
            self.event(now, self.command_events.sent, command_id=p["id"])

    def on_command_ack(self, rx: Rx, now: int) -> None:
        """An acknowledgement (BU: VRAO, controller: VRAI): completes the command in flight."""
        command_id = _CMD_ID.unpack_from(rx.payload)[0]
        p = self.pending
        if p is not None and p["id"] == command_id:
            self.event(now, self.command_events.acked, command_id=command_id,
                       latency_ms=(now - p["first"]) / 1000, transmissions=p["count"])
            self.pending = None
            self._reschedule()
        else:
            self.event(now, self.command_events.ignored, command_id=command_id)
