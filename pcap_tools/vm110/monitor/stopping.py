"""The signals that end a monitoring run: SIGINT (Ctrl-C; a second one at once), SIGTERM, and
SIGHUP (its terminal or SSH session closed). They are caught from before dumpcap starts to the
report's end: one that came during the start-up killed the process where it stood, dumpcap left
running behind it (docs/monitor.md, "Stopping"). A signal ignored when the monitor started stays
ignored (`nohup vm110 monitor ...` outlives its SSH session)."""
from __future__ import annotations

import errno
import os
import signal
from types import FrameType, TracebackType
from typing import IO, Optional

STOPPING = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Signals:
    """While entered, a stopping signal sets `asked` (its number); a second SIGINT raises
    KeyboardInterrupt. The handlers in place before are put back at the exit."""

    def __init__(self) -> None:
        self.asked: Optional[int] = None
        self.previous: dict = {}

    def __enter__(self) -> Signals:
        self.previous = {sig: signal.signal(sig, self._handler) for sig in STOPPING
                         if signal.getsignal(sig) is not signal.SIG_IGN}
        return self

    def __exit__(self, kind: Optional[type], exc: Optional[BaseException], tb: Optional[TracebackType]) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)

    def _handler(self, signum: int, frame: Optional[FrameType]) -> None:
        if self.asked is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt      # a second Ctrl-C: give up at once
        self.asked = signum


def hung_up(stream: IO[str]) -> bool:
    """Whether `stream` is a terminal that hung up (its SSH session or window closed): every write
    to it fails with EIO, an empty one too, which writes nothing anywhere else."""
    try:
        os.write(stream.fileno(), b"")
    except OSError as exc:
        return exc.errno == errno.EIO
    except (AttributeError, ValueError):     # (no file descriptor: a test's capture)
        return False
    return False
