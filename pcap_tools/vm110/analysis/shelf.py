"""Senders set aside in a file (`vm110 monitor`, for runs of days; docs/monitor.md, "Memory for
long runs").

The report lists every sender ever heard, and a sender's state is some 10 kB of memory: a fuzzer,
spoofed packets or a device on a new source port for every packet grew the monitor by 10 MB per
1000 senders, for as long as it ran. `Analysis` keeps in memory the KEEP senders heard last; one
heard before them, with nothing pending (no undecided packet, no serial scope still being chosen,
no predecessor's state still to come), goes whole to the file, pickled as it is, and memory keeps
a `Shelved` stub. A sender heard again, or taken over by a restart on a new port, comes back as
it was: the analysis goes on exactly as if it had never left, and the report is `analyze`'s. Its
place in the file (twice its size, to grow into) is taken again each time it leaves, while it
fits: more senders than KEEP heard in turn for days come and go without the file growing.
"""
from __future__ import annotations

import os
import pickle
from typing import Any, BinaryIO, Optional

from .periodic import spill, write_at

KEEP = 2048         # senders kept in memory, those heard last (a mirror port of 20 pairs has 40)


class Shelved:
    """What memory keeps of a sender in the file: where it lies, and what is asked of every sender
    (its id; the new-port rule's port and last packet; the live view's `taken_over`). Anything else
    is read from a copy read back (`Analysis.sender`), not to be changed."""

    __slots__ = ("analysis", "at", "id", "key", "last_frame", "last_ts", "port", "size", "space", "taken_over")

    def __init__(self, analysis: Any, key: int, at: int, size: int, space: int, snd: Any) -> None:
        self.analysis, self.key, self.at, self.size, self.space = analysis, key, at, size, space
        self.id, self.port, self.taken_over = snd.id, snd.port, snd.taken_over
        self.last_ts, self.last_frame = snd.last_ts, snd.last_frame

    def __getattr__(self, name: str) -> Any:
        return getattr(self.analysis.sender(self.key, keep=False), name)


class Shelf:
    """Senders pickled to `spool`, a temporary file of the caller's (appended to, and read only
    where a sender lies: other appenders may share it)."""

    def __init__(self, spool: BinaryIO) -> None:
        self.fd = spool.fileno()

    def put(self, analysis: Any, key: int, snd: Any, room: Optional[tuple[int, int]] = None) -> Shelved:
        """`room`: the place (offset, bytes) it had before, taken again if it fits."""
        data = pickle.dumps(snd, protocol=pickle.HIGHEST_PROTOCOL)
        if room is not None and len(data) <= room[1]:
            at, space = room
            write_at(self.fd, data, at)
        else:
            space = 2 * len(data)
            at = spill(self.fd, data.ljust(space, b"\0"))
        return Shelved(analysis, key, at, len(data), space, snd)

    def get(self, stub: Shelved) -> Any:
        return pickle.loads(os.pread(self.fd, stub.size, stub.at))
