"""Serial number bookkeeping of one sender (interpretation.md, "Serial numbers").

For a received serial s after the highest h, d = (s - h) mod 65536: d = 1 in order;
1 < d < 32768 a gap of d - 1; d = 0 or already seen a duplicate; otherwise late (out of order),
which fills its gap. A serial still missing once the counter has moved more than half the range
past it can never be filled (its number will come round again) and stays lost.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .. import constants as C

MOD, HALF = C.SERIAL_MODULUS, C.SERIAL_HALF
MASK = MOD - 1


@dataclass
class SerialResult:
    received: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    wraps: int = 0
    lost_serials: list = field(default_factory=list)
    duplicate_serials: list = field(default_factory=list)
    out_of_order_serials: list = field(default_factory=list)
    gaps: list = field(default_factory=list)          # (after, count, time)
    duplicate_index: list = field(default_factory=list)   # positions in the input of duplicates
    aborted: bool = False

    @property
    def lost(self) -> int:
        return len(self.lost_serials)

    @property
    def anomalies(self) -> int:
        return self.lost + self.duplicates + self.out_of_order

    def merge(self, other: "SerialResult") -> None:
        for name in ("received", "duplicates", "out_of_order", "wraps"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for name in ("lost_serials", "duplicate_serials", "out_of_order_serials", "gaps", "duplicate_index"):
            getattr(self, name).extend(getattr(other, name))
        self.aborted = self.aborted or other.aborted


def classify(serials: Sequence[int], times: Sequence[float], index: Optional[Sequence[int]] = None,
             limit: Optional[int] = None) -> SerialResult:
    """Classify a sender's serials in arrival order. `index` maps positions back to the caller's
    arrays (for `duplicate_index`); `limit` stops early once the anomalies exceed it.

    Runs of consecutive serials continuing the highest one are handled a run at a time with
    numpy; only the packets around anomalies go through the per-packet rules."""
    res = SerialResult(received=len(serials))
    n = len(serials)
    if not n:
        return res
    arr = np.asarray(serials, dtype=np.int64)
    breaks = np.flatnonzero((np.diff(arr) & MASK) != 1) + 1   # where s[i] != s[i-1] + 1
    breaks_list = breaks.tolist()
    seen = np.zeros(MOD, dtype=bool)
    is_missing = np.zeros(MOD, dtype=bool)
    missing: dict[int, None] = {}         # insertion-ordered set of serials in open gaps
    lost_for_good: list[int] = []
    dup, ooo, gaps = res.duplicate_serials, res.out_of_order_serials, res.gaps
    dup_index = res.duplicate_index
    h = int(arr[0])
    seen[h] = True
    wraps = 0
    i, b = 1, 0                           # position, and index of the next break at or after it
    while i < n:
        s = int(arr[i])
        d = (s - h) & MASK
        if d == 1:
            while b < len(breaks_list) and breaks_list[b] <= i:
                b += 1
            j = breaks_list[b] if b < len(breaks_list) else n
            run = arr[i:j]                # s[i] = h + 1 and every later one follows its predecessor
            seen[run] = True
            if missing:
                hits = run[is_missing[run]]
                if len(hits):
                    is_missing[hits] = False
                    for x in hits.tolist():
                        del missing[x]
                        lost_for_good.append(x)   # an old gap's number came round again
            wraps += int(np.count_nonzero(run == 0))
            h = int(arr[j - 1])
            i = j
            continue
        if d == 0 or (d >= HALF and seen[s]):
            dup.append(s)
            dup_index.append(index[i] if index is not None else i)
        elif d < HALF:
            gaps.append((h, d - 1, float(times[i])))
            new = (np.arange(h + 1, h + d + 1) & MASK)
            if missing:
                hits = new[is_missing[new]]
                is_missing[hits] = False
                for x in hits.tolist():
                    del missing[x]
                    lost_for_good.append(x)
            hole = new[:-1]
            seen[hole] = False
            is_missing[hole] = True
            missing.update(dict.fromkeys(hole.tolist()))
            seen[s] = True
            if s < h:
                wraps += 1
            h = s
        else:
            ooo.append(s)
            seen[s] = True
            if is_missing[s]:
                is_missing[s] = False
                del missing[s]
        i += 1
        if limit is not None and len(dup) + len(ooo) + len(missing) + len(lost_for_good) > limit:
            res.aborted = True
            break
    res.wraps = wraps
    res.duplicates, res.out_of_order = len(dup), len(ooo)
    res.lost_serials = lost_for_good + list(missing)
    return res


def classify_sender(serials: np.ndarray, times: np.ndarray, codes: np.ndarray, scope: str,
                    limit: Optional[int] = None) -> SerialResult:
    """One counter for the sender (`sender`) or one per packet type (`type`)."""
    if scope == "sender":
        return classify(serials, times, limit=limit)
    total = SerialResult()
    for code in np.unique(codes).tolist():
        positions = np.flatnonzero(codes == code)
        part = classify(serials[positions], times[positions], positions.tolist(),
                        None if limit is None else limit - total.anomalies)
        total.merge(part)
        if part.aborted:
            break
    total.gaps.sort(key=lambda g: g[2])
    total.duplicate_index.sort()
    return total
