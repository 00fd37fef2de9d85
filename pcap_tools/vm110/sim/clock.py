"""Clocks in integer microseconds: exact arithmetic, and the resolution of a pcap timestamp."""
from __future__ import annotations

import time

US_PER_MS = 1000
US_PER_S = 1_000_000


def ms(value: float) -> int:
    """Milliseconds to microseconds."""
    return int(round(value * US_PER_MS))


def seconds(value: float) -> int:
    """Seconds to microseconds."""
    return int(round(value * US_PER_S))


class WallClock:
    """Monotonic time since the clock was made; `epoch_us` maps it to wall time for captures."""

    def __init__(self) -> None:
        self._start = time.monotonic_ns()
        self.epoch_us = time.time_ns() // 1000

    def now(self) -> int:
        return (time.monotonic_ns() - self._start) // 1000


class VirtualClock:
    """Time that moves only when the synthesis loop advances it: no sleeping."""

    def __init__(self, epoch_us: int = 0) -> None:
        self.epoch_us = epoch_us
        self._now = 0

    def now(self) -> int:
        return self._now

    def advance(self, t_us: int) -> None:
        if t_us > self._now:
            self._now = t_us
