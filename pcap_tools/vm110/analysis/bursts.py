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


def split(times: Sequence[float], gap_ms: float = C.VRPO_BURST_GAP_MS) -> list[range]:
    """Positions of each burst: a new one begins at a gap of at least `gap_ms`."""
    gap = gap_ms / 1000.0
    t = np.asarray(times, dtype=np.float64)
    cuts = [0, *(np.flatnonzero(np.diff(t) >= gap) + 1).tolist(), len(t)]
    return [range(a, b) for a, b in zip(cuts, cuts[1:]) if b > a]


def count(times: Sequence[float], numbers: Sequence[int], sizes: Sequence[int],
          gap_ms: float = C.VRPO_BURST_GAP_MS, start: int = 0, data_size: int = 0) -> tuple[int, list, np.ndarray]:
    """(complete, positions of the first packet of each incomplete burst, positions of the first
    packet of every burst) of one sender's VRPO packets."""
    if not len(times):
        return 0, [], np.empty(0, dtype=np.int64)
    number, size = np.asarray(numbers), np.asarray(sizes)
    spaced = len(times) < 2 or float(np.min(np.diff(np.asarray(times, dtype=np.float64)))) >= gap_ms / 1000.0
    if not data_size and spaced and int(size.max()) < DATA_OFFSET + C.VRPO_MAX_DATA:
        # Nothing split, nothing close together: every packet is a burst of one.
        return (int(np.count_nonzero(number == start)), np.flatnonzero(number != start).tolist(),
                np.arange(len(times)))
    complete, incomplete, firsts = 0, [], []
    for burst in split(times, gap_ms):
        firsts.append(burst.start)
        parts = sorted((int(number[i]), int(size[i]) - DATA_OFFSET) for i in burst)
        full = all(data == C.VRPO_MAX_DATA for _, data in parts[:-1])
        ends = sum(data for _, data in parts) == data_size if data_size else parts[-1][1] < C.VRPO_MAX_DATA
        # Numbers start, start+1, ... each once (in any order: reordering inside a burst is harmless).
        if [n for n, _ in parts] == list(range(start, start + len(parts))) and full and ends:
            complete += 1
        else:
            incomplete.append(burst.start)
    return complete, incomplete, np.array(firsts, dtype=np.int64)
