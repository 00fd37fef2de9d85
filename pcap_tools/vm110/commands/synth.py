"""Synthesise a capture of a named scenario, with its ground truth next to it.

Runs the simulators on a virtual clock (no sleeping) and writes FILE (pcap or pcapng, as a network
tap on the multicast group sees it) and FILE.truth.json (exact figures: loss, duplicates, order,
commands, watchdogs, illegal packets, VRPO bursts). The same seed gives byte-identical files.
"""
from __future__ import annotations

import argparse

from ..capture.writer import FORMATS
from ..errors import CliError
from ..sim.scenario import SCENARIOS
from ..synth import remove_outputs, synthesize, truth_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    parser.add_argument("--out", help="capture file to write; the truth goes to OUT.truth.json")
    parser.add_argument("--seed", type=int, default=1, help="seed of every random choice (default 1)")
    parser.add_argument("--duration", type=float, help="seconds of traffic (default: the scenario's)")
    parser.add_argument("--format", choices=FORMATS, help="capture format (default: from the extension, else pcap)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")


def run(args: argparse.Namespace) -> int:
    if args.list:
        for sc in SCENARIOS.values():
            print(f"{sc.name:<20} {sc.duration_s:>7g} s  {sc.description}")
        return 0
    if not args.scenario or not args.out:
        raise CliError("give a SCENARIO and --out FILE (or --list)")
    if args.scenario not in SCENARIOS:
        raise CliError(f"unknown scenario {args.scenario!r}; choose from {', '.join(SCENARIOS)}")
    if args.duration is not None and args.duration <= 0:
        raise CliError("--duration must be positive")
    fmt = args.format or ("pcapng" if args.out.endswith(".pcapng") else "pcap")
    try:
        truth = synthesize(args.scenario, args.out, args.seed, args.duration, fmt)
    except OSError as exc:
        remove_outputs(args.out)
        raise CliError(f"cannot write {exc.filename or args.out}: {exc.strerror}") from None
    print(f"wrote {truth['capture']['packets']} packets ({truth['capture']['duration_s']:.3f} s) to {args.out}, "
          f"ground truth to {truth_path(args.out)}")
    return 0
