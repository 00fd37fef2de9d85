"""Synthesise a capture with its ground truth (work in progress)."""
from __future__ import annotations

import argparse

from ..errors import CliError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?")


def run(args: argparse.Namespace) -> int:
    raise CliError("not ready yet")
