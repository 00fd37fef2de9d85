"""What a pcapng capture says it dropped itself: its Interface Statistics Blocks' isb_ifdrop and
isb_osdrop (cumulative since the capture started: per interface the last block's count), and the
epb_dropcount of its Enhanced Packet Blocks (packets lost on the interface just before that one).
Packets the capture dropped are no packets the EG-Link lost, though both leave a serial gap.

`Drops` is kept by the capture reader (both engines, the monitor) and fed the blocks it walks.
Options of another length than 8 are ignored, as wiretap ignores them (its checks of a block's
option layout, which stop the reading, are the reader's); of an option given twice, the first
counts, as in wiretap.
"""
from __future__ import annotations

import struct
from typing import Iterator, Optional

IDB_NAME = 2
ISB_IFDROP, ISB_OSDROP = 5, 7
EPB_DROPCOUNT = 4
COUNTS = ("ifdrop", "osdrop", "dropcount")      # the report's names of the three, as pcapng's


def options(data: bytes, pos: int, end: int, e: str) -> Iterator[tuple[int, bytes]]:
    """(code, value) of the options from `pos` to `end` of a block, up to opt_endofopt."""
    while pos + 4 <= end:
        code, length = struct.unpack_from(e + "HH", data, pos)
        if code == 0:
            return
        yield code, data[pos + 4:min(pos + 4 + length, end)]
        pos += 4 + ((length + 3) & ~3)


def _u64(values: dict[int, bytes], code: int, e: str) -> Optional[int]:
    value = values.get(code)
    return struct.unpack(e + "Q", value)[0] if value is not None and len(value) == 8 else None


def _first(data: bytes, pos: int, end: int, e: str, codes: tuple[int, ...]) -> dict[int, bytes]:
    found: dict[int, bytes] = {}
    for code, value in options(data, pos, end, e):
        if code in codes and len(value) == 8:
            found.setdefault(code, value)
    return found


class Drops:
    """Per interface, in Wireshark's order (each section's interfaces its own), its name and its
    three counts (None: the capture says nothing of it)."""

    def __init__(self) -> None:
        self.interfaces: list[dict] = []
        self.sections = 0                       # sections begun
        self.section_start = 0                  # index of the current section's first interface

    def section(self) -> None:
        self.sections += 1
        self.section_start = len(self.interfaces)

    def interface(self, data: bytes, pos: int, blen: int, e: str) -> None:
        """An Interface Description Block at `pos`."""
        name = next((value for code, value in options(data, pos + 16, pos + blen - 4, e) if code == IDB_NAME), None)
        self.interfaces.append({"section": max(self.sections - 1, 0),
                                "interface": len(self.interfaces) - self.section_start,
                                "name": None if name is None else name.decode("utf-8", "replace"),
                                "ifdrop": None, "osdrop": None, "dropcount": None})

    def _of(self, iface: int) -> Optional[dict]:
        # (an interface the section does not have: wiretap skips the block)
        index = self.section_start + iface
        return self.interfaces[index] if index < len(self.interfaces) else None

    def statistics(self, data: bytes, pos: int, blen: int, e: str) -> None:
        """An Interface Statistics Block at `pos`: its counts replace the interface's."""
        mine = self._of(struct.unpack_from(e + "I", data, pos + 8)[0])
        if mine is None:
            return
        found = _first(data, pos + 20, pos + blen - 4, e, (ISB_IFDROP, ISB_OSDROP))
        for key, code in (("ifdrop", ISB_IFDROP), ("osdrop", ISB_OSDROP)):
            value = _u64(found, code, e)
            if value is not None:
                mine[key] = value

    def packet(self, data: bytes, iface: int, options_at: int, end: int, e: str) -> None:
        """The options of an Enhanced Packet Block of `iface`, from `options_at` to `end`."""
        value = _u64(_first(data, options_at, end, e, (EPB_DROPCOUNT,)), EPB_DROPCOUNT, e)
        mine = self._of(iface)
        if value is not None and mine is not None:
            mine["dropcount"] = (mine["dropcount"] or 0) + value

    def report(self) -> Optional[dict]:
        """The capture's `dropped` (docs/report.md); None when it says nothing of drops."""
        said = [dict(i) for i in self.interfaces if any(i[k] is not None for k in COUNTS)]
        if not said:
            return None
        for i in said:       # (the counts may be of the same packets: the larger of the two readings)
            i["total"] = max((i["ifdrop"] or 0) + (i["osdrop"] or 0), i["dropcount"] or 0)
        sums = {k: sum(i[k] for i in said if i[k] is not None) if any(i[k] is not None for i in said) else None
                for k in COUNTS}
        return {"total": sum(i["total"] for i in said), **sums, "interfaces": said}
