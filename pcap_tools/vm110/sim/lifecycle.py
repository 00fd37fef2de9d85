"""A node's life beyond normal running: hanging (stalls), restarting, stopping for good.

A restart is what a rebooting base unit or a controller program started again does: it goes down
at `at_s` (sends and hears nothing), comes back `silence_s` later with its serial counter and
command IDs started afresh and its commands in flight forgotten, optionally sending from a new
source port (a socket reopened on another ephemeral port). All of it becomes stall windows of
the node (µs), each remembering the restart it ends, if any.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from .clock import seconds

NEVER = 1 << 62             # the end of a stop: later than any run (µs)
DEFAULT_SILENCE_S = 1.5


@dataclass(frozen=True)
class Restart:
    at_s: float                       # the node goes down
    silence_s: float = DEFAULT_SILENCE_S    # and is back this much later
    serial: int = 0                   # the counter's first serial afterwards
    command_id: int = 0               # the first command ID afterwards
    port: Optional[int] = None        # a new source port (0: any free one, on sockets), or the same one

    def __post_init__(self) -> None:
        if self.silence_s <= 0:
            raise ValueError("a restart needs a silence > 0")


# A window in which the node neither sends nor receives: (start µs, end µs, the restart at its end).
Window = tuple[int, int, Optional[Restart]]


@dataclass
class Life:
    """The part of a node's configuration (BU and controller alike) that this module handles."""

    stalls: tuple[tuple[float, float], ...] = ()     # (start s, end s): the node hangs
    restarts: tuple[Restart, ...] = ()
    stop_at_s: Optional[float] = None                 # sends nothing from then on, for good

    def windows(self) -> tuple[Window, ...]:
        """Stalls, restarts and the stop as one sorted tuple of windows (µs)."""
        out: list[Window] = [(seconds(a), seconds(b), None) for a, b in self.stalls]
        out += [(seconds(r.at_s), seconds(r.at_s + r.silence_s), r) for r in self.restarts]
        if self.stop_at_s is not None:
            out.append((seconds(self.stop_at_s), NEVER, None))
        return tuple(sorted(out, key=lambda w: (w[0], w[1])))
