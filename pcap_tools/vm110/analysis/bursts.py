"""VRPO bursts (interpretation.md, "VRPO split into several packets"; docs/rules.md, "VRPO bursts").

A burst is a run of VRPO packets from one sender less than the burst gap (20 ms) apart, each at or
after the one before (a step back of the clock begins a new burst). Its packet numbers must be
start, start+1, ... each once (in any order), every packet but the last by number carrying 488 data
bytes. With a configured periodic data size, a burst is complete when its data add up to exactly
that size. With 0 (infer, the default) it is complete when its last packet carries fewer than 488
bytes, or, every packet carrying 488 (a data size that is a multiple of 488, which no packet
marks), when the sender has sent no shorter VRPO packet before it and no complete burst of full
packets longer than it. A burst is over when it is complete by its own packets, when a packet
restarts the numbering (the start number again), or when it has reached the inferred size and the
next packet does not go on from it: the sender's next packet begins another burst even within the
gap. Two unsplit VRPO packets closer than the gap (jitter) are two bursts; a split one whose parts
arrive out of order is one, complete once its parts are all there.

`Bursts` is fed a sender's accepted VRPO packets a batch at a time and keeps only the burst still
open, judged in constant time per packet (a burst may be endless): bursts of one packet (the usual
case) are judged a batch at a time with numpy. The time of each burst's first packet is kept for
the exact statistics of the intervals between bursts; as long as every burst is a single packet
these are the times of the VRPO stream (`packets`, shared with `periodic.Stream`), and only a
sender that splits gets its own array.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np

from .. import constants as C
from ..vrpo_burst import DATA_OFFSET, Open
from . import timing
from .periodic import Floats

__all__ = ["DATA_OFFSET", "Bursts", "Open"]


class Bursts:
    """Burst assembly of one sender: complete bursts counted, the first packet (where, time) of
    each incomplete one, the time of each burst's first packet (`starts`), and the bursts that
    follow the one before after an interval outside [low_ms, high_ms] (`outside`: where, time,
    interval; not a negative one, a step back of the clock, which is time_backwards)."""

    def __init__(self, packets: Floats, gap_ms: float = C.VRPO_BURST_GAP_MS, start: int = 0, data_size: int = 0,
                 low_ms: float = C.VRPO_PERIOD_MIN_MS, high_ms: float = C.VRPO_PERIOD_MAX_MS,
                 floats: Callable[[], Floats] = Floats) -> None:
        self.floats = floats                         # makes the store of `own` (periodic.Stream)
        self.gap_ms, self.start, self.data_size = gap_ms, start, data_size
        self.low_ms, self.high_ms = low_ms, high_ms
        self.complete = 0
        self.incomplete: list[tuple[int, float]] = []
        self.outside: list[tuple[int, float, float]] = []
        self.packets = packets                       # the times of every packet, fed before each batch
        self.own: Optional[Floats] = None            # burst starts, once a burst has several packets
        self.last_start: Optional[float] = None
        self.firsts: list = []                       # where of each burst's first packet (count() only)
        self.first: tuple[int, float] = (0, 0.0)    # the open burst's first packet
        self.open = Open(start, data_size)
        self.last_time: Optional[float] = None

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "floats"}    # (the analysis' own: Sender.attach)

    def _close(self) -> None:
        if self.open.n:
            if self.open.close():
                self.complete += 1
            else:
                self.incomplete.append(self.first)

    def feed(self, times: np.ndarray, numbers: np.ndarray, sizes: np.ndarray, where: Sequence[int],
             keep_firsts: bool = False) -> None:
        """The sender's next accepted VRPO packets: times, packet numbers, payload sizes."""
        n = len(times)
        if not n:
            return
        times = np.asarray(times, dtype=np.float64)
        begins = np.empty(n, dtype=bool)
        # (a step back of the clock begins a burst too: two captures appended end to end)
        # (to the microsecond, as every interval: an epoch time in a float carries 0.24 us of noise)
        begins[0] = self.last_time is None or not 0 <= timing.interval_ms(float(times[0]), self.last_time) < self.gap_ms
        steps = timing.intervals_ms(times)
        begins[1:] = (steps >= self.gap_ms) | (steps < 0)
        self.last_time = float(times[-1])
        if begins[0]:
            self._close()
        data = np.asarray(sizes, dtype=np.int64) - DATA_OFFSET
        number = np.asarray(numbers, dtype=np.int64)
        # Bursts of one packet by the gap alone are judged all at once (but for one of 488 bytes
        # with the size inferred: that depends on the sender's packets before it) ...
        lone = begins.copy()
        lone[:-1] &= begins[1:]
        lone[-1] = False
        short = data < C.VRPO_MAX_DATA
        if not self.data_size:
            lone &= short
        ok = (number == self.start) & ((data == self.data_size) if self.data_size else short)
        self.complete += int(np.count_nonzero(lone & ok))
        for i in np.flatnonzero(lone & ~ok).tolist():
            self.incomplete.append((int(where[i]), float(times[i])))
        # ... the rest a packet at a time: the burst open from before, longer ones, the last one. A
        # packet within the gap after a burst that is over begins the next one. (The short packets
        # judged alone count for `open` from the first packet fed after them, once it has closed the
        # burst before them: the batch's last packet is always fed.)
        alone_short = np.flatnonzero(lone & short)
        first_short = int(alone_short[0]) if len(alone_short) else n
        for i in np.flatnonzero(~lone).tolist():
            if begins[i] or self.open.over(int(number[i])):
                self._close()
                self.first = (int(where[i]), float(times[i]))
                begins[i] = True
            if first_short < i:
                self.open.short_seen = True
            self.open.add(int(number[i]), int(data[i]))
        firsts = np.flatnonzero(begins)
        new = times[firsts]
        if self.own is None and len(new) < n:
            self.own = self.floats()
            for block in self.packets.blocks:        # every packet before these began a burst
                self.own.extend(block[:max(0, min(len(block), len(self.packets) - n - len(self.own)))])
        if self.own is not None:
            self.own.extend(new)
        between = timing.intervals_ms(np.concatenate(([] if self.last_start is None else [self.last_start], new)))
        self.last_start = float(new[-1]) if len(new) else self.last_start
        # (a negative interval is a step back of the clock, counted as time_backwards: no period)
        out = np.flatnonzero(((between < self.low_ms) & (between >= 0)) | (between > self.high_ms))
        shift = len(new) - len(between)             # the first start has no interval before it
        for k in out.tolist():
            i = int(firsts[k + shift])
            self.outside.append((int(where[i]), float(times[i]), float(between[k])))
        if keep_firsts:
            self.firsts += [where[i] for i in firsts.tolist()]

    @property
    def starts(self) -> Floats:
        """The time of each burst's first packet."""
        return self.packets if self.own is None else self.own

    def finish(self) -> None:
        """The capture ended: the open burst is closed."""
        self._close()

