"""From the analysis state (`Collected` and its `Analysis`) to the report dictionary (the JSON
report, docs/report.md) and its verdict."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from .. import __version__
from .. import constants as C
from .. import crc
from ..printable import unicode_text
from . import commands, findings, serials, timing
from .collect import CODE, TYPES, VRPO_CODE, Collected
from .report_json import normalise
from .bursts import Bursts
from .sender import Sender

SCHEMA_VERSION = 6
SCOPES = ("auto", "sender", "type")


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


def build(got: Collected) -> dict:
    """The whole report of one capture, from what its engine read and analysed."""
    # Damaged timestamps can make inf and nan on the way; the report shows them as null.
    with np.errstate(all="ignore"):
        return _build(got)


def _build(got: Collected) -> dict:
    analysis = got.analysis
    analysis.finish()
    opt = analysis.opt
    order = sorted(analysis.senders, key=lambda k: analysis.senders[k].id)
    sender_reports, periodic, burst_rows, states = [], [], [], []
    located: findings.Located = {}
    where = findings.Where(located)
    for key in order:
        snd = analysis.sender(key, keep=False)      # (one in the monitor's file: a copy, one at a time)
        sender_reports.append(_sender_report(snd, where))
        end = None if snd.taken_over else got.last_ts
        for code, stream in sorted(snd.streams.items()):
            row, backwards = stream.row(snd.before.get(code), end, opt.vrpi_period_ms if code != VRPO_CODE else None)
            for v in row["watchdog"]["violations"]:
                where.add("watchdog", v["frame"], v["start"], snd.id, type=stream.ptype, gap_ms=v["gap_ms"],
                          until_end=v["until_end"])
            for frame, t in backwards:
                where.add("time_backwards", frame, t, snd.id, type=stream.ptype)
            if code == VRPO_CODE and snd.bursts is not None:     # always: the VRPO stream comes with them
                burst_rows.append(_bursts(snd, snd.bursts, row, opt, where))
            periodic.append(row)
        if snd.timeline is not None:
            states.append({"sender": snd.id, **snd.timeline.report(got.last_ts)})
    periodic.sort(key=lambda p: (p["type"], p["sender"]))
    tallies = analysis.tracker.tallies
    fail = analysis.tracker.fail_ms
    # A command has failed once the capture went on past its limit, on the analysis clock that its
    # times run on: after a step back of the clock (appended captures) the last record is earlier.
    cmd_end = None if got.last_ts is None else max(got.last_ts, analysis.clock)
    cmd = {t.value: commands.report(tallies[CODE[t]], fail[CODE[t]], opt.resend_ms, cmd_end)
           for t in commands.COMMAND_TYPES}
    invalid = got.illegal_reasons[C.Problem.BAD_CRC.value]
    stepped_back = sum(p["time_backwards"] for p in periodic)
    report = {
        "schema_version": SCHEMA_VERSION,
        "tool": {"name": "vm110", "version": __version__, "engine": got.engine},
        "capture": {
            "file": unicode_text(got.path), "format": got.format or None, "link_types": got.link_types,
            "packets": got.frames, "udp_packets": got.udp, "eglink_packets": got.eglink,
            "other_udp_packets": got.other_udp, "non_udp_packets": got.non_udp,
            "fragments": got.fragments, "unread_frames": got.unread,
            "tunnelled_frames": got.tunnelled, "snaplen_truncated": got.snap_truncated,
            "first_time": got.first_ts, "last_time": got.last_ts,
            # From the earliest record to the latest, as capinfos gives it: the last record need not
            # be the latest (appended captures, a clock set back), and a span is never negative.
            "duration_s": got.latest_ts - got.earliest_ts if got.earliest_ts <= got.latest_ts else 0.0,
            "earliest_time": got.earliest_ts if got.earliest_ts <= got.latest_ts else None,
            "latest_time": got.latest_ts if got.earliest_ts <= got.latest_ts else None,
            "time_backwards": stepped_back, "behind_clock": analysis.behind,
            "problem": got.problem, "ports": list(got.ports), "dropped": got.dropped,
            "damage": None if got.problem is None else {"offset": got.damage, "message": got.problem},
        },
        "crc": {"variant": got.crc_variant, "byte_order": got.crc_order, "auto": got.crc_auto,
                "valid": got.eglink - invalid, "invalid": invalid, "unchecked": got.eglink - got.crc_checked,
                "candidates": {f"{v}/{o}": n for (v, o), n in sorted(got.crc_counts.items()) if n}},
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
    report["verdict"] = normalise(findings.verdict(report, located, *wireshark_prefs(report, opt)))
    return report


# The options that decide what the rule filters show, each a dissector preference of the same name
# but vrpo_start (the periods set only the nominal of the jitter figures).
_PREFS = ("vrpi_watchdog_ms", "vrpo_watchdog_ms", "vrpo_min_ms", "vrpo_max_ms", "resend_ms", "vrci_fail_ms",
          "vrco_give_up_ms", "reuse_gap_ms", "dup_window_ms", "burst_gap_ms", "vrpo_start", "vrpo_data_size")
_PREF_NAMES = {"vrpo_start": "vrpo_number_start"}


def wireshark_prefs(report: dict, opt: Options) -> tuple[Optional[list[str]], Optional[str]]:
    """The dissector's preferences (`-o` values, `vm110.NAME:VALUE`) under which Wireshark judges
    the capture as the report did, those not at their defaults; None when no preferences do, and
    why: some senders' serials counted per sender and others' per type, or a time of a fraction
    of a millisecond (the preferences are whole milliseconds). A sender of one packet type has one
    counter under either scope: its scope does not decide the preference."""
    scopes = {s["serial"]["scope"] for s in report["senders"] if len(s["by_type"]) > 1}
    if len(scopes) > 1:
        return None, ("some senders' serials are counted per sender and others' per type, and the dissector's "
                      "vm110.serial_scope is one for all (--serial-scope sender or type gives the filters)")
    prefs = ["vm110.serial_scope:type"] if scopes == {"type"} else []
    if report["capture"]["ports"][0] != C.INPUT_PORT:
        prefs.append(f"vm110.input_port:{report['capture']['ports'][0]}")
    variant, order = report["crc"]["variant"], report["crc"]["byte_order"]
    if variant is not None and variant != crc.DEFAULT_VARIANT:
        prefs.append(f"vm110.crc_variant:{variant}")
    if order is not None and order != crc.DEFAULT_BYTE_ORDER:
        prefs.append(f"vm110.crc_byte_order:{order}")
    default = Options()
    for name in _PREFS:
        value = getattr(opt, name)
        if value == getattr(default, name):
            continue
        pref = f"vm110.{_PREF_NAMES.get(name, name)}"
        if value != int(value):
            return None, f"{name} is {value:g}, and the dissector's {pref} takes whole milliseconds"
        prefs.append(f"{pref}:{int(value)}")
    return prefs, None


def _sender_report(snd: Sender, where: findings.Where) -> dict:
    res = snd.serial_result()
    counts = {c: int(n) for c, n in enumerate(snd.counts.tolist()) if n}
    name = snd.id
    # Times as Wireshark shows the frames (the rules judged them on the analysis clock).
    restarts = [{"time": res.time_of(f, t), "frame": int(f), "from": a, "to": b} for f, a, b, t in res.restarts]
    if snd.link is not None:
        restarts.insert(0, snd.link)
    # A gap's serials that came late are out of order, not lost: the `lost` items add up to `lost`.
    gaps = [{"after": a, "count": n, "time": res.time_of(f, t), "frame": int(f),
             **({"late": res.gap_late[f]} if f in res.gap_late else {})} for a, n, t, f in res.gaps]
    for g in gaps:
        what = serials.gap_lost(g["after"], g["count"], g.get("late", 0))
        if what is not None:
            where.add("lost", g["frame"], g["time"], name, **what)
    for rule, located, count in (("duplicates", res.duplicates_located, res.duplicates),
                                 ("out_of_order", res.out_of_order_located, res.out_of_order)):
        for f, t, s in located:                             # the first few (serials.LOCATED) ...
            where.add(rule, int(f), res.time_of(f, t), name, serial=s)
        where.skip(rule, count - len(located))             # ... and how many more
    for r in restarts:
        where.add("restarts", r["frame"], r["time"], name, **{k: v for k, v in r.items() if k not in ("frame", "time")})
    return {
        "id": name, "direction": snd.direction, "origin": snd.origin, "src": snd.src,
        "by_type": {TYPES[c].value: counts[c] for c in sorted(counts, key=lambda c: TYPES[c].value)},
        "serial": {
            "scope": snd.scope, "scope_reason": snd.scope_reason,
            "received": res.received, "lost": res.lost, "duplicates": res.duplicates,
            "out_of_order": res.out_of_order, "wraps": res.wraps, "restarts": len(restarts),
            "lost_serials": res.lost_serials, "duplicate_serials": res.duplicate_serials,
            "out_of_order_serials": res.out_of_order_serials, "gaps": gaps, "restart_events": restarts,
        },
    }


def _bursts(snd: Sender, b: Bursts, row: dict, opt: Options, where: findings.Where) -> dict:
    """Period, jitter and the 50-200 ms recommendation of VRPO apply to bursts: split packets go
    back to back. Completes the sender's VRPO `row`; returns its `vrpo_bursts.per_sender` row."""
    starts = b.starts
    between = starts.intervals_ms()
    ordered = np.sort(between)
    median = timing.percentile(ordered, 50.0)      # None when there are no intervals
    period = opt.vrpo_period_ms or (round(median) if median is not None else None)
    spread = timing.summary_sorted(ordered)
    del ordered                              # before the jitter's series: one copy at a time
    row["nominal_ms"] = period
    row["jitter_ms"] = timing.jitter_summary(between, period)
    row["bursts"] = len(starts)
    row["burst_interval_ms"] = spread
    row["outside_recommended"] = {"low_ms": opt.vrpo_min_ms, "high_ms": opt.vrpo_max_ms, "count": len(b.outside)}
    for frame, t in b.incomplete:
        where.add("vrpo_incomplete", frame, t, snd.id)
    for frame, t, interval in b.outside:
        where.add("vrpo_outside_recommended", frame, t, snd.id, interval_ms=interval)
    return {"sender": snd.id, "complete": b.complete, "incomplete": len(b.incomplete)}
