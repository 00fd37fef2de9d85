"""Clocks in integer microseconds: exact arithmetic, and the resolution of a pcap timestamp."""
from __future__ import annotations

import time
from typing import Optional

US_PER_MS = 1000
US_PER_S = 1_000_000


def ms(value: float) -> int:
    """Milliseconds to microseconds."""
    return round(value * US_PER_MS)


def seconds(value: float) -> int:
    """Seconds to microseconds."""
    return round(value * US_PER_S)


def log_seconds(value: Optional[int]) -> Optional[float]:
    """Microseconds to seconds for a log entry; None (e.g. a packet never received) stays None."""
    return None if value is None else value / US_PER_S


class WallClock:
    """Monotonic time since the clock was made; `epoch`: the wall-clock time (UNIX seconds) then."""

    def __init__(self) -> None:
        self._start = time.monotonic_ns()
        self.epoch = time.time()

    def wall(self, us: int) -> float:
        """The wall-clock time (UNIX seconds) of clock time `us`: an event logged late (after a
        stall) keeps the time it happened."""
        return self.epoch + us / US_PER_S

    def now(self) -> int:
        return (time.monotonic_ns() - self._start) // 1000


class VirtualClock:
    """Time that moves only when the synthesis loop sets `t`: no sleeping."""

    def __init__(self) -> None:
        self.t = 0          # µs; the loop assigns it directly (it is on the hot path)

    def now(self) -> int:
        return self.t
