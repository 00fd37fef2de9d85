"""VRPO bursts (interpretation.md, "VRPO split into several packets").

A burst is a run of VRPO packets from one sender less than the burst gap (20 ms) apart: the gap
is the whole definition, since a receiver cannot know what was sent back to back. It is complete
when its packet numbers are start, start+1, ... each once (in any order), every packet but the
last by number carries 488 data bytes, and the last fewer, or, with a configured periodic data
size, the data add up to exactly that size. Two unsplit VRPO packets that arrive closer than the
gap (jitter, reordering) therefore form one incomplete burst, as the truth of `vm110 synth` has it.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .. import constants as C

DATA_OFFSET = C.VRPO_HEADER_SIZE


def split(packets: Sequence[tuple[float, int, int]], gap_ms: float = C.VRPO_BURST_GAP_MS
          ) -> list[list[tuple[float, int, int]]]:
    """Group (ts, packet number, payload size) into bursts at gaps of at least `gap_ms`."""
    bursts: list[list] = []
    current: list = []
    gap = gap_ms / 1000.0
    for pkt in packets:
        if current and pkt[0] - current[-1][0] >= gap:
            bursts.append(current)
            current = []
        current.append(pkt)
    if current:
        bursts.append(current)
    return bursts


def _numbered(burst: list, start: int) -> bool:
    """Numbers start, start+1, ... each once (in any order: reordering inside a burst is harmless)."""
    return sorted(number for _, number, _ in burst) == list(range(start, start + len(burst)))


def _total(burst: list) -> int:
    return sum(size - DATA_OFFSET for _, _, size in burst)


def count(times: Sequence[float], numbers: Sequence[int], sizes: Sequence[int],
          gap_ms: float = C.VRPO_BURST_GAP_MS, start: int = 0, data_size: int = 0) -> tuple[int, int, list]:
    """(complete, incomplete, burst start times) of one sender's VRPO packets."""
    if not len(times):
        return 0, 0, []
    spaced = len(times) < 2 or float(np.min(np.diff(np.asarray(times, dtype=np.float64)))) >= gap_ms / 1000.0
    if not data_size and spaced and max(sizes) < DATA_OFFSET + C.VRPO_MAX_DATA:
        # Nothing split, nothing close together: every packet is a burst of one.
        complete = int(np.count_nonzero(np.asarray(numbers) == start))
        return complete, len(times) - complete, times
    bursts = split(list(zip(np.asarray(times).tolist(), np.asarray(numbers).tolist(),
                            np.asarray(sizes).tolist())), gap_ms)
    complete = 0
    for burst in bursts:
        by_number = sorted(burst, key=lambda p: p[1])
        full = all(p[2] - DATA_OFFSET == C.VRPO_MAX_DATA for p in by_number[:-1])
        ends = (_total(burst) == data_size) if data_size else by_number[-1][2] - DATA_OFFSET < C.VRPO_MAX_DATA
        if _numbered(burst, start) and full and ends:
            complete += 1
    return complete, len(bursts) - complete, np.array([b[0][0] for b in bursts])
