"""The rule of one VRPO burst (interpretation.md, "VRPO split into several packets"; docs/rules.md,
"VRPO bursts"), a packet at a time and without numpy: the analysis (`analysis.bursts`, which
documents the rule in full), the live monitor and the simulated base unit judge bursts by it.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

from . import constants as C
from . import protocol as P

DATA_OFFSET = P.PAYLOAD_BOUNDS[C.PacketType.VRPO][0]


class Open:
    """The burst being received, judged in constant time per packet: `bad` (a number below the
    start, or seen before), `top` (the highest number) and its data length, `short` (packets of
    fewer than 488 data bytes). n distinct numbers from the start whose highest is start + n - 1
    are exactly start ... start + n - 1. What the sender's earlier packets tell about its data size
    outlives each burst: `short_seen` (a packet of fewer than 488 bytes) and `full` (the most
    packets of a complete burst of full packets)."""

    def __init__(self, start: int, data_size: int) -> None:
        self.start, self.data_size = start, data_size
        self.short_seen = False
        self.full = 0
        self.clear()

    def clear(self) -> None:
        self.seen: set[int] = set()                 # (at most 65,536 numbers)
        self.bad = False
        self.top, self.top_data = -1, 0
        self.n = self.short = self.total = 0
        self.done = False                           # `ended()`, kept by `add` (asked of every packet)

    def add(self, number: int, data: int) -> None:
        if number < self.start or number in self.seen:
            self.bad = True
        else:
            self.seen.add(number)
        if number > self.top:
            self.top, self.top_data = number, data
        short = data != C.VRPO_MAX_DATA
        self.short += short
        self.short_seen |= short                    # (a burst with a short packet is judged by its own)
        self.n += 1
        self.total += data
        last_short = self.top_data != C.VRPO_MAX_DATA
        self.done = (not self.bad and self.top - self.start == self.n - 1 and self.short == last_short
                     and (self.total == self.data_size if self.data_size else last_short))

    def _numbered(self) -> bool:
        """Numbers start ... start + n - 1, each once."""
        return self.n > 0 and not self.bad and self.top - self.start == self.n - 1

    def ended(self) -> bool:
        """Complete by its own packets: numbered from the start, no packet but the last short, and
        the data add up to the configured size, or (infer) the last is short."""
        return self.done

    def over(self, number: int) -> bool:
        """A packet of this number, within the gap, begins the next burst: this one ended, or the
        number restarts the numbering, or (infer) the inferred size is reached and the number does
        not go on from it (if it does, the size was inferred too small)."""
        if self.ended() or (number == self.start and number in self.seen):
            return True
        return (not self.data_size and 0 < self.full <= self.n and not self.short_seen
                and number != self.top + 1 and self._numbered())

    def complete(self) -> bool:
        """Ended; or (infer) full packets numbered from the start, no shorter packet before them
        (`short_seen` counts none of theirs) and at least as many as the longest complete such burst."""
        return self.ended() or (not self.data_size and not self.short and self._numbered()
                                and not self.short_seen and self.n >= self.full)

    def close(self) -> bool:
        """The burst has ended: whether complete, learnt from, and cleared for the next one."""
        complete = self.complete()
        if complete and not self.short:
            self.full = max(self.full, self.n)
        self.clear()
        return complete


class Incomplete(NamedTuple):
    """An incomplete burst, as `BurstWatch` found it when it ended."""

    first_us: int            # when its first packet arrived
    packets: int
    numbers: tuple[int, ...]  # the distinct packet numbers received, in order
    data: int                # data bytes received


class BurstWatch:
    """The VRPO bursts of one sender as its packets arrive (µs): a burst ends at the burst gap, at
    a step back of the clock, or once over (`Open.over`), and is judged then (per VRPO of a
    simulated BU: nothing is built for a complete one)."""

    def __init__(self, start: int = 0, data_size: int = 0, gap_ms: float = C.VRPO_BURST_GAP_MS) -> None:
        self.open = Open(start, data_size)
        self.gap_us = round(gap_ms * 1000)
        self.last_us: Optional[int] = None
        self.first_us = 0

    def add(self, now_us: int, number: int, data: int) -> Optional[Incomplete]:
        """One VRPO packet (its packet number and data bytes); the burst it ended, if incomplete."""
        last, burst = self.last_us, self.open
        ended = None
        if burst.done and burst.short:
            # (most VRPO: a burst of one short packet. Ended and complete, its close would learn
            # nothing: `full` counts bursts of full packets only)
            burst.clear()
            self.first_us = now_us
        elif last is None or not 0 <= now_us - last < self.gap_us or burst.over(number):
            if burst.n:
                seen, packets, data_in = burst.seen, burst.n, burst.total    # (`close` makes a new set)
                if not burst.close():
                    ended = Incomplete(self.first_us, packets, tuple(sorted(seen)), data_in)
            self.first_us = now_us
        self.last_us = now_us
        burst.add(number, data)
        return ended
