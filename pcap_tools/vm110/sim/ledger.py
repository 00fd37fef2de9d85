"""What a receiver remembers of the commands it handled, so that each is carried out once.

A command is (sender, command ID), a sender (origin, source address and port), and several of a
sender's commands may be open at once: a command ID heard again from the same sender less than the
reuse gap after its previous transmission is a retransmission of a command already handled; after
a longer pause, or after the sender restarted, the same ID is a new command (interpretation.md,
"Commands", "Sender restarts").
"""
from __future__ import annotations

from typing import Any, Hashable, NamedTuple, Optional

from .clock import ms
from .node import Rx
from .peers import PeerRestarts

REUSE_GAP_MS = 2000.0


class CommandLedger:
    """(sender, command ID) -> when it was last heard (µs)."""

    def __init__(self, reuse_gap_ms: float = REUSE_GAP_MS) -> None:
        self._gap = ms(reuse_gap_ms)
        self._heard: dict[tuple[Hashable, int], int] = {}

    def recent(self, sender: Hashable, command_id: int, now: int) -> bool:
        """Was this command ID heard from `sender` less than the reuse gap ago?"""
        last = self._heard.get((sender, command_id))
        return last is not None and now - last < self._gap

    def hear(self, sender: Hashable, command_id: int, now: int) -> bool:
        """Note a transmission; True when it begins a new command."""
        new = not self.recent(sender, command_id, now)
        self._heard[(sender, command_id)] = now
        return new

    def forget(self, sender: Hashable, before: int) -> None:
        """`sender` restarted at `before`: what it sent earlier belongs to its old command stream."""
        self._heard = {k: t for k, t in self._heard.items() if k[0] != sender or t >= before}


class Held(NamedTuple):
    """A command heard in the packet that may restart its sender: new or a repeat, as the sender's
    next packet tells."""

    origin: int
    serial: int
    command_id: int
    data: bytes
    heard: int


def sender(rx: Rx) -> tuple[int, Any]:
    """Who sent `rx`: its origin and source address (direction: the receiver hears one)."""
    return rx.origin, rx.src


class PeerCommands:
    """The commands a node receives, each carried out once, across restarts of their senders (their
    serials tell, `sim.peers`; `per_type`: a counter per packet type, as the node numbers its own)."""

    def __init__(self, per_type: bool = False, reuse_gap_ms: float = REUSE_GAP_MS) -> None:
        self.ledger = CommandLedger(reuse_gap_ms)
        self.peers = PeerRestarts(per_type)
        self._held: dict[tuple[int, Any], Held] = {}

    def recent(self, rx: Rx, command_id: int, now: int) -> bool:
        """Was this command ID heard from the sender of `rx` less than the reuse gap ago?"""
        return self.ledger.recent(sender(rx), command_id, now)

    def follow(self, rx: Rx, now: int) -> tuple[Optional[tuple[int, int]], Optional[Held], bool]:
        """Every legal packet the node receives, first: ((first serial, time) of its sender's restart,
        if this packet shows it; the command held at the sender's previous packet, if any, and whether it is new)."""
        key = sender(rx)
        restart, gone = self.peers.restarted(rx.origin, rx.src, rx.ptype, rx.serial, now)
        for old in gone:                      # (an earlier source port of a sender back on a new one)
            self.ledger.forget(old, now)
        if restart is not None:
            self.ledger.forget(key, restart[1])
        held = self._held.get(key)
        if held is None or held.serial == rx.serial:      # (a copy of its packet tells nothing)
            return restart, None, False
        del self._held[key]
        return restart, held, restart is not None and restart[1] == held.heard

    def command(self, rx: Rx, command_id: int, data: bytes, now: int) -> Optional[bool]:
        """A command heard (after `follow`): True when new, False for a repeat, None when that waits
        for the sender's next packet (a repeat unless this packet restarted the sender)."""
        key = sender(rx)
        if self.ledger.hear(key, command_id, now):
            return True
        if self.peers.pending(rx.origin, rx.src, rx.ptype, rx.serial):
            self._held[key] = Held(rx.origin, rx.serial, command_id, data, now)
            return None
        return False
