"""Synthesise a capture of a named scenario, with its ground truth next to it.

Runs the simulators on a virtual clock (no sleeping) and writes FILE (pcap or pcapng, as a network
tap on the multicast group sees it) and FILE.truth.json (exact figures: loss, duplicates, order,
commands, watchdogs, illegal packets, VRPO bursts). The same seed gives byte-identical files.
`--crc`, `--crc-order`, `--serial-scope` and `--vrpo-start` make both devices speak another reading
of TS-0006, as `simulate` does; the truth is then what `analyze` gives under the same options.
Each file is written to a temporary file beside it and renamed into place when complete: a failure
leaves what was there before. A target that is not a regular file is refused.
"""
from __future__ import annotations

import argparse
import signal
from typing import Any, NoReturn

from ..capture.writer import FORMATS, Format, format_of
from ..errors import CliError
from ..numbers import number
from ..sim.scenario import SCENARIOS
from ..synth import output_rate, synthesize, truth_path
from ..timefmt import utc_iso
from .options import SEED, VRPO_START, VRPO_START_HELP, add_reading_options, reading_of

GIB = 1 << 30
MAX_OUTPUT_BYTES = 4 * GIB
# Finite and positive; how long is too long depends on the scenario's rate (MAX_OUTPUT_BYTES).
DURATION = number(1e-6, 1e9, "s")      # from the clock's step (less was no packet at all)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    parser.add_argument("--out", help="capture file to write; the truth goes to OUT.truth.json")
    parser.add_argument("--seed", type=SEED, default=1,
                        help=f"seed of every random choice, {SEED.range_text} (default 1)")
    parser.add_argument("--duration", type=DURATION, metavar="S",
                        help=f"seconds of traffic, {DURATION.range_text}, and at most "
                             f"{MAX_OUTPUT_BYTES // GIB} GiB of output (default: the scenario's)")
    parser.add_argument("--format", choices=FORMATS, help="capture format (default: from the extension, else pcap)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    add_reading_options(parser, found=False)     # (another reading of TS-0006: analyze takes the same)
    parser.add_argument("--vrpo-start", type=VRPO_START, default=0, metavar="N", help=VRPO_START_HELP)


def check_size(name: str, duration: float, seed: int, fmt: Format) -> None:
    """CliError, with the projected size, when `duration` s of `name` would write more than
    MAX_OUTPUT_BYTES."""
    if duration <= SCENARIOS[name].duration_s:
        return      # the scenarios' own durations are small: no need to measure
    rate = output_rate(name, seed, fmt)
    if rate * duration > MAX_OUTPUT_BYTES:
        raise CliError(f"--duration {duration:g} s would write about {rate * duration / GIB:,.0f} GiB; "
                       f"at most {MAX_OUTPUT_BYTES / rate:.0f} s for {name} "
                       f"({MAX_OUTPUT_BYTES // GIB} GiB at {rate / 1024:.0f} KiB/s)")


def _interrupt(signum: int, frame: Any) -> NoReturn:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    # SIGTERM (`timeout`, a CI job cancelled) and SIGHUP (its terminal closed) are interruptions
    # like Ctrl-C: the temporary files are removed on the way out (killed by either, a run left
    # them beside OUT, up to gigabytes).
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        return _synth(args)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _synth(args: argparse.Namespace) -> int:
    if args.list:
        for sc in SCENARIOS.values():
            print(f"{sc.name:<20} {sc.duration_s:>7g} s  {sc.description}")
        return 0
    if not args.scenario or not args.out:
        raise CliError("give a SCENARIO and --out FILE (or --list)")
    if args.out == "-":      # (elsewhere standard output: here a capture and its truth beside it)
        raise CliError("--out - : synth writes a capture file and OUT.truth.json beside it; give a file name")
    if args.scenario not in SCENARIOS:
        raise CliError(f"unknown scenario {args.scenario!r}; choose from {', '.join(SCENARIOS)}")
    fmt: Format = args.format or format_of(args.out)
    if args.duration is not None:
        check_size(args.scenario, args.duration, args.seed, fmt)
    truth = synthesize(args.scenario, args.out, args.seed, args.duration, fmt, reading_of(args))
    cap = truth["capture"]
    span = "no packet" if cap["first_time"] is None else \
        f"{cap['duration_s']:.3f} s from {utc_iso(cap['first_time'])} to {utc_iso(cap['last_time'])}"
    print(f"wrote {cap['packets']} packets ({span}) to {args.out}, ground truth to {truth_path(args.out)}")
    return 0
