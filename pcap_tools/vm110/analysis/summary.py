"""The terminal summary: verdict, then one table per sender, commands, bursts and relays.

Times: the capture's start and end in ISO 8601 UTC, everything else in seconds from its start
(the HTML report's tables use the same `since`)."""
from __future__ import annotations

from collections import Counter
from typing import Optional

from ..printable import escaped
from ..timefmt import since, stamp, utc_iso
from ..words import plural
from .findings import SEVERITIES


def _f(value: Optional[float], digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _table(rows: list[list[str]], indent: str = "  ") -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [indent + "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))
            for r in rows]


def open_gaps(gaps: list[dict]) -> int:
    """The gaps with serials still missing (those whose serials all came late lost nothing)."""
    return sum(g.get("late", 0) < g["count"] for g in gaps)


SHOWN_ITEMS = 3           # located items printed per finding without --list
# Every key an item may have besides where and when it lies (findings.located_item), in this order.
_ITEM_KEYS = ("sender", "type", "command_id", "serial", "after", "count", "late", "from", "to", "port_from",
              "port_to", "gap_ms", "until_end", "interval_ms", "latency_ms", "ack_frame", "command_frame", "reasons",
              "interrupted_frame", "duration_s", "states", "open_at_end", "offset")


def _value(value: object) -> str:
    """An item's value: its floats are seconds or milliseconds (duration_s, gap_ms, interval_ms),
    kept to 3 decimals as elsewhere in the summary (0.249991 s is 0.250, not 0.2); a list (reasons,
    states) as words, not Python's ['bad_crc']."""
    if isinstance(value, list):
        return "/".join(map(str, value))
    return _f(value, 3) if isinstance(value, float) else str(value)


def details(item: dict, skip: tuple[str, ...] = ()) -> str:
    """What an item of a finding says besides its frames and time, in words (the HTML's too)."""
    return ", ".join(f"{k} {_value(item[k])}" for k in _ITEM_KEYS
                     if k in item and k not in skip and item[k] is not None and item[k] is not False)


def _item(item: dict, t0: float) -> str:
    frames = item.get("frames", [item["frame"]])
    where = f"frame {frames[0]}" if len(frames) == 1 else f"frames {', '.join(map(str, frames[:8]))}" + (
        ", ..." if len(frames) > 8 else "")
    what = details(item)
    # A watchdog item names the packet that ended the silence, and the time the silence began.
    when = "ends a silence from" if item.get("until_end") is False else "at"
    return f"{where} {when} {since(item['time'], t0)} s: {what}  [{item['filter']}]"


def in_wireshark(verdict: dict) -> str:
    """Where a rule's filter shows all of its items: Wireshark, with the preferences the report
    judged by when they are not the defaults."""
    prefs = verdict.get("wireshark_prefs")
    return "all of them in Wireshark" + (f" (with {' '.join('-o ' + p for p in prefs)})" if prefs else "")


def _finding(f: dict, everything: bool, t0: float, wireshark: str) -> list[str]:
    items = f.get("items", [])
    shown = items if everything else items[:SHOWN_ITEMS]
    lines = [f"  {f['severity']:<7} {f['message']}"] + [f"            {_item(i, t0)}" for i in shown]
    more = f.get("more", 0)
    rest = len(items) - len(shown) + more
    if rest:
        where = []
        if len(shown) < len(items):
            where.append("--list, or the JSON report" + (f": the first {len(items)}" if more else ""))
        if f.get("filter"):
            where.append(f"{wireshark}: [{f['filter']}]")
        elif more and len(shown) == len(items):      # (else said with --list above)
            where.append(f"the report keeps the first {len(items)}")
        lines.append(f"            ... {rest} more" + (f" ({'; '.join(where)})" if where else ""))
    return lines


def time_range(cap: dict) -> str:
    """When the capture's records lie (`capture` of a report with a record): first to last, or,
    where they are not in time order, both and the span they cover."""
    first, last, earliest, latest = (cap[k] for k in ("first_time", "last_time", "earliest_time", "latest_time"))
    if (earliest, latest) == (first, last) or earliest is None:
        return f"{utc_iso(first)} to {utc_iso(last)} (UTC); times below in s from the start"
    return (f"first record {utc_iso(first)}, last {utc_iso(last)}: not in time order, they span "
            f"{utc_iso(earliest)} to {utc_iso(latest)} (UTC); times below in s from the first record")


def counted(findings: list[dict]) -> str:
    """`1 error, 0 warnings`, and the notes when there are any (they are no problem)."""
    n = Counter(f["severity"] for f in findings)
    return ", ".join(plural(n[sev], sev) for sev in SEVERITIES
                     if sev != "note" or n[sev])


def crc_words(crc: dict) -> str:
    """The CRC check in words: the variant, "(auto)" when the capture chose it, and the counts.
    Packets cut short (snaplen) carry no CRC, and count as valid (they do not fail it), which
    "all valid" alone would hide."""
    unchecked = f" ({crc['unchecked']} of them unchecked: too short to carry a CRC)" if crc["unchecked"] else ""
    return (f"CRC {crc['variant']}/{crc['byte_order']}{' (auto)' if crc['auto'] else ''}: "
            f"{crc['valid']} valid, {crc['invalid']} invalid{unchecked}")


def render(report: dict, everything: bool = False) -> str:
    """The summary; `everything`: the located items of each finding the report keeps, not just the first few."""
    cap, crc, verdict = report["capture"], report["crc"], report["verdict"]
    lines = [(f"{cap['file']}: {cap['packets']} packets, {cap['eglink_packets']} EG-Link, "
              f"{_f(cap['duration_s'])} s; {crc_words(crc)}")]
    t0 = cap["first_time"] or 0.0
    if cap["first_time"] is not None:
        lines.append(f"Time: {time_range(cap)}")
    lines.append(f"VERDICT: {'OK' if verdict['ok'] else 'FAIL'} ({counted(verdict['findings'])})")
    for f in verdict["findings"]:
        lines += _finding(f, everything, t0, in_wireshark(verdict))
    if verdict["findings"] and "no_filters" in verdict:
        lines.append(f"  No Wireshark filter for the rules: {verdict['no_filters']}")
    if report["illegal"]["total"]:
        reasons = ", ".join(f"{k} {v}" for k, v in report["illegal"]["by_reason"].items())
        lines.append(f"Illegal packets: {report['illegal']['total']} ({reasons})")
    periodic = {(p["sender"], p["type"]): p for p in report["periodic"]}
    for snd in report["senders"]:
        ser = snd["serial"]
        lines.append("")
        lines.append(f"Sender {snd['id']}  (serial scope {ser['scope']}: {ser['scope_reason']})")
        types = ", ".join(f"{t} {n}" for t, n in snd["by_type"].items())
        lines.append(f"  packets: {types}")
        gaps = plural(open_gaps(ser["gaps"]), "gap")
        lines.append(f"  serials: received {ser['received']}, lost {ser['lost']} in {gaps}, "
                     f"duplicates {ser['duplicates']}, out of order {ser['out_of_order']}, wraps {ser['wraps']}, "
                     f"restarts {ser['restarts']}")
        for r in ser["restart_events"]:
            port = f", port {r['port_from']} -> {r['port_to']}" if "port_from" in r else ""
            lines.append(f"  restart at {since(r['time'], t0)} s (frame {r['frame']}): "
                         f"serial {r['from']} -> {r['to']}{port}")
        rows = [["stream", "count", "min", "mean", "p50", "p95", "p99", "p99.9", "max", "jitter", "watchdog"]]
        for ptype in ("VRPI", "VRPO"):
            p = periodic.get((snd["id"], ptype))
            if not p:
                continue
            iv, jit = p["interval_ms"], p["jitter_ms"] or {}
            rows.append([f"{ptype} ms", str(p["count"]),
                         *(_f(iv[k]) for k in ("min", "mean", "p50", "p95", "p99", "p999", "max")),
                         _f(jit.get("max"), 2), f"{len(p['watchdog']['violations'])} > {p['watchdog']['limit_ms']:g}"])
        if len(rows) > 1:
            lines += _table(rows)
    lines.append("")
    # Two tables of the commands, each within 80 columns (one of 135 wrapped, its numbers under no heading).
    counts = [["commands", "cmds", "tx", "retx", "acked", "unacked", "interrupted", "failed", "spurious"]]
    acks = [["acks", "orphan acks", "dup acks", "lat p50 ms", "lat p95 ms", "lat max ms"]]
    for name, c in report["commands"].items():
        lat = c["ack_latency_ms"]
        counts.append([name, *(str(c[k]) for k in ("commands", "transmissions", "retransmissions", "acked", "unacked",
                                                   "interrupted", "failed", "spurious_retransmissions"))])
        acks.append([name, str(c["acks_without_command"]), str(c["duplicate_acks"]),
                     _f(lat["p50"]), _f(lat["p95"]), _f(lat["max"])])
    lines += _table(counts, "") + _table(acks, "")
    b = report["vrpo_bursts"]
    lines.append(f"VRPO bursts: {b['complete']} complete, {b['incomplete']} incomplete")
    for st in report["state"]:
        eps = st["episodes_relays_open"]
        if eps:
            lines.append(f"ES-Link relays open ({st['sender']}): " + "; ".join(
                f"{stamp(e['start'], t0)} for {_f(e['duration_s'], 3)} s {'/'.join(e['states'])}"
                + (", still open at the end" if e["open_at_end"] else "") for e in eps[:5])
                + (f" ... {len(eps)} in all" if len(eps) > 5 else ""))
    return "\n".join(map(escaped, lines))      # (packet IDs, file names: bytes from anywhere)


def render_combined(combined: dict) -> str:
    rows = [["capture", "verdict", "packets", "lost", "illegal", "watchdog", "unacked", "failed"]]
    for c in combined["captures"]:
        t = c["totals"]
        rows.append([c["file"], "OK" if c["ok"] else "FAIL", *(str(t[k]) for k in ("packets", "lost", "illegal",
                                                                                   "watchdog", "unacked", "failed"))])
    return "\n".join(map(escaped, [(f"Combined: {len(combined['captures'])} captures, "
                                    f"{'all OK' if combined['ok'] else 'FAIL'}"), *_table(rows)]))
