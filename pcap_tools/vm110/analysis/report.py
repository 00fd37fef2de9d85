"""From `Collected` to the report dictionary (the JSON report, docs/report.md) and its verdict."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from .. import __version__
from .. import constants as C
from . import bursts, commands, serials, state, timing
from .report_json import normalise
from .collect import CODE, TYPES, VRPI_CODE, VRPO_CODE, Collected, Sender

SCHEMA_VERSION = 1
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
    burst_gap_ms: float = C.VRPO_BURST_GAP_MS
    vrpo_start: int = 0
    vrpo_data_size: int = 0


def build(got: Collected, opt: Options) -> dict:
    """The whole report of one capture."""
    # Damaged timestamps can make inf and nan on the way; the report shows them as null.
    with np.errstate(all="ignore"):
        return _build(got, opt)


def _build(got: Collected, opt: Options) -> dict:
    sender_reports, periodic, events, burst_rows, states = [], [], [], [], []
    backwards = 0
    for snd in got.take_senders():
        res, scope = _serials(snd, opt.serial_scope)
        dup = res.duplicate_index
        sender_reports.append(_sender_report(snd, res, scope))
        for code in (VRPI_CODE, VRPO_CODE):
            mask = snd.code == code
            if not mask.any():
                continue
            times = snd.ts[mask]              # duplicates are legal packets too: they count here
            row, back = _periodic(TYPES[code].value, snd, times, opt)
            backwards += back
            periodic.append(row)
        live = np.ones(len(snd.code), dtype=bool)     # duplicates are neither commands nor burst parts
        if dup:
            live[dup] = False
        rows = np.flatnonzero(live & np.isin(snd.code, COMMAND_CODES))
        name = snd.id
        events += zip(snd.frame[rows].tolist(), snd.ts[rows].tolist(), snd.code[rows].tolist(),
                      [name] * len(rows), snd.aux[rows].tolist())
        vrpo = live & (snd.code == VRPO_CODE)
        if vrpo.any():
            burst_rows.append(_bursts(snd, snd.ts[vrpo], snd.aux[vrpo], snd.size[vrpo], opt, periodic))
        vrpi = snd.code == VRPI_CODE
        if vrpi.any():
            states.append({"sender": snd.id, **state.timeline(snd.ts[vrpi], snd.state[vrpi], snd.frame[vrpi],
                                                              got.last_ts)})
    periodic.sort(key=lambda p: (p["type"], p["sender"]))
    events.sort()
    tallies = commands.track(events)
    cmd = {t.value: commands.report(tallies[CODE[t]], opt.vrci_fail_ms if t is C.PacketType.VRCI else None,
                                    opt.resend_ms)
           for t in commands.COMMAND_TYPES}
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
    report = normalise(report)
    report["totals"] = totals(report)
    report["verdict"] = verdict(report)
    return report


def _serials(snd: Sender, scope: str) -> tuple[serials.SerialResult, str]:
    codes = snd.code
    by_sender = serials.classify_sender(snd.serial, snd.ts, codes, "sender")
    if scope == "sender" or (scope == "auto" and (by_sender.anomalies == 0 or len(np.unique(codes)) < 2)):
        return by_sender, "sender"
    if scope == "type":
        return serials.classify_sender(snd.serial, snd.ts, codes, "type"), "type"
    # Per-type numbering must explain the capture clearly better: with one counter per sender,
    # a type's stream can look clean only by accident (say, a loss just before its first packet).
    by_type = serials.classify_sender(snd.serial, snd.ts, codes, "type", limit=by_sender.anomalies // 2)
    if not by_type.aborted and 2 * by_type.anomalies + TYPE_SCOPE_MARGIN <= by_sender.anomalies:
        return by_type, "type"
    return by_sender, "sender"


def _sender_report(snd: Sender, res: serials.SerialResult, scope: str) -> dict:
    counts = dict(enumerate(np.bincount(snd.code, minlength=len(TYPES)).tolist()))
    counts = {c: n for c, n in counts.items() if n}
    return {
        "id": snd.id, "direction": snd.direction, "origin": snd.origin, "src": snd.src,
        "by_type": {TYPES[c].value: counts[c] for c in sorted(counts, key=lambda c: TYPES[c].value)},
        "serial": {
            "scope": scope, "received": res.received, "lost": res.lost, "duplicates": res.duplicates,
            "out_of_order": res.out_of_order, "wraps": res.wraps, "lost_serials": res.lost_serials,
            "duplicate_serials": res.duplicate_serials, "out_of_order_serials": res.out_of_order_serials,
            "gaps": [{"after": a, "count": n, "time": t} for a, n, t in res.gaps],
        },
    }


def _periodic(ptype: str, snd: Sender, times: list, opt: Options) -> tuple[dict, int]:
    vrpi = ptype == C.PacketType.VRPI.value
    gaps = timing.intervals_ms(times)
    limit = opt.vrpi_watchdog_ms if vrpi else opt.vrpo_watchdog_ms
    row = {
        "type": ptype, "sender": snd.id, "count": len(times),
        "interval_ms": timing.summary(gaps),
        "nominal_ms": opt.vrpi_period_ms if vrpi else None,
        "jitter_ms": timing.jitter_ms(times, opt.vrpi_period_ms) if vrpi else None,
        "watchdog": {"limit_ms": limit, "violations": timing.violations(times, gaps, limit)},
        "time_backwards": int(np.count_nonzero(gaps < 0)),
    }
    row["plot"] = _plot(times, gaps)
    return row, row["time_backwards"]


def _bursts(snd: Sender, times: np.ndarray, numbers: np.ndarray, sizes: np.ndarray, opt: Options,
            periodic: list) -> dict:
    complete, incomplete, starts = bursts.count(times, numbers, sizes, opt.burst_gap_ms, opt.vrpo_start,
                                                opt.vrpo_data_size)
    # Period, jitter and the 50-200 ms recommendation apply to bursts: split packets go back to back.
    between = timing.intervals_ms(starts)
    ordered = np.sort(between)
    period = opt.vrpo_period_ms or (round(timing.percentile(ordered, 50.0)) if len(ordered) else None)
    row = next(p for p in periodic if p["type"] == C.PacketType.VRPO.value and p["sender"] == snd.id)
    row["nominal_ms"] = period
    row["jitter_ms"] = timing.jitter_ms(starts, period) if period else timing.jitter_ms([], 1.0)
    row["bursts"] = len(starts)
    row["burst_interval_ms"] = timing.summary(between)
    row["outside_recommended"] = {"low_ms": opt.vrpo_min_ms, "high_ms": opt.vrpo_max_ms,
                                  "count": timing.outside(between, opt.vrpo_min_ms, opt.vrpo_max_ms)}
    return {"sender": snd.id, "complete": complete, "incomplete": incomplete}


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


def totals(report: dict) -> dict:
    """The numbers `--fail-on` rules refer to."""
    senders, periodic, cmds = report["senders"], report["periodic"], report["commands"]
    jitters = [p["jitter_ms"]["max"] for p in periodic if p["jitter_ms"] and p["jitter_ms"]["max"] is not None]
    maxes = [p["interval_ms"]["max"] for p in periodic if p["interval_ms"]["max"] is not None]
    lat = [c["ack_latency_ms"]["max"] for c in cmds.values() if c["ack_latency_ms"]["max"] is not None]
    return {
        "packets": report["capture"]["packets"],
        "eglink_packets": report["capture"]["eglink_packets"],
        "lost": sum(s["serial"]["lost"] for s in senders),
        "duplicates": sum(s["serial"]["duplicates"] for s in senders),
        "out_of_order": sum(s["serial"]["out_of_order"] for s in senders),
        "illegal": report["illegal"]["total"],
        "crc_invalid": report["crc"]["invalid"],
        "watchdog": sum(len(p["watchdog"]["violations"]) for p in periodic),
        "vrpo_outside_recommended": sum(p.get("outside_recommended", {}).get("count", 0) for p in periodic),
        "commands": sum(c["commands"] for c in cmds.values()),
        "retransmissions": sum(c["retransmissions"] for c in cmds.values()),
        "unacked": sum(c["unacked"] for c in cmds.values()),
        "failed": sum(c["failed"] for c in cmds.values()),
        "spurious": sum(c["spurious_retransmissions"] for c in cmds.values()),
        "acks_without_command": sum(c["acks_without_command"] for c in cmds.values()),
        "duplicate_acks": sum(c["duplicate_acks"] for c in cmds.values()),
        "relays_open": sum(len(s["episodes_relays_open"]) for s in report["state"]),
        "vrpo_incomplete": report["vrpo_bursts"]["incomplete"],
        "time_backwards": report["capture"]["time_backwards"],
        "snaplen_truncated": report["capture"]["snaplen_truncated"],
        "jitter_max_ms": max(jitters) if jitters else 0.0,
        "interval_max_ms": max(maxes) if maxes else 0.0,
        "ack_latency_max_ms": max(lat) if lat else 0.0,
    }


TOTAL_NAMES = ("packets", "eglink_packets", "lost", "duplicates", "out_of_order", "illegal", "crc_invalid",
               "watchdog", "vrpo_outside_recommended", "commands", "retransmissions", "unacked", "failed",
               "spurious", "acks_without_command", "duplicate_acks", "relays_open", "vrpo_incomplete",
               "time_backwards", "snaplen_truncated", "jitter_max_ms", "interval_max_ms", "ack_latency_max_ms")
MAX_TOTALS = frozenset({"jitter_max_ms", "interval_max_ms", "ack_latency_max_ms"})   # combined by max, not sum

# (total, severity, message) for each finding the verdict reports when its total is above 0.
FINDINGS = (
    ("lost", "error", "packets lost (serial gaps)"),
    ("illegal", "error", "illegal packets"),
    ("watchdog", "error", "watchdog violations"),
    ("failed", "error", "VRCI commands failed (no VRAO within the limit)"),
    ("unacked", "error", "commands never acknowledged"),
    ("relays_open", "warning", "episodes with the ES-Link relays open"),
    ("duplicates", "warning", "duplicated packets"),
    ("out_of_order", "warning", "packets out of order"),
    ("spurious", "warning", "retransmissions after the acknowledgement"),
    ("acks_without_command", "warning", "acknowledgements without a command"),
    ("duplicate_acks", "warning", "duplicate acknowledgements"),
    ("vrpo_incomplete", "warning", "incomplete VRPO bursts"),
    ("vrpo_outside_recommended", "warning", "VRPO intervals outside the recommended range"),
    ("time_backwards", "warning", "timestamps going backwards"),
    ("snaplen_truncated", "warning", "datagrams cut short by the capture's snaplen"),
)


def verdict(report: dict) -> dict:
    tot = report["totals"]
    findings = [{"rule": key, "severity": sev, "count": tot[key], "message": f"{tot[key]} {msg}"}
                for key, sev, msg in FINDINGS if tot[key] > 0]
    if report["capture"]["problem"]:
        findings.insert(0, {"rule": "capture", "severity": "error", "count": 1,
                            "message": report["capture"]["problem"]})
    if not report["capture"]["eglink_packets"]:
        findings.insert(0, {"rule": "no_eglink", "severity": "warning", "count": 0,
                            "message": "no EG-Link packets in the capture"})
    return {"ok": not any(f["severity"] == "error" for f in findings), "findings": findings}
