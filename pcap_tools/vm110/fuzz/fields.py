"""Where each field of an input packet sits, from the protocol declaration (vm110.protocol): the
one adapter the coverage-guided mutator reads the protocol through.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Optional

from .. import constants as C
from .. import protocol as P

SERIAL_AT = P.HEADER_OFFSETS["serial"]
SIZE_AT = P.SIZE_OFFSET
COMMAND_ID_AT = C.PREFIX_LEN + P.PACKETS[C.PacketType.VRCI].offsets()["command_id"]


@dataclass(frozen=True)
class FieldSpot:
    name: str
    offset: int                   # from the start of the packet
    width: int                    # bytes
    signed: bool = False
    text: bool = False            # a byte string, not a number
    enum: tuple[int, ...] = ()
    limits: Optional[tuple[int, int]] = None     # the documented range

    def interesting(self) -> list[int]:
        """Values at and beyond the boundaries: type limits, range edges, the enum and its neighbours."""
        bits = 8 * self.width
        low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if self.signed else (0, (1 << bits) - 1)
        values = [low, high, 0, 1, low + 1, high - 1]
        if self.limits:
            values += [self.limits[0] - 1, self.limits[0], self.limits[1], self.limits[1] + 1]
        for v in self.enum:
            values += [v - 1, v, v + 1]
        return [v for v in dict.fromkeys(values) if low <= v <= high]

    def pack(self, value: int) -> bytes:
        bits = 8 * self.width
        return (value % (1 << bits)).to_bytes(self.width, "little")


def _declared(ptype: C.PacketType) -> list[FieldSpot]:
    out, offset = [], C.PREFIX_LEN
    for field in P.PACKETS[ptype].fields:
        if field.kind == "bytes":
            out.append(FieldSpot(field.name, offset, field.size, text=True))
        else:
            enum = tuple(sorted(int(v) for v in field.enum.values)) if field.enum else ()
            out.append(FieldSpot(field.name, offset, field.size, field.kind == "s16", enum=enum,
                                 limits=field.range))
        offset += field.size
    return out


# The header's fields, as plain numbers: what the mutator may do to them is not bounded by a range.
_HEADER = [FieldSpot(f.name, P.HEADER_OFFSETS[f.name], f.size) for f in P.HEADER_FIELDS]


@functools.lru_cache(maxsize=None)
def spots(type_id: bytes) -> tuple[FieldSpot, ...]:
    """The payload fields of a packet type (by its 4-byte ID), then the header's; () when unknown."""
    try:
        ptype = C.PacketType(type_id.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        return ()
    if ptype is C.PacketType.VRPO:
        return tuple(_HEADER)          # variable layout: header only
    return tuple(_declared(ptype) + _HEADER)
