"""Fuzz a machine controller: play the base unit, inject odd packets, judge what it does.

Keeps a valid VRPI stream going (every 125 ms) so the controller stays in normal operation,
answers its VRCO with VRAI, resends an unacknowledged valid VRCI every 100 ms as the base unit does
(not with --no-resend), and sends cases (field boundary values, structural defects, sequences,
random byte changes) reproducible from --seed and the case index. Oracles: crash, stall,
missing_ack, illegal_acked, malformed_output, vrco_retransmit, and with --target-cmd memory (the
controller's RSS beyond --target-memory, or rising well past its warm-up level). Each confirmed finding is saved in
--out as JSON (with the minimised packet) and a pcap; --out/findings.json summarises the run.
Sends only to --target (multicast TTL 1), and only on loopback unless --allow-remote; never to a
broadcast address. Exit code 1 when there are findings or the controller was lost (it stopped and
could not be restarted), 0 when none, 2 on usage errors.
`--replay FINDING` sends a finding again and says whether it still triggers (a crash or a malformed
output: with the same signature or another); the finding is data: its stored command is never run and its stored target
obeys the --target rules. A crash finding keeps the controller's output, signal, sanitizer report,
core and gdb backtrace; triggers of one signature are one finding (a bucket with a count).
`--coverage` is coverage-guided fuzzing of a controller built with AFL++: --corpus keeps and
resumes its corpus, --out/coverage.html plots its edges (README: Fuzzing a controller you build).
"""
from __future__ import annotations

import argparse
import ipaddress
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from .. import constants as C
from ..errors import EXIT_FINDINGS, EXIT_INTERRUPTED, EXIT_OK, CliError
from ..fuzz.corpus import Entry, checked_entry, is_entry
from ..fuzz.coverage import map_size
from ..fuzz.destination import check
from ..fuzz.findings import MAX_FILE, check_out, finding_from_json, write_summary
from ..fuzz.guided import GuidedConfig
from ..fuzz.link import parse_endpoint
from ..fuzz.memory import Rule
from ..fuzz.oracles import CRASH, MEMORY, Limits
from ..fuzz.report_html import write_coverage_html
from ..fuzz.runner import RunConfig, Runner, finding_kind, replay_corpus_case, replay_finding, same_bug
from ..fuzz.session import Settings, TargetLost
from ..jsonin import load_file
from ..numbers import number
from ..words import plural
from .options import SEED

DEFAULT_RATE = 100.0
COVERAGE_RATE = 5000.0
DEFAULT_DURATION_S = 60.0
DURATION = number(0, 30 * 86400, "s", allow_zero=False)
CASES = number(1, 10**9, integer=True)
RATE = number(0.01, 10_000, "packets/s")
MAX_FINDINGS = number(1, 1000, integer=True)
MINIMIZE_BUDGET = number(0, 3600, "s", allow_zero=False)
STARTUP = number(0, 600, "s", allow_zero=False)
TARGET_MEMORY = number(1, 1 << 20, "MiB")
MEMORY_GROWTH = number(0, 1 << 20, "MiB", least=1)
DEFAULT_GROWTH_MIB = int((Rule().growth_kib or 0) // 1024)     # the rule's (README: what it finds)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--target", metavar="HOST:PORT",
                        help="where the controller receives input packets (the only destination; a name "
                             "is resolved once); loopback unless --allow-remote, never a broadcast address")
    parser.add_argument("--allow-remote", action="store_true",
                        help="allow a --target that is not loopback, a multicast group included (it reaches "
                             "every node on the segment); the address is printed before the first packet")
    parser.add_argument("--listen", metavar="HOST:PORT",
                        help=f"where the controller's output arrives (default 0.0.0.0:<target port + "
                             f"{C.OUTPUT_PORT_OFFSET}>, as the specification has it)")
    parser.add_argument("--group", metavar="ADDR", help=f"join this multicast group on the --listen port "
                        f"for the output (the specification's is {C.MULTICAST_GROUP})")
    parser.add_argument("--target-cmd", metavar="CMD", help="command that starts the controller; "
                        "it is started, watched, restarted after a crash and stopped at the end")
    parser.add_argument("--seed", type=SEED, default=0, help=f"case schedule seed, {SEED.range_text} (default 0)")
    stop = parser.add_mutually_exclusive_group()
    stop.add_argument("--duration", type=DURATION, metavar="S",
                      help=f"seconds to start new cases, {DURATION.range_text} (default {DEFAULT_DURATION_S:.0f}); "
                           "judging the last ones, replays and minimisation come on top")
    stop.add_argument("--cases", type=CASES, metavar="N", help=f"number of cases to run, {CASES.range_text}")
    parser.add_argument("--rate", type=RATE, metavar="PPS",
                        help=f"case packets per second at most, {RATE.range_text} (default {DEFAULT_RATE:.0f}, "
                             f"{COVERAGE_RATE:.0f} with --coverage)")
    parser.add_argument("--out", default="fuzz-out", metavar="DIR", help="findings directory (default fuzz-out)")
    parser.add_argument("--max-findings", type=MAX_FINDINGS, default=20, metavar="N",
                        help=f"stop after N findings, {MAX_FINDINGS.range_text} (default 20)")
    parser.add_argument("--minimize-budget", type=MINIMIZE_BUDGET, default=30.0, metavar="S",
                        help=f"seconds of replays spent minimising one finding, {MINIMIZE_BUDGET.range_text} "
                             "(default 30)")
    parser.add_argument("--startup", type=STARTUP, default=10.0, metavar="S",
                        help=f"seconds allowed for the controller's first VRPO, {STARTUP.range_text} (default 10)")
    parser.add_argument("--target-memory", type=TARGET_MEMORY, metavar="MIB",
                        help=f"with --target-cmd: a finding when the controller's resident memory (its process "
                             f"group's RSS, sampled every second) exceeds this, {TARGET_MEMORY.range_text} "
                             "(default: no limit)")
    parser.add_argument("--memory-growth", type=MEMORY_GROWTH, default=DEFAULT_GROWTH_MIB, metavar="MIB",
                        help="with --target-cmd: a finding when the RSS is at least this much, and half its warm-up "
                             "level (its highest in the first 5 s), above that level for 5 samples while still rising, "
                             f"{MEMORY_GROWTH.range_text}; 0 turns it off (default {DEFAULT_GROWTH_MIB})")
    parser.add_argument("--no-resend", action="store_true",
                        help=f"do not resend an unacknowledged VRCI (default: resent every {C.COMMAND_RESEND_MS} ms "
                             "on a new serial until its VRAO comes or the ack timeout passes, as the base unit "
                             "does); a missing ack is then any transmission not acknowledged. --replay: resend as "
                             "the finding says it did, unless given")
    parser.add_argument("--no-core", action="store_true",
                        help="start the controller with core files off (default: allowed, kept with a crash "
                             "finding, with a gdb backtrace when gdb is installed)")
    parser.add_argument("--coverage", action="store_true",
                        help="coverage-guided: the controller is built with AFL++ (afl-clang-fast / afl-cc) and "
                             "gets its coverage map through __AFL_SHM_ID (size AFL_MAP_SIZE, default 65536); "
                             f"--rate defaults to {COVERAGE_RATE:.0f}")
    parser.add_argument("--corpus", metavar="DIR", help="with --coverage: keep the corpus here (one JSON per "
                        "case) and resume from what is there")
    parser.add_argument("--dict", metavar="FILE", help="with --coverage: tokens in AFL's dictionary format "
                        "(name=\"value\" lines), besides the strings found in the target program")
    parser.add_argument("--replay", metavar="FINDING", help="send a saved finding (or a --corpus case) again "
                        "(its stored command is "
                        "not run: give --target-cmd); exit 1 if it still triggers")


def _settings(args: argparse.Namespace, target: str, listen: str | None, group: str | None,
              stored_in: str | None = None, listen_stored_in: str | None = None) -> Settings:
    """Settings from the options, or from a finding file (`stored_in` its target's, `listen_stored_in`
    its listen address's) where they are not given: a stored target obeys the --target rules, and
    stored addresses are never names to look up."""
    what = f"the target stored in {stored_in}" if stored_in else "--target"
    host_port = parse_endpoint(target, what, numeric=bool(stored_in))
    check(host_port[0], what, args.allow_remote)
    if ":" in host_port[0]:
        raise CliError(f"{what}: {host_port[0]} is IPv6; the fuzzer sends IPv4 only")
    if group is not None:
        try:
            if not ipaddress.IPv4Address(group).is_multicast:
                raise ValueError
        except ValueError:
            raise CliError(f"--group {group[:80]!r} is not an IPv4 multicast address") from None
    listen_what = f"the listen address stored in {listen_stored_in}" if listen_stored_in else "--listen"
    if listen:
        listen_at = parse_endpoint(listen, listen_what, numeric=bool(listen_stored_in))
    elif host_port[1] + C.OUTPUT_PORT_OFFSET <= 65535:
        listen_at = ("0.0.0.0", host_port[1] + C.OUTPUT_PORT_OFFSET)
    else:
        raise CliError("--listen is needed: target port + 2 is not a port")
    if listen_at[1] == host_port[1] and (listen_at[0] == host_port[0] or (
            listen_at[0] == "0.0.0.0" and ipaddress.ip_address(host_port[0]).is_loopback)):
        # The fuzzer would receive what it sends, and the controller could not bind its port.
        raise CliError(f"{listen_what} {listen_at[0]}:{listen_at[1]} is the --target: the "
                       "controller's output arrives on another port (the specification's: the target port + 2)")
    if args.allow_remote:
        _progress(f"sending to {host_port[0]}:{host_port[1]} only ({what} {_printable(target)})")
    rate = args.rate or (COVERAGE_RATE if getattr(args, "coverage", False) else DEFAULT_RATE)
    return Settings(target=host_port, listen=listen_at, group=group, rate=rate, limits=Limits(),
                    startup_s=args.startup, allow_remote=args.allow_remote,
                    resend_ms=0.0 if args.no_resend else float(C.COMMAND_RESEND_MS))


def _printable(text: str, limit: int = 200) -> str:
    """Text from a file, safe to print: no control characters, bounded."""
    return "".join(c if c.isprintable() else "?" for c in text[:limit])


def _progress(text: str) -> None:
    # What the runner says quotes the controller's output and the cases' bytes (a sanitizer's
    # frames, a havoc'd packet ID): no control character reaches the terminal.
    print(f"vm110 fuzz: {_printable(text, 2000)}", file=sys.stderr, flush=True)


# Set by Ctrl-C or SIGTERM. The KeyboardInterrupt raised with it can land in a finalizer (a Popen's
# __del__), where Python ignores it: the runner also stops at its next case or replay on the flag.
_STOP = threading.Event()


def _interrupt(signum: int, frame: Any) -> None:
    _STOP.set()
    raise KeyboardInterrupt   # unwinds through the runner, which stops the supervised controller


def run(args: argparse.Namespace) -> int:
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    for option, value in (("--target-cmd", args.target_cmd), ("--out", args.out)):
        if value is not None and not value.strip():
            raise CliError(f"{option} is empty")
    if args.replay:
        return _replay(args)
    if not args.target:
        raise CliError("--target HOST:PORT is required (or --replay FINDING)")
    settings = _settings(args, args.target, args.listen, args.group)
    out = Path(args.out)
    check_out(out)    # refused now, not after the run
    duration = None if args.cases else (args.duration or DEFAULT_DURATION_S)
    guided = None
    if args.coverage:
        if not args.target_cmd:
            raise CliError("--coverage needs --target-cmd (the fuzzer starts the controller with its coverage map)")
        guided = GuidedConfig(map_size(), Path(args.corpus) if args.corpus else None, args.dict)
    elif args.corpus or args.dict:
        raise CliError("--corpus and --dict go with --coverage")
    if args.target_memory is not None and not args.target_cmd:
        raise CliError("--target-memory needs --target-cmd (only a controller the fuzzer starts is measured)")
    memory = Rule(limit_kib=None if args.target_memory is None else args.target_memory * 1024,
                  growth_kib=args.memory_growth * 1024 or None)
    status = _StatusLine() if sys.stderr.isatty() else None
    cfg = RunConfig(settings=settings, seed=args.seed, duration_s=duration, cases=args.cases, out=out,
                    target_cmd=args.target_cmd, minimize_budget_s=args.minimize_budget,
                    max_findings=args.max_findings, progress=status.message if status else _progress,
                    status=status, core=not args.no_core, coverage=guided, stop=_STOP.is_set, memory=memory)
    runner = Runner(cfg)
    try:
        summary = runner.run()
    finally:
        if status is not None:
            status.done()
    if summary["stopped_early"] and not runner.interrupted and not summary["findings"] and summary["cases_run"] == 0:
        raise CliError(summary["stopped_early"])    # it never started: no summary to keep --out from a retry
    write_summary(out, summary)
    if guided is not None:
        write_coverage_html(out / "coverage.html", summary)
    for bucket in summary["buckets"]:
        seen = f"{bucket['count']} time{'s' if bucket['count'] != 1 else ''}"
        print(f"{_printable(bucket['headline'])} [{seen}] -> {out / bucket['file']}")
    replayable = [b for b in summary["buckets"] if b["oracle"] != MEMORY]
    if replayable:
        first = shlex.quote(str(out / replayable[0]["file"]))
        print(f"replay one: vm110 fuzz --replay {first}"
              + (f" --target-cmd {shlex.quote(args.target_cmd)}" if args.target_cmd else ""))
    for finding in summary["findings"]:
        if finding["oracle"] == MEMORY:     # no case of its own to replay: the same cases again
            print(f"the memory finding comes of many cases, not one (no --replay): rerun them with "
                  f"{_printable(finding['rerun'], 2000)}")
    rate = summary["cases_run"] / max(summary["duration_s"], 1e-6)
    triggers = sum(b["count"] for b in summary["buckets"])
    print(f"{plural(summary['cases_run'], 'case')} in {summary['duration_s']:.1f} s ({rate:.0f}/s), "
          f"{plural(len(summary['findings']), 'finding')} ({plural(triggers, 'trigger')}), "
          f"{plural(len(summary['unreproduced']), 'unreproduced trigger')}, {plural(summary['restarts'], 'restart')}"
          + (f", {plural(summary['replay_starts'], 'start')} for replays" if summary["replay_starts"] else "")
          + (f"; stopped early: {summary['stopped_early']}" if summary["stopped_early"] else ""))
    if "coverage" in summary:
        cov = summary["coverage"]
        by_second = {round(p["s"]): p["edges"] for p in cov["edges_over_time"]}   # each second's last count
        seconds = list(by_second)
        shown = dict.fromkeys(seconds[::max(1, len(seconds) // 6)][:6] + seconds[-1:])
        over_time = ", ".join(f"{s} s: {by_second[s]}" for s in shown)
        print(f"coverage: {cov['edges']} edges, corpus {cov['corpus']} cases; edges over time {over_time} "
              f"(all in {out / 'findings.json'}, plotted in {out / 'coverage.html'})")
        resumed = cov.get("resumed")
        if resumed and resumed["cases"] < resumed["of"]:
            why = summary["stopped_early"] or "--duration or --cases"
            print(f"--corpus: only {resumed['cases']} of its {resumed['of']} cases were played again before the run "
                  f"ended ({_printable(why)}): its coverage is not all restored")
        elif resumed and resumed["stored_edges"] and resumed["edges"] < resumed["stored_edges"]:
            print(f"--corpus: its {resumed['of']} cases played again reached {resumed['edges']} edges, the runs "
                  f"that kept them {resumed['stored_edges']}: the rest depend on a state the stored cases do not "
                  "make again (what cases not kept left behind, the order they ran in)")
        elif resumed:
            print(f"--corpus: its {resumed['of']} cases played again reached {resumed['edges']} edges")
        if cov["corpus_skipped"]:
            print(f"--corpus: {len(cov['corpus_skipped'])} unreadable files skipped, e.g. "
                  f"{_printable(cov['corpus_skipped'][0])} (all in findings.json)")
    if args.target_cmd:
        options = ", ".join(f"{k}={'(yours)' if v == 'user' else v}" for k, v in summary["sanitizer_options"].items())
        cores = "core files: on" if summary["core_files"] == "on" else f"no core files: {summary['core_files']}"
        print((f"sanitizer options: {options}; " if options else "") + cores)
    print(_memory_line(summary["memory"]))
    if summary["controller_lost"]:
        last = summary["unreproduced"][-1] if summary["unreproduced"] else None
        seen = _printable(last["detail"]) if last else "no VRPO"
        print((f"the controller could not be restarted ({_printable(summary['stopped_early'])}) to replay what it "
               f"did ({seen})" if args.target_cmd else f"the controller stopped while being fuzzed ({seen}) and "
               "there is no --target-cmd to restart and replay it") + ": the cases that may have caused it, "
              f"{', '.join(_printable(c) for c in last.get('suspect_cases', [])[:3]) if last else 'unknown'}, "
              f"... (most likely first) are in {out / 'findings.json'} (unreproduced)")
    # A process that died is no hiccup of a loaded machine, as a late ack may be: a crash no replay
    # made again (a race, a state its cases alone do not make) is no finding, but no pass either.
    crashed = [u for u in summary["unreproduced"] if u["oracle"] == CRASH and "not_replayed" not in u]
    if crashed:
        print(f"the controller crashed {plural(len(crashed), 'time')} where replaying its cases did not crash it again "
              f"({_printable(crashed[0]['detail'])}): no finding, no reproducer, but no pass; its output is in "
              f"{out / 'target.log'}, the cases in {out / 'findings.json'} (unreproduced)")
    if runner.interrupted:
        return EXIT_INTERRUPTED
    if summary["findings"] or summary["controller_lost"] or crashed:
        return EXIT_FINDINGS
    if summary["cases_run"] == 0 and duration is not None:     # (nothing was tested: no pass for a CI gate)
        raise CliError(f"no case ran: --duration {duration:g} s ended before the first case (the controller's "
                       "start and its first VRPO come first)")
    return EXIT_OK


def _memory_line(memory: dict[str, Any]) -> str:
    """What the memory oracle watched: the RSS at the end and at most, or why it was off."""
    if memory["oracle"] == "off":
        return f"memory oracle off: {memory['why']}"
    seen = (f"RSS {memory['rss_kib'] / 1024:.1f} MiB at the last sample, {memory['peak_kib'] / 1024:.1f} MiB at most"
            if memory["rss_kib"] is not None else "no sample taken")
    return f"memory: {seen} ({memory['rule']})"


class _StatusLine:
    """One line on the terminal, rewritten in place: cases, rate, findings, coverage, time left."""

    def __init__(self) -> None:
        self.shown = False

    def __call__(self, line: dict[str, Any]) -> None:
        parts = [plural(line["cases"], "case"), f"{line['rate_now']:.0f}/s (average {line['rate']:.0f}/s)",
                 f"{plural(line['findings'], 'finding')} ({plural(line['triggers'], 'trigger')})"]
        if "edges" in line:
            parts += [f"{line['edges']} edges", f"corpus {line['corpus']}"]
        if "rss_kib" in line:
            parts.append(f"RSS {line['rss_kib'] / 1024:.1f} MiB")
        if line["left_s"] is not None:
            parts.append(f"{line['left_s']:.0f} s left")
        sys.stderr.write("\r\x1b[Kvm110 fuzz: " + ", ".join(parts))
        sys.stderr.flush()
        self.shown = True

    def message(self, text: str) -> None:
        self.done()
        _progress(text)

    def done(self) -> None:
        if self.shown:
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()
            self.shown = False


def _replay(args: argparse.Namespace) -> int:
    # Read once: a pipe (--replay <(...)) cannot be read again to tell a corpus case from a finding.
    raw = load_file(args.replay, MAX_FILE, "a vm110 fuzz finding or corpus case")
    if is_entry(raw):
        return _replay_corpus(args, checked_entry(raw, args.replay))
    finding = finding_from_json(raw, args.replay)
    if finding.oracle == MEMORY:
        # No case of its own to send: what it measured came of many, over seconds.
        rerun = (finding.memory or {}).get("rerun")
        raise CliError(f"{args.replay} is a memory finding: a leak grows over many cases, and one case played "
                       "again shows none; run the fuzzer again instead"
                       + (f": {_printable(str(rerun), 2000)}" if rerun else f" (--seed {finding.seed})"))
    if finding.oracle == CRASH and not args.target_cmd:
        # Only a controller the fuzzer started can be seen to exit: "fixed" would be a guess.
        raise CliError(f"{args.replay} is a crash finding: give --target-cmd (a crash is seen only in a "
                       "controller the fuzzer starts)")
    stored_in = None if args.target else args.replay
    # Joining a group sends IGMP out of an interface: only when the command line says so.
    settings = _settings(args, args.target or finding.target, args.listen or finding.listen, args.group, stored_in,
                         None if args.listen else args.replay)
    if not args.no_resend:
        settings.resend_ms = finding.resend_ms     # the base unit as it was when the finding was made
    if finding.group and not args.group:
        _progress(f"not joining the multicast group stored in {args.replay} (give --group to join it): "
                  f"{_printable(finding.group)}")
    if finding.family == "sequence-of-cases" and finding.cases is None:
        # (written before a finding of several cases kept each one's stream, pause and withholding)
        _progress(f"{args.replay} keeps the packets of its cases, not what the base unit did during each (a "
                  "disarmed stream, a pause): its replay sends them under the armed stream, and 'does not "
                  "trigger' may only mean that")
    if finding.target_cmd and not args.target_cmd:
        _progress(f"not running the command stored in {args.replay} (give --target-cmd to start a "
                  f"controller): {_printable(finding.target_cmd)!r}")
    try:
        trig = replay_finding(finding, settings, args.target_cmd, sys.stderr.buffer, not args.no_core)
    except TargetLost as exc:
        raise CliError(str(exc)) from None
    verdict = "still triggers" if trig else "does not trigger any more"
    kind = finding_kind(finding)
    if trig is not None and kind is not None:
        signal_only = trig.crash is not None and trig.kind != kind and trig.crash.signal_only(finding.crash)
        same = ": the same signal (with no stack to compare, it may be another bug)" if signal_only else \
            ": the same signature"
        verdict += (same if same_bug(finding, trig) else
                    f": another signature ({_printable(trig.detail)}; the finding's: {_printable(finding.signature)})")
        if trig.crash is not None and trig.crash.site_moved(finding.crash):
            # (an edit of the controller moves its lines: the same function, kind and callers)
            verdict += f" but for its line ({_printable(trig.detail)}; the finding's: {_printable(finding.detail)})"
    print(f"{args.replay}: {finding.oracle} ({_printable(finding.mutation)}): {verdict}")
    return EXIT_FINDINGS if trig else EXIT_OK


def _replay_corpus(args: argparse.Namespace, entry: Entry) -> int:
    """A `--corpus` case: it stores no target (give --target), and says what the oracles saw."""
    if not args.target:
        raise CliError(f"--target HOST:PORT is needed to replay {args.replay} (a corpus case stores none)")
    settings = _settings(args, args.target, args.listen, args.group)
    try:
        triggers = replay_corpus_case(entry, settings, args.target_cmd, sys.stderr.buffer, not args.no_core)
    except TargetLost as exc:
        raise CliError(str(exc)) from None
    for trig in triggers:
        print(f"{args.replay}: {trig.oracle}: {_printable(trig.detail)}")
    outcome = f"{len(triggers)} trigger(s)" if triggers else "no trigger"
    print(f"{args.replay}: {len(entry.packets)} packet(s), {outcome}")
    return EXIT_FINDINGS if triggers else EXIT_OK
