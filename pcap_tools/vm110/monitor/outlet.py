"""Standard output that a reader who stops reading cannot stop the watch with.

A pipe whose reader stalls (`| less` at a full screen, a `tee` on a hung disk) or a terminal
paused by Ctrl-S blocks every write once its buffer is full: the monitor's loop stood still in
the middle of a finding line, and with it the watchdog, the evidence, dumpcap's pipe (the kernel
dropping the capture) and SIGTERM, which only sets a flag the blocked loop never looked at.

Here a write never waits: what the descriptor takes now is written (in pieces of PIPE_BUF, which
a writable pipe takes without blocking), the rest waits in a backlog of at most BACKLOG_BYTES,
written as the reader goes on. A text that would pass it is left out whole (no torn line), and
counted; once the backlog is written again, `note(count)` says how many were left out there.
"""
from __future__ import annotations

import os
import select
import time
from typing import IO, Any, Callable, Optional

BACKLOG_BYTES = 1 << 20        # about a thousand finding lines, or a few hundred screens
PIECE = select.PIPE_BUF        # what a pipe that polls writable takes without blocking


class Outlet:
    """Writes text to `stream` without waiting for its reader."""

    def __init__(self, stream: IO[str], note: Callable[[int], str]) -> None:
        self.stream, self.note = stream, note
        try:
            self.fd: Optional[int] = stream.fileno()
        except (AttributeError, ValueError, OSError):     # (a test's capture: written as it is)
            self.fd = None
        self.backlog = bytearray()
        self.left_out = 0               # texts left out since the backlog last emptied
        self.left_out_all = 0

    @property
    def busy(self) -> bool:
        """Whether the reader has not taken all that was written yet."""
        return bool(self.backlog)

    def write(self, text: str) -> None:
        """Write `text` now as far as the reader takes it (raises the stream's write errors)."""
        if self.fd is None:
            self.stream.write(text)
            self.stream.flush()
            return
        data = text.encode("utf-8", "replace")
        # (once one is left out, those after it are too until the reader caught up: the note's place)
        if self.left_out or len(self.backlog) + len(data) > BACKLOG_BYTES:
            self.left_out += 1
            self.left_out_all += 1
        else:
            self.backlog += data
        self.flush()

    def flush(self, timeout: float = 0.0) -> bool:
        """Write the backlog, waiting at most `timeout` seconds for the reader; whether it is all written."""
        if self.fd is None:
            return True
        deadline = time.monotonic() + timeout
        while self.backlog or self.left_out:
            if not self.backlog:        # (the reader caught up: say what it missed, then go on)
                self.backlog += self.note(self.left_out).encode("utf-8", "replace")
                self.left_out = 0
            wait = max(0.0, deadline - time.monotonic())
            if not select.select([], [self.fd], [], wait)[1]:
                return False
            del self.backlog[:os.write(self.fd, self.backlog[:PIECE])]
        return True

    def drop(self) -> None:
        """Forget what waits (the stream is gone, or pointed at /dev/null)."""
        self.backlog.clear()
        self.left_out = 0

    def __getattr__(self, name: str) -> Any:       # (isatty, name, ... of the stream)
        return getattr(self.stream, name)
