"""Standard output whose reader went away (`vm110 analyze x | head`): end the output quietly.

Python ignores SIGPIPE, so a write to a closed pipe raises BrokenPipeError; after that the
interpreter's own flush at exit would fail again and print "Exception ignored ...". As the
Python documentation advises (signal module, "Note on SIGPIPE"), standard output is pointed at
/dev/null once the pipe is gone. The command decides its exit code itself: a cut-off output never
hides a verdict (analyze --fail-on still exits 1).
"""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

from .errors import CliError


def silence_stdout() -> None:
    """Point standard output's file descriptor at /dev/null (nothing to do without one)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):     # replaced by a test's capture, or closed
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


@contextlib.contextmanager
def tolerated() -> Iterator[None]:
    """Writes to standard output inside, then a flush: a closed pipe ends them, nothing else."""
    try:
        yield
        sys.stdout.flush()
    except BrokenPipeError:
        silence_stdout()


def print_line(text: str) -> None:
    """`text` as one line on standard output, flushed. Standard output that cannot be written (a
    log on a full disk) is a CliError naming it, not a traceback; a closed pipe passes on to
    `tolerated`."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        raise
    except OSError as exc:
        silence_stdout()       # what stays buffered would fail again at exit
        raise CliError(f"cannot write standard output: {exc.strerror or exc}") from None
