"""One sender's analysis state between batches (docs/rules.md): its serial counter(s), the rows
they have not decided yet, its periodic streams, VRPO bursts and state timeline.

A counter may leave packets undecided at the end of a batch (a restart candidate waits for its
next packet); they are kept here and handed in again with the sender's next rows. The command
events after a candidate wait for it serials.CANDIDATE_WAIT_MS at most on the analysis clock
(rules.md rule 5): then it is released (`timeout`), accepted as a packet (its periodic arrival,
its own command event) with no command change, and only its serial verdict waits on; a restart
confirmed after that changes no command. With
`--serial-scope auto`, while the sender has sent one packet type its one counter is both
readings' (rules.md, "Choosing the scope"), and its packets are judged at once. From its first
packet of a second type on, its packets of WARMUP_S seconds are kept as they came, the scope is
chosen on them as `choose_scope` says, and they are then judged as every later packet is: a
stream cannot wait for the end of the capture to choose. When they cannot tell (too few
anomalies yet), the look is made again on the packets of twice the time, up to WARMUP_MAX_S or
WARMUP_PACKETS packets. A look is made once the analysis clock has passed its time (`expire`: a
sender heard no more cannot hold the command events after it for ever), always on the same rows
however the batches are cut. When the choice is `type`, the one counter becomes the counter of
the sender's first type.

A sender that restarts on a new port asks its predecessor (`probe`) for the predecessor's state
just before the new sender's first frame: its counter's highest serial and its last accepted
packet of each periodic type. Every packet of the predecessor before that frame has been handed
to it by then; a candidate still undecided is out of order as far as that moment can tell (as
it would be in a capture that ended there), and it is accepted whatever its decision (copies of
it are duplicates).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .. import constants as C
from ..words import plural
from . import serials, timing
from .bursts import Bursts
from .collect import CODE, RECORD_DTYPE, TYPES, VRPI_CODE, VRPO_CODE, code_of, sender_id
from .commands import RESTART
from .periodic import Floats, FloatsFactory, Stream
from .state import Timeline

WARMUP_PACKETS = 4096
WARMUP_S = 10.0           # the first look at a sender's scope (from its second type), then at 20, 40, ... s
WARMUP_MAX_S = 320.0
TYPE_SCOPE_MARGIN = 4     # auto: type scope needs 4 anomalies fewer
COMMAND_CODES = np.array(sorted(CODE[t] for t in (C.PacketType.VRCI, C.PacketType.VRCO, *C.ACK_OF)))


def choose_scope(rows: np.ndarray, opt) -> tuple[str, bool, str]:
    """`auto`: per-type counters only when they explain the packets clearly better: with one
    counter per sender, a type's stream can look clean only by accident (say, a loss just before
    its first packet). And whether the rows tell: not when per-type counters explain them better,
    but not by the margin (too few anomalies yet). Last, why, in words for the report."""
    codes, window = code_of(rows["pid"]), opt.dup_window_ms
    if (codes == codes[0]).all():
        # (the rows from the second type on: one type there cannot tell whether the jump to it was one)
        return "sender", True, f"{TYPES[int(codes[0])].value} only from there: cannot tell, one counter assumed"
    by_sender = serials.classify(rows["serial"], rows["ts"], dup_window_ms=window)
    if by_sender.anomalies == 0:
        return "sender", True, "one counter explains them without an anomaly"
    one = f"{plural(by_sender.anomalies, 'anomaly', 'anomalies')} with one counter"
    by_type = serials.classify_sender(rows["serial"], rows["ts"], codes, "type", limit=by_sender.anomalies - 1,
                                      dup_window_ms=window)
    if by_type.aborted:
        return "sender", True, f"{one}, as many or more with one per type"
    two = f"{one}, {by_type.anomalies} with one per type"
    if by_type.anomalies + TYPE_SCOPE_MARGIN <= by_sender.anomalies:
        return "type", True, two
    return "sender", False, f"{two} (not {TYPE_SCOPE_MARGIN} fewer: cannot tell, one counter assumed)"


@dataclass
class Probe:
    frame: int             # the successor's first frame
    successor: "Sender"
    last_code: int         # this sender's last packet type before that frame


class Sender:
    """(direction, origin, source address, source port) and everything judged of it so far."""

    SHARED = ("opt", "floats", "stamps")     # the analysis' own: not pickled with it (shelf.py), `attach`ed

    def __init__(self, direction: str, origin: int, src: str, first: np.void, opt,
                 floats: FloatsFactory = Floats, stamps: Optional[dict[int, float]] = None) -> None:
        self.direction, self.origin, self.src = direction, origin, src
        self.floats = floats                     # the store of periodic times (periodic.Stream)
        # Rows carry the analysis clock (rules.md); frame -> own timestamp where that differs,
        # for the periodic streams (shared by the senders; taken out as the rows are decided).
        self.stamps: dict[int, float] = {} if stamps is None else stamps
        self.id = sender_id(direction, origin, src)
        self.host, port = src.rsplit(":", 1)
        self.port = int(port)
        self.opt = opt
        self.first_frame, self.first_ts = int(first["frame"]), float(first["ts"])
        self.first_serial, self.first_code = int(first["serial"]), int(code_of(first["pid"]))
        self.last_ts, self.last_frame, self.last_code = self.first_ts, self.first_frame, self.first_code
        self.counts = np.zeros(len(TYPES), dtype=np.int64)
        self.scope: Optional[str] = None if opt.serial_scope == "auto" else opt.serial_scope
        self.scope_reason = "set by --serial-scope"    # (auto: how the packets chose it)
        self.warm: list[np.ndarray] = []
        self.warm_count = 0
        # auto: the sender's first packet of a second type (the choice starts there): analysis
        # time, frame, type code; the next look is look_s after it.
        self.second: Optional[tuple[float, int, int]] = None
        self.look_s = WARMUP_S
        self.counters: dict = {}                 # None (scope sender) or type code -> serials.Counter
        self.pending: dict = {}                  # counter key -> its undecided candidate (a row)
        self.released: set[int] = set()          # frames of the undecided candidates released
        self.streams: dict[int, Stream] = {}
        self.bursts: Optional[Bursts] = None
        self.timeline: Optional[Timeline] = None
        self.probes: list[Probe] = []
        self.taken_over = False                  # a later sender on a new port followed it
        self.link: Optional[dict] = None         # the restart on a new port that began it
        self.before: dict[int, Optional[float]] = {}   # the predecessor's last packet per periodic type

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in self.SHARED}

    def attach(self, opt, floats: FloatsFactory, stamps: dict[int, float]) -> None:
        """Back from a pickle: the analysis' shared objects in place again."""
        self.opt, self.floats, self.stamps = opt, floats, stamps
        if self.bursts is not None:
            self.bursts.floats = floats

    def feed(self, rows: np.ndarray, events: list) -> None:
        """The sender's next legal packets, in arrival order; command events go to `events`."""
        codes = code_of(rows["pid"])
        self.last_ts, self.last_frame, self.last_code = float(rows["ts"][-1]), int(rows["frame"][-1]), int(codes[-1])
        self.counts += np.bincount(codes, minlength=len(TYPES))
        while self.scope is None and len(rows):
            if self.second is None:
                # One type so far: one counter under either scope, judged at once.
                other = np.flatnonzero(codes != self.first_code)
                k = int(other[0]) if len(other) else len(rows)
                if k:
                    self._dispatch(rows[:k], events, False)
                    rows, codes = rows[k:], codes[k:]
                if not len(rows):
                    break
                self.second = float(rows["ts"][0]), int(rows["frame"][0]), int(codes[0])
            # The rows before the next look (`ts` is the analysis clock, so ascending).
            k = min(WARMUP_PACKETS - self.warm_count,
                    int(np.searchsorted(rows["ts"] - self.second[0], self.look_s)))
            if k:
                self.warm.append(rows[:k].copy())         # not a view: the batch itself is not kept
                self.warm_count += k
                rows, codes = rows[k:], codes[k:]
            if len(rows) or self.warm_count >= WARMUP_PACKETS:
                self._look(events)
        if len(rows):
            self._dispatch(rows, events, False)

    def due(self) -> Optional[float]:
        """auto: the analysis time of the next look; None when none is to come (the scope is
        chosen, or the sender has sent one type so far)."""
        return None if self.scope is not None or self.second is None else self.second[0] + self.look_s

    def expire(self, clock: float, events: list) -> None:
        """Make the looks due by `clock` (the analysis clock): a sender heard no more cannot hold
        its packets and the command events after them."""
        while self.scope is None and self.second is not None and clock - self.second[0] >= self.look_s:
            self._look(events)

    def _look(self, events: list) -> None:
        """Choose the scope on the warm-up rows, or look again later when they cannot tell (the
        last look, or a full count, chooses anyway)."""
        rows = np.concatenate(self.warm)
        self.warm = [rows]
        scope, tells, why = choose_scope(rows, self.opt)
        if not tells and self.warm_count < WARMUP_PACKETS and self.look_s < WARMUP_MAX_S:
            self.look_s *= 2
            return
        which = (f"the first {len(rows)} packets" if self.warm_count >= WARMUP_PACKETS
                 else f"the {plural(len(rows), 'packet')} of {self.look_s:g} s")
        self._decide(events, False, (scope, f"auto, on {which} {self._from()}: {why}"))

    def _from(self) -> str:
        assert self.second is not None
        return f"from its first {TYPES[self.second[2]].value} (frame {self.second[1]})"

    def finish(self, events: list) -> None:
        """The capture ended: decide what is left."""
        if self.scope is None:
            self._decide(events, True)
        else:
            self._dispatch(np.empty(0, dtype=RECORD_DTYPE), events, True)
        if self.bursts is not None:
            self.bursts.finish()

    def waiting(self) -> Optional[float]:
        """The analysis time of its oldest undecided candidate not released (None: none), while
        no look is to come (a look decides them with the rest)."""
        if self.warm:
            return None
        times = [float(r["ts"][0]) for r in self._holding()]
        return min(times) if times else None

    def timeout(self, clock: float, events: list) -> None:
        """The analysis clock is at `clock`: the candidates it has waited for long enough are
        released (the sender has had all its rows up to it, none deciding them)."""
        if self.warm:
            return
        for row in self._holding():
            if not timing.shorter(clock - float(row["ts"][0]), serials.CANDIDATE_WAIT_MS):
                self.released.add(int(row["frame"][0]))
                self._accept(row, self._own_times(row, take=False), events)

    def _holding(self) -> list[np.ndarray]:
        """The undecided candidates that hold the command events after them."""
        return [r for r in self.pending.values() if int(r["frame"][0]) not in self.released]

    def settled(self) -> bool:
        """Nothing pending: no packet undecided or waiting for the scope's choice, no probe of a
        successor to resolve, no predecessor's state still to come (shelf.py: it may leave memory)."""
        return not (self.warm or self.pending or self.probes or (self.link is not None and not self.before))

    def undecided(self) -> Optional[tuple[int, float]]:
        """The frame and analysis time of the first packet not decided yet (its events and any
        restart before them wait)."""
        rows = [*self._holding(), *self.warm[:1]]
        return min((int(r["frame"][0]), float(r["ts"][0])) for r in rows) if rows else None

    def _decide(self, events: list, final: bool, chosen: Optional[tuple[str, str]] = None) -> None:
        """`chosen`: the scope and why; None at the end of the capture, chosen here on all rows."""
        rows = np.concatenate(self.warm) if self.warm else np.empty(0, dtype=RECORD_DTYPE)
        self.warm, self.warm_count = [], 0
        if chosen is None and self.second is None:
            chosen = "sender", f"auto: {TYPES[self.first_code].value} only, one counter under either scope"
        elif chosen is None:
            scope, _, why = choose_scope(rows, self.opt)
            every = "all its" if len(rows) > 1 else "its"
            chosen = scope, f"auto, on {every} {plural(len(rows), 'packet')} {self._from()}: {why}"
        self.scope, self.scope_reason = chosen
        if self.scope == "type":
            # The one counter so far is its first type's (it had no other).
            for store in (self.counters, self.pending):
                if None in store:
                    store[self.first_code] = store.pop(None)
            self.counters[self.first_code].key = self.first_code
        # Probes that came while warming up: their moment lies inside these rows.
        for probe in sorted(self.probes, key=lambda p: p.frame):
            cut = int(np.searchsorted(rows["frame"], probe.frame))
            self._dispatch(rows[:cut], events, False)
            rows = rows[cut:]
            self._resolve(probe)
        self.probes = []
        self._dispatch(rows, events, final)

    def probe(self, successor: "Sender") -> None:
        """`successor` restarted this sender on a new port at its first frame (see the module doc)."""
        self.taken_over = True
        probe = Probe(successor.first_frame, successor, self.last_code)
        if self.warm:
            self.probes.append(probe)
        else:
            self._resolve(probe)

    def _resolve(self, probe: Probe) -> None:
        key = None if self.scope != "type" else (
            probe.successor.first_code if probe.successor.first_code in self.counters else probe.last_code)
        counter = self.counters.get(key)
        link = probe.successor.link
        assert link is not None, "a successor is probed once its restart link is set"
        link["from"] = counter.h if counter is not None else 0
        probe.successor.before = {code: self._last_accepted(code) for code in (VRPI_CODE, VRPO_CODE)}

    def _last_accepted(self, code: int) -> Optional[float]:
        """Time of the last accepted packet of that type so far, an undecided candidate included
        (accepted whatever its decision)."""
        for held in self.pending.values():
            if code_of(held["pid"])[0] == code:
                frame = int(held["frame"][0])
                return self.stamps.get(frame, float(held["ts"][0]))
        stream = self.streams.get(code)
        return stream.times.last() if stream is not None and len(stream.times) else None

    def _dispatch(self, rows: np.ndarray, events: list, final: bool) -> None:
        """Judge rows (and the undecided ones before them) by the counter(s) of the scope (one,
        while auto has not chosen: the sender has sent one type so far)."""
        if self.scope != "type":
            parts = {None: rows}
        else:
            codes = code_of(rows["pid"])
            parts = {c: rows[codes == c] for c in np.unique(codes).tolist()}
        if final:
            parts.update({k: rows[:0] for k in self.pending if k not in parts})
        for key, new in parts.items():
            held = self.pending.pop(key, None)
            if held is not None and not final and len(new) and (new["serial"] == held["serial"][0]).all():
                self.pending[key] = held
                self._hold(key, new)          # more copies of the undecided candidate
                continue
            todo = new if held is None else np.concatenate((held, new))
            if not len(todo):
                continue
            counter = self.counters.get(key)
            if counter is None:
                counter = self.counters[key] = serials.Counter(self.opt.dup_window_ms, key)
            restarts = len(counter.res.restarts)
            done = counter.feed(todo["serial"], todo["ts"], todo["frame"].tolist(), final,
                                own=self._own_times(todo, take=False))
            decided = todo[:done]
            if done < len(todo):                   # an undecided candidate, then copies of it only
                self.pending[key] = todo[done:done + 1].copy()            # a copy: not the batch
                self._hold(key, todo[done + 1:])
            for frame, _, _, t in counter.res.restarts[restarts:]:
                if frame not in counter.fed_late:              # (late: it changes no command)
                    events.append((frame, t, RESTART, self.id, None, None))
            own = self._own_times(decided)
            if counter.fed_duplicates or self.released:
                # (a released candidate was accepted when released)
                kept = ~np.isin(decided["frame"], [*counter.fed_duplicates, *self.released])
                self.released.difference_update(decided["frame"].tolist())
                decided, own = decided[kept], own[kept]
            self._accept(decided, own, events)

    def _own_times(self, rows: np.ndarray, take: bool = True) -> np.ndarray:
        """The rows' own timestamps (their `ts` is the analysis clock), taken out of `stamps`
        (left there, when not `take`: rows not decided yet)."""
        if not self.stamps:
            return rows["ts"]
        get = self.stamps.pop if take else self.stamps.get
        return np.array([get(f, t) for f, t in zip(rows["frame"].tolist(), rows["ts"].tolist())], dtype=np.float64)

    def _hold(self, key, copies: np.ndarray) -> None:
        """Copies of the counter's undecided candidate: duplicates whatever it turns out to be
        (rules.md, rule 5), judged at once (a flood of them costs nothing kept)."""
        if len(copies):
            self.counters[key].copies(int(copies["serial"][0]), copies["ts"], copies["frame"].tolist(),
                                      self._own_times(copies).tolist())

    def _accept(self, rows: np.ndarray, own: np.ndarray, events: list) -> None:
        """Accepted packets (not duplicates) of one counter, in arrival order; `own`: their own
        timestamps, which the periodic streams use."""
        if not len(rows):
            return
        codes = code_of(rows["pid"])
        for code in (VRPI_CODE, VRPO_CODE):
            which = codes == code
            mine = rows[which]
            if not len(mine):
                continue
            frames, times = mine["frame"], own[which]
            stream = self.streams.get(code)
            if stream is None:
                limit = self.opt.vrpi_watchdog_ms if code == VRPI_CODE else self.opt.vrpo_watchdog_ms
                stream = self.streams[code] = Stream(TYPES[code].value, self.id, limit, self.floats)
            stream.feed(times, frames)
            if code == VRPI_CODE:
                if self.timeline is None:
                    self.timeline = Timeline()
                self.timeline.feed(times, mine["state"], frames)
            else:
                if self.bursts is None:
                    opt = self.opt
                    self.bursts = Bursts(stream.times, opt.burst_gap_ms, opt.vrpo_start, opt.vrpo_data_size,
                                         opt.vrpo_min_ms, opt.vrpo_max_ms, self.floats)
                self.bursts.feed(times, mine["aux"], mine["size"], frames)
        command = np.isin(codes, COMMAND_CODES)
        if command.any():
            picked = rows[command]
            events += zip(picked["frame"].tolist(), picked["ts"].tolist(), codes[command].tolist(),
                          [self.id] * len(picked), picked["aux"].tolist(), own[command].tolist())

    def serial_counts(self) -> dict:
        """The serial verdicts so far (decided packets only), cheaply: for a live view."""
        counters = self.counters.values()
        return {"received": sum(c.res.received for c in counters),
                "lost": sum(len(c.lost_for_good) + len(c.missing) for c in counters),
                "duplicates": sum(len(c.res.duplicate_serials) for c in counters),
                "out_of_order": sum(len(c.res.out_of_order_serials) for c in counters),
                "restarts": sum(len(c.res.restarts) for c in counters) + (self.link is not None),
                "scope": self.scope, "choosing": self.due() is not None}

    def serial_result(self) -> serials.SerialResult:
        """The counters' results together, as one counter (scope sender) or per type."""
        if self.scope == "sender":
            return self.counters[None].result()
        total = serials.SerialResult()
        for code in sorted(self.counters):
            total.merge(self.counters[code].result())
        total.gaps.sort(key=lambda g: g[3])
        total.restarts.sort()
        return total
