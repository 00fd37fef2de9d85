"""Watch a live EG-Link: dashboard, alarms as they happen, evidence around each alarm.

At the end, the report of `vm110 analyze` for everything seen.

Input: an interface through dumpcap (-i), a capture file followed as it grows (--read FILE), or
pcap/pcapng on standard input (--read -). The dashboard is drawn on a terminal about once a
second (--no-dashboard, or no terminal: one line per finding). Ends at Ctrl-C, SIGTERM,
--duration or the end of the input; exit code 0, 1 when a --fail-on rule holds, 2 when the input
could not be read to its end (the report of what was seen is still given), docs/monitor.md.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys

from ..errors import EXIT_USAGE, CliError
from ..fileio import check_target
from ..numbers import number
from .analyze import add_analysis_arguments, analysis_options, deliver, report_on_stdout, report_rules

SECONDS = number(0, 30 * 86400, "s", allow_zero=False)
WINDOW = number(0, 3600, "s")
EVIDENCE_FILES = number(1, 1_000_000, integer=True)
EVIDENCE_MIB = number(0, 1 << 20, "MiB", allow_zero=False)
MAX_FILES, MAX_MIB = 1000, 1024        # a weekend of alarms fills no disk (docs/monitor.md, "Evidence")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("-i", "--interface", metavar="IFACE", help="capture on this interface with dumpcap")
    source.add_argument("--read", metavar="FILE", help="a pcap/pcapng file, followed as it grows; - for standard input")
    parser.add_argument("--realtime", action="store_true", help="replay --read at the pace of its timestamps")
    parser.add_argument("--idle", type=WINDOW, metavar="S",
                        help=f"--read FILE: end when the file has not grown for S seconds, {WINDOW.range_text} "
                             "(default: follow until interrupted)")
    parser.add_argument("--duration", type=SECONDS, metavar="S", help=f"stop after S seconds, {SECONDS.range_text}")
    parser.add_argument("--json-lines", metavar="FILE",
                        help="append one JSON object per second (the dashboard's numbers) and one per finding; "
                             "- for standard output")
    parser.add_argument("--evidence", metavar="DIR", help="write a pcapng and a JSON around every alarm into DIR")
    parser.add_argument("--before", type=WINDOW, default=10.0, metavar="S",
                        help=f"evidence: seconds before the alarm, {WINDOW.range_text}; default 10")
    parser.add_argument("--after", type=WINDOW, default=5.0, metavar="S",
                        help=f"evidence: seconds after the alarm, {WINDOW.range_text}; default 5")
    parser.add_argument("--evidence-max-files", type=EVIDENCE_FILES, default=MAX_FILES, metavar="N",
                        help=f"evidence: at most N alarm windows (a pcapng and a JSON each) this run, "
                             f"{EVIDENCE_FILES.range_text}; default {MAX_FILES}")
    parser.add_argument("--evidence-max-size", type=EVIDENCE_MIB, default=MAX_MIB, metavar="MIB",
                        help=f"evidence: at most MIB MiB of files this run, {EVIDENCE_MIB.range_text}; default "
                             f"{MAX_MIB}. At either limit the first evidence is kept and no more is written")
    parser.add_argument("--no-dashboard", action="store_true", help="one line per finding instead of the dashboard")
    add_analysis_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..monitor.evidence import Evidence
    from ..monitor.session import Session, Settings
    from ..monitor.sources import FILE_READ_SIZE, PACED_READ_SIZE, READ_SIZE, Dumpcap, FollowFile, PipeSource, Source
    from ..monitor.stopping import Signals
    options = analysis_options(args)
    fail_rules = report_rules(args)
    if args.realtime and args.read is None:
        raise CliError("--realtime replays --read FILE|-; a live interface is real time already")
    if args.idle is not None and args.read in (None, "-"):
        raise CliError("--idle applies to --read FILE")
    if args.evidence is not None and not os.path.isdir(args.evidence):
        raise CliError(f"--evidence {args.evidence}: " +
                       ("not a directory" if os.path.exists(args.evidence) else "no such directory"))
    # A report on standard output (--json - / --html -) is alone there: finding lines go to
    # standard error, and there is no dashboard.
    report_out = report_on_stdout(args)
    if report_out and args.json_lines == "-":
        raise CliError("--json-lines - and a report on standard output (--json - or --html -): only one can go there")
    name = args.read if args.read is not None else f"interface {args.interface}"
    with contextlib.ExitStack() as stack:
        signals = stack.enter_context(Signals())     # before dumpcap starts, till it is stopped
        json_lines = None
        if args.json_lines == "-":
            json_lines = sys.stdout
        elif args.json_lines is not None:
            check_target(args.json_lines)
            try:
                json_lines = stack.enter_context(open(args.json_lines, "a", encoding="utf-8"))
            except OSError as exc:
                raise CliError(f"cannot write {args.json_lines}: {exc.strerror}") from None
        evidence = None
        if args.evidence is not None:
            evidence = Evidence(args.evidence, args.before, args.after,
                                {"before_s": args.before, "after_s": args.after, "max_files": args.evidence_max_files,
                                 "max_size_mib": args.evidence_max_size, "port": args.port,
                                 "source": name, "analysis": vars(options)},
                                args.evidence_max_files, args.evidence_max_size)
        source: Source
        if args.read == "-":
            source = PipeSource(sys.stdin.fileno(), "standard input", PACED_READ_SIZE if args.realtime else READ_SIZE)
        elif args.read is not None:
            source = FollowFile(args.read, args.idle, PACED_READ_SIZE if args.realtime else FILE_READ_SIZE)
        else:
            source = Dumpcap(args.interface, (args.port, args.port + 2))
        stack.callback(source.close)
        on_terminal = sys.stdout.isatty() and not args.no_dashboard and args.json_lines != "-" and not report_out
        cfg = Settings(name=name, port=args.port, crc=args.crc, crc_order=args.crc_order, realtime=args.realtime,
                       live=args.read is None or args.read == "-", duration=args.duration, dashboard=on_terminal,
                       lines=args.json_lines != "-" and not args.quiet, lines_to_stderr=report_out,
                       json_lines=json_lines, evidence=evidence)
        session = Session(source, options, cfg, signals)
        stack.callback(session.close)
        session.run()
        if session.failure and (not session.reader.format or session.no_capture):   # no interface, not a capture
            print(f"vm110 monitor: {session.failure}", file=sys.stderr)
            return EXIT_USAGE
        if session.board is None and cfg.lines and not args.quiet:
            print(file=sys.stderr if report_out else sys.stdout)
        regret = session.intake.regret()
        if regret is not None:
            print(f"vm110 monitor: CRC {regret[0]}/{regret[1]} validates more packets than "
                  f"{session.intake.variant}/{session.intake.order}, chosen from the first ones; "
                  "`vm110 analyze` would judge them with it", file=sys.stderr)
        from ..analysis.report import build
        report = build(session.report_state())
        if evidence is not None and evidence.failed:       # (said when it happened; again here, with the report)
            print(f"vm110 monitor: evidence: {evidence.failed} alarm window(s) not written, the last: {evidence.error}",
                  file=sys.stderr)
        if evidence is not None and (evidence.written or evidence.over_limit or evidence.skipped) and not args.quiet:
            print(evidence.told(), file=sys.stderr)
        # The terminal hung up (the SSH session closed): the summary goes to standard error, a log
        # when it was sent to one (else nowhere); a report on standard output is lost with it.
        with contextlib.redirect_stdout(sys.stderr) if session.hung_up and not report_out else \
                contextlib.nullcontext():
            code = deliver(args, [name], [report], fail_rules, "monitor")
        if session.failure:        # (a capture damaged partway is the report's: deliver says it)
            print(f"vm110 monitor: {session.failure}", file=sys.stderr)
            return EXIT_USAGE
        return code
