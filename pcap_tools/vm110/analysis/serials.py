"""Serial number bookkeeping of one counter (docs/rules.md, "Serial numbers"; interpretation.md,
"Serial numbers" and "Sender restarts").

For a packet with serial s at time t after the highest h, d = (s - h) mod 65536, the first rule
that holds decides: a duplicate (s accepted less than the duplicate window ago); in order (d = 1);
late (s missing in a gap opened within the window: it fills it); a gap (a forward jump the
counter's rate can explain in the time since its previous packet); otherwise a restart
candidate, a restart when the counter's next packet that is not a copy of it follows it
(s + 1 .. s + 4), out of order when not.
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .. import constants as C

MOD, HALF = C.SERIAL_MODULUS, C.SERIAL_HALF
MASK = MOD - 1
DUP_WINDOW_MS = 1000.0
RATE_WINDOW_S = 10.0
PLAUSIBLE_BASE = 64            # d - 1 <= BASE + FACTOR * max(r, MIN_RATE) * dt is plausible loss
PLAUSIBLE_FACTOR = 4
MIN_RATE = 20.0
CONFIRM = 4                    # a restart's next packet is s + 1 .. s + CONFIRM
NEVER = -np.inf


@dataclass
class SerialResult:
    received: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    wraps: int = 0
    lost_serials: list = field(default_factory=list)
    duplicate_serials: list = field(default_factory=list)
    out_of_order_serials: list = field(default_factory=list)
    gaps: list = field(default_factory=list)              # (after, count, time, position)
    duplicate_index: list = field(default_factory=list)   # positions in the input of duplicates
    out_of_order_index: list = field(default_factory=list)
    restarts: list = field(default_factory=list)          # (position, from, to)
    last: dict = field(default_factory=dict)              # counter key -> its highest serial at the end
    aborted: bool = False

    @property
    def lost(self) -> int:
        return len(self.lost_serials)

    @property
    def anomalies(self) -> int:
        return self.lost + self.duplicates + self.out_of_order + len(self.restarts)

    def merge(self, other: "SerialResult") -> None:
        for name in ("received", "duplicates", "out_of_order", "wraps"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for name in ("lost_serials", "duplicate_serials", "out_of_order_serials", "gaps", "duplicate_index",
                     "out_of_order_index", "restarts"):
            getattr(self, name).extend(getattr(other, name))
        self.last.update(other.last)
        self.aborted = self.aborted or other.aborted


class _Counter:
    """The state of one counter between packets: everything rules.md says it keeps."""

    def __init__(self, s: int, t: float, pos: int) -> None:
        self.accepted_at = np.full(MOD, NEVER)     # time each serial was last accepted
        self.gap_at = np.full(MOD, NEVER)          # time the gap a missing serial lies in opened
        self.missing: dict[int, None] = {}         # insertion-ordered set of serials in open gaps
        self.restart(s, t, pos)

    def restart(self, s: int, t: float, pos: int) -> None:
        if self.missing:
            self.gap_at[list(self.missing)] = NEVER
            self.missing.clear()
        self.accepted_at.fill(NEVER)
        self.h, self.start, self.start_pos, self.prev = s, t, pos, t
        self.accepted_at[s] = t


def classify(serials: Sequence[int], times: Sequence[float], index: Optional[Sequence[int]] = None,
             limit: Optional[int] = None, dup_window_ms: float = DUP_WINDOW_MS) -> SerialResult:
    """Classify one counter's serials in arrival order. `index` maps positions back to the caller's
    arrays (for the `*_index` lists and `gaps`); `limit` stops early once the anomalies exceed it.

    Runs of consecutive serials continuing the highest one are handled a run at a time with
    numpy; only the packets around anomalies go through the per-packet rules."""
    res = SerialResult(received=len(serials))
    n = len(serials)
    if not n:
        return res
    arr = np.asarray(serials, dtype=np.int64)
    ts = np.asarray(times, dtype=np.float64)
    window = dup_window_ms / 1000.0
    breaks = (np.flatnonzero((np.diff(arr) & MASK) != 1) + 1).tolist()   # where s[i] != s[i-1] + 1
    where = (lambda i: index[i]) if index is not None else (lambda i: i)
    dup, ooo, gaps = res.duplicate_serials, res.out_of_order_serials, res.gaps
    dup_pos: list[int] = []               # positions of duplicates, for the rate (sorted)
    lost_for_good: list[int] = []
    ctr = _Counter(int(arr[0]), float(ts[0]), 0)
    wraps = 0
    i, b = 1, 0                           # position, and index of the next break at or after it

    def rate(t: float) -> float:
        """Accepted packets of the counter in [t - W, t), per second (W: 10 s or its life)."""
        span = min(RATE_WINDOW_S, t - ctr.start)
        if span <= 0:
            return 0.0
        lo = max(int(np.searchsorted(ts, t - span, "left")), ctr.start_pos)
        hi = int(np.searchsorted(ts, t, "left"))
        if hi <= lo:
            return 0.0
        return (hi - lo - (bisect_left(dup_pos, hi) - bisect_left(dup_pos, lo))) / span

    def plausible(missing: int, t: float) -> bool:
        """Loss the counter's rate explains in its silence (the rate only counts when the floor
        of MIN_RATE does not explain it already)."""
        dt = t - ctr.prev
        if missing <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * MIN_RATE * dt:
            return True
        return missing <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * max(rate(t), MIN_RATE) * dt

    def fill(serials_now: np.ndarray) -> None:
        """Serials the counter reaches again while still missing: their number came round, so the
        old gap can never be filled and stays lost."""
        hits = serials_now[ctr.gap_at[serials_now] > NEVER]
        if len(hits):
            ctr.gap_at[hits] = NEVER
            for x in hits.tolist():
                del ctr.missing[x]
                lost_for_good.append(x)

    while i < n:
        s, t = int(arr[i]), float(ts[i])
        d = (s - ctr.h) & MASK
        if d == 1 and t - ctr.accepted_at[s] >= window:
            while b < len(breaks) and breaks[b] <= i:
                b += 1
            j = breaks[b] if b < len(breaks) else n
            run = arr[i:j]                # s[i] = h + 1 and every later one follows its predecessor
            # A serial accepted within the window is a duplicate even in sequence (rule 1 first):
            # the run stops before it.
            recent = np.flatnonzero(ts[i:j] - ctr.accepted_at[run] < window)
            if len(recent):
                j = i + int(recent[0])
                run = arr[i:j]
            ctr.accepted_at[run] = ts[i:j]
            if ctr.missing:
                fill(run)
            wraps += int(np.count_nonzero(run == 0))
            ctr.h, ctr.prev = int(arr[j - 1]), float(ts[j - 1])
            i = j
            continue
        if t - ctr.accepted_at[s] < window:
            dup.append(s)
            dup_pos.append(i)
            res.duplicate_index.append(where(i))
        elif ctr.gap_at[s] > NEVER and t - ctr.gap_at[s] < window:
            ooo.append(s)                 # late: fills its gap
            res.out_of_order_index.append(where(i))
            ctr.gap_at[s] = NEVER
            del ctr.missing[s]
            ctr.accepted_at[s], ctr.prev = t, t
        elif 1 < d < HALF and plausible(d - 1, t):
            gaps.append((ctr.h, d - 1, t, where(i)))
            new = np.arange(ctr.h + 1, ctr.h + d + 1) & MASK
            if ctr.missing:
                fill(new)
            hole = new[:-1]
            ctr.gap_at[hole] = t
            ctr.missing.update(dict.fromkeys(hole.tolist()))
            if s < ctr.h:
                wraps += 1
            ctr.h, ctr.prev = s, t
            ctr.accepted_at[s] = t
        else:
            nxt = i + 1
            while nxt < n and arr[nxt] == s:          # copies of the candidate confirm nothing
                nxt += 1
            if nxt < n and 1 <= (int(arr[nxt]) - s) & MASK <= CONFIRM:
                res.restarts.append((where(i), ctr.h, s))
                lost_for_good.extend(ctr.missing)     # serials lost before stay lost
                ctr.restart(s, t, i)
            else:
                ooo.append(s)                         # unconfirmed: moves nothing
                res.out_of_order_index.append(where(i))
                ctr.accepted_at[s], ctr.prev = t, t
        i += 1
        if limit is not None and len(dup) + len(ooo) + len(ctr.missing) + len(lost_for_good) > limit:
            res.aborted = True
            break
    res.wraps = wraps
    res.duplicates, res.out_of_order = len(dup), len(ooo)
    res.lost_serials = lost_for_good + list(ctr.missing)
    res.last[None] = ctr.h
    return res


def classify_sender(serials: np.ndarray, times: np.ndarray, codes: np.ndarray, scope: str,
                    limit: Optional[int] = None, dup_window_ms: float = DUP_WINDOW_MS) -> SerialResult:
    """One counter for the sender (`sender`) or one per packet type (`type`)."""
    if scope == "sender":
        return classify(serials, times, limit=limit, dup_window_ms=dup_window_ms)
    total = SerialResult()
    for code in np.unique(codes).tolist():
        positions = np.flatnonzero(codes == code)
        part = classify(serials[positions], times[positions], positions.tolist(),
                        None if limit is None else limit - total.anomalies, dup_window_ms)
        part.last = {code: part.last[None]}
        total.merge(part)
        if part.aborted:
            break
    total.gaps.sort(key=lambda g: g[3])
    total.duplicate_index.sort()
    total.out_of_order_index.sort()
    total.restarts.sort()
    return total
