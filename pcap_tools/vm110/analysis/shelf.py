"""Senders set aside in a file (`vm110 monitor`, for runs of days; docs/monitor.md, "Memory for
long runs").

The report lists every sender ever heard, and a sender's state is some 10 kB of memory: a fuzzer,
spoofed packets or a device on a new source port for every packet grew the monitor by 10 MB per
1000 senders, for as long as it ran. `Analysis` keeps in memory the KEEP senders heard last; one
heard before them, with nothing pending (no undecided packet, no serial scope still being chosen,
no predecessor's state still to come), goes whole to the file, pickled as it is, and memory keeps
a `Shelved` stub. A sender heard again, or taken over by a restart on a new port, comes back as
it was: the analysis goes on exactly as if it had never left, and the report is `analyze`'s.
"""
from __future__ import annotations

import os
import pickle
from typing import Any, BinaryIO

from .periodic import spill

KEEP = 2048         # senders kept in memory, those heard last (a mirror port of 20 pairs has 40)


class Shelved:
    """What memory keeps of a sender in the file: where it lies, and what is asked of every sender
    (its id; the new-port rule's port and last packet; the live view's `taken_over`). Anything else
    is read from a copy read back (`Analysis.sender`), not to be changed."""

    __slots__ = ("analysis", "at", "id", "key", "last_frame", "last_ts", "port", "size", "taken_over")

    def __init__(self, analysis: Any, key: int, at: int, size: int, snd: Any) -> None:
        self.analysis, self.key, self.at, self.size = analysis, key, at, size
        self.id, self.port, self.taken_over = snd.id, snd.port, snd.taken_over
        self.last_ts, self.last_frame = snd.last_ts, snd.last_frame

    def __getattr__(self, name: str) -> Any:
        return getattr(self.analysis.sender(self.key, keep=False), name)


class Shelf:
    """Senders pickled to `spool`, a temporary file of the caller's (appended to, and read only
    where a sender lies: other appenders may share it)."""

    def __init__(self, spool: BinaryIO) -> None:
        self.fd = spool.fileno()

    def put(self, analysis: Any, key: int, snd: Any) -> Shelved:
        data = pickle.dumps(snd, protocol=pickle.HIGHEST_PROTOCOL)
        return Shelved(analysis, key, spill(self.fd, data), len(data), snd)

    def get(self, stub: Shelved) -> Any:
        return pickle.loads(os.pread(self.fd, stub.size, stub.at))
