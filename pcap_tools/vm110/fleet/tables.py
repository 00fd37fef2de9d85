"""The dataset's tables, as rows made from one capture's analysis report (docs/report.md).

Every row starts with the capture's id and file; the capture's metadata columns are added to
every table. Columns named after the report's `totals` follow `TOTAL_NAMES`, the list `--fail-on`
uses, so that a total added to the report is a column here too.
"""
from __future__ import annotations

import hashlib
import json
from typing import Any, Iterable, Optional

import pyarrow as pa

from ..analysis.findings import TOTAL_NAMES

TABLES = ("captures", "senders", "streams", "commands", "findings", "errors", "packets")
TYPES = ("VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO")
FLOAT_TOTALS = frozenset(name for name in TOTAL_NAMES if name.endswith("_ms"))

_KEY = [("capture_id", pa.string()), ("file", pa.string())]
_TS = pa.timestamp("us")       # UTC (no zone in the column: readers need no time zone data)
_MAX_S = 9.2e12                 # seconds a column of int64 microseconds holds (about 290,000 years)
SCHEMAS: dict[str, pa.Schema] = {
    "captures": pa.schema(_KEY + [
        ("size", pa.int64()), ("sha256", pa.string()), ("status", pa.string()), ("format", pa.string()),
        ("first_time", _TS), ("last_time", _TS), ("duration_s", pa.float64()), ("verdict_ok", pa.bool_()),
        ("problem", pa.string()), ("damage_offset", pa.int64()), ("crc_variant", pa.string()),
        ("crc_byte_order", pa.string()), ("findings", pa.int64()), ("tool_version", pa.string())]
        + [(name, pa.float64() if name in FLOAT_TOTALS else pa.int64()) for name in TOTAL_NAMES]),
    "senders": pa.schema(_KEY + [
        ("sender", pa.string()), ("direction", pa.string()), ("origin", pa.int64()), ("src", pa.string()),
        ("serial_scope", pa.string()), ("received", pa.int64()), ("lost", pa.int64()), ("duplicates", pa.int64()),
        ("out_of_order", pa.int64()), ("wraps", pa.int64()), ("restarts", pa.int64())]
        + [(t, pa.int64()) for t in TYPES]),
    "streams": pa.schema(_KEY + [
        ("sender", pa.string()), ("type", pa.string()), ("count", pa.int64()), ("nominal_ms", pa.float64())]
        + [(f"interval_{q}_ms", pa.float64()) for q in ("min", "mean", "p50", "p95", "p99", "p999", "max")]
        + [(f"jitter_{q}_ms", pa.float64()) for q in ("final", "mean", "max")]
        + [("watchdog_limit_ms", pa.float64()), ("watchdog_violations", pa.int64()),
           ("watchdog_until_end", pa.int64()), ("watchdog_max_gap_ms", pa.float64()),
           ("time_backwards", pa.int64()), ("bursts", pa.int64()), ("outside_recommended", pa.int64())]),
    "commands": pa.schema(_KEY + [
        ("type", pa.string()), ("sender", pa.string()), ("command_id", pa.int64()), ("time", _TS),
        ("first_frame", pa.int64()), ("transmissions", pa.int64()), ("retransmissions", pa.int64()),
        ("acked", pa.bool_()), ("ack_frame", pa.int64()), ("latency_first_ms", pa.float64()),
        ("latency_last_ms", pa.float64()), ("spurious", pa.int64()), ("interrupted_frame", pa.int64()),
        ("failed", pa.bool_()), ("fail_limit_ms", pa.float64())]),
    "findings": pa.schema(_KEY + [
        ("rule", pa.string()), ("severity", pa.string()), ("message", pa.string()), ("count", pa.int64()),
        ("item", pa.int64()), ("frame", pa.int64()), ("frames", pa.list_(pa.int64())), ("time", _TS),
        ("sender", pa.string()), ("type", pa.string()), ("command_id", pa.int64()), ("filter", pa.string()),
        ("details", pa.string()), ("more", pa.int64())]),
    "errors": pa.schema(_KEY + [("kind", pa.string()), ("message", pa.string()), ("file_offset", pa.int64())]),
    "packets": pa.schema(_KEY + [
        ("frame", pa.int64()), ("time", _TS), ("src", pa.string()), ("sport", pa.int64()), ("dport", pa.int64()),
        ("type", pa.string()), ("origin", pa.int64()), ("serial", pa.int64()), ("size", pa.int64()),
        ("command_id", pa.int64()), ("legal", pa.bool_()), ("problems", pa.string())]),
}
# Names the tables' columns (a total added to the report adds one): the manifest gives it with
# each capture, so that the parts of one set of columns are read together, and parts an older
# vm110 wrote (no mark) by name.
SCHEMA_ID = hashlib.sha256(repr([(t, [(f.name, str(f.type)) for f in s]) for t, s in SCHEMAS.items()]).encode()
                           ).hexdigest()[:12]
COLUMNS = frozenset(f.name for schema in SCHEMAS.values() for f in schema)     # no metadata field may take one
# Item keys that have a column of their own in `findings`; the rest go to `details` (JSON).
_ITEM_COLUMNS = ("frame", "frames", "time", "sender", "type", "command_id", "filter")


def _time(seconds: Optional[float]) -> Optional[int]:
    """Capture seconds to the microseconds of a timestamp column; None (null) for a time the column
    cannot hold (a hostile capture's timestamps beyond its range)."""
    if seconds is None or not -_MAX_S < seconds < _MAX_S:
        return None
    return round(seconds * 1_000_000)


def capture_rows(report: dict, capture_id: str, size: Optional[int], sha256: Optional[str]) -> dict[str, list[dict]]:
    """Every table's rows for one analysed capture."""
    cap, totals = report["capture"], report["totals"]
    key = {"capture_id": capture_id, "file": cap["file"]}
    findings_list = report["verdict"]["findings"]
    captures = [{**key, "size": size, "sha256": sha256, "status": "ok" if cap["problem"] is None else "damaged",
                 "format": cap["format"], "first_time": _time(cap["first_time"]), "last_time": _time(cap["last_time"]),
                 "duration_s": cap["duration_s"], "verdict_ok": report["verdict"]["ok"], "problem": cap["problem"],
                 "damage_offset": (cap["damage"] or {}).get("offset"), "crc_variant": report["crc"]["variant"],
                 "crc_byte_order": report["crc"]["byte_order"], "findings": len(findings_list),
                 "tool_version": report["tool"]["version"], **{name: totals.get(name) for name in TOTAL_NAMES}}]
    senders = [{**key, "sender": s["id"], "direction": s["direction"], "origin": s["origin"], "src": s["src"],
                "serial_scope": s["serial"]["scope"],
                **{k: s["serial"][k] for k in ("received", "lost", "duplicates", "out_of_order", "wraps", "restarts")},
                **{t: s["by_type"].get(t, 0) for t in TYPES}} for s in report["senders"]]
    streams = [_stream_row(key, p) for p in report["periodic"]]
    commands = []
    for ctype, block in sorted(report["commands"].items()):
        limit = block["fail_limit_ms"]
        for c in block["list"]:
            acked = c["ack_frame"] is not None
            commands.append({
                **key, "type": ctype, "sender": c["sender"], "command_id": c["command_id"], "time": _time(c["time"]),
                "first_frame": c["frames"][0] if c["frames"] else None, "transmissions": len(c["frames"]),
                "retransmissions": c["retransmissions"], "acked": acked, "ack_frame": c["ack_frame"],
                "latency_first_ms": c["latency_first_ms"], "latency_last_ms": c["latency_last_ms"],
                "spurious": c["spurious"], "interrupted_frame": c["interrupted_frame"],
                "failed": c["failed"], "fail_limit_ms": limit})
    findings = []
    for f in findings_list:
        head = {**key, "rule": f["rule"], "severity": f["severity"], "message": f["message"], "count": f["count"],
                "more": f.get("more", 0)}
        items = f.get("items") or [None]
        for n, item in enumerate(items):
            findings.append({**head, **_item_columns(item), "item": None if item is None else n})
    errors = []
    if cap["problem"] is not None:
        errors.append({**key, "kind": "damaged", "message": cap["problem"],
                       "file_offset": (cap["damage"] or {}).get("offset")})
    return {"captures": captures, "senders": senders, "streams": streams, "commands": commands,
            "findings": findings, "errors": errors}


def error_rows(path: str, capture_id: str, size: Optional[int], sha256: Optional[str], message: str,
               kind: str = "unreadable") -> dict[str, list[dict]]:
    """The rows of a capture that could not be analysed: a `captures` row that says so (its
    counts null) and an `errors` row with the reason."""
    key = {"capture_id": capture_id, "file": path}
    return {"captures": [{**key, "size": size, "sha256": sha256, "status": kind}],
            "errors": [{**key, "kind": kind, "message": message, "file_offset": None}]}


def _stream_row(key: dict, p: dict) -> dict:
    iv, jit, wd = p.get("interval_ms") or {}, p.get("jitter_ms") or {}, p["watchdog"]
    gaps = [v["gap_ms"] for v in wd["violations"] if v.get("gap_ms") is not None]
    return {**key, "sender": p["sender"], "type": p["type"], "count": p["count"], "nominal_ms": p.get("nominal_ms"),
            **{f"interval_{q}_ms": iv.get(q) for q in ("min", "mean", "p50", "p95", "p99", "p999", "max")},
            **{f"jitter_{q}_ms": jit.get(q) for q in ("final", "mean", "max")},
            "watchdog_limit_ms": wd["limit_ms"], "watchdog_violations": len(wd["violations"]),
            "watchdog_until_end": sum(1 for v in wd["violations"] if v.get("until_end")),
            "watchdog_max_gap_ms": max(gaps) if gaps else None, "time_backwards": p.get("time_backwards"),
            "bursts": p.get("bursts"), "outside_recommended": (p.get("outside_recommended") or {}).get("count")}


def _item_columns(item: Optional[dict]) -> dict[str, Any]:
    if item is None:
        return dict.fromkeys(_ITEM_COLUMNS + ("details",))
    row: dict[str, Any] = {k: item.get(k) for k in _ITEM_COLUMNS}
    row["time"] = _time(row["time"])
    if row["sender"] is None:
        row["sender"] = item.get("src")          # an illegal packet's source
    rest = {k: v for k, v in item.items() if k not in _ITEM_COLUMNS}
    row["details"] = json.dumps(rest, sort_keys=True) if rest else None
    if not isinstance(row["type"], (str, type(None))):
        row["type"] = str(row["type"])
    if not isinstance(row["command_id"], (int, type(None))):
        row["command_id"] = None
    return row


def table_schema(name: str, meta: Iterable[str]) -> pa.Schema:
    """The schema of table `name` with the metadata columns (text) appended."""
    schema = SCHEMAS[name]
    for key in meta:
        schema = schema.append(pa.field(key, pa.string()))
    return schema


def arrow_table(name: str, rows: list[dict], meta: dict[str, Optional[str]]) -> pa.Table:
    """The rows of `name` with the metadata columns appended, as an Arrow table."""
    return pa.Table.from_pylist([{**row, **meta} for row in rows], schema=table_schema(name, meta))


def check_meta_keys(keys: set[str]) -> None:
    """A metadata field may not shadow a column of any table."""
    from ..errors import CliError
    clash = sorted(keys & COLUMNS)
    if clash:
        raise CliError(f"metadata field {clash[0]!r} is a column of the dataset already; rename it")
