"""The one analysis every front-end shares: `feed(batch)` with legal packets in arrival order,
then `finish()`; `report.build` turns the state into the report.

The state is bounded by the senders, the open commands and the findings, not by the packets:
per sender its counters and streams (`sender.Sender`), the commands (`commands.Tracker`), and
the command events not yet applied. Per periodic packet one float64 time is kept for the exact
interval statistics (`periodic`); `floats` chooses where (in memory by default; `vm110 monitor`
spills them to a file, `periodic.SpilledFloats`, so that its memory stays flat for days; it sets
the senders heard least recently aside in that file too, `shelf`: `sender(key)` reads one back).
`snapshot()` gives the verdicts so far at any moment, without disturbing the state.

Order across senders matters twice:
- A sender on a new port is a restart of an earlier one silent for NEW_PORT_SILENCE_MS, judged
  at its first packet by what was heard before it. A batch is therefore split at the first
  packet of each new sender, so that the earlier senders have been fed exactly the packets
  before it when it is linked.
- Commands are applied in capture order, a restart's marker before the packet of its frame. A
  sender may not have decided its latest packets yet (a restart candidate, the scope's choice);
  the events at or after the first undecided frame of any sender wait until it is decided. Both
  end on the analysis clock, whether the sender is heard again or not (a look when its time has
  come; a candidate released serials.CANDIDATE_WAIT_MS after it, its serial verdict still to come).
"""
from __future__ import annotations

from collections import OrderedDict
from heapq import heapify, heappop, heappush, heapreplace
from typing import BinaryIO, Optional, Union

import numpy as np

from .. import constants as C
from ..capture.reader import address
from . import commands, serials, shelf, timing
from .collect import CODE, _groups, code_of, key_sender, sender_keys
from .periodic import Floats, FloatsFactory
from .sender import Sender
from .shelf import Shelf, Shelved

NEW_PORT_SILENCE_MS = 250.0


class Analysis:
    def __init__(self, opt, floats: FloatsFactory = Floats, spool: Optional[BinaryIO] = None) -> None:
        self.opt = opt
        self.floats = floats
        self.senders: dict[int, Union[Sender, Shelved]] = {}   # sender key -> its state, in order of appearance
        self.hosts: dict[tuple, list] = {}            # (direction, origin, host) -> [(order, sender key)]
        self.names: list[bytes] = []                  # source index -> packed address
        fail = {CODE[C.PacketType.VRCI]: opt.vrci_fail_ms, CODE[C.PacketType.VRCO]: opt.vrco_give_up_ms}
        self.tracker = commands.Tracker(fail, opt.reuse_gap_ms)
        self.events: list[tuple] = []                 # command events not applied yet
        self.finished = False
        self.clock = -np.inf                          # the analysis clock (rules.md): latest time so far
        self.stamps: dict[int, float] = {}            # frame -> own time, where the clock is later
        self.behind = 0                               # packets whose own time was behind the clock
        # Kept so that a batch costs what its own senders cost, not a look at every sender:
        self.warming: list[tuple[float, int]] = []    # heap of (time of its next look, key): auto choosing
        self.looking: set[int] = set()                # the keys in `warming`
        self.candidates: list[tuple[float, int]] = [] # heap of (time of its oldest candidate, key)
        self.waiting: set[int] = set()                # the keys in `candidates`
        self.undecided: dict[int, tuple[int, float]] = {}   # sender key -> its first undecided frame, time
        self.held: list[tuple[int, int]] = []         # heap of (frame, key); stale where undecided differs
        # `spool`: a file for the senders heard least recently (shelf.py); `heard`: the keys of
        # those in memory, heard last last.
        self.shelf = None if spool is None else Shelf(spool)
        self.heard: OrderedDict[int, None] = OrderedDict()
        self.rooms: dict[int, tuple[int, int]] = {}   # key -> its place in the file, of those back from it

    def feed(self, rec: np.ndarray, sources: dict[bytes, int]) -> None:
        """Legal packets (collect.RECORD_DTYPE) in arrival order; `sources`: packed source
        address -> the index the records' `src` holds."""
        if len(sources) > len(self.names):
            self.names = [b""] * len(sources)
            for src, index in sources.items():
                self.names[index] = src
        rec = self._clocked(rec)
        key = sender_keys(rec, code_of(rec["pid"]))
        values, firsts = np.unique(key, return_index=True)
        new = sorted((f, k) for k, f in zip(values.tolist(), firsts.tolist()) if k not in self.senders)
        cuts = [f for f, _ in new]
        starts = ([0] if not cuts or cuts[0] else []) + cuts
        for a, b in zip(starts, [*starts[1:], len(rec)]):
            if new and new[0][0] == a:
                self._join(new.pop(0)[1], rec[a])
            part = rec[a:b]
            if len(self.senders) == 1 or (b - a) == 1:
                self.sender(int(key[a])).feed(part, self.events)
                continue
            for value, rows in _groups(key[a:b]):
                self.sender(value).feed(part[rows], self.events)
        heard = values.tolist()
        self._settle(heard, self.clock)
        if self.shelf is not None:
            self._shelve(heard)

    def sender(self, key: int, keep: bool = True) -> Sender:
        """The sender's state: one in the file comes back to memory (`keep`), or is read as a copy
        (finished when the analysis is) for a look that changes nothing."""
        snd = self.senders[key]
        if not isinstance(snd, Shelved):
            return snd
        assert self.shelf is not None
        back: Sender = self.shelf.get(snd)
        back.attach(self.opt, self.floats, self.stamps)
        if keep:
            self.senders[key] = back
            self.heard[key] = None
            self.rooms[key] = snd.at, snd.space
        elif self.finished:
            back.finish([])                     # (nothing pending: no event)
        return back

    def _shelve(self, heard: list[int]) -> None:
        """The senders just `heard` are the latest; those beyond the KEEP latest go to the file,
        but for those with something pending (they stay, as if heard now)."""
        assert self.shelf is not None
        latest = self.heard
        for k in heard:
            latest[k] = None
            latest.move_to_end(k)
        for _ in range(len(latest) - shelf.KEEP):
            k = next(iter(latest))
            snd = self.senders[k]
            assert isinstance(snd, Sender)
            if k in self.looking or k in self.waiting or k in self.undecided or not snd.settled():
                latest.move_to_end(k)
                continue
            del latest[k]
            self.senders[k] = self.shelf.put(self, k, snd, self.rooms.pop(k, None))

    def advance(self, clock: float) -> None:
        """A live link's time has reached `clock` with every packet before it fed (the caller
        keeps a margin): the looks and the candidates' waits due by then end as if the analysis
        clock were there, which only packets move, and a link gone silent would not."""
        if clock > self.clock:
            self._settle([], clock)

    def _settle(self, touched: list[int], clock: float) -> None:
        """After the senders `touched` were fed, at analysis time `clock`: make the looks and
        release the candidates due, then apply the command events no undecided packet holds."""
        for k in touched:
            first_look = self.sender(k).due()
            if first_look is not None and k not in self.looking:     # its second packet type came: choosing
                self.looking.add(k)
                heappush(self.warming, (first_look, k))
        while self.warming:
            due, k = self.warming[0]
            snd = self.sender(k)
            snd.expire(clock, self.events)
            later = snd.due()
            if later is None:                           # chosen
                heappop(self.warming)
                self.looking.discard(k)
                touched.append(k)
            elif later != due:                          # it looked and could not tell: later
                heapreplace(self.warming, (later, k))
            else:
                break
        self._time_out(touched, clock)
        for k in touched:
            self._note(k)
        self._apply(self._horizon())

    def _time_out(self, touched: list[int], clock: float) -> None:
        """Release the restart candidates the analysis clock has waited out (their senders join
        `touched`)."""
        for k in list(touched):
            since = self.sender(k).waiting()
            if since is not None and k not in self.waiting:
                self.waiting.add(k)
                heappush(self.candidates, (since, k))
        while self.candidates:
            since, k = self.candidates[0]
            if timing.shorter(clock - since, serials.CANDIDATE_WAIT_MS):
                break
            snd = self.sender(k)
            snd.timeout(clock, self.events)
            later = snd.waiting()
            if later is None:
                heappop(self.candidates)
                self.waiting.discard(k)
            else:
                heapreplace(self.candidates, (later, k))
            touched.append(k)

    def _clocked(self, rec: np.ndarray) -> np.ndarray:
        """The records with `ts` on the analysis clock; the own times it replaces go to `stamps`
        (the periodic streams use those). Nothing is copied while the capture's clock runs forward."""
        if not len(rec):
            return rec
        clock = np.maximum.accumulate(np.concatenate(([self.clock], rec["ts"])))[1:]
        self.clock = float(clock[-1])
        behind = clock != rec["ts"]
        if not behind.any():
            return rec
        self.behind += int(behind.sum())
        self.stamps.update(zip(rec["frame"][behind].tolist(), rec["ts"][behind].tolist()))
        rec = rec.copy()
        rec["ts"] = clock
        return rec

    def finish(self) -> None:
        """The capture ended: decide everything left and apply every command event."""
        if self.finished:
            return
        self.finished = True
        for snd in self.senders.values():
            if not isinstance(snd, Shelved):    # (a shelved one has nothing pending: finished as read)
                snd.finish(self.events)
        self.warming, self.looking, self.undecided, self.held = [], set(), {}, []
        self.candidates, self.waiting = [], set()
        self._apply(None)

    def snapshot(self) -> list[dict]:
        """Per sender, in order of appearance: its key, id, direction, packets and serial verdicts
        so far (decided packets; a sender still choosing its serial scope has none yet)."""
        return [{"key": key, "id": snd.id, "direction": snd.direction, "packets": int(snd.counts.sum()),
                 "taken_over": snd.taken_over, **snd.serial_counts()}
                for key, snd in self.senders.items()]

    def applied_until(self) -> float:
        """The analysis time before which every command event has been applied (inf: all): the
        first undecided packet's, as the events at or after it wait. A command unacknowledged
        then was so at every time before it (while a sender chooses its serial scope, or a
        candidate waits, the commands before are told without waiting for it)."""
        if self._horizon() is None:
            return np.inf if not self.events else self.clock
        return self.undecided[self.held[0][1]][1]

    def _join(self, key: int, first: np.void) -> None:
        """A new sender: a restart on a new port of the earlier sender of its address, direction
        and origin heard last among those silent for NEW_PORT_SILENCE_MS and not restarted on a
        new port already (a sender taken over lives on in its successor: one that moved on and on
        was linked back to its first port, past the one it moved from)."""
        direction, origin, src, port = key_sender(key)
        new = self.senders[key] = Sender(direction, origin, address(self.names[src], port), first, self.opt,
                                         self.floats, self.stamps)
        # Only the senders of its host not taken over yet: a capture of many senders, or a sender
        # on a new port after every pause (for days), costs no scan of them all.
        same_host = self.hosts.setdefault((direction, origin, new.host), [])
        quiet = [(old.last_ts, old.last_frame, i, k) for i, k in same_host
                 if (old := self.senders[k]).port != new.port
                 and not timing.shorter(new.first_ts - old.last_ts, NEW_PORT_SILENCE_MS)]
        same_host.append((len(self.senders) - 1, key))
        if not quiet:
            return
        _, _, i, k = max(quiet, key=lambda q: q[:3])
        same_host.remove((i, k))               # (taken over: never linked again)
        old = self.sender(k)
        new.link = {"time": self.stamps.get(new.first_frame, new.first_ts), "frame": new.first_frame, "from": 0,
                    "to": new.first_serial, "port_from": old.port, "port_to": new.port}   # (the frame's own time)
        old.probe(new)
        self.events.append((new.first_frame, new.first_ts, commands.RESTART, old.id, None, None))

    def _note(self, key: int) -> None:
        """Keep the sender's first undecided frame and its time (they only move when the sender is
        fed or decided)."""
        first = self.sender(key).undecided()
        if first == self.undecided.get(key):
            return
        if first is None:
            del self.undecided[key]
            return
        self.undecided[key] = first
        heappush(self.held, (first[0], key))
        if len(self.held) > 2 * len(self.undecided) + 64:      # stale entries stay few
            self.held = [(f, k) for k, (f, _) in self.undecided.items()]
            heapify(self.held)

    def _horizon(self) -> Optional[int]:
        held, undecided = self.held, self.undecided
        while held and undecided.get(held[0][1], (None,))[0] != held[0][0]:
            heappop(held)
        return held[0][0] if held else None

    def _apply(self, horizon: Optional[int]) -> None:
        """Apply the command events before `horizon` (all when None), in capture order."""
        if not self.events:
            return
        if horizon is None:
            ready, self.events = self.events, []
        else:
            ready = [e for e in self.events if e[0] < horizon]
            if not ready:
                return
            self.events = [e for e in self.events if e[0] >= horizon]
        ready.sort(key=lambda e: (e[0], e[2]))
        self.tracker.apply(ready)
