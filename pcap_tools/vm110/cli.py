"""The `vm110` command: one subcommand per module, registered in COMMANDS.

Exit codes are those of `vm110.errors`: 0 success, 1 findings (rule violations, fuzzer findings),
2 usage error or unreadable input, 130 interrupted.
"""
from __future__ import annotations

import argparse
import gc
import importlib
import sys
from typing import NoReturn, Optional, Sequence

from . import __version__, closedpipe
from .printable import escaped
from .errors import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, CliError

# The analyses keep many small objects (per sender, command and finding) that live for the whole
# run: at the collector's default (a collection every 700 new ones, each also looking at the
# older) the collections took a third of the CPU time of a capture of 20,000 senders. Fewer and
# larger ones, as mypy runs; restored for a caller that runs `main` in its own process.
GC_THRESHOLD = (100_000, 50, 100)

# Subcommand name -> module under vm110.commands with `add_arguments(parser)` and `run(args)`.
COMMANDS = {
    "analyze": "analyze",
    "craft": "craft",
    "decode": "decode",
    "dissect": "dissect",
    "fleet": "fleet",
    "fuzz": "fuzz",
    "monitor": "monitor",
    "simulate": "simulate",
    "synth": "synth",
    "wireshark": "wireshark",
}


class Parser(argparse.ArgumentParser):
    """Usage errors as one line, `vm110 <cmd>: <message>`, exit 2: the message names the option,
    and the usage lines argparse prints first would bury it (`--help` gives them)."""

    commands: dict[str, argparse.ArgumentParser]

    def error(self, message: str) -> NoReturn:
        command = " ".join(self.prog.split()[:2])     # a role (simulate bu) is not part of the name
        self.exit(EXIT_USAGE, f"{command}: {' '.join(message.splitlines())}\n")

    def parse_command(self, argv: Optional[Sequence[str]]) -> argparse.Namespace:
        """parse_args, with an unknown argument told by its command ("vm110 analyze: ..."; argparse
        leaves it to the top parser, which says "vm110: ...")."""
        args, extra = self.parse_known_args(argv)
        if extra:
            self.commands[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
        return args


def build_parser() -> Parser:
    parser = Parser(prog="vm110", description="Tools for the VM-110 EG-Link (TS-0006).")
    parser.commands = {}
    parser.add_argument("--version", action="version", version=f"vm110 {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(f"vm110.commands.{module_name}")
        doc = (module.__doc__ or "").strip().splitlines()
        command = sub.add_parser(name, help=doc[0] if doc else None, description=module.__doc__)
        module.add_arguments(command)
        command.set_defaults(run=module.run)
        parser.commands[name] = command
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    try:
        args = build_parser().parse_command(argv)
    except KeyboardInterrupt:       # while the commands' modules load (scapy's take a while)
        return EXIT_INTERRUPTED
    # A closed pipe ends the output quietly, and the final flush is made here, not at exit. It
    # keeps the command's code; one that escapes the command keeps 0: commands with a verdict
    # (analyze) catch it around their output and go on to the verdict.
    code = EXIT_OK
    closedpipe.said.unwritable = None
    threshold = gc.get_threshold()
    gc.set_threshold(*GC_THRESHOLD)
    with closedpipe.tolerated(args.command):
        try:
            code = int(args.run(args) or EXIT_OK)
        except CliError as exc:
            # (its file names and values may come from anywhere: a terminal's escapes as text)
            print(f"vm110 {args.command}: {escaped(str(exc))}", file=sys.stderr)
            code = EXIT_USAGE
        except KeyboardInterrupt:
            code = EXIT_INTERRUPTED
        finally:
            gc.set_threshold(*threshold)
    if closedpipe.said.unwritable is not None and code != EXIT_INTERRUPTED:
        code = EXIT_USAGE       # (the output is incomplete: 2 wins over 1, as for input not read whole)
    return code


if __name__ == "__main__":
    sys.exit(main())
