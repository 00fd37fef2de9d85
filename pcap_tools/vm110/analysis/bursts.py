"""VRPO bursts (interpretation.md, "VRPO split into several packets").

A burst is a run of VRPO packets from one sender less than the burst gap (20 ms) apart, each at or
after the one before (a step back of the clock begins a new burst): the gap is the whole
definition, since a receiver cannot know what was sent back to back. It is complete when its
packet numbers are start, start+1, ... each once (in any order), every packet but the last by
number carries 488 data bytes, and the last fewer, or, with a configured periodic data size, the
data add up to exactly that size. Two unsplit VRPO packets that arrive closer than the
gap (jitter, reordering) therefore form one incomplete burst, as the truth of `vm110 synth` has it.

`Bursts` is fed a sender's accepted VRPO packets a batch at a time and keeps only the burst still
open: bursts of one packet (the usual case) are judged a batch at a time with numpy. A burst of
more packets than there are packet numbers cannot be complete; its parts are then no longer kept.
The time of each burst's first packet is kept for the exact statistics of the intervals between
bursts; as long as every burst is a single packet these are the times of the VRPO stream
(`packets`, shared with `periodic.Stream`), and only a sender that splits gets its own array.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np

from .. import constants as C
from .. import protocol as P
from . import timing
from .periodic import Floats

DATA_OFFSET = P.PAYLOAD_BOUNDS[C.PacketType.VRPO][0]
MAX_PARTS = 1 << 16          # packet numbers are 16 bits: a longer burst is incomplete


class Bursts:
    """Burst assembly of one sender: complete bursts counted, the first packet (where, time) of
    each incomplete one, the time of each burst's first packet (`starts`), and the bursts that
    follow the one before after an interval outside [low_ms, high_ms] (`outside`: where, time,
    interval)."""

    def __init__(self, packets: Floats, gap_ms: float = C.VRPO_BURST_GAP_MS, start: int = 0, data_size: int = 0,
                 low_ms: float = C.VRPO_PERIOD_MIN_MS, high_ms: float = C.VRPO_PERIOD_MAX_MS,
                 floats: Callable[[], Floats] = Floats) -> None:
        self.floats = floats                         # makes the store of `own` (periodic.Stream)
        self.gap, self.start, self.data_size = gap_ms / 1000.0, start, data_size
        self.low_ms, self.high_ms = low_ms, high_ms
        self.complete = 0
        self.incomplete: list[tuple[int, float]] = []
        self.outside: list[tuple[int, float, float]] = []
        self.packets = packets                       # the times of every packet, fed before each batch
        self.own: Optional[Floats] = None            # burst starts, once a burst has several packets
        self.last_start: Optional[float] = None
        self.firsts: list = []                       # where of each burst's first packet (count() only)
        self.first: tuple[int, float] = (0, 0.0)    # the open burst's first packet
        self.parts: list[tuple[int, int]] = []       # its (packet number, data bytes)
        self.overflow = False                        # more parts than MAX_PARTS
        self.last_time: Optional[float] = None

    def _whole(self, parts: list[tuple[int, int]]) -> bool:
        parts = sorted(parts)
        full = all(data == C.VRPO_MAX_DATA for _, data in parts[:-1])
        ends = sum(data for _, data in parts) == self.data_size if self.data_size else parts[-1][1] < C.VRPO_MAX_DATA
        # Numbers start, start+1, ... each once (in any order: reordering inside a burst is harmless).
        return [n for n, _ in parts] == list(range(self.start, self.start + len(parts))) and full and ends

    def _close(self) -> None:
        if self.parts or self.overflow:
            if not self.overflow and self._whole(self.parts):
                self.complete += 1
            else:
                self.incomplete.append(self.first)
        self.parts, self.overflow = [], False

    def feed(self, times: np.ndarray, numbers: np.ndarray, sizes: np.ndarray, where: Sequence[int],
             keep_firsts: bool = False) -> None:
        """The sender's next accepted VRPO packets: times, packet numbers, payload sizes."""
        n = len(times)
        if not n:
            return
        times = np.asarray(times, dtype=np.float64)
        begins = np.empty(n, dtype=bool)
        # (a step back of the clock begins a burst too: two captures appended end to end)
        begins[0] = self.last_time is None or not 0 <= float(times[0]) - self.last_time < self.gap
        steps = np.diff(times)
        begins[1:] = (steps >= self.gap) | (steps < 0)
        self.last_time = float(times[-1])
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
        out = np.flatnonzero((between < self.low_ms) | (between > self.high_ms))
        shift = len(new) - len(between)             # the first start has no interval before it
        for k in out.tolist():
            i = int(firsts[k + shift])
            self.outside.append((int(where[i]), float(times[i]), float(between[k])))
        if keep_firsts:
            self.firsts += [where[i] for i in firsts.tolist()]
        if begins[0]:
            self._close()
        data = np.asarray(sizes, dtype=np.int64) - DATA_OFFSET
        number = np.asarray(numbers, dtype=np.int64)
        # Bursts of one packet closed within the batch are judged all at once ...
        lone = begins.copy()
        lone[:-1] &= begins[1:]
        lone[-1] = False
        ok = (number == self.start) & ((data == self.data_size) if self.data_size else (data < C.VRPO_MAX_DATA))
        self.complete += int(np.count_nonzero(lone & ok))
        for i in np.flatnonzero(lone & ~ok).tolist():
            self.incomplete.append((int(where[i]), float(times[i])))
        # ... the rest a packet at a time: the burst open from before, longer ones, the last one.
        for i in np.flatnonzero(~lone).tolist():
            if begins[i]:
                self._close()
                self.first = (int(where[i]), float(times[i]))
            if len(self.parts) < MAX_PARTS:
                self.parts.append((int(number[i]), int(data[i])))
            else:
                self.overflow = True

    @property
    def starts(self) -> Floats:
        """The time of each burst's first packet."""
        return self.packets if self.own is None else self.own

    def finish(self) -> None:
        """The capture ended: the open burst is closed."""
        self._close()

