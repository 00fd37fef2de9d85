"""What a receiver remembers of the commands it handled, so that each is carried out once.

A command is (sender, command ID), and several of a sender's commands may be open at once: a
command ID heard again from the same origin less than the reuse gap after its previous
transmission is a retransmission of a command already handled; after a longer pause the same ID
is a new command (interpretation.md, "Commands").
"""
from __future__ import annotations

from .clock import ms

REUSE_GAP_MS = 2000.0


class CommandLedger:
    """(origin, command ID) -> when it was last heard (µs)."""

    def __init__(self, reuse_gap_ms: float = REUSE_GAP_MS) -> None:
        self._gap = ms(reuse_gap_ms)
        self._heard: dict[tuple[int, int], int] = {}

    def recent(self, origin: int, command_id: int, now: int) -> bool:
        """Was this command ID heard from `origin` less than the reuse gap ago?"""
        last = self._heard.get((origin, command_id))
        return last is not None and now - last < self._gap

    def hear(self, origin: int, command_id: int, now: int) -> bool:
        """Note a transmission; True when it begins a new command."""
        new = not self.recent(origin, command_id, now)
        self._heard[(origin, command_id)] = now
        return new
