"""`vm110 fleet query`: DuckDB over a dataset, one view per table, and the named queries.

The views read exactly the parts the manifest lists. After they are made, DuckDB may read those
files and nothing else, and write nothing (`allowed_paths`, no external access, configuration
locked): a query cannot change the dataset or reach other files.
"""
from __future__ import annotations

import csv
import datetime as dt
import decimal
import io
import json
import math
import re
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import pyarrow as pa

from ..errors import CliError
from ..printable import escaped
from ..timefmt import datetime_iso
from .dataset import Dataset, view_files
from .tables import TABLES, table_schema

FORMATS = ("table", "csv", "json")
PERIODS = ("day", "week", "month")
METRICS = ("jitter", "loss", "latency", "watchdog", "findings")
WHO = ("site", "machine")               # metadata that names a machine, when the dataset has it
COLUMN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
MAX_SCHEMAS = 8                         # sets of metadata fields read apart; more: united file by file


@dataclass
class Result:
    columns: list[str]
    rows: list[tuple]


class Fleet:
    """A DuckDB connection with the dataset's tables as views."""

    def __init__(self, url: str) -> None:
        import duckdb
        self.duckdb = duckdb
        self.dataset = Dataset(url)
        self.manifest = self.dataset.read_manifest()
        self.meta_keys = sorted({k for e in self.manifest["captures"].values() for k in (e.get("meta") or {})})
        self.con = duckdb.connect(":memory:")
        if not self.dataset.local:
            self.con.register_filesystem(self.dataset.fs)
        try:
            self._views()
        except duckdb.Error as exc:     # a part damaged or gone since it was written
            self.con.close()
            raise self._damaged(str(exc)) from None

    def _damaged(self, error: str) -> CliError:
        first = error.splitlines()[0][:300]
        return CliError(f"{self.dataset.url}: the dataset cannot be read: {first} (build it again into a new folder)")

    def _views(self) -> None:
        """A view per table over its Parquet parts (the manifest's), locked to those files."""
        files = view_files(self.manifest, self.dataset)
        for table in TABLES:
            # One scan per group of parts of one schema, united by name (union_by_name over every
            # part read each file's schema at every query: seconds per thousand captures); with
            # many groups (sidecars of many kinds) the unions cost more than that. The parts of an
            # older vm110 (schema not known) are read by name: another group's columns may be
            # missing from some of them, and a scan takes its first file's columns.
            groups = sorted(files[table].items())
            if len(groups) > MAX_SCHEMAS:
                groups = [(("", ()), [f for _, paths in groups for f in paths])]
            scans = [f"SELECT * FROM read_parquet([{', '.join(_quote(f) for f in paths)}]"
                     f"{'' if schema else ', union_by_name = true'})" for (schema, _), paths in groups]
            # Every column of this vm110 and every metadata field, also where no part has it (an
            # older vm110's parts; `errors` of captures without a sidecar): NULL there.
            self.con.register(f"_empty_{table}", pa.Table.from_pylist([], schema=table_schema(table, self.meta_keys)))
            scans.append(f"SELECT * FROM _empty_{table}")
            self.con.execute(f"CREATE VIEW {table} AS {' UNION ALL BY NAME '.join(scans)}")
        every = [f for t in TABLES for paths in files[t].values() for f in paths]
        self.parts = frozenset(every)
        self.con.execute(f"SET allowed_paths = [{', '.join(_quote(f) for f in every)}]")
        self.con.execute("SET parquet_metadata_cache = true")     # (each query opens every part again)
        self.con.execute("SET enable_external_access = false")
        self.con.execute("SET lock_configuration = true")
        self.columns = {t: [r[0] for r in self.con.execute(f"DESCRIBE {t}").fetchall()] for t in TABLES}

    def run(self, sql: str) -> Result:
        """The result of `sql`; CliError (one line) when DuckDB refuses it."""
        try:
            cursor = self.con.execute(sql)
            if cursor is None:               # nothing but comments or semicolons
                raise CliError("query failed: the SQL has no statement")
            columns = [d[0] for d in cursor.description] if cursor.description else []
            return Result(columns, cursor.fetchall() if columns else [])
        except self.duckdb.Error as exc:
            # A part damaged since it was written is found when a query reads it: the dataset's
            # fault, not the query's.
            if any(path in str(exc) for path in self.parts):
                raise self._damaged(str(exc)) from None
            first = " ".join(str(exc).split("\n")[0].split())
            raise CliError(f"query failed: {first}") from None

    def in_memory(self, tables: Sequence[str]) -> None:
        """`tables` read once, into memory, for a caller that queries them many times (the report):
        a scan of a view opens every part, a cost that grows with the captures. For tables of a
        few rows per capture only (not commands, findings, packets: memory)."""
        for table in tables:
            self.run(f"CREATE TEMP TABLE _kept_{table} AS SELECT * FROM {table}")
            self.run(f"CREATE OR REPLACE VIEW {table} AS SELECT * FROM _kept_{table}")

    def who(self, table: str = "captures") -> list[str]:
        """The columns that name a machine: site and machine when the metadata has them, else the file."""
        got = [c for c in WHO if c in self.columns[table]]
        return got or ["file"]


@dataclass(frozen=True)
class Named:
    name: str
    help: str
    sql: Callable[[Fleet, "Args"], str]
    options: tuple[str, ...] = ()       # of --limit, --by, --month: those it takes (others are refused)
    sums: bool = False                  # adds up captures: two captures of one link at once count twice


@dataclass
class Args:
    limit: int = 20
    metric: str = "jitter"
    by: str = "week"
    month: Optional[str] = None

    @classmethod
    def given(cls, named: Named, metric: str, **options: Any) -> "Args":
        """The arguments of `named` from the options given (None: not given); CliError for one it
        does not take (`--worst links --month 2025-06` ranked over all months, saying nothing)."""
        for option, value in options.items():
            if value is not None and option not in named.options:
                takers = [n.name for n in NAMED.values() if option in n.options]
                raise CliError(f"--{option} does not apply to {named.name}; it goes with {', '.join(takers)}")
        return cls(metric=metric, **{k: v for k, v in options.items() if v is not None})


def _cols(prefix: str, cols: Sequence[str]) -> str:
    return ", ".join(f"{prefix}.{c}" for c in cols)


def machine_key(f: Fleet, table: str = "captures", alias: str = "") -> tuple[list[str], str]:
    """A machine's key columns, and the select list that gives them: site and machine when the
    metadata has them, and for a capture with neither its file (docs/fleet.md), so that captures
    without metadata are not one blank machine; else the file."""
    who, p = f.who(table), f"{alias}." if alias else ""
    if who == ["file"]:
        return who, f"{p}file"
    unnamed = " AND ".join(f"{p}{c} IS NULL" for c in who)
    return [*who, "file"], ", ".join(f"{p}{c}" for c in who) + f", CASE WHEN {unnamed} THEN {p}file END AS file"


def _same(left: str, right: str, keys: Sequence[str]) -> str:
    """Join condition on the machine's key: NULL (a metadata field a capture lacks) matches NULL."""
    return " AND ".join(f"{left}.{k} IS NOT DISTINCT FROM {right}.{k}" for k in keys)


# The packets a sender sent: each serial received once (`received` counts duplicates too: a
# mirror port that shows every packet twice would halve the loss share) and those lost.
def _sent(p: str = "") -> str:
    return f"sum({p}received) - sum({p}duplicates) + sum({p}lost)"


# A capture read whole or in part without one EG-Link packet (a dead link, the wrong interface):
# it says nothing of the link, good or bad, so the rankings list it apart rather than as failing.
_NO_EGLINK = "status <> 'unreadable' AND eglink_packets = 0"

# Both rankings count every capture of a machine (`captures`) and, of those, the ones that could
# not be read (`unreadable`: they give no link figures and count as failing, but are the machine's)
# and the ones without EG-Link traffic (`no_eglink`: no link figures, not failing).
_CAPTURE_COUNTS = ("count(*) AS captures, count(*) FILTER (WHERE status = 'unreadable') AS unreadable, "
                   f"count(*) FILTER (WHERE {_NO_EGLINK}) AS no_eglink")


def _worst_links(f: Fleet, a: Args) -> str:
    keys, w = machine_key(f)
    return f"""
WITH c AS (SELECT {w}, {_CAPTURE_COUNTS}, sum(capture_dropped) AS capture_dropped FROM captures GROUP BY ALL),
s AS (SELECT {w}, sum(lost) AS lost, {_sent()} AS sent, sum(restarts) AS restarts FROM senders GROUP BY ALL),
t AS (SELECT {w}, sum(watchdog_violations) AS watchdog,
             max(jitter_max_ms) FILTER (WHERE type = 'VRPI') AS vrpi_jitter_max_ms,
             max(jitter_max_ms) FILTER (WHERE type = 'VRPO') AS vrpo_jitter_max_ms FROM streams GROUP BY ALL)
SELECT {_cols('c', keys)}, c.captures, c.unreadable, c.no_eglink, coalesce(s.lost, 0) AS lost,
       round(100.0 * coalesce(s.lost, 0) / nullif(s.sent, 0), 3) AS loss_pct, c.capture_dropped,
       coalesce(t.watchdog, 0) AS watchdog, t.vrpi_jitter_max_ms, t.vrpo_jitter_max_ms,
       coalesce(s.restarts, 0) AS restarts
FROM c LEFT JOIN s ON {_same('c', 's', keys)} LEFT JOIN t ON {_same('c', 't', keys)}
ORDER BY loss_pct DESC NULLS LAST, watchdog DESC, greatest(t.vrpi_jitter_max_ms, t.vrpo_jitter_max_ms) DESC NULLS LAST
LIMIT {a.limit}"""


def _worst_machines(f: Fleet, a: Args) -> str:
    keys, w = machine_key(f)
    k = ", ".join(keys)
    return f"""
WITH c AS (SELECT {w}, {_CAPTURE_COUNTS},
                  count(*) FILTER (WHERE status <> 'ok' OR (NOT verdict_ok AND NOT ({_NO_EGLINK})))
                      AS failing_captures
           FROM captures GROUP BY ALL),
r AS (SELECT {w}, capture_id, rule, any_value(severity) AS severity, any_value(count) AS n FROM findings
      WHERE rule <> 'no_eglink' GROUP BY ALL),
f AS (SELECT {k}, count(*) FILTER (WHERE severity = 'error') AS error_findings,
             count(*) FILTER (WHERE severity <> 'error') AS other_findings, sum(n) AS items FROM r GROUP BY ALL)
SELECT {_cols('c', keys)}, c.captures, c.unreadable, c.no_eglink, c.failing_captures,
       coalesce(f.error_findings, 0) AS error_findings, coalesce(f.other_findings, 0) AS other_findings,
       coalesce(f.items, 0) AS counted
FROM c LEFT JOIN f ON {_same('c', 'f', keys)}
ORDER BY error_findings DESC, failing_captures DESC, other_findings DESC, counted DESC
LIMIT {a.limit}"""


def _failing_commands(f: Fleet, a: Args) -> str:
    keys, w = machine_key(f, "commands")
    return f"""
SELECT {w}, type, command_id, count(*) AS commands, count(*) FILTER (WHERE failed) AS failed,
       count(*) FILTER (WHERE NOT acked AND interrupted_frame IS NULL) AS unacked,
       round(100.0 * count(*) FILTER (WHERE failed) / count(*), 1) AS failed_pct,
       round(quantile_cont(latency_first_ms, 0.95), 3) AS ack_p95_ms, count(DISTINCT capture_id) AS captures
FROM commands GROUP BY ALL HAVING count(*) FILTER (WHERE failed) > 0
ORDER BY failed DESC, failed_pct DESC, {", ".join(f"#{i + 1}" for i in range(len(keys)))}, type, command_id
LIMIT {a.limit}"""


def _month(f: Fleet, a: Args) -> str:
    if a.month is None:
        return "(SELECT date_trunc('month', max(first_time)) FROM captures)"
    if not re.fullmatch(r"\d{4}-(0[1-9]|1[0-2])", a.month):
        raise CliError(f"--month {a.month[:20]!r}: give YYYY-MM")
    return f"TIMESTAMP '{a.month}-01'"


def _watchdog(f: Fleet, a: Args) -> str:
    _, w = machine_key(f, alias="c")
    return f"""
WITH m AS (SELECT {_month(f, a)} AS start)
SELECT strftime(m.start, '%Y-%m') AS month, {w}, count(DISTINCT c.capture_id) AS captures,
       sum(s.watchdog_violations) AS violations, sum(s.watchdog_until_end) AS until_end,
       max(s.watchdog_max_gap_ms) AS max_gap_ms, string_agg(DISTINCT s.type, ',' ORDER BY s.type) AS types
FROM streams s JOIN captures c USING (capture_id), m
WHERE s.watchdog_violations > 0 AND c.first_time >= m.start AND c.first_time < m.start + INTERVAL 1 MONTH
GROUP BY ALL ORDER BY violations DESC, max_gap_ms DESC
LIMIT {a.limit}"""


# A capture's senders summed, one row per capture: joined to `captures`, a value of the capture
# (capture_dropped) is then summed once, not once per sender.
_SENDERS_PER_CAPTURE = ("(SELECT capture_id, sum(lost) AS lost, sum(received) AS received, "
                        "sum(duplicates) AS duplicates FROM senders GROUP BY capture_id)")

_TREND = {   # metric -> (table, aggregates over it as t and captures as c)
    "jitter": ("streams", ("round(avg(t.jitter_mean_ms) FILTER (WHERE t.type = 'VRPI'), 3) AS vrpi_jitter_mean_ms, "
                           "max(t.jitter_max_ms) FILTER (WHERE t.type = 'VRPI') AS vrpi_jitter_max_ms, "
                           "round(avg(t.jitter_mean_ms) FILTER (WHERE t.type = 'VRPO'), 3) AS vrpo_jitter_mean_ms, "
                           "max(t.jitter_max_ms) FILTER (WHERE t.type = 'VRPO') AS vrpo_jitter_max_ms")),
    # Beside the loss, what the captures dropped themselves (as --worst links: up to that many of
    # the lost may be the capture host's, not the link's; blank where not known).
    "loss": (_SENDERS_PER_CAPTURE, ("sum(t.lost) AS lost, sum(t.received) AS received, "
                                    f"round(100.0 * sum(t.lost) / nullif({_sent('t.')}, 0), 3) AS loss_pct, "
                                    "sum(c.capture_dropped) AS capture_dropped")),
    # VRCI acked by the controller (VRAO), VRCO by the base unit (VRAI): two devices' latencies,
    # apart ("which BU firmware acks slowest" mixed the controller's acks in).
    "latency": ("commands", ", ".join(
        f"count(*) FILTER (WHERE t.type = '{k}') AS {k.lower()}_commands, "
        f"round(quantile_cont(t.latency_first_ms, 0.5) FILTER (WHERE t.type = '{k}'), 3) AS {k.lower()}_ack_p50_ms, "
        f"round(quantile_cont(t.latency_first_ms, 0.95) FILTER (WHERE t.type = '{k}'), 3) AS {k.lower()}_ack_p95_ms, "
        f"max(t.latency_first_ms) FILTER (WHERE t.type = '{k}') AS {k.lower()}_ack_max_ms, "
        f"count(*) FILTER (WHERE t.type = '{k}' AND t.failed) AS {k.lower()}_failed" for k in ("VRCI", "VRCO"))),
    "watchdog": ("captures", ("sum(t.watchdog) AS watchdog, "
                              "count(*) FILTER (WHERE t.watchdog > 0) AS captures_with_watchdog")),
    "findings": ("captures", ("sum(t.findings) AS findings, count(*) FILTER (WHERE NOT t.verdict_ok AND "
                              "t.eglink_packets > 0) AS failing_captures, "
                              "count(*) FILTER (WHERE t.eglink_packets = 0) AS no_eglink")),
}


def _trend(f: Fleet, a: Args) -> str:
    if a.metric not in _TREND:
        raise CliError(f"--trend {a.metric[:20]!r}: choose from {', '.join(METRICS)}")
    table, aggregates = _TREND[a.metric]
    if a.by in PERIODS:
        key = f"CAST(date_trunc('{a.by}', c.first_time) AS DATE)"
    elif COLUMN.match(a.by) and a.by in f.columns["captures"]:
        key = f"c.{a.by}"
    else:
        raise CliError(f"--by {a.by[:30]!r}: choose from {', '.join(PERIODS)} or a column of captures "
                       f"({', '.join(f.meta_keys) or 'the dataset has no metadata'})")
    return f"""
SELECT {key} AS {a.by}, count(DISTINCT c.capture_id) AS captures, {aggregates}
FROM {table} t JOIN captures c USING (capture_id)
WHERE c.status <> 'unreadable'
GROUP BY 1 ORDER BY 1 NULLS LAST"""


def _no_eglink(f: Fleet, a: Args) -> str:
    lead = "".join(f"{c}, " for c in f.who() if c != "file")
    return f"""
SELECT {lead}file, status, first_time, duration_s, packets FROM captures
WHERE {_NO_EGLINK} ORDER BY {lead}file"""


def _overlaps(f: Fleet, a: Args) -> str:
    """Pairs of captures of one named machine (site and machine) that share a sender and overlap in
    time: one link captured twice (a tap and a mirror port at once, a ring-buffer file and a merged
    file of the same period), whose packets, losses and findings every sum counts twice. A capture
    without site and machine is a machine of its own, as in the rankings: paired by addresses
    alone, every machine's capture would pair with every other's taken at the same time where all
    machines have the same addresses."""
    who = [c for c in f.who() if c != "file"]
    lead = "".join(f"a.{c}, " for c in who)
    same = (" AND ".join(f"a.{c} IS NOT DISTINCT FROM b.{c}" for c in who)
            + " AND NOT (" + " AND ".join(f"a.{c} IS NULL" for c in who) + ")") if who else "false"
    return f"""
WITH c AS (SELECT * FROM captures WHERE status <> 'unreadable'),
s AS (SELECT DISTINCT capture_id, sender FROM senders)
SELECT {lead}a.file, b.file AS other_file, greatest(a.first_time, b.first_time) AS overlap_from,
       least(a.last_time, b.last_time) AS overlap_to,
       round(date_diff('microsecond', greatest(a.first_time, b.first_time), least(a.last_time, b.last_time)) / 1e6, 3)
           AS overlap_s,
       string_agg(DISTINCT sa.sender, '; ' ORDER BY sa.sender) AS senders
FROM c a JOIN c b ON a.file < b.file AND {same} AND a.first_time < b.last_time AND b.first_time < a.last_time
JOIN s sa ON sa.capture_id = a.capture_id JOIN s sb ON sb.capture_id = b.capture_id AND sa.sender = sb.sender
GROUP BY ALL ORDER BY {lead}a.file, other_file
LIMIT {a.limit}"""


def overlap_warnings(f: Fleet, most: int = 5) -> list[str]:
    """A line per overlap (up to `most`, then how many more): said beside every query that sums."""
    res = f.run(_overlaps(f, Args(limit=most + 1)))
    if not res.rows:
        return []
    total = f.run(f"SELECT count(*) FROM ({_overlaps(f, Args(limit=1_000_000_000))})").rows[0][0]
    at = {c: i for i, c in enumerate(res.columns)}
    lines = [f"overlap, counted twice: {_cell(r[at['file']])} and {_cell(r[at['other_file']])} hold the same link "
             f"({_cell(r[at['senders']])}) from {_cell(r[at['overlap_from']])} to {_cell(r[at['overlap_to']])} "
             f"({_cell(r[at['overlap_s']])} s)" for r in res.rows[:most]]
    if total > most:
        lines.append(f"overlap, counted twice: {total - most} more pairs of captures")
    return lines + ["overlap: --named overlaps lists them; remove or move the second capture of each pair"]


def _errors(f: Fleet, a: Args) -> str:
    who = f.who("errors")
    columns = who + ([] if "file" in who else ["file"])
    return f"SELECT {', '.join(columns)}, kind, message, file_offset FROM errors ORDER BY file"


def _findings(f: Fleet, a: Args) -> str:
    who = [c for c in f.who("findings") if c != "file"]
    lead = ", ".join(who) + ", " if who else ""
    return f"""
SELECT {lead}file, rule, severity, frame, time, sender, filter, message
FROM findings
ORDER BY severity = 'error' DESC, rule, file, item
LIMIT {a.limit}"""


NAMED = {n.name: n for n in (
    Named("worst-links", "machines by lost packets (share; beside it what the captures dropped themselves), "
                         "watchdog violations, then jitter (--worst links)",
          _worst_links, ("limit",), sums=True),
    Named("worst-machines", "machines ranked by findings: error findings, failing captures, others (--worst machines)",
          _worst_machines, ("limit",), sums=True),
    Named("failing-commands", "commands that fail most, per machine and command ID, with failure share and ack "
                              "latency (--worst commands)",
          _failing_commands, ("limit",), sums=True),
    Named("watchdog", "machines with watchdog violations in a month (--month YYYY-MM; default the latest in the data)",
          _watchdog, ("limit", "month"), sums=True),
    Named("trend", f"--trend METRIC ({', '.join(METRICS)}) --by {'|'.join(PERIODS)}|COLUMN", _trend, ("by",),
          sums=True),
    Named("no-eglink", "captures without one EG-Link packet (a dead link, the wrong interface): listed apart, "
                       "neither failing nor ranked by --worst", _no_eglink),
    Named("overlaps", "pairs of captures of one machine that share a sender and overlap in time: the same link "
                      "captured twice, counted twice in every sum", _overlaps, ("limit",)),
    Named("errors", "captures that could not be read, or only in part, and why", _errors),
    Named("findings", "findings to open in Wireshark: file, frame, time, sender and display filter (none for a "
                      "finding of the whole capture: no EG-Link packet, frames not read), message", _findings,
          ("limit",)),
)}
WORST = {"links": "worst-links", "machines": "worst-machines", "commands": "failing-commands"}


def _quote(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


# -- output -------------------------------------------------------------------------------------------
def _plain(value: Any) -> Any:
    """A JSON / CSV friendly value; a time as every command prints one (ISO 8601 UTC with µs and
    Z: the columns hold UTC), so that it reads as `vm110 decode` and `analyze` print that frame's."""
    if isinstance(value, dt.datetime):
        return datetime_iso(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    if isinstance(value, decimal.Decimal):
        return float(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (bytes, bytearray)):
        return value.hex()
    return value


def _cell(value: Any) -> str:
    """A table cell: one line, whatever a file name holds (a newline in one split its row in two)."""
    value = _plain(value)
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".") if value != int(value) or abs(value) < 1e15 else f"{value:g}"
    return escaped(str(value))


# A spreadsheet (Excel, LibreOffice) opening a CSV takes a cell that begins with one of these as a
# formula (`=HYPERLINK(...)` in a sidecar's value, a folder named `@SUM(...)`): such a text cell
# begins with a single quote, as OWASP (CSV Injection) recommends. Control characters, which
# OWASP also lists (tab, carriage return), are escaped before (as the table shows them).
_FORMULA_START = ("=", "+", "-", "@")


def _csv_cell(value: Any) -> Any:
    """A CSV cell: numbers as they are, text escaped and never a formula."""
    value = _plain(value)
    if value is None:
        return ""
    if not isinstance(value, str):
        return value
    text = escaped(value)
    return "'" + text if text.startswith(_FORMULA_START) else text


def render(result: Result, fmt: str) -> str:
    if fmt == "json":
        # A value JSON has no type for (an INTERVAL, TIME or UUID of a query) as the text the
        # table and CSV show, not a traceback.
        return json.dumps([dict(zip(result.columns, map(_plain, row))) for row in result.rows], indent=1,
                          default=str) + "\n"
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow([_csv_cell(c) for c in result.columns])
        for row in result.rows:
            writer.writerow([_csv_cell(v) for v in row])
        return out.getvalue()
    heads, cells = [escaped(c) for c in result.columns], [[_cell(v) for v in row] for row in result.rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(heads)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(heads, widths)).rstrip(),
             "  ".join("-" * w for w in widths)]
    for shown, raw in zip(cells, result.rows):
        lines.append("  ".join(c.rjust(w) if isinstance(v, (int, float)) and not isinstance(v, bool) else c.ljust(w)
                               for c, w, v in zip(shown, widths, raw)).rstrip())
    lines.append(f"({len(result.rows)} row{'s' if len(result.rows) != 1 else ''})")
    return "\n".join(lines) + "\n"
