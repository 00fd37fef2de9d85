"""Serial number bookkeeping of one counter (docs/rules.md, "Serial numbers"; interpretation.md,
"Serial numbers" and "Sender restarts").

For a packet with serial s at time t after the highest h, d = (s - h) mod 65536, the first rule
that holds decides: a duplicate (s accepted less than the duplicate window ago); in order (d = 1);
late (s missing in a gap opened within the window: it fills it); a gap (a forward jump the
counter's rate can explain in the time since its previous packet); otherwise a restart
candidate, a restart when the counter's next packet that is not a copy of it follows it
(s + 1 .. s + 4), out of order when not. A restart confirmed CANDIDATE_WAIT_MS or more after its
candidate changes no command (rules.md rule 5): `fed_late` names those of the last feed.

`Counter` is fed a counter's packets a batch at a time and carries everything rules.md says a
counter keeps from batch to batch; for the rate it keeps the times of its packets of the last
RATE_WINDOW_S only. A restart candidate whose deciding packet has not arrived yet stays
undecided: `feed` returns how many of the given packets it decided, and the caller hands the
rest in again with the next batch (or with `final=True` at the end of the capture, where an
undecided candidate is out of order).
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np

from .. import constants as C
from . import timing
from .timing import FloatSeq, IntSeq

MOD, HALF = C.SERIAL_MODULUS, C.SERIAL_HALF
MASK = MOD - 1
DUP_WINDOW_MS = 1000.0
RATE_WINDOW_S = 10.0
PLAUSIBLE_BASE = 64            # d - 1 <= BASE + FACTOR * max(r, MIN_RATE) * dt is plausible loss
PLAUSIBLE_FACTOR = 4
MIN_RATE = 20.0
CONFIRM = 4                    # a restart's next packet is s + 1 .. s + CONFIRM
CANDIDATE_WAIT_MS = 10000.0    # the command events behind a candidate wait this long at most
NEVER = -np.inf
LOCATED = 100                  # duplicates and out-of-order packets located (findings.MAX_ITEMS)


@dataclass
class SerialResult:
    """What a counter found. Packets are named by the caller's `where` (a frame number, or a
    position) and located by their time (`*_at`): the time the rules judged them at (the
    analysis clock); `shown` has the packet's own timestamp where that differs (a step back of
    the capture's clock), which is what a finding names."""
    received: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    wraps: int = 0
    lost_serials: list = field(default_factory=list)
    duplicate_serials: list = field(default_factory=list)
    out_of_order_serials: list = field(default_factory=list)
    gaps: list = field(default_factory=list)              # (after, count, time, where)
    gap_late: dict = field(default_factory=dict)          # a gap's `where` -> its serials that came late
    # The first LOCATED duplicates and out-of-order packets: (where, time, serial).
    duplicates_located: list = field(default_factory=list)
    out_of_order_located: list = field(default_factory=list)
    restarts: list = field(default_factory=list)          # (where, from, to, time)
    last: dict = field(default_factory=dict)              # counter key -> its highest serial at the end
    shown: dict = field(default_factory=dict)             # where -> own time, of those located above
    aborted: bool = False

    def time_of(self, where, t: float) -> float:
        """The own timestamp of a located packet (`t`: the time it was judged at)."""
        return self.shown.get(where, t)

    @property
    def lost(self) -> int:
        return len(self.lost_serials)

    @property
    def anomalies(self) -> int:
        """What `auto` weighs the scopes by (rules.md, "Choosing the scope"): a gap is one,
        however many serials it lost (a burst of lost acks is one event, as a restart is)."""
        return len(self.gaps) + self.duplicates + self.out_of_order + len(self.restarts)

    def merge(self, other: "SerialResult") -> None:
        for name in ("received", "duplicates", "out_of_order", "wraps"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for name in ("lost_serials", "duplicate_serials", "out_of_order_serials", "gaps", "duplicates_located",
                     "out_of_order_located", "restarts"):
            getattr(self, name).extend(getattr(other, name))
        self.gap_late.update(other.gap_late)
        self.shown.update(other.shown)
        self.last.update(other.last)
        self.aborted = self.aborted or other.aborted


def gap_lost(after: int, count: int, late: int) -> Optional[dict]:
    """What a `lost` finding says of a gap (analyze's item, the monitor's live one): the serial
    after it, the one before, the serials missing when seen and how many of them came late; None
    when they all came late (those packets are out of order, nothing was lost)."""
    if late >= count:
        return None
    return {"serial": (after + count + 1) % MOD, "after": after, "count": count, **({"late": late} if late else {})}


class SerialTimes:
    """A time per serial number (NEVER when none): a dict while few are set, then the full array
    of 65536. A sender that sends a few packets, or a capture full of senders (every source port
    is one), costs a few entries each, not half a megabyte."""

    SMALL = 2048

    def __init__(self) -> None:
        self.few: dict[int, float] = {}              # unused (empty) once `all` exists
        self.all: Optional[np.ndarray] = None
        self.sorted: Optional[tuple] = None          # `few` as sorted arrays, until it changes

    def __getitem__(self, key):
        if self.all is not None:
            return self.all[key]
        if isinstance(key, (int, np.integer)):
            return self.few.get(int(key), NEVER)
        key = np.asarray(key)
        out = np.full(len(key), NEVER)
        if self.few:
            if self.sorted is None:
                serials = np.fromiter(self.few, dtype=np.int64, count=len(self.few))
                times = np.fromiter(self.few.values(), dtype=np.float64, count=len(self.few))
                order = np.argsort(serials)
                self.sorted = serials[order], times[order]
            serials, times = self.sorted
            at = np.searchsorted(serials, key).clip(0, len(serials) - 1)
            hit = serials[at] == key
            out[hit] = times[at[hit]]
        return out

    def __setitem__(self, key, value) -> None:
        if self.all is not None:
            self.all[key] = value
            return
        self.sorted = None
        if isinstance(key, (int, np.integer)):
            self.few[int(key)] = float(value)
        else:
            keys = np.asarray(key).tolist()
            self.few.update(zip(keys, np.broadcast_to(np.asarray(value, dtype=np.float64), (len(keys),)).tolist()))
        if len(self.few) > self.SMALL:
            self.all = np.full(MOD, NEVER)
            self.all[list(self.few)] = list(self.few.values())
            self.few = {}

    def clear(self) -> None:
        if self.all is not None:
            self.all.fill(NEVER)
        else:
            self.few.clear()
            self.sorted = None


class Counter:
    """One counter, fed its packets in arrival order a batch at a time (see the module doc)."""

    def __init__(self, dup_window_ms: float = DUP_WINDOW_MS, key=None) -> None:
        self.window_ms = dup_window_ms
        self.key = key
        self.res = SerialResult()
        self.started = False
        self.accepted_at = SerialTimes()           # time each serial was last accepted
        self.gap_at = SerialTimes()                # time the gap a missing serial lies in opened
        self.missing: dict[int, Any] = {}          # serials in open gaps (in order) -> the gap's `where`
        self.lost_for_good: list[int] = []
        self.h = 0
        self.start = self.prev = 0.0
        # Packets of the last RATE_WINDOW_S (all, duplicates too) for the rate: their times, the
        # number of the first among every packet of the counter, and the numbers of duplicates.
        self.recent: np.ndarray = np.empty(0)
        self.recent_base = 0
        self.start_pos = 0
        self.dup_pos: list[int] = []
        self.fed_duplicates: list = []             # where of the duplicates of the last feed
        self.fed_late: list = []                   # where of the restarts of the last feed confirmed late

    def _restart(self, s: int, t: float, pos: int) -> None:
        if self.missing:
            self.gap_at[list(self.missing)] = NEVER
            self.missing.clear()
        self.accepted_at.clear()
        self.h, self.start, self.start_pos, self.prev = s, t, pos, t
        self.accepted_at[s] = t

    def feed(self, serials: IntSeq, times: FloatSeq, where: IntSeq, final: bool = False,
             limit: Optional[int] = None, own: Optional[FloatSeq] = None) -> int:
        """Judge packets in arrival order; returns how many were decided (all when `final`).
        `where` names each packet in the results; `limit` stops once the anomalies exceed it;
        `own`: the packets' own timestamps where `times` is the analysis clock (default: the same)."""
        n = len(serials)
        if not n:
            return 0
        res = self.res
        fed = self.fed_duplicates = []
        self.fed_late = []
        arr = np.asarray(serials, dtype=np.int64)
        ts = np.asarray(times, dtype=np.float64)
        base = self.recent_base
        off = base + len(self.recent)               # number of the first packet given here
        all_ts = np.concatenate((self.recent, ts)) if len(self.recent) else ts
        edge = timing.edge_us(self.window_ms)     # t - a within the window: (t - a) * 1e6 < edge
        breaks = (np.flatnonzero((np.diff(arr) & MASK) != 1) + 1).tolist()   # where s[i] != s[i-1] + 1
        dup, ooo, gaps = res.duplicate_serials, res.out_of_order_serials, res.gaps
        own_ts = ts if own is None else np.asarray(own, dtype=np.float64)
        behind = np.flatnonzero(own_ts != ts)         # (none while the capture's clock runs forward)
        own_at = dict(zip(behind.tolist(), own_ts[behind].tolist()))

        def show(k: int) -> None:
            """Packet k is located in the results: keep its own time if the clock is ahead of it."""
            if k in own_at:
                res.shown[where[k]] = own_at[k]
        dup_pos, lost_for_good = self.dup_pos, self.lost_for_good
        accepted_at, gap_at, missing = self.accepted_at, self.gap_at, self.missing
        i, b = 0, 0                           # position, and index of the next break at or after it
        changes = None                        # where the serial differs from the one before
        if not self.started:
            self.started = True
            self._restart(int(arr[0]), float(ts[0]), off)
            i = 1

        def rate(t: float) -> float:
            """Accepted packets of the counter in [t - W, t), per second (W: 10 s or its life)."""
            span = min(RATE_WINDOW_S, t - self.start)
            if span <= 0:
                return 0.0
            lo = max(int(np.searchsorted(all_ts, t - span, "left")) + base, self.start_pos)
            hi = int(np.searchsorted(all_ts, t, "left")) + base
            if hi <= lo:
                return 0.0
            return (hi - lo - (bisect_left(dup_pos, hi) - bisect_left(dup_pos, lo))) / span

        def plausible(missing_: int, t: float) -> bool:
            """Loss the counter's rate explains in its silence (the rate only counts when the floor
            of MIN_RATE does not explain it already)."""
            dt = t - self.prev
            if missing_ <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * MIN_RATE * dt:
                return True
            return missing_ <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * max(rate(t), MIN_RATE) * dt

        def fill(serials_now: np.ndarray) -> None:
            """Serials the counter reaches again while still missing: their number came round, so
            the old gap can never be filled and stays lost."""
            hits = serials_now[gap_at[serials_now] > NEVER]
            if len(hits):
                gap_at[hits] = NEVER
                for x in hits.tolist():
                    del missing[x]
                    lost_for_good.append(x)

        def duplicate(k: int, s: int, t: float) -> None:
            dup.append(s)
            dup_pos.append(off + k)
            fed.append(where[k])
            if len(res.duplicates_located) < LOCATED:
                res.duplicates_located.append((where[k], t, s))
                show(k)

        while i < n:
            s, t = int(arr[i]), float(ts[i])
            d = (s - self.h) & MASK
            if d == 1 and (t - accepted_at[s]) * 1e6 >= edge:
                while b < len(breaks) and breaks[b] <= i:
                    b += 1
                j = breaks[b] if b < len(breaks) else n
                run = arr[i:j]                # s[i] = h + 1 and every later one follows its predecessor
                # A serial accepted within the window is a duplicate even in sequence (rule 1
                # first): the run stops before it.
                recent = np.flatnonzero((ts[i:j] - accepted_at[run]) * 1e6 < edge)
                if len(recent):
                    j = i + int(recent[0])
                    run = arr[i:j]
                accepted_at[run] = ts[i:j]
                if missing:
                    fill(run)
                res.wraps += int(np.count_nonzero(run == 0))
                self.h, self.prev = int(arr[j - 1]), float(ts[j - 1])
                i = j
                continue
            if (t - accepted_at[s]) * 1e6 < edge:
                duplicate(i, s, t)
            elif gap_at[s] > NEVER and (t - gap_at[s]) * 1e6 < edge:
                ooo.append(s)                 # late: fills its gap
                if self._locate(where[i], t, s):
                    show(i)
                gap_at[s] = NEVER
                opened = missing.pop(s)
                res.gap_late[opened] = res.gap_late.get(opened, 0) + 1
                accepted_at[s], self.prev = t, t
            elif 1 < d < HALF and plausible(d - 1, t):
                gaps.append((self.h, d - 1, t, where[i]))
                show(i)
                new = np.arange(self.h + 1, self.h + d + 1) & MASK
                if missing:
                    fill(new)
                hole = new[:-1]
                gap_at[hole] = t
                missing.update(dict.fromkeys(hole.tolist(), where[i]))
                if s < self.h:
                    res.wraps += 1
                self.h, self.prev = s, t
                accepted_at[s] = t
            else:
                # The next packet that is not a copy of the candidate decides; the copies in
                # between are duplicates, whenever they come (they confirm nothing).
                if changes is None:
                    changes = np.flatnonzero(arr[1:] != arr[:-1]) + 1
                k = int(np.searchsorted(changes, i, "right"))
                nxt = int(changes[k]) if k < len(changes) else n
                if nxt == n and not final:
                    break                                 # undecided until its next packet comes
                if nxt < n and 1 <= (int(arr[nxt]) - s) & MASK <= CONFIRM:
                    res.restarts.append((where[i], self.h, s, t))
                    if not timing.shorter(float(ts[nxt]) - t, CANDIDATE_WAIT_MS):
                        self.fed_late.append(where[i])
                    show(i)
                    lost_for_good.extend(missing)         # serials lost before stay lost
                    self._restart(s, t, off + i)
                else:
                    ooo.append(s)                         # unconfirmed: moves nothing
                    if self._locate(where[i], t, s):
                        show(i)
                    accepted_at[s], self.prev = t, t
                for k in range(i + 1, nxt):
                    duplicate(k, s, float(ts[k]))
                i = nxt - 1
            i += 1
            if limit is not None and len(dup) + len(ooo) + len(gaps) + len(res.restarts) > limit:
                res.aborted = True
                break
        res.received += i
        self._keep_recent(all_ts[:len(all_ts) - n + i])
        return i

    def copies(self, serial: int, times: Sequence[float], where: Sequence, own: Sequence[float]) -> None:
        """Copies of the undecided candidate `serial` within the duplicate window of it: duplicates
        whatever the candidate turns out to be (it is accepted at its own time either way), so
        they are judged at once instead of waiting with it. They take no part in the rate.
        `own`: their own timestamps (`times` is the analysis clock)."""
        res = self.res
        res.received += len(times)
        res.duplicate_serials.extend([serial] * len(times))
        for t, w, o in zip(times, where, own):
            if len(res.duplicates_located) >= LOCATED:
                break
            res.duplicates_located.append((w, float(t), serial))
            if o != t:
                res.shown[w] = float(o)

    def _locate(self, where, t: float, s: int) -> bool:
        """Locate an out-of-order packet among the first LOCATED; whether it was."""
        if len(self.res.out_of_order_located) < LOCATED:
            self.res.out_of_order_located.append((where, t, s))
            return True
        return False

    def _keep_recent(self, done: np.ndarray) -> None:
        """Keep the times the rate can still ask for: those of the last RATE_WINDOW_S."""
        if not len(done):
            return
        cut = int(np.searchsorted(done, float(done[-1]) - RATE_WINDOW_S, "left"))
        self.recent = done[cut:].copy()
        self.recent_base += cut
        if self.dup_pos and self.dup_pos[0] < self.recent_base:
            del self.dup_pos[:bisect_left(self.dup_pos, self.recent_base)]

    def result(self) -> SerialResult:
        """The results so far, as if the capture ended here (decided packets only)."""
        res = self.res
        res.duplicates, res.out_of_order = len(res.duplicate_serials), len(res.out_of_order_serials)
        res.lost_serials = self.lost_for_good + list(self.missing)
        res.last = {self.key: self.h}
        return res


def classify(serials: IntSeq, times: FloatSeq, index: Optional[IntSeq] = None,
             limit: Optional[int] = None, dup_window_ms: float = DUP_WINDOW_MS) -> SerialResult:
    """Classify one counter's serials in arrival order, all at once. `index` names the positions
    in the results (default: the positions); `limit` stops early once the anomalies exceed it."""
    counter = Counter(dup_window_ms)
    counter.feed(serials, times, range(len(serials)) if index is None else index, final=True, limit=limit)
    return counter.result()


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
    total.restarts.sort()
    return total
