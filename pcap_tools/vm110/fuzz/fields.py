"""Where each field of an input packet sits, from the protocol declaration: the one adapter the
coverage-guided mutator reads the protocol through.

Today the declaration is the scapy layers (`layers.PAYLOAD_CLASSES`) with the ranges and enums of
`constants`; a change of where the protocol is declared changes only `_declared`.
"""
from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from typing import Any, Optional

from .. import constants as C
from .. import protocol as P
from ..layers import PAYLOAD_CLASSES

SERIAL_AT = C.ID_LEN + 4
SIZE_AT = C.ID_LEN + 6


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
    out = []
    offset = C.PREFIX_LEN
    for field in PAYLOAD_CLASSES[ptype].fields_desc:
        fmt = getattr(field, "fmt", "")
        if isinstance(field.default, bytes):
            width = len(field.default) or C.COMMAND_DATA_LEN
            out.append(FieldSpot(field.name, offset, width, text=True))
        else:
            width = struct.calcsize(fmt)
            names: Any = P.ENUM_FIELDS.get(field.name, {})
            enum = tuple(sorted(int(v) for v in names))
            out.append(FieldSpot(field.name, offset, width, fmt[-1].islower(), enum=enum,
                                 limits=P.RANGES.get(field.name)))
        offset += width
    return out


_HEADER = [FieldSpot("revision", C.ID_LEN, 2), FieldSpot("origin", C.ID_LEN + 2, 2),
           FieldSpot("serial", SERIAL_AT, 2), FieldSpot("size", SIZE_AT, 2), FieldSpot("spare", C.ID_LEN + 8, 4)]


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
