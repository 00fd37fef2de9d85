"""VRPO bursts (interpretation.md, "VRPO split into several packets").

A burst is a run of VRPO packets from one sender less than the burst gap apart. It ends with a
packet carrying fewer than 488 data bytes, when the configured periodic data size is reached, or
at a gap; a packet numbered like the first of a burst starts a new one. It is complete when its
packet numbers run start, start+1, ... without a hole and it ends properly: a short last packet,
or exactly the periodic data size (configured, or with 0 inferred as the most common total of
the sender's well-numbered bursts).
"""
from __future__ import annotations

from collections import Counter
from typing import Sequence

from .. import constants as C

DATA_OFFSET = C.VRPO_HEADER_SIZE


def split(packets: Sequence[tuple[float, int, int]], gap_ms: float = C.VRPO_BURST_GAP_MS,
          start: int = 0, data_size: int = 0) -> list[list[tuple[float, int, int]]]:
    """Group (ts, packet number, payload size) into bursts."""
    bursts: list[list] = []
    current: list = []
    total = 0
    gap = gap_ms / 1000.0
    for pkt in packets:
        ts, number, size = pkt
        if current and (ts - current[-1][0] > gap or number == start):
            bursts.append(current)
            current, total = [], 0
        current.append(pkt)
        total += size - DATA_OFFSET
        if size - DATA_OFFSET < C.VRPO_MAX_DATA or (data_size and total >= data_size):
            bursts.append(current)
            current, total = [], 0
    if current:
        bursts.append(current)
    return bursts


def _numbered(burst: list, start: int) -> bool:
    return all(number == start + i for i, (_, number, _) in enumerate(burst))


def _total(burst: list) -> int:
    return sum(size - DATA_OFFSET for _, _, size in burst)


def count(times: Sequence[float], numbers: Sequence[int], sizes: Sequence[int],
          gap_ms: float = C.VRPO_BURST_GAP_MS, start: int = 0, data_size: int = 0) -> tuple[int, int, list]:
    """(complete, incomplete, burst start times) of one sender's VRPO packets."""
    if not times:
        return 0, 0, []
    if not data_size and max(sizes) < DATA_OFFSET + C.VRPO_MAX_DATA:
        # Nothing is split: every packet is a burst of one, complete when numbered `start`.
        complete = list(numbers).count(start)
        return complete, len(times) - complete, list(times)
    bursts = split(list(zip(times, numbers, sizes)), gap_ms, start, data_size)
    size = data_size
    if not size:
        totals = Counter(_total(b) for b in bursts if _numbered(b, start))
        size = totals.most_common(1)[0][0] if totals else 0
    complete = 0
    for burst in bursts:
        last_short = burst[-1][2] - DATA_OFFSET < C.VRPO_MAX_DATA
        if _numbered(burst, start) and (last_short or _total(burst) == size):
            complete += 1
    return complete, len(bursts) - complete, [b[0][0] for b in bursts]
