"""A periodic stream (one sender's accepted VRPI, or its accepted VRPO), fed a batch at a time.

Watchdog violations and timestamps going backwards are found as the packets come (they are
findings: a list, not a packet array). The interval statistics must be exact (percentiles of
every interval, RFC 3550 jitter from the first interval, a histogram up to p99.9), so the stream
keeps the time of each packet: 8 bytes per packet, as float64, since a float32 interval would
change the microseconds the report shows. Everything else is computed from these times at the
end, one stream at a time, by the same functions (`timing`) as always.

The times are kept in fixed-size blocks (`Floats`): an array grown by reallocation leaves holes
in the heap as large as itself, which the process keeps.
"""
from __future__ import annotations

import math
import os
from typing import BinaryIO, Callable, Iterator, Optional, Sequence

import numpy as np

from . import timing

HISTOGRAM_BINS = 60
SERIES_POINTS = 600
_CHUNK = 1 << 16


class Floats:
    """float64 values appended a batch at a time, in blocks of BLOCK values. The last block grows
    from FIRST values as it fills: a stream of a few packets (thousands of senders heard once, a
    hostile capture) holds a few hundred bytes, not a whole block (512 KiB of address space, and
    the page or more of it that is touched)."""

    BLOCK = 1 << 16
    FIRST = 1 << 4

    def __init__(self) -> None:
        self.blocks: list[np.ndarray] = []
        self.used = 0                     # values in the last block
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def extend(self, values: np.ndarray) -> None:
        while len(values):
            if not self.blocks or self.used == self.BLOCK:
                self.blocks.append(np.empty(min(self.FIRST, self.BLOCK)))
                self.used = 0
            elif self.used == len(self.blocks[-1]):
                grown = np.empty(min(2 * self.used, self.BLOCK))
                grown[:self.used] = self.blocks[-1][:self.used]
                self.blocks[-1] = grown
            take = min(len(self.blocks[-1]) - self.used, len(values))
            self.blocks[-1][self.used:self.used + take] = values[:take]
            self.used += take
            self.size += take
            values = values[take:]

    def last(self) -> float:
        return float(self.blocks[-1][self.used - 1])

    def __getitem__(self, i: int) -> float:
        return float(self.blocks[i // self.BLOCK][i % self.BLOCK])

    def intervals_ms(self, before: Optional[float] = None) -> np.ndarray:
        """`timing.intervals_ms` of the values (after `before`, when given), a block at a time."""
        out = np.empty(max(self.size - (before is None), 0))
        prev: timing.FloatSeq = [] if before is None else [before]
        at = 0
        for k, block in enumerate(self.blocks):
            part = block[:self.used] if k == len(self.blocks) - 1 else block
            gaps = timing.intervals_ms(np.concatenate((prev, part)))
            out[at:at + len(gaps)] = gaps
            at += len(gaps)
            prev = part[-1:]
        return out


def spill(fd: int, data: bytes) -> int:
    """Append `data` to the file `fd` (shared by appenders that each keep where theirs lie, read
    back with os.pread); its offset."""
    at = os.lseek(fd, 0, os.SEEK_END)
    write_at(fd, data, at)
    return at


def write_at(fd: int, data: bytes, at: int) -> None:
    done = 0
    while done < len(data):
        done += os.pwrite(fd, data[done:], at + done)


class SpooledBlocks:
    """The blocks of a SpilledFloats, as a sequence: the full ones in `spool` (an anonymous file
    of the caller's; where each lies is kept), the last one in memory. A spilled block is read
    back when asked for (the report, a burst array's first copy, a point of a plot)."""

    def __init__(self, spool: BinaryIO) -> None:
        self.fd = spool.fileno()
        self.where: list[tuple[int, int]] = []       # (offset, values) of each spilled block
        self.tail: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.where) + (self.tail is not None)

    def append(self, block: np.ndarray) -> None:
        if self.tail is not None:                    # full: to the spool
            at = spill(self.fd, np.ascontiguousarray(self.tail, dtype="<f8").tobytes())
            self.where.append((at, len(self.tail)))
        self.tail = block

    def __setitem__(self, k: int, block: np.ndarray) -> None:
        """The last block, in memory, grown (Floats.extend)."""
        if (k + len(self) if k < 0 else k) != len(self.where) or self.tail is None:
            raise IndexError("only the last block, in memory, is replaced")
        self.tail = block

    def __getitem__(self, k: int) -> np.ndarray:
        k = k + len(self) if k < 0 else k
        if k == len(self.where) and self.tail is not None:
            return self.tail
        at, count = self.where[k]
        return np.frombuffer(os.pread(self.fd, count * 8, at), dtype="<f8")

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[k] for k in range(len(self)))


class SpilledFloats(Floats):
    """Floats whose full blocks live in a file (SpooledBlocks): memory holds one small block per
    stream, the values stay exact, the disk takes 8 bytes per value (`vm110 monitor`, for runs
    of days)."""

    BLOCK = 1 << 12

    def __init__(self, spool: BinaryIO) -> None:
        super().__init__()
        self.blocks = SpooledBlocks(spool)      # type: ignore[assignment]


FloatsFactory = Callable[[], Floats]


class Stream:
    """One periodic stream: `ptype` of `sender`, watchdog `limit_ms`; `floats` makes the store
    of its times (default in memory)."""

    def __init__(self, ptype: str, sender: str, limit_ms: float, floats: FloatsFactory = Floats) -> None:
        self.ptype, self.sender, self.limit = ptype, sender, limit_ms
        self.times = floats()
        self.first_frame = self.last_frame = 0
        self.violations: list[dict] = []
        self.backwards: list[tuple[int, float]] = []     # (frame, time) of the packet after each

    def feed(self, times: np.ndarray, frames: Sequence[int]) -> None:
        if not len(times):
            return
        times = np.asarray(times, dtype=np.float64)
        if len(self.times):
            stream, after = np.concatenate(([self.times.last()], times)), frames
        else:
            stream, after = times, frames[1:]
            self.first_frame = int(frames[0])
        violations, backwards = self._judge(stream, after)
        self.violations += violations
        self.backwards += backwards
        self.times.extend(times)
        self.last_frame = int(frames[-1])

    def _judge(self, stream: np.ndarray, after: Sequence[int]) -> tuple[list, list]:
        """Watchdog violations and backward steps of the intervals of `stream` (`after`: the
        frame of the packet after each interval)."""
        gaps = timing.intervals_ms(stream)
        violations = [{"start": float(stream[i]), "gap_ms": float(gaps[i]), "until_end": False, "frame": int(after[i])}
                      for i in np.flatnonzero(gaps > self.limit).tolist()]
        backwards = [(int(after[i]), float(stream[i + 1])) for i in np.flatnonzero(gaps < 0).tolist()]
        return violations, backwards

    def row(self, before: Optional[float], end: Optional[float], period_ms: Optional[float]) -> tuple[dict, list]:
        """The `periodic[]` row and the (frame, time) of each step back in time: `before`, the
        predecessor's last packet (a restart on a new port), is the stream's first arrival;
        `end`, the capture's last record (None: taken over)."""
        times = self.times
        violations, backwards = list(self.violations), list(self.backwards)
        if before is not None:
            # The interval from the predecessor's last packet comes first.
            first_v, first_b = self._judge(np.array([before, times[0]]), [self.first_frame])
            violations, backwards = first_v + violations, first_b + backwards
        last = times.last()
        if end is not None and (end - last) * timing.MS > self.limit:
            violations.append({"start": last, "gap_ms": (end - last) * timing.MS, "until_end": True,
                               "frame": self.last_frame})
        gaps = times.intervals_ms(before)
        jitter = timing.jitter_summary(gaps, period_ms) if period_ms else None
        # The arrival after each interval, for the plot: the stream's packets from the first
        # (from the second without a predecessor).
        shown = plot(lambda i: times[i if before is not None else i + 1], gaps)   # sorts gaps
        return {
            "type": self.ptype, "sender": self.sender, "count": len(times),
            "interval_ms": timing.summary_sorted(gaps),
            "nominal_ms": period_ms,
            "jitter_ms": jitter,
            "watchdog": {"limit_ms": self.limit, "violations": violations},
            "time_backwards": len(backwards),
            "plot": shown,
        }, backwards


def plot(after: Callable[[int], float], gaps: np.ndarray) -> dict:
    """Histogram of intervals (the last bin holds everything above the bins' range) and a down-sampled
    interval-over-time series (the largest interval of each bucket, so no watchdog gap hides);
    `after(i)`: the time of the arrival that ends interval i. Sorts `gaps` in place once the
    series is taken."""
    finite = np.isfinite(gaps)
    if not finite.all():                       # damaged timestamps: plot what can be plotted
        kept = np.flatnonzero(finite)
        out = plot(lambda i: after(int(kept[i])), gaps[finite])
        gaps.sort()
        return out
    if not len(gaps):
        return {"histogram": [], "bin_ms": None, "series": []}
    step = max(1, math.ceil(len(gaps) / SERIES_POINTS))
    series = [[after(i), float(gaps[i:i + step].max())] for i in range(0, len(gaps), step)]
    gaps.sort()
    # The bins cover the bulk: up to p99.9, but no further than 4 x the median or p95 + 3 x (p95 -
    # min). Among a few hundred intervals, p99.9 is the longest one: a single watchdog gap would
    # make the bins so wide that every other interval fell into the first (the HTML plot showed an
    # empty, stretched histogram). Everything above goes to the last bin.
    # A step back in time (negative intervals, time_backwards) stretches no bin either: the bins
    # start at the lowest interval of 0 or more, and the first one holds the negative ones.
    bulk = gaps[int(np.searchsorted(gaps, 0.0)):] if gaps[-1] >= 0 else gaps
    low = float(bulk[0])
    p50, p95, top = (low if v is None else v for v in (timing.percentile(bulk, q) for q in (50, 95, 99.9)))
    high = min(top, max(4 * p50, p95 + 3 * (p95 - low)))
    high = max(high, low + 1e-3)
    width = (high - low) / HISTOGRAM_BINS
    counts = np.zeros(HISTOGRAM_BINS + 1, dtype=np.int64)
    for a in range(0, len(gaps), _CHUNK):      # a chunk at a time: no per-interval temporaries
        bins = np.clip(np.nan_to_num((gaps[a:a + _CHUNK] - low) / width), 0, HISTOGRAM_BINS).astype(np.int64)
        counts += np.bincount(bins, minlength=HISTOGRAM_BINS + 1)
    hist = [[low + i * width, int(c)] for i, c in enumerate(counts)]
    return {"histogram": hist, "bin_ms": width, "series": series}
