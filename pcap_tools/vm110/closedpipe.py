"""Standard output whose reader went away (`vm110 analyze x | head`): end the output quietly.

Python ignores SIGPIPE, so a write to a closed pipe raises BrokenPipeError; after that the
interpreter's own flush at exit would fail again and print "Exception ignored ...". As the
Python documentation advises (signal module, "Note on SIGPIPE"), standard output is pointed at
/dev/null once the pipe is gone. The command decides its exit code itself: a cut-off output never
hides a verdict (analyze --fail-on still exits 1). Standard output that cannot be written for
another reason (a full disk) is said in one line, and the command's exit code becomes 2.
"""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from typing import IO, Any, Optional


def silence_stdout(stream: Optional[IO[Any]] = None) -> None:
    """Point standard output's (or `stream`'s) file descriptor at /dev/null (nothing to do without one)."""
    try:
        fd = (sys.stdout if stream is None else stream).fileno()
    except (AttributeError, ValueError, OSError):     # replaced by a test's capture, or closed
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


class StdoutUnwritable(Exception):
    """Standard output failed otherwise than by a closed pipe (`> /dev/full`, a full disk). Not an
    OSError: the handlers of a command's own files must not take it for theirs."""


class _Guarded:
    """Standard output whose write errors, but a closed pipe's, are StdoutUnwritable: a command
    writes to it in many places, and only here is such an error told from one of its input or
    files (it was a traceback)."""

    def __init__(self, stream: IO[Any]) -> None:
        self._stream = stream

    def write(self, data: Any) -> int:          # (text, or bytes on the buffer)
        return self._call(self._stream.write, data)

    def flush(self) -> None:
        self._call(self._stream.flush)

    def _call(self, method: Callable[..., Any], *args: Any) -> Any:
        try:
            return method(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise StdoutUnwritable(exc.strerror or str(exc)) from None

    @property
    def buffer(self) -> "_Guarded":
        """The binary stream beneath, guarded alike (a capture written to standard output)."""
        return _Guarded(self._stream.buffer)      # type: ignore[attr-defined]  # (a TextIO's)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


class _Said:
    # Why standard output could not be written, once said: the command's output is incomplete,
    # and its exit code 2.
    unwritable: Optional[str] = None


said = _Said()


@contextlib.contextmanager
def tolerated(command: Optional[str]) -> Iterator[None]:
    """Writes to standard output inside, then a flush. A closed pipe ends them quietly; standard
    output that cannot be written ends them with one line on standard error, `vm110 COMMAND:
    cannot write standard output: ...`, and sets `said.unwritable`. What follows the block (report
    files, a verdict) still runs."""
    stream = sys.stdout
    sys.stdout = _Guarded(stream)
    try:
        yield
        sys.stdout.flush()
    except BrokenPipeError:
        silence_stdout()
    except StdoutUnwritable as exc:
        silence_stdout()        # (what stays in the buffer would fail again at exit)
        if said.unwritable is None:
            said.unwritable = str(exc)
            print(f"{f'vm110 {command}' if command else 'vm110'}: cannot write standard output: {exc}",
                  file=sys.stderr)
    finally:
        sys.stdout = stream
