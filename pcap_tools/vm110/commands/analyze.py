"""Analyse captures: serial gaps, timing and jitter, watchdogs, commands, bursts; verdict and reports.

Prints a summary per capture (and a combined one for several), writes the JSON report (--json,
docs/report.md) and the self-contained HTML report (--html). Exit code 1 when a --fail-on rule
is violated, 2 for unreadable input or bad arguments.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
from typing import Optional, Union

from .. import closedpipe
from .. import constants as C
from .. import resources, workers
from ..analysis import analyze, report_html, report_json, rules, summary
from ..analysis.commands import REUSE_GAP_MS
from ..analysis.findings import MAX_TOTALS, TOTAL_NAMES
from ..analysis.serials import DUP_WINDOW_MS
from ..analysis.report import SCHEMA_VERSION, Options
from ..capture.spool import as_given, named, stdin_spool
from ..fileio import check_distinct, check_report_target
from ..errors import EXIT_FINDINGS, EXIT_OK, EXIT_USAGE, CliError
from ..numbers import number
from ..printable import escaped, unicode_text
from .options import INPUT_PORT, INPUT_PORT_HELP, VRPO_START, VRPO_START_HELP, add_reading_options

# Times in ms: above 0 (a zero watchdog or period flags everything) and at most an hour.
MS = number(0, 3_600_000, "ms", allow_zero=False)
JOBS = number(1, 256, integer=True)
DATA_SIZE = number(0, 0xFFFF, "bytes", integer=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("captures", nargs="*", metavar="CAPTURE", help="pcap or pcapng files; - reads standard input")
    parser.add_argument("--engine", choices=("fast", "tshark"), default="fast",
                        help="fast (default, streams the file) or tshark (the Lua dissector through pyshark)")
    parser.add_argument("--jobs", type=JOBS, default=1, metavar="N",
                        help=f"captures analysed in parallel, {JOBS.range_text}; default 1")
    parser.add_argument("--schema", action="store_true",
                        help="print the JSON Schema of the --json report (docs/report.schema.json) and exit")
    add_analysis_arguments(parser)


def add_analysis_arguments(parser: argparse.ArgumentParser) -> None:
    """The analysis and its reports (shared with `vm110 monitor`)."""
    add_report_options(parser)
    add_analysis_options(parser)


def add_report_options(parser: argparse.ArgumentParser) -> None:
    """Where the reports go and what makes the exit code."""
    parser.add_argument("--json", metavar="FILE", help="write the JSON report (docs/report.md); - for standard "
                        "output (the summary then goes to standard error)")
    parser.add_argument("--html", metavar="FILE", help="write the self-contained HTML report; - for standard "
                        "output (the summary then goes to standard error)")
    parser.add_argument("--fail-on", metavar="RULES",
                        help="exit 1 when a rule holds, e.g. lost>0,watchdog>0,unacked>0,illegal>0; "
                             f"names: {', '.join(TOTAL_NAMES)}")
    parser.add_argument("--quiet", action="store_true", help="no summary on standard output")
    parser.add_argument("--list", action="store_true",
                        help="list the located items of each finding as the JSON report keeps them (the first "
                             "100; default: the first few)")


def add_analysis_options(parser: argparse.ArgumentParser) -> None:
    """The options that decide what the analysis says (shared with `vm110 monitor` and `vm110 fleet build`)."""
    add_reading_options(parser, found=True)
    parser.add_argument("--port", type=INPUT_PORT, default=C.INPUT_PORT, help=INPUT_PORT_HELP)
    parser.add_argument("--vrpo-period", type=MS, metavar="MS",
                        help=f"nominal VRPO period for jitter, {MS.range_text} (default: median interval "
                             "between bursts)")
    parser.add_argument("--burst-gap", type=MS, default=C.VRPO_BURST_GAP_MS, metavar="MS",
                        help=f"largest gap inside a VRPO burst, {MS.range_text}; default {C.VRPO_BURST_GAP_MS}")
    parser.add_argument("--vrpo-start", type=VRPO_START, default=0, metavar="N", help=VRPO_START_HELP)
    parser.add_argument("--vrpo-data-size", type=DATA_SIZE, default=0, metavar="BYTES",
                        help=f"configured periodic data size, {DATA_SIZE.range_text}; 0 (default): inferred, a burst "
                             "ends with a packet under 488 data bytes, or has at least as many 488-byte packets as "
                             "the sender's longest complete such burst (docs/rules.md)")
    limits = parser.add_argument_group("thresholds (interpretation.md, 'Timing')")
    limits.add_argument("--vrpi-watchdog", type=MS, default=C.VRPI_WATCHDOG_MS, metavar="MS",
                        help=f"controller watchdog on VRPI, {MS.range_text}; default {C.VRPI_WATCHDOG_MS}")
    limits.add_argument("--vrpo-watchdog", type=MS, default=C.VRPO_WATCHDOG_MS, metavar="MS",
                        help=f"base-unit watchdog on VRPO, {MS.range_text}; default {C.VRPO_WATCHDOG_MS}")
    limits.add_argument("--vrpo-range", type=MS, nargs=2, default=(C.VRPO_PERIOD_MIN_MS, C.VRPO_PERIOD_MAX_MS),
                        metavar=("MIN", "MAX"), help=f"recommended VRPO interval, each {MS.range_text}, MIN at most "
                                                     f"MAX; default {C.VRPO_PERIOD_MIN_MS} {C.VRPO_PERIOD_MAX_MS}")
    limits.add_argument("--vrci-fail", type=MS, default=C.VRCI_FAIL_MS, metavar="MS",
                        help=f"VRCI not acknowledged within this has failed, {MS.range_text}; "
                             f"default {C.VRCI_FAIL_MS}")
    limits.add_argument("--vrco-give-up", type=MS, default=C.VRCO_GIVE_UP_MS, metavar="MS",
                        help=f"VRCO not acknowledged within this has failed, {MS.range_text}; "
                             f"default {C.VRCO_GIVE_UP_MS}")
    limits.add_argument("--reuse-gap", type=MS, default=REUSE_GAP_MS, metavar="MS",
                        help="the same command ID after a longer silence starts a new command, "
                             f"{MS.range_text}; default {REUSE_GAP_MS:g}")
    limits.add_argument("--dup-window", type=MS, default=DUP_WINDOW_MS, metavar="MS",
                        help="a serial seen again within this is a duplicate, a gap filled within it a late "
                             f"packet, {MS.range_text}; default {DUP_WINDOW_MS:g}")
    limits.add_argument("--resend", type=MS, default=C.COMMAND_RESEND_MS, metavar="MS",
                        help=f"nominal command resend interval, {MS.range_text}; default {C.COMMAND_RESEND_MS}")


def _progress(path: str):
    if not sys.stderr.isatty():
        return None
    name = path if len(path) < 40 else "..." + path[-37:]

    def show(done: int, total: int) -> None:
        pct = 100 * done // total if total else 100
        bar = "#" * (pct // 4)
        sys.stderr.write(f"\r{name} [{bar:<25}] {pct:3d}%")
        sys.stderr.flush()
    return show


def _one(job: tuple) -> Union[dict, str]:
    """The report of one capture, or the one-line reason it cannot be read."""
    path, engine, port, crc, crc_order, options, show_progress = job
    progress = _progress(path) if show_progress else None
    try:
        return analyze(path, engine, port, crc, crc_order, options, progress)
    except CliError as exc:
        return str(exc)
    except MemoryError:
        return f"{path}: out of memory"
    except Exception as exc:     # a broken file must give one line, never a traceback
        return f"cannot analyse {path}: {type(exc).__name__}: {exc}"
    finally:
        if progress is not None:
            sys.stderr.write("\r\033[K")


def combine(reports: list[dict]) -> dict:
    """Totals over several captures (sums; maxima for the *_max_ms ones) and each one's verdict."""
    total = {}
    for name in TOTAL_NAMES:
        values = [r["totals"][name] for r in reports]
        total[name] = max(values) if name in MAX_TOTALS else sum(values)
    return {"ok": all(r["verdict"]["ok"] for r in reports), "totals": total,
            "captures": [{"file": r["capture"]["file"], "ok": r["verdict"]["ok"], "totals": r["totals"]}
                         for r in reports]}


def analysis_options(args: argparse.Namespace) -> Options:
    """The analysis `Options` of parsed `add_analysis_options` arguments, checked together."""
    low, high = args.vrpo_range
    if low > high:
        raise CliError(f"--vrpo-range: MIN {low:g} ms is above MAX {high:g} ms")
    # A gap as long as a VRPO interval would join consecutive cycles into one burst.
    shortest = min(low, args.vrpo_period or low)
    if args.burst_gap >= shortest:
        raise CliError(f"--burst-gap: {args.burst_gap:g} ms must be below the shortest VRPO interval "
                       f"({shortest:g} ms, --vrpo-range MIN or --vrpo-period)")
    return Options(serial_scope=args.serial_scope, vrpo_period_ms=args.vrpo_period,
                   vrpi_watchdog_ms=args.vrpi_watchdog, vrpo_watchdog_ms=args.vrpo_watchdog,
                   vrpo_min_ms=low, vrpo_max_ms=high, resend_ms=args.resend,
                   vrci_fail_ms=args.vrci_fail, vrco_give_up_ms=args.vrco_give_up,
                   reuse_gap_ms=args.reuse_gap, dup_window_ms=args.dup_window, burst_gap_ms=args.burst_gap,
                   vrpo_start=args.vrpo_start, vrpo_data_size=args.vrpo_data_size)


def report_on_stdout(args: argparse.Namespace) -> bool:
    """--json - or --html -: standard output is the report's alone."""
    return "-" in (args.json, args.html)


def report_rules(args: argparse.Namespace) -> list:
    """The --fail-on rules of `add_report_options` arguments; the report files checked up front,
    not after minutes of analysis."""
    fail_rules = rules.parse(args.fail_on, TOTAL_NAMES) if args.fail_on is not None else []
    if args.json == "-" and args.html == "-":
        raise CliError("--json - and --html -: only one report can go to standard output")
    outputs = {o: v for o, v in (("--json", args.json), ("--html", args.html),
                                 ("--json-lines", getattr(args, "json_lines", None))) if v is not None}
    inputs = list(getattr(args, "captures", None) or [getattr(args, "read", None) or "-"])
    check_distinct(outputs, inputs)
    for target in (args.json, args.html):
        if target not in (None, "-"):
            check_report_target(target)
    return fail_rules


def run(args: argparse.Namespace) -> int:
    if args.schema:
        sys.stdout.write(resources.report_schema().read_text(encoding="utf-8"))
        return EXIT_OK
    if not args.captures:
        raise CliError("give at least one CAPTURE (or --schema)")
    options = analysis_options(args)
    fail_rules = report_rules(args)
    if args.engine == "tshark":
        from ..analysis.tshark_engine import check_available
        check_available()
    with contextlib.ExitStack() as stack:
        paths = [stdin_spool(stack) if p == "-" else p for p in args.captures]
        jobs = [(p, args.engine, args.port, args.crc, args.crc_order, options, args.jobs == 1) for p in paths]
        results: list = [None] * len(jobs)
        for index, result in workers.each(_one, jobs, args.jobs):
            results[index] = f"{paths[index]}: {result}" if isinstance(result, workers.Died) else result
    for i, (name, path, result) in enumerate(zip(args.captures, paths, results)):
        if name == "-" and isinstance(result, dict):
            result["capture"]["file"] = "-"
        elif isinstance(result, str):
            results[i] = as_given(result, path, name)
    return deliver(args, list(args.captures), results, fail_rules, "analyze")


def deliver(args: argparse.Namespace, names: list[str], results: list, fail_rules: list, command: str) -> int:
    """Print and write the reports (`results`: a report, or the one-line reason a capture could
    not be read, per name) as the options say; the exit code."""
    # Every readable capture is reported; an unreadable one is an error entry beside them, and one
    # damaged partway is reported up to the damage: either is exit 2 (README, "Exit codes").
    reports = [r for r in results if isinstance(r, dict)]
    # File names are any bytes: valid Unicode in the reports, escaped on the terminal (an escape
    # sequence or a newline in a name must not reach it), as the summary has them.
    errors = [{"file": unicode_text(name), "error": unicode_text(r)} for name, r in zip(names, results)
              if isinstance(r, str)]
    for e in errors:
        print(f"vm110 {command}: {escaped(e['error'])}", file=sys.stderr)
    damaged = [f"{named(name)}: {r['capture']['problem']}"
               for name, r in zip(names, results) if isinstance(r, dict) and r["capture"]["problem"]]
    for line in damaged:
        print(f"vm110 {command}: {escaped(line)}", file=sys.stderr)
    if not reports:
        return EXIT_USAGE
    combined: Optional[dict] = combine(reports) if len(names) > 1 else None
    document = reports[0] if combined is None else {
        "schema_version": SCHEMA_VERSION, "reports": reports, "errors": errors, "combined": combined}
    # A reader that stops early (`| head`) cuts standard output short; the report files and the
    # verdict below still follow. A report (or the monitor's JSON lines) on standard output keeps
    # it to itself: the summary then goes to standard error.
    with closedpipe.tolerated(command):
        if not args.quiet:
            on_stdout = report_on_stdout(args) or getattr(args, "json_lines", None) == "-"
            out = sys.stderr if on_stdout else sys.stdout
            print("\n\n".join(summary.render(r, args.list) for r in reports), file=out)
            if combined:
                print(file=out)
                print(summary.render_combined(combined), file=out)
        if args.json == "-":
            report_json.dump(sys.stdout, document)
        if args.html == "-":
            sys.stdout.write(report_html.render(reports, combined, errors))
    if args.json not in (None, "-"):
        report_json.write(args.json, document)
    if args.html not in (None, "-"):
        report_html.write(args.html, reports, combined, errors)
    broken = [f"{r['capture']['file']}: {v}" for r in reports for v in rules.violations(fail_rules, r["totals"])]
    for line in broken:
        print(f"fail-on: {escaped(line)}", file=sys.stderr)
    if errors or damaged:
        return EXIT_USAGE
    return EXIT_FINDINGS if broken else EXIT_OK
