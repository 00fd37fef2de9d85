"""The live view of a link: what the dashboard shows each second, and the findings that cannot
wait for the end of the capture.

Everything here is bounded: at most MAX_SENDERS senders (a few numbers each, windows of a minute;
beyond, the one heard least recently leaves the view: a controller restarting on a new port every
few seconds for days, or spoofed senders, would grow it for ever) and the commands still open;
nothing is kept per packet.

Where the numbers come from:
- serial verdicts (lost, duplicates, out of order, restarts) and commands (in flight, failed, ack
  latency) are those of the `Analysis` itself, as it decides them: the same rules as the report.
  A sender still choosing its serial scope (`--serial-scope auto`, 10 s from its first packet of
  a second type) has decided nothing since, so those findings come when the choice is made;
- what needs the current time is judged here, from the legal packets as they arrive: a periodic
  stream silent beyond its watchdog limit raises the watchdog alarm while it is still silent
  (cleared by its next packet, or by its sender's restart on a new port); link state, ages of
  the last VRPI/VRPO, the running RFC 3550 jitter, VRPO burst intervals and the BU's state.
"""
from __future__ import annotations

import collections
import itertools
import math
from typing import Callable, Optional

import numpy as np

from .. import constants as C
from .. import protocol as P
from ..analysis import serials
from ..analysis.bursts import DATA_OFFSET, Open
from ..analysis.collect import (CODE_OF_ID, RECORD, RECORD_DTYPE, STATE, STATE_FIELDS, TYPES, VRPI_CODE, VRPO_CODE,
                                code_of, sender_id, sender_keys)
from ..capture.reader import address
from ..analysis.findings import FINDINGS
from ..analysis.findings import located_item as item
from ..analysis.state import _name as state_name
from ..analysis.timing import JITTER_GAIN, interval_ms

SILENT_S = 10.0            # a watchdog lasting longer than this shows as "silent"
MAX_SENDERS = 1024         # senders in the live view (a mirror port of 20 pairs has 40)
WINDOW_S = 60              # "last minute" numbers
Emit = Callable[[dict], None]
_INPUT = [t.direction is C.Direction.INPUT for t in TYPES]
_ORIGIN = P.HEADER_OFFSETS["origin"]          # the origin, u16 little-endian
_SIZE = P.SIZE_OFFSET                          # the payload size, u16 little-endian


class LiveSender:
    """The live numbers of one sender."""

    def __init__(self, key: tuple, sid: str, direction: str, opt) -> None:
        self.key, self.id, self.direction = key, sid, direction
        self.akey = 0                                 # its key in the analysis (Live.feed)
        self.code = VRPI_CODE if direction == C.Direction.INPUT.value else VRPO_CODE
        self.ptype = TYPES[self.code].value
        limit = opt.vrpi_watchdog_ms if self.code == VRPI_CODE else opt.vrpo_watchdog_ms
        self.limit = limit / 1000.0
        self.period = opt.vrpi_period_ms if self.code == VRPI_CODE else opt.vrpo_period_ms
        self.gap_ms = opt.burst_gap_ms
        self.low, self.high = opt.vrpo_min_ms, opt.vrpo_max_ms
        self.packets = 0
        self.last_ts: Optional[float] = None          # of its periodic type
        self.last_frame = 0
        self.alarm: Optional[dict] = None             # the watchdog item while raised
        self.replaced = False
        self.jitter: Optional[float] = None
        self.prev: Optional[float] = None             # previous periodic arrival (VRPI) or burst start (VRPO)
        self.vrpo_last: Optional[float] = None        # last VRPO packet (bursts)
        self.burst = Open(opt.vrpo_start, opt.vrpo_data_size)   # the VRPO burst being received
        self.interval: Optional[float] = None         # the last interval (ms)
        self.outside = 0
        self.recent: collections.deque = collections.deque(maxlen=64)   # intervals, for the VRPO period
        self.fresh = False                            # `recent` changed this second
        self.second: list = [None, None]              # min, max interval of the current second
        self.window: collections.deque = collections.deque(maxlen=WINDOW_S)   # per second: min, max
        self.marks: collections.deque = collections.deque(maxlen=WINDOW_S + 1)   # per second: totals
        self.state: Optional[dict] = None
        self.nominal: Optional[float] = None          # VRPO without --vrpo-period: median of the recent intervals

    def periodic(self, ts: float, frame: int, packet: bytes, emit: Emit) -> None:
        if self.code == VRPO_CODE:
            # (a burst ends at its gap, or once it is over: docs/rules.md, "VRPO bursts")
            number = packet[C.PREFIX_LEN] | packet[C.PREFIX_LEN + 1] << 8
            begins = (self.vrpo_last is None or interval_ms(ts, self.vrpo_last) >= self.gap_ms
                      or self.burst.over(number))
            self.vrpo_last = ts
            if begins:
                self.burst.close()
            self.burst.add(number, (packet[_SIZE] | packet[_SIZE + 1] << 8) - DATA_OFFSET)
            if not begins:
                self._arrived(ts, frame, emit)
                return
        if self.prev is not None and ts >= self.prev:
            self._interval((ts - self.prev) * 1000.0)
        self.prev = ts
        self._arrived(ts, frame, emit)

    def _arrived(self, ts: float, frame: int, emit: Emit) -> None:
        last = self.last_ts
        if last is not None and ts - last > self.limit:
            gap_ms = (ts - last) * 1000.0
            if self.alarm is None:           # silent and back between two looks: raised and cleared at once
                self.alarm = item(self.last_frame, last, self.id, type=self.ptype, gap_ms=gap_ms, until_end=False)
                emit(finding("watchdog", "raised", self.alarm, f"{self.ptype} watchdog: silent {gap_ms:.0f} ms"))
            cleared = item(frame, ts, self.id, type=self.ptype, gap_ms=gap_ms, since_frame=self.last_frame)
            emit(finding("watchdog", "cleared", cleared, f"{self.ptype} back after {gap_ms:.0f} ms"))
            self.alarm = None
        self.last_ts, self.last_frame = ts, frame   # (in capture order, as analyze's silence to the end)

    def _interval(self, ms: float) -> None:
        self.interval = ms
        lo, hi = self.second
        self.second = [ms if lo is None else min(lo, ms), ms if hi is None else max(hi, ms)]
        if self.code == VRPO_CODE:
            self.recent.append(ms)
            self.fresh = True
            if not self.low <= ms <= self.high:
                self.outside += 1
        period = self.period or self.nominal or ms
        if period:
            k = max(1.0, math.floor(ms / period + 0.5))
            d = abs(ms - k * period)
            self.jitter = d if self.jitter is None else self.jitter + (d - self.jitter) * JITTER_GAIN

    def tick(self, now: float, emit: Emit) -> None:
        if self.replaced or self.last_ts is None or self.alarm is not None:
            return
        if now - self.last_ts > self.limit:
            self.alarm = item(self.last_frame, self.last_ts, self.id, type=self.ptype,
                              gap_ms=(now - self.last_ts) * 1000.0, until_end=True)
            emit(finding("watchdog", "raised", self.alarm,
                         f"{self.ptype} watchdog: silent {(now - self.last_ts) * 1000.0:.0f} ms (limit "
                         f"{self.limit * 1000.0:g} ms), still silent"))

    def link_state(self, now: float) -> str:
        if self.replaced:
            return "replaced"
        if self.last_ts is None:
            return "starting"
        if self.alarm is None:
            return "alive"
        return "silent" if now - self.last_ts > SILENT_S else "watchdog"

    def close_second(self, totals: dict) -> None:
        """A second of capture time ended: push its window entries."""
        if self.fresh:                    # (a median a second for each sender heard, not each one kept)
            self.nominal = float(np.median(self.recent))
            self.fresh = False
        self.window.append(tuple(self.second))
        self.second = [None, None]
        self.marks.append((totals.get("lost", 0), totals.get("duplicates", 0), self.outside))

    def view(self, now: float, totals: dict) -> dict:
        lows = [lo for lo, _ in self.window if lo is not None]
        highs = [hi for _, hi in self.window if hi is not None]
        first = self.marks[0] if self.marks else (0, 0, 0)
        lost, dups = totals.get("lost", 0), totals.get("duplicates", 0)
        out = {"sender": self.id, "role": "BU" if self.code == VRPI_CODE else "controller",
               "state": self.link_state(now), "type": self.ptype,
               "age_ms": None if self.last_ts is None else max(0.0, (now - self.last_ts) * 1000.0),
               "limit_ms": self.limit * 1000.0, "packets": self.packets,
               "lost": lost, "lost_1m": lost - first[0], "duplicates": dups, "duplicates_1m": dups - first[1],
               "out_of_order": totals.get("out_of_order", 0), "restarts": totals.get("restarts", 0),
               "serial_scope": totals.get("scope"), "serial_choosing": totals.get("choosing", False),
               "jitter_ms": self.jitter, "interval_ms": self.interval,
               "interval_1m_ms": [min(lows), max(highs)] if lows else None}
        if self.code == VRPO_CODE:
            out["outside_recommended"] = self.outside
            out["outside_recommended_1m"] = self.outside - first[2]
            out["recommended_ms"] = [self.low, self.high]
        if self.state is not None:
            out.update(self.state)
        return out


def analysis_key(src: int, sport: int, packet: bytes) -> int:
    """The analysis' key of the sender of `packet` from source index `src`, port `sport`: the
    record the analysis gets of it, keyed as it keys it (collect.sender_keys, its one definition)."""
    rec = np.frombuffer(RECORD.pack(0.0, 0, src, sport, packet), dtype=RECORD_DTYPE)
    return int(sender_keys(rec, code_of(rec["pid"]))[0])


def finding(rule: str, event: str, where: dict, message: str) -> dict:
    """A live finding: `event` raised / cleared (an alarm's state) or found (a one-off)."""
    return {"type": "finding", "rule": rule, "severity": SEVERITY[rule], "event": event,
            "time": where["time"], "frame": where["frame"], "sender": where.get("sender"), "message": message,
            "item": where}


SEVERITY = {rule: severity for rule, severity, *_ in FINDINGS}      # the report's, by its rule


class Live:
    """The live view of `analysis` (options `opt`); findings go to `emit`."""

    def __init__(self, analysis, opt, emit: Emit, sources: dict) -> None:
        self.analysis, self.opt, self.emit = analysis, opt, emit
        self.sources = sources                 # packed source address -> its index in the analysis' keys
        self.senders: collections.OrderedDict[tuple, LiveSender] = collections.OrderedDict()   # heard last, last
        self.dropped = 0                       # senders that left the view (more than MAX_SENDERS)
        self.gaps_seen: dict = {}              # (sender key, counter key) -> gaps and restarts reported
        self.senders_told = 0                   # the analysis' senders whose new-port link is told
        # The analysis' senders whose serial verdicts may have grown since the last look: those fed
        # packets since (a verdict comes with a sender's own packets, or at the end), and those with
        # a gap still within its duplicate window. Only these are looked at each tick, not every
        # sender ever heard (spoofed senders, a restart on a new port every few seconds for days).
        self.to_look: dict[int, None] = {}
        self.cmd_seen = dict.fromkeys(analysis.tracker.tallies, 0)
        self.watch: list = []                  # (code, command) not acknowledged yet
        self.cmd = {"commands": 0, "acked": 0, "failed": 0, "interrupted": 0}
        self.latency_last: Optional[float] = None
        self.latencies: collections.deque = collections.deque(maxlen=WINDOW_S)
        self.latency_second: Optional[float] = None
        self.counts: collections.Counter = collections.Counter()   # live findings per rule
        self.active: dict = {}                 # rule, sender -> raised item

    # -- packets -------------------------------------------------------------------------------
    def feed(self, rows: list) -> None:
        """Legal packets in arrival order: (ts, frame, packed source, source port, EG-Link packet)."""
        senders, emit = self.senders, self.emit
        last_vrpi: dict = {}
        for ts, frame, src, sport, packet in rows:
            code = CODE_OF_ID[packet[:4]]
            key = (_INPUT[code], src, sport, packet[_ORIGIN] | packet[_ORIGIN + 1] << 8)
            snd = senders.get(key)
            if snd is not None:
                senders.move_to_end(key)
            else:
                if len(senders) >= MAX_SENDERS:
                    self._drop()
                direction = C.Direction.INPUT.value if key[0] else C.Direction.OUTPUT.value
                snd = senders[key] = LiveSender(key, sender_id(direction, key[3], address(src, sport)), direction,
                                                self.opt)
                snd.akey = analysis_key(self.sources[src], sport, packet)
            snd.packets += 1
            self.to_look[snd.akey] = None
            if code == snd.code:
                snd.periodic(ts, frame, packet, emit)
                if code == VRPI_CODE:
                    last_vrpi[key] = packet
        for key, packet in last_vrpi.items():
            snd = senders.get(key)
            if snd is None:                     # (left the view later in the batch: more senders than it holds)
                continue
            st = dict(zip(STATE_FIELDS, STATE.unpack_from(packet, C.PREFIX_LEN), strict=True))
            snd.state = {
                "bu_state": state_name("bu_state", st["bu_state"]), "armed_ru": state_name("armed_ru", st["armed_ru"]),
                "ru_state": state_name("ru_state", st["ru_state"]), "ru_battery": st["ru_battery"],
                "ru_rssi": st["ru_rssi"], "relays_open": st["bu_state"] < C.ES_RELAYS_CLOSED_FROM}

    def _drop(self) -> None:
        """The sender heard least recently leaves the view; its watchdog alarm, if raised, is
        cleared (no longer watched), so that the alarms told stay paired."""
        _, old = self.senders.popitem(last=False)
        self.dropped += 1
        if old.alarm is not None and old.last_ts is not None:
            self.emit(finding("watchdog", "cleared", item(old.last_frame, old.last_ts, old.id, type=old.ptype,
                                                          dropped=True),
                              f"{old.ptype}: no longer watched live (more than {MAX_SENDERS} senders)"))
            old.alarm = None

    def _totals(self, snd: LiveSender) -> dict:
        a = self.analysis.senders.get(snd.akey)
        return {} if a is None else a.serial_counts()

    # -- the current time ----------------------------------------------------------------------
    def tick(self, now: float, final: bool = False) -> None:
        """Judge what needs the time `now` (capture time) and what the analysis decided since
        (`final`: the input has ended)."""
        for snd in self.senders.values():
            a = self.analysis.senders.get(snd.akey)
            if a is not None and a.taken_over and not snd.replaced:
                snd.replaced = True
                if snd.alarm is not None and snd.last_ts is not None:
                    cleared = item(snd.last_frame, snd.last_ts, snd.id, type=snd.ptype, restarted=True)
                    self.emit(finding("watchdog", "cleared", cleared, f"{snd.ptype}: sender restarted on a new port"))
                    snd.alarm = None
            snd.tick(now, self.emit)
        # The periodic streams judge on the records' own times; serials and commands on the analysis
        # clock (rules.md), later than `now` after a step back of the time (appended captures).
        clock = max(now, self.analysis.clock)
        self._serials(clock, final)
        self._commands(clock)

    def _serials(self, now: float, final: bool) -> None:
        """A gap is reported once no late packet can fill it any more (the duplicate window after
        it opened, or the end of the input), with its serials still missing: as analyze's items."""
        window = self.opt.dup_window_ms / 1000
        senders = self.analysis.senders
        # (a sender's link is made with it, and senders are only added: those past senders_told
        # are new, the last ones, and no set of every sender's key grows for days)
        joined = list(itertools.islice(reversed(senders.values()), len(senders) - self.senders_told))
        for a in reversed(joined):
            if a.link is not None:
                link = a.link
                self.emit(finding("restarts", "found", item(link["frame"], link["time"], a.id, **{
                    k: v for k, v in link.items() if k not in ("frame", "time")}), "sender restarted on a new port"))
        self.senders_told = len(senders)
        look, self.to_look = (senders if final else self.to_look), {}
        for key in look:
            a = self.analysis.sender(key, keep=False)     # (one in the file: a copy, looked at only)
            for ckey, counter in a.counters.items():
                seen_gaps, seen_restarts = self.gaps_seen.get((key, ckey), (0, 0))
                res = counter.res
                while seen_gaps < len(res.gaps):
                    after, count, t, f = res.gaps[seen_gaps]
                    if not final and now - t < window:
                        break
                    seen_gaps += 1
                    what = serials.gap_lost(after, count, res.gap_late.get(f, 0))
                    if what is not None:
                        lost = count - what.get("late", 0)
                        self.emit(finding("lost", "found", item(f, res.time_of(f, t), a.id, **what),
                                          f"{lost} packet(s) lost before serial {what['serial']}"))
                for f, old, new, t in res.restarts[seen_restarts:]:
                    self.emit(finding("restarts", "found", item(f, res.time_of(f, t), a.id, **{"from": old, "to": new}),
                                      f"serial counter started afresh ({old} -> {new})"))
                if seen_gaps or res.restarts:          # (none kept for a counter with nothing to tell)
                    self.gaps_seen[(key, ckey)] = (seen_gaps, len(res.restarts))
                if seen_gaps < len(res.gaps):          # (a gap still within its window: look again)
                    self.to_look[key] = None

    def _commands(self, now: float) -> None:
        tracker = self.analysis.tracker
        for code, tally in tracker.tallies.items():
            new = tally.commands[self.cmd_seen[code]:]
            self.cmd_seen[code] = len(tally.commands)
            self.cmd["commands"] += len(new)
            self.watch += [(code, c, False) for c in new]
        known = min(now, self.analysis.applied_until())   # every event before it applied: silence is known
        keep = []
        for code, cmd, was_flagged in self.watch:
            flagged = was_flagged
            limit = tracker.fail_ms[code]
            kind = TYPES[code].value
            began = tracker.tallies[code].time_of(cmd.frames[0], cmd.times[0])   # (its own time, as shown)
            if cmd.interrupted_frame is not None:
                self.cmd["interrupted"] += 1
                continue
            if cmd.ack_frame is not None:
                latency = cmd.latency_first_ms
                self.cmd["acked"] += 1
                self.latency_last = latency
                self.latency_second = latency if self.latency_second is None else max(self.latency_second, latency)
                if latency > limit and not flagged:
                    self.cmd["failed"] += 1
                    self.emit(finding("failed", "found", item(cmd.frames + [cmd.ack_frame], began, cmd.sender,
                                                              type=kind, command_id=cmd.command_id,
                                                              latency_ms=latency, ack_frame=cmd.ack_frame),
                                      f"{kind} {cmd.command_id} acknowledged after {latency:.0f} ms "
                                      f"(limit {limit:g} ms)"))
                continue
            if not flagged and (known - cmd.times[0]) * 1000.0 > limit:
                flagged = True
                self.cmd["failed"] += 1
                self.emit(finding("failed", "raised", item(cmd.frames, began, cmd.sender, type=kind,
                                                           command_id=cmd.command_id, latency_ms=None, ack_frame=None),
                                  f"{kind} {cmd.command_id} not acknowledged within {limit:g} ms"))
            if flagged and (now - cmd.times[-1]) * 1000.0 > max(self.opt.reuse_gap_ms, limit):
                continue        # given up on: counted as failed, no longer watched
            keep.append((code, cmd, flagged))
        self.watch = keep

    def close_second(self) -> None:
        for snd in self.senders.values():
            snd.close_second(self._totals(snd))
        self.latencies.append(self.latency_second)
        self.latency_second = None

    def view(self, now: float) -> dict:
        """The dashboard's numbers at `now`."""
        senders = [snd.view(now, self._totals(snd)) for snd in self.senders.values()]
        senders.sort(key=lambda s: (s["role"] != "BU", s["sender"]))
        window = [x for x in self.latencies if x is not None]
        in_flight = sum(1 for _, c, flagged in self.watch if not flagged)
        return {"senders": senders, "senders_dropped": self.dropped,
                "commands": {**self.cmd, "in_flight": in_flight,
                             "unacked": sum(1 for _ in self.watch),
                             "ack_latency_ms": {"last": self.latency_last, "max_1m": max(window) if window else None}}}
