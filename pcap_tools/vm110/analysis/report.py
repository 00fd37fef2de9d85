"""From `Collected` to the report dictionary (the JSON report, docs/report.md) and its verdict."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from .. import __version__
from .. import constants as C
from . import bursts, commands, findings, serials, state, timing
from .report_json import normalise
from .collect import CODE, TYPES, VRPI_CODE, VRPO_CODE, Collected, Sender

SCHEMA_VERSION = 2
NEW_PORT_SILENCE_MS = 250.0
SCOPES = ("auto", "sender", "type")
COMMAND_CODES = [CODE[t] for t in (*commands.COMMAND_TYPES, *C.ACK_OF)]
TYPE_SCOPE_MARGIN = 4     # auto: type scope needs at most half the anomalies, and 4 fewer
HISTOGRAM_BINS = 60
SERIES_POINTS = 600


@dataclass
class Options:
    serial_scope: str = "auto"
    vrpi_period_ms: float = C.VRPI_PERIOD_MS
    vrpo_period_ms: Optional[float] = None        # None: the median interval between bursts
    vrpi_watchdog_ms: float = C.VRPI_WATCHDOG_MS
    vrpo_watchdog_ms: float = C.VRPO_WATCHDOG_MS
    vrpo_min_ms: float = C.VRPO_PERIOD_MIN_MS
    vrpo_max_ms: float = C.VRPO_PERIOD_MAX_MS
    resend_ms: float = C.COMMAND_RESEND_MS
    vrci_fail_ms: float = C.VRCI_FAIL_MS
    vrco_give_up_ms: float = C.VRCO_GIVE_UP_MS
    reuse_gap_ms: float = commands.REUSE_GAP_MS
    dup_window_ms: float = serials.DUP_WINDOW_MS
    burst_gap_ms: float = C.VRPO_BURST_GAP_MS
    vrpo_start: int = 0
    vrpo_data_size: int = 0


def build(got: Collected, opt: Options) -> dict:
    """The whole report of one capture."""
    # Damaged timestamps can make inf and nan on the way; the report shows them as null.
    with np.errstate(all="ignore"):
        return _build(got, opt)


@dataclass
class _Judged:
    """One sender with its serials judged: which of its packets were accepted (not duplicates)."""
    snd: Sender
    res: serials.SerialResult
    scope: str
    live: np.ndarray
    predecessor: Optional["_Judged"] = None
    successor: Optional["_Judged"] = None

    def before(self, frame: int) -> int:
        """How many of its packets came before that frame."""
        return int(np.searchsorted(self.snd.frame, frame))

    def last_time(self, code: int, frame: int) -> Optional[float]:
        """Time of its last accepted packet of that type before that frame."""
        n = self.before(frame)
        mask = self.live[:n] & (self.snd.code[:n] == code)
        return float(self.snd.ts[:n][mask][-1]) if mask.any() else None

    def highest_before(self, frame: int, code: int, opt: "Options") -> int:
        """Its counter's highest serial before that frame (of the counter that frame's type
        would use, with per-type counters)."""
        n, snd = self.before(frame), self.snd
        res = serials.classify_sender(snd.serial[:n], snd.ts[:n], snd.code[:n], self.scope,
                                      dup_window_ms=opt.dup_window_ms)
        return res.last.get(None, res.last.get(code, res.last.get(int(snd.code[n - 1]), 0)))


def _judge(got: Collected, opt: Options) -> list[_Judged]:
    judged = []
    for snd in got.take_senders():
        res, scope = _serials(snd, opt)
        live = np.ones(len(snd.code), dtype=bool)
        live[res.duplicate_index] = False
        judged.append(_Judged(snd, res, scope, live))
    _link_new_ports(judged)
    return judged


def _link_new_ports(judged: list[_Judged]) -> None:
    """A sender whose first packet comes from the address, direction and origin of an earlier
    sender silent for at least NEW_PORT_SILENCE_MS at that moment restarted on a new port (the
    one heard last before it). Late packets of the earlier one after it change nothing."""
    by_start = sorted(judged, key=lambda j: int(j.snd.frame[0]))
    silence = NEW_PORT_SILENCE_MS / timing.MS
    for k, new in enumerate(by_start):
        snd, first, frame = new.snd, float(new.snd.ts[0]), int(new.snd.frame[0])
        host = snd.src.rsplit(":", 1)[0]
        heard = [(float(old.snd.ts[old.before(frame) - 1]), int(old.snd.frame[old.before(frame) - 1]), i)
                 for i, old in enumerate(by_start[:k])
                 if (old.snd.direction, old.snd.origin, old.snd.src.rsplit(":", 1)[0]) == (snd.direction, snd.origin, host)
                 and old.snd.src != snd.src]
        quiet = [h for h in heard if first - h[0] >= silence]
        if quiet:
            new.predecessor = by_start[max(quiet)[2]]
            new.predecessor.successor = new


def _restart_events(j: _Judged, opt: Options) -> list[dict]:
    snd = j.snd
    events = [{"time": float(snd.ts[i]), "frame": int(snd.frame[i]), "from": a, "to": b} for i, a, b in j.res.restarts]
    if j.predecessor is not None:
        old = j.predecessor
        events.insert(0, {"time": float(snd.ts[0]), "frame": int(snd.frame[0]),
                          "from": old.highest_before(int(snd.frame[0]), int(snd.code[0]), opt),
                          "to": int(snd.serial[0]), "port_from": int(old.snd.src.rsplit(":", 1)[1]),
                          "port_to": int(snd.src.rsplit(":", 1)[1])})
    return events


def _build(got: Collected, opt: Options) -> dict:
    sender_reports, periodic, events, burst_rows, states = [], [], [], [], []
    located: dict[str, list[dict]] = {}
    backwards = 0
    judged = _judge(got, opt)
    for j in judged:
        snd, live = j.snd, j.live
        restarts = _restart_events(j, opt)
        sender_reports.append(_sender_report(j, restarts, located))
        for code in (VRPI_CODE, VRPO_CODE):
            mask = live & (snd.code == code)
            if not mask.any():
                continue
            before = None if j.predecessor is None else j.predecessor.last_time(code, int(snd.frame[0]))
            row, back = _periodic(TYPES[code].value, snd, snd.ts[mask], snd.frame[mask], before,
                                  None if j.successor is not None else got.last_ts, opt, located)
            backwards += back
            periodic.append(row)
        rows = np.flatnonzero(live & np.isin(snd.code, COMMAND_CODES))
        name = snd.id
        events += zip(snd.frame[rows].tolist(), snd.ts[rows].tolist(), snd.code[rows].tolist(),
                      [name] * len(rows), snd.aux[rows].tolist())
        for r in restarts:
            gone = j.predecessor.snd.id if "port_from" in r else name
            events.append((r["frame"], r["time"], commands.RESTART, gone, None))
        vrpo = live & (snd.code == VRPO_CODE)
        if vrpo.any():
            burst_rows.append(_bursts(snd, vrpo, opt, periodic, located))
        vrpi = live & (snd.code == VRPI_CODE)
        if vrpi.any():
            states.append({"sender": snd.id, **state.timeline(snd.ts[vrpi], snd.state[vrpi], snd.frame[vrpi],
                                                              got.last_ts)})
    periodic.sort(key=lambda p: (p["type"], p["sender"]))
    events.sort(key=lambda e: (e[0], e[2]))
    fail = {CODE[C.PacketType.VRCI]: opt.vrci_fail_ms, CODE[C.PacketType.VRCO]: opt.vrco_give_up_ms}
    tallies = commands.track(events, fail, opt.reuse_gap_ms)
    cmd = {t.value: commands.report(tallies[CODE[t]], fail[CODE[t]], opt.resend_ms) for t in commands.COMMAND_TYPES}
    invalid = got.illegal_reasons[C.Problem.BAD_CRC.value]
    report = {
        "schema_version": SCHEMA_VERSION,
        "tool": {"name": "vm110", "version": __version__, "engine": got.engine},
        "capture": {
            "file": got.path, "format": got.format, "link_types": got.link_types,
            "packets": got.frames, "udp_packets": got.udp, "eglink_packets": got.eglink,
            "other_udp_packets": got.other_udp, "non_udp_packets": got.non_udp,
            "fragments": got.fragments, "snaplen_truncated": got.snap_truncated,
            "first_time": got.first_ts, "last_time": got.last_ts,
            "duration_s": (got.last_ts - got.first_ts) if got.first_ts is not None else 0.0,
            "time_backwards": backwards, "problem": got.problem, "ports": list(got.ports),
            "damage": None if got.problem is None else {"offset": got.damage, "message": got.problem},
        },
        "crc": {"variant": got.crc_variant, "byte_order": got.crc_order, "auto": got.crc_auto,
                "valid": got.eglink - invalid, "invalid": invalid, "unchecked": got.eglink - got.crc_checked,
                "candidates": {f"{v}/{o}": n for (v, o), n in sorted(got.crc_counts.items())}},
        "illegal": {"total": got.illegal, "by_reason": dict(sorted(got.illegal_reasons.items())),
                    "examples": [{"frame": f, "time": t, "src": s, "type": p, "reasons": list(r)}
                                 for f, t, s, p, r in got.illegal_examples]},
        "senders": sender_reports,
        "periodic": periodic,
        "commands": cmd,
        "vrpo_bursts": {"complete": sum(b["complete"] for b in burst_rows),
                        "incomplete": sum(b["incomplete"] for b in burst_rows), "per_sender": burst_rows},
        "state": states,
        "options": asdict(opt),
    }
    findings.locate_report(report, tallies, located)
    report = normalise(report)
    report["totals"] = findings.totals(report)
    report["verdict"] = normalise(findings.verdict(report, located))
    return report


def _serials(snd: Sender, opt: Options) -> tuple[serials.SerialResult, str]:
    codes, scope, window = snd.code, opt.serial_scope, opt.dup_window_ms
    by_sender = serials.classify_sender(snd.serial, snd.ts, codes, "sender", dup_window_ms=window)
    if scope == "sender" or (scope == "auto" and (by_sender.anomalies == 0 or len(np.unique(codes)) < 2)):
        return by_sender, "sender"
    if scope == "type":
        return serials.classify_sender(snd.serial, snd.ts, codes, "type", dup_window_ms=window), "type"
    # Per-type numbering must explain the capture clearly better: with one counter per sender,
    # a type's stream can look clean only by accident (say, a loss just before its first packet).
    by_type = serials.classify_sender(snd.serial, snd.ts, codes, "type", limit=by_sender.anomalies // 2,
                                      dup_window_ms=window)
    if not by_type.aborted and 2 * by_type.anomalies + TYPE_SCOPE_MARGIN <= by_sender.anomalies:
        return by_type, "type"
    return by_sender, "sender"


def _sender_report(j: _Judged, restarts: list[dict], located: dict) -> dict:
    snd, res = j.snd, j.res
    counts = dict(enumerate(np.bincount(snd.code, minlength=len(TYPES)).tolist()))
    counts = {c: n for c, n in counts.items() if n}
    name = snd.id
    gaps = [{"after": a, "count": n, "time": t, "frame": int(snd.frame[p])} for a, n, t, p in res.gaps]
    where = findings.Where(located)
    for g in gaps:
        where.add("lost", g["frame"], g["time"], name, serial=(g["after"] + g["count"] + 1) % serials.MOD,
                  after=g["after"], count=g["count"])
    for rule, positions in (("duplicates", res.duplicate_index), ("out_of_order", res.out_of_order_index)):
        for p in positions:
            where.add(rule, int(snd.frame[p]), float(snd.ts[p]), name, serial=int(snd.serial[p]))
    for r in restarts:
        where.add("restarts", r["frame"], r["time"], name, **{k: v for k, v in r.items() if k not in ("frame", "time")})
    return {
        "id": name, "direction": snd.direction, "origin": snd.origin, "src": snd.src,
        "by_type": {TYPES[c].value: counts[c] for c in sorted(counts, key=lambda c: TYPES[c].value)},
        "serial": {
            "scope": j.scope, "received": res.received, "lost": res.lost, "duplicates": res.duplicates,
            "out_of_order": res.out_of_order, "wraps": res.wraps, "restarts": len(restarts),
            "lost_serials": res.lost_serials, "duplicate_serials": res.duplicate_serials,
            "out_of_order_serials": res.out_of_order_serials, "gaps": gaps, "restart_events": restarts,
        },
    }


def _periodic(ptype: str, snd: Sender, times: np.ndarray, frames: np.ndarray, before: Optional[float],
              end: Optional[float], opt: Options, located: dict) -> tuple[dict, int]:
    """One periodic stream: its accepted packets' `times`, with the predecessor's last packet
    `before` them (a restart on a new port) and the capture's `end` (None: taken over)."""
    vrpi = ptype == C.PacketType.VRPI.value
    stream = times if before is None else np.concatenate(([before], times))
    after = frames[1:] if before is None else frames      # the packet after each interval
    gaps = timing.intervals_ms(stream)
    limit = opt.vrpi_watchdog_ms if vrpi else opt.vrpo_watchdog_ms
    over = np.flatnonzero(gaps > limit)
    violations = [{"start": float(stream[i]), "gap_ms": float(gaps[i]), "until_end": False, "frame": int(after[i])}
                  for i in over]
    if end is not None and (end - float(times[-1])) * timing.MS > limit:
        violations.append({"start": float(times[-1]), "gap_ms": (end - float(times[-1])) * timing.MS,
                           "until_end": True, "frame": int(frames[-1])})
    where = findings.Where(located)
    for v in violations:
        where.add("watchdog", v["frame"], v["start"], snd.id, type=ptype, gap_ms=v["gap_ms"],
                  until_end=v["until_end"])
    for i in np.flatnonzero(gaps < 0).tolist():
        where.add("time_backwards", int(after[i]), float(stream[i + 1]), snd.id, type=ptype)
    row = {
        "type": ptype, "sender": snd.id, "count": len(times),
        "interval_ms": timing.summary(gaps),
        "nominal_ms": opt.vrpi_period_ms if vrpi else None,
        "jitter_ms": timing.jitter_ms(stream, opt.vrpi_period_ms) if vrpi else None,
        "watchdog": {"limit_ms": limit, "violations": violations},
        "time_backwards": int(np.count_nonzero(gaps < 0)),
    }
    row["plot"] = _plot(stream, gaps)
    return row, row["time_backwards"]


def _bursts(snd: Sender, vrpo: np.ndarray, opt: Options, periodic: list, located: dict) -> dict:
    times, frames = snd.ts[vrpo], snd.frame[vrpo]
    complete, incomplete, firsts = bursts.count(times, snd.aux[vrpo], snd.size[vrpo], opt.burst_gap_ms,
                                                opt.vrpo_start, opt.vrpo_data_size)
    # Period, jitter and the 50-200 ms recommendation apply to bursts: split packets go back to back.
    starts = times[firsts]
    between = timing.intervals_ms(starts)
    ordered = np.sort(between)
    period = opt.vrpo_period_ms or (round(timing.percentile(ordered, 50.0)) if len(ordered) else None)
    row = next(p for p in periodic if p["type"] == C.PacketType.VRPO.value and p["sender"] == snd.id)
    row["nominal_ms"] = period
    row["jitter_ms"] = timing.jitter_ms(starts, period) if period else timing.jitter_ms([], 1.0)
    row["bursts"] = len(starts)
    row["burst_interval_ms"] = timing.summary(between)
    outside = np.flatnonzero((between < opt.vrpo_min_ms) | (between > opt.vrpo_max_ms))
    row["outside_recommended"] = {"low_ms": opt.vrpo_min_ms, "high_ms": opt.vrpo_max_ms, "count": len(outside)}
    where = findings.Where(located)
    for i in incomplete:
        where.add("vrpo_incomplete", int(frames[i]), float(times[i]), snd.id)
    for k in outside.tolist():
        i = int(firsts[k + 1])
        where.add("vrpo_outside_recommended", int(frames[i]), float(times[i]), snd.id, interval_ms=float(between[k]))
    return {"sender": snd.id, "complete": complete, "incomplete": len(incomplete)}


def _plot(times: np.ndarray, gaps: np.ndarray) -> dict:
    """Histogram of intervals (the last bin holds everything above p99.9) and a down-sampled
    interval-over-time series (the largest interval of each bucket, so no watchdog gap hides)."""
    finite = np.isfinite(gaps)
    if not finite.all():                       # damaged timestamps: plot what can be plotted
        times, gaps = times[1:][finite], gaps[finite]
        times = np.concatenate(([times[0] if len(times) else 0.0], times))
    if not len(gaps):
        return {"histogram": [], "bin_ms": None, "series": []}
    ordered = np.sort(gaps)
    low, high = float(ordered[0]), timing.percentile(ordered, 99.9)
    high = max(high, low + 1e-3)
    width = (high - low) / HISTOGRAM_BINS
    bins = np.clip(np.nan_to_num((gaps - low) / width), 0, HISTOGRAM_BINS).astype(np.int64)
    counts = np.bincount(bins, minlength=HISTOGRAM_BINS + 1)
    hist = [[low + i * width, int(c)] for i, c in enumerate(counts)]
    step = max(1, math.ceil(len(gaps) / SERIES_POINTS))
    series = [[float(times[i + 1]), float(gaps[i:i + step].max())] for i in range(0, len(gaps), step)]
    return {"histogram": hist, "bin_ms": width, "series": series}


