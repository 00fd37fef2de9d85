"""IP fragments put back together as Wireshark does with its default `ip.defragment` and
`ipv6.defragment` on: a VRPO of 488 data bytes sent over a link of a small MTU arrives in
fragments, and the base unit's IP stack (like Wireshark) receives the whole datagram.

As in Wireshark's reassembly tables (epan/reassemble.c, read as a capture is read, one pass): the
fragments of a datagram are those of one (source, destination, protocol, identification; and VLAN,
for IPv4 between private or link-local addresses); it is whole once the fragment without "more
fragments" has come and the fragments cover every byte up to its end (a fragment past it takes no
part), and it is then taken at the frame that completed it, with that frame's time; where fragments
overlap, the bytes placed first (lowest offset, then first arrived) stand; a fragment the capture
did not record whole takes no part. A datagram completed is forgotten: copies of its fragments that
follow (a mirror port) begin a new one, which is a copy of the datagram once it is whole again.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Optional

# Datagrams in reassembly at once, and their bytes: beyond either the oldest is given up (its
# fragments stay counted as not reassembled), so that a flood of fragments never whole (another
# protocol's, a lossy link) cannot grow memory without bound.
MAX_PENDING = 4096
MAX_PENDING_BYTES = 16 << 20
MAX_DATAGRAM = 1 << 16      # the largest IP payload a fragment offset and length can reach
# What a fragment held costs beyond its bytes (its bytes object, its tuple, its place in the list):
# counted with them, else copies of one 8-byte fragment held some 350 MB within the "16 MiB".
PART_COST = 112


class _Pending:
    __slots__ = ("covered", "end", "frames", "parts", "seen")

    def __init__(self) -> None:
        self.parts: list[tuple[int, int, bytes]] = []    # (offset, arrival, bytes)
        self.end: Optional[int] = None                   # the datagram's length, once its last fragment came
        self.frames = 0                                  # fragment frames taken in
        # A byte per byte of the datagram, 1 once a fragment brought it, and how many of those lie
        # below `end`: whether it is whole costs the fragment's own length, however many came
        # (sorting every fragment again at each one was quadratic in a capture's fragments).
        self.seen = bytearray()
        self.covered = 0

    def take(self, offset: int, more: bool, part: bytes) -> int:
        """One fragment's bytes; how many bytes `seen` grew by."""
        stop = offset + len(part)
        grown = max(0, stop - len(self.seen))
        self.seen.extend(bytes(grown))
        if self.end is not None and offset < self.end:
            self.covered += self.seen.count(0, offset, min(stop, self.end))
        self.seen[offset:stop] = b"\x01" * len(part)
        if not more and self.end is None:
            self.end = stop
            self.covered = self.seen.count(1, 0, stop)
        self.parts.append((offset, self.frames, part))
        return grown

    def whole(self) -> Optional[bytes]:
        """The datagram when every byte up to its end is here, else None."""
        if self.end is None or self.covered < self.end:
            return None
        out = bytearray(self.end)
        reached = 0
        for offset, _, part in sorted(self.parts, key=lambda p: (p[0], p[1])):
            if reached >= self.end:         # (a fragment past the end takes no part)
                break
            stop = min(offset + len(part), self.end)
            if stop > reached:              # (where fragments overlap, the bytes placed first stand)
                out[reached:stop] = part[reached - offset:stop - offset]
                reached = stop
        return bytes(out)


class Reassembly:
    """The fragments of one capture's datagrams still waiting for the rest."""

    def __init__(self) -> None:
        self._pending: OrderedDict[tuple, _Pending] = OrderedDict()
        self._bytes = 0

    def add(self, key: tuple, offset: int, more: bool, part: bytes) -> Optional[tuple[bytes, int]]:
        """Take in one fragment (`offset` in bytes); (the datagram, how many fragment frames made
        it) when this one completes it, else None."""
        pending = self._pending.get(key)
        if pending is None:
            pending = self._pending[key] = _Pending()
        pending.frames += 1
        if offset + len(part) <= MAX_DATAGRAM:        # (one past it takes no part; its frame is counted)
            self._bytes += len(part) + PART_COST + pending.take(offset, more, part)
            datagram = pending.whole()
            if datagram is not None:
                self._drop(key)
                return datagram, pending.frames
        # (after a fragment past 64 KiB too: a flood of those, each a datagram of its own, is bounded)
        while len(self._pending) > MAX_PENDING or self._bytes > MAX_PENDING_BYTES:
            self._drop(next(iter(self._pending)))
        return None

    def _drop(self, key: tuple) -> None:
        pending = self._pending.pop(key)
        self._bytes -= len(pending.seen) + sum(len(part) + PART_COST for _, _, part in pending.parts)
