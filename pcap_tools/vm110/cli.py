"""The `vm110` command: one subcommand per module, registered in COMMANDS.

Exit codes are those of `vm110.errors`: 0 success, 1 findings (rule violations, fuzzer findings),
2 usage error or unreadable input, 130 interrupted.
"""
from __future__ import annotations

import argparse
import ast
import gc
import importlib
import importlib.abc
import importlib.util
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


def _chosen(argv: Sequence[str]) -> Optional[str]:
    """The command `argv` names: its first word that is no option (the top parser's options,
    --help and --version, take no value). None for none, or a word that names no command."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def _summary(module_name: str) -> Optional[str]:
    """The first line of a command module's docstring, read without importing it."""
    name = f"vm110.commands.{module_name}"
    spec = importlib.util.find_spec(name)
    loader = spec.loader if spec is not None else None
    source = loader.get_source(name) if isinstance(loader, importlib.abc.InspectLoader) else None
    doc = ast.get_docstring(ast.parse(source)) if source else None
    return doc.strip().splitlines()[0] if doc else None


def build_parser(argv: Optional[Sequence[str]] = None) -> Parser:
    """The whole parser; given the command line, only the command it names is loaded.

    (A command's module brings its libraries: all of them took a second to load before any
    command started, `vm110 --help` included.)"""
    parser = Parser(prog="vm110", description="Tools for the VM-110 EG-Link (TS-0006).")
    parser.commands = {}
    parser.add_argument("--version", action="version", version=f"vm110 {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = _chosen(argv) if argv is not None else None
    for name, module_name in COMMANDS.items():
        if argv is not None and name != chosen:
            # (shown only by the top parser's help and errors, which load no command)
            parser.commands[name] = sub.add_parser(name, help=None if chosen else _summary(module_name))
            continue
        module = importlib.import_module(f"vm110.commands.{module_name}")
        doc = (module.__doc__ or "").strip().splitlines()
        command = sub.add_parser(name, help=doc[0] if doc else None, description=module.__doc__)
        module.add_arguments(command)
        command.set_defaults(run=module.run)
        parser.commands[name] = command
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    closedpipe.said.unwritable = None
    args: Optional[argparse.Namespace] = None
    stopped = EXIT_OK
    # (--help and --version print, then exit: into a full disk that was exit 0 and no word)
    with closedpipe.tolerated(_chosen(words)):
        try:
            args = build_parser(words).parse_command(argv)
        except KeyboardInterrupt:       # while the commands' modules load (scapy's take a while)
            return EXIT_INTERRUPTED
        except SystemExit as exc:       # --help, --version, a usage error
            stopped = exc.code if isinstance(exc.code, int) else EXIT_USAGE
    if args is None:        # (as argparse ends: a SystemExit, for callers in-process too)
        raise SystemExit(EXIT_USAGE if closedpipe.said.unwritable is not None else stopped)
    # A closed pipe ends the output quietly, and the final flush is made here, not at exit. It
    # keeps the command's code; one that escapes the command keeps 0: commands with a verdict
    # (analyze) catch it around their output and go on to the verdict.
    code = EXIT_OK
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
