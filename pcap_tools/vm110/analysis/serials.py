"""Serial number bookkeeping of one sender (interpretation.md, "Serial numbers").

For a received serial s after the highest h, d = (s - h) mod 65536: d = 1 in order;
1 < d < 32768 a gap of d - 1; d = 0 or already seen a duplicate; otherwise late (out of order),
which fills its gap. A serial still missing once the counter has moved more than half the range
past it can never be filled (its number will come round again) and stays lost.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import compress
from typing import Optional, Sequence

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
    arrays (for `duplicate_index`); `limit` stops early once the anomalies exceed it."""
    res = SerialResult(received=len(serials))
    if not serials:
        return res
    seen = bytearray(MOD)
    missing: dict[int, None] = {}         # insertion-ordered set of serials in open gaps
    lost_for_good: list[int] = []
    h = serials[0]
    seen[h] = 1
    dup, ooo, gaps = res.duplicate_serials, res.out_of_order_serials, res.gaps
    dup_index = res.duplicate_index
    wraps = 0
    for i in range(1, len(serials)):
        s = serials[i]
        d = (s - h) & MASK
        if d == 1:
            if missing and s in missing:          # an old gap's number comes round again
                del missing[s]
                lost_for_good.append(s)
            seen[s] = 1
            if s == 0:
                wraps += 1
            h = s
            continue
        if d == 0 or (d >= HALF and seen[s]):
            dup.append(s)
            dup_index.append(index[i] if index is not None else i)
        elif d < HALF:
            gaps.append((h, d - 1, times[i]))
            first = h + 1
            new = [(first + k) & MASK for k in range(d)]
            if missing:
                for x in new:
                    if x in missing:
                        del missing[x]
                        lost_for_good.append(x)
            for x in new[:-1]:
                seen[x] = 0
                missing[x] = None
            seen[s] = 1
            if s < h:
                wraps += 1
            h = s
        else:
            ooo.append(s)
            seen[s] = 1
            missing.pop(s, None)
        if limit is not None and len(dup) + len(ooo) + len(missing) + len(lost_for_good) > limit:
            res.aborted = True
            break
    res.wraps = wraps
    res.duplicates, res.out_of_order = len(dup), len(ooo)
    res.lost_serials = lost_for_good + list(missing)
    return res


def classify_sender(serials: Sequence[int], times: Sequence[float], codes: bytes, scope: str,
                    limit: Optional[int] = None) -> SerialResult:
    """One counter for the sender (`sender`) or one per packet type (`type`)."""
    if scope == "sender":
        return classify(serials, times, limit=limit)
    total = SerialResult()
    for code in sorted(set(codes)):
        mask = codes.translate(_ONLY[code])
        positions = list(compress(range(len(serials)), mask))
        part = classify(list(compress(serials, mask)), list(compress(times, mask)), positions,
                        None if limit is None else limit - total.anomalies)
        total.merge(part)
        if part.aborted:
            break
    total.gaps.sort(key=lambda g: g[2])
    return total


# bytes.translate tables that keep 1 where the code matches, 0 elsewhere: masks for compress().
_ONLY = [bytes(1 if b == code else 0 for b in range(256)) for code in range(256)]
