"""Fleet analysis: captures from many machines in one Parquet dataset, queried with DuckDB.

`build SRC... --out DATASET` analyses every capture as `vm110 analyze` does (same options) into
the tables captures, senders, streams, commands, findings, errors (and packets); incremental.
`query DATASET "SQL"` or a named query (--list); `report DATASET --html FILE` writes one
self-contained page. docs/fleet.md describes the dataset. Exit code 2 for unreadable input (the
other captures are built all the same) or bad arguments.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Optional, Sequence

from ..cli import Parser
from ..errors import EXIT_OK, EXIT_USAGE, CliError
from ..fileio import check_distinct, check_target, write_text
from ..numbers import number
from .analyze import add_analysis_options, analysis_options

JOBS = number(1, 256, integer=True)
LIMIT = number(1, 1_000_000, integer=True)


class ActionParser(Parser):
    """The parser of one action (`vm110 fleet query`): options may come between positionals.
    argparse alone takes `query DATASET --format json SQL` as DATASET with SQL absent (nargs '?'
    is matched, empty, before the option) and then refuses SQL as an extra argument."""

    _inner = False       # parse_known_intermixed_args calls parse_known_args (Python < 3.12.7)

    def parse_known_args(self, args: Optional[Sequence[str]] = None,     # type: ignore[override]  # typeshed: overloads
                         namespace: Optional[argparse.Namespace] = None) -> tuple[argparse.Namespace, list[str]]:
        if self._inner:
            return super().parse_known_args(args, namespace)
        self._inner = True
        try:
            parsed, extras = self.parse_known_intermixed_args(args, namespace)
        finally:
            self._inner = False
        if extras:      # said here, as `vm110 fleet: ...` (the top-level parser would say `vm110: ...`)
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed, extras


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="fleet_command", metavar="ACTION", required=True, parser_class=ActionParser)
    build = sub.add_parser("build", help="analyse captures into a dataset (incremental)",
                           description="Analyse captures (files, folders, globs) into a Parquet dataset.")
    build.add_argument("sources", nargs="+", metavar="SRC", help="capture files, folders (recursive) or glob patterns")
    build.add_argument("--out", required=True, metavar="DATASET", help="dataset folder or fsspec URL (created if new)")
    build.add_argument("--meta", metavar="PATTERN",
                       help="fields from the path, e.g. 'sites/{site}/{machine}/*.pcapng'; a sidecar CAPTURE.meta.json "
                            "adds more")
    build.add_argument("--packets", action="store_true", help="also a per-packet table (packets) for drill-down")
    build.add_argument("--engine", choices=("local", "dask"), default="local",
                       help="local (default): processes on this machine; dask: dask.distributed workers")
    build.add_argument("--scheduler", metavar="ADDRESS",
                       help="Dask scheduler (e.g. tcp://host:8786); default: a LocalCluster of --jobs workers")
    build.add_argument("-j", "--jobs", type=JOBS, default=os.cpu_count() or 1, metavar="N",
                       help=f"processes (local) or LocalCluster workers (dask), {JOBS.range_text}; "
                            "default: the number of CPUs")
    add_analysis_options(build)

    query = sub.add_parser("query", help="SQL or a named query over a dataset",
                           description="DuckDB over the dataset: tables captures, senders, streams, commands, "
                                       "findings, errors, packets as views.")
    query.add_argument("dataset", metavar="DATASET")
    query.add_argument("sql", nargs="?", metavar="SQL", help="a query over the views")
    query.add_argument("--format", choices=("table", "csv", "json"), default="table",
                       help="how the rows are printed; default table")
    query.add_argument("--list", action="store_true", help="list the named queries and the tables' columns")
    query.add_argument("--named", metavar="NAME", help="a named query (see --list)")
    query.add_argument("--worst", choices=("links", "machines", "commands"), help="worst links, machines or commands")
    query.add_argument("--trend", metavar="METRIC", help="jitter, loss, latency, watchdog or findings over time")
    query.add_argument("--by", help="for --trend: day, week, month or a metadata column; default week")
    query.add_argument("--month", metavar="YYYY-MM", help="for watchdog: the month; default the latest in the data")
    query.add_argument("--limit", type=LIMIT, metavar="N",
                       help=f"rows of a ranked query, {LIMIT.range_text}; default 20")

    report = sub.add_parser("report", help="one self-contained HTML page over a dataset")
    report.add_argument("dataset", metavar="DATASET")
    report.add_argument("--html", required=True, metavar="FILE", help="the page to write; - for standard output")


# The fleet extra's modules (pyproject.toml): `pip install vm110` alone, from a wheel say, has none of them.
FLEET_MODULES = frozenset({"pyarrow", "duckdb", "dask", "distributed", "fsspec"})


def run(args: argparse.Namespace) -> int:
    try:
        return {"build": _build, "query": _query, "report": _report}[args.fleet_command](args)
    except ModuleNotFoundError as exc:
        if (exc.name or "").partition(".")[0] not in FLEET_MODULES:
            raise
        raise CliError(f"needs the package's fleet extra, which is not installed ({exc.name} is missing): install "
                       "vm110 again with it, pip install 'PATH[fleet]' or pipx install --force 'PATH[fleet]' "
                       "(PATH: the vm110 folder or wheel)") from None


def _build(args: argparse.Namespace) -> int:
    from ..fleet.build import absolute, build
    from ..fleet.sources import MetaPattern
    from ..fleet.work import Settings
    if args.scheduler and args.engine != "dask":
        raise CliError("--scheduler goes with --engine dask")
    settings = Settings(dataset=absolute(args.out), port=args.port, crc=args.crc, crc_order=args.crc_order,
                        options=analysis_options(args), packets=args.packets)
    pattern = MetaPattern(args.meta) if args.meta else None
    outcome = build(args.sources, settings, pattern, args.engine, args.jobs, args.scheduler, sys.stderr.isatty())
    for line in outcome.unreadable:
        print(f"vm110 fleet: {line}", file=sys.stderr)
    for line in outcome.damaged:
        print(f"vm110 fleet: damaged: {line}", file=sys.stderr)
    for line in outcome.copies:
        print(f"vm110 fleet: copy, counted once: {line}", file=sys.stderr)
    if outcome.unmatched and pattern is not None:      # (a typo in the pattern: fields empty, silently)
        print(f"vm110 fleet: --meta {args.meta!r} does not match the path of {len(outcome.unmatched)} of "
              f"{outcome.given} captures (the first: "
              f"{outcome.unmatched[0]}); their {', '.join(pattern.keys)} are empty unless a sidecar gives them",
              file=sys.stderr)
    print(f"{args.out}: {outcome.analysed} analysed ({len(outcome.damaged)} damaged, {len(outcome.unreadable)} "
          f"unreadable), {outcome.skipped} already in the dataset, {outcome.replaced} replaced"
          + (f", {len(outcome.copies)} {'copies' if len(outcome.copies) > 1 else 'copy'} not counted"
             if outcome.copies else "")
          + (f", {outcome.cleared} unreadable no longer there (removed)" if outcome.cleared else ""))
    return EXIT_USAGE if outcome.unreadable or outcome.damaged else EXIT_OK


def _query(args: argparse.Namespace) -> int:
    from ..fleet.query import NAMED, WORST, Args, Fleet, overlap_warnings, render
    chosen = [x for x in (args.sql, args.named, args.worst, args.trend) if x]
    if len(chosen) > 1:
        raise CliError("give one of SQL, --named, --worst, --trend")
    fleet = Fleet(args.dataset)
    if args.list:
        for named in NAMED.values():
            print(f"{named.name:<18} {named.help}")
        print()
        for table, columns in fleet.columns.items():
            print(f"{table}: {', '.join(columns)}")
        return EXIT_OK
    if not chosen:
        raise CliError("give SQL, --named NAME, --worst WHAT or --trend METRIC (--list shows them)")
    if args.sql:
        given = [f"--{o}" for o in ("limit", "by", "month") if getattr(args, o) is not None]
        if given:
            raise CliError(f"{given[0]} does not apply to SQL (say it in the query)")
        sql = args.sql
    else:
        name = args.named or (WORST[args.worst] if args.worst else "trend")
        if name not in NAMED:
            raise CliError(f"--named {name[:30]!r}: choose from {', '.join(NAMED)}")
        named = NAMED[name]
        sql = named.sql(fleet, Args.given(named, args.trend or "jitter", limit=args.limit, by=args.by,
                                          month=args.month))
    sys.stdout.write(render(fleet.run(sql), args.format))
    if not args.sql and named.sums:
        for line in overlap_warnings(fleet):
            print(f"vm110 fleet: {line}", file=sys.stderr)
    return EXIT_OK


def _report(args: argparse.Namespace) -> int:
    from ..fleet.query import Fleet
    from ..fleet.report import render
    if args.html != "-":
        check_target(args.html)
    fleet = Fleet(args.dataset)
    if args.html != "-":        # (the page written over the manifest lost the whole dataset)
        check_distinct({"--html": args.html}, fleet.dataset.own_files(fleet.manifest))
    page = render(fleet)
    if args.html == "-":
        sys.stdout.write(page)
    else:
        write_text(args.html, page)
    return EXIT_OK
