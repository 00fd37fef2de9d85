"""Packets for the fuzzer, built through the scapy layers: valid ones, and their mutations.

Field mutations set one field of a valid packet to a boundary value and keep the CRC valid, so the
packet stays legal (a controller must handle it). Structural mutations work on the bytes of a
valid packet and make it illegal (a controller must ignore it) or oversize.
"""
from __future__ import annotations

import random
import struct
from typing import Any, Iterator

from scapy.fields import Field, StrField

from .. import constants as C
from .. import protocol as P
from ..crc import BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, VARIANTS, crc_bytes
from ..decode import crc_span
from ..layers import PAYLOAD_CLASSES, VM110, crc_settings

BU_ORIGIN = 0x0101          # the origin the fuzzing base unit claims
OTHER_ORIGIN = 0x0202       # a second base unit, for origin variations
LARGE_DATAGRAM = 60000      # big, yet a whole Ethernet/IP/UDP frame still fits a pcap snaplen
INPUT_TYPES = (C.PacketType.VRPI, C.PacketType.VRCI, C.PacketType.VRAI)
OUTPUT_TYPES = (C.PacketType.VRPO, C.PacketType.VRCO, C.PacketType.VRAO)

# A base unit with an armed remote in normal operation: what the periodic stream reports.
ARMED_VRPI: dict[str, Any] = dict(
    bu_state=C.BuState.ARMED, vlaps=1, unarmed_rus=0, eg_link=C.LinkStatus.OPERATIONAL,
    ec_link=C.LinkStatus.OPERATIONAL, c_link=C.LinkStatus.OPERATIONAL, armed_ru=0x0C07,
    ru_state=C.RuState.ENABLED, ru_battery=80, ru_rssi=70,
)
DISARMED_VRPI: dict[str, Any] = dict(
    bu_state=C.BuState.DISARMED, vlaps=1, unarmed_rus=2, eg_link=C.LinkStatus.OPERATIONAL,
    ec_link=C.LinkStatus.OPERATIONAL, c_link=C.LinkStatus.PASSIVE,
)
# Field sweeps start from a packet with non-zero sticks and switches, so sign flips mean something.
SWEEP_VRPI: dict[str, Any] = dict(ARMED_VRPI, joystick1=250, joystick2=-400, joystick3=1, joystick4=-1,
                                  switch1=1, switch2=-1, switch3=500, switch4=3, encoder=200)


def build(ptype: C.PacketType | str, serial: int, fields: dict[str, Any] | None = None,
          header: dict[str, Any] | None = None, variant: str = DEFAULT_VARIANT,
          order: str = DEFAULT_BYTE_ORDER) -> bytes:
    """A packet of a known type with the given payload and header fields, as the wire carries it."""
    ptype = C.PacketType(ptype)
    head: dict[str, Any] = dict(origin=0 if ptype.direction is C.Direction.OUTPUT else BU_ORIGIN,
                                serial=serial % C.SERIAL_MODULUS)
    head.update(header or {})
    pkt = VM110(type=ptype.value.encode(), **head) / PAYLOAD_CLASSES[ptype](**(fields or {}))
    with crc_settings(variant, order):
        return bytes(pkt)


def default_fields(ptype: C.PacketType, command_id: int = 0) -> dict[str, Any]:
    if ptype is C.PacketType.VRPI:
        return dict(ARMED_VRPI)
    if ptype in (C.PacketType.VRCI, C.PacketType.VRCO):
        return dict(command_id=command_id, command_data=b"FUZZ".ljust(C.COMMAND_DATA_LEN, b"\0"))
    if ptype in (C.PacketType.VRAI, C.PacketType.VRAO):
        return dict(command_id=command_id)
    return dict(packet_number=0, periodic_data=bytes(range(32)))


# --- field boundary values -------------------------------------------------------------------
def _width(field: Field) -> tuple[int, bool]:
    """(bits, signed) of an integer field, from its struct format."""
    code = field.fmt[-1]
    return struct.calcsize(code) * 8, code.islower()


def _int_values(name: str, bits: int, signed: bool, base: int) -> list[int]:
    low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
    values = [low, high]
    if name in P.RANGES:   # documented range: just outside first, then its edges
        r_low, r_high = P.RANGES[name]
        values += [r_low - 1, r_high + 1, r_low, r_high]
    if name in P.ENUM_FIELDS:   # values outside the set, then the edges of the set
        names: Any = P.ENUM_FIELDS[name]
        known = sorted(int(v) for v in names)
        values += [known[-1] + 1] + [v + 1 for v in known if v + 1 not in known] + [known[0], known[-1]]
    values += [0, 1, -1, low + 1, high - 1, -base, base + 1, base - 1]
    if not signed:
        values += [1 << bits - 1, (1 << bits - 1) - 1]
    seen: list[int] = []
    for v in values:
        if low <= v <= high and v != base and v not in seen:
            seen.append(v)
    return seen


# First bytes of a byte string a controller parses (command data: an opcode and its argument
# count or length): a one-byte value and NUL after it, so a count of 0 is sent too. Byte values
# alone (FF FF ...) never give a controller an opcode with nothing after it.
_FIRST_BYTES = (0xFF, 0x80, 0x7F, 0x01)


def bytes_values(length: int, rng: random.Random) -> list[bytes]:
    """Boundary values of a byte-string field: every byte at a boundary, text without a NUL, all
    NUL, one boundary byte then NULs, random bytes."""
    return [b"\xff" * length, b"\x80" * length, b"A" * length, bytes(length),
            *(bytes([b]).ljust(length, b"\0") for b in _FIRST_BYTES), bytes(rng.randrange(256) for _ in range(length))]


def field_mutations(ptype: C.PacketType, fields: dict[str, Any], rng: random.Random,
                    skip: tuple[str, ...] = ()) -> list[tuple[str, Any]]:
    """(field, value) pairs: boundary values of every payload field, most telling first per field.

    The list is ordered value-major (first value of every field, then the second ...) so that
    every field is hit early in a sweep.
    """
    columns: list[list[tuple[str, Any]]] = []
    layer = PAYLOAD_CLASSES[ptype](**fields)
    for cond in PAYLOAD_CLASSES[ptype].fields_desc:
        field = cond.fld  # type: ignore[union-attr]  # payload fields: CondWholeField (vm110.layers)
        if field.name in skip:
            continue
        base = layer.getfieldval(field.name)
        if isinstance(field, StrField):
            length = len(base) if base else 16
            values: list[Any] = [v for v in bytes_values(length, rng) if v != base]
        else:
            bits, signed = _width(field)
            values = _int_values(field.name, bits, signed, int(base))
        columns.append([(field.name, v) for v in values])
    return [col[i] for i in range(max(map(len, columns), default=0)) for col in columns if i < len(col)]


def header_mutations() -> list[tuple[str, int, bool]]:
    """(header field, value, legal): header values a controller must accept or must ignore."""
    return [
        ("revision", 1, False), ("revision", 0xFFFF, False),
        ("origin", 0, True), ("origin", 0xFFFF, True), ("origin", OTHER_ORIGIN, True),
        ("spare", 1, True), ("spare", 0xFFFFFFFF, True),
    ]


# --- structural mutations on bytes -----------------------------------------------------------
def recrc(body: bytes, variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> bytes:
    """body (no CRC) + its CRC."""
    return body + crc_bytes(body, variant, order)


def set_u16(data: bytes, offset: int, value: int) -> bytes:
    return data[:offset] + struct.pack("<H", value & 0xFFFF) + data[offset + 2:]


SIZE_OFFSET = P.SIZE_OFFSET
SERIAL_OFFSET = P.HEADER_OFFSETS["serial"]


def reserial(valid: bytes, serial: int) -> bytes:
    """A valid packet sent again on another serial (the base unit's resend): the same bytes, that
    serial and the CRC over them."""
    return recrc(set_u16(valid[:-C.CRC_LEN], SERIAL_OFFSET, serial))


def structural(valid: bytes, rng: random.Random) -> Iterator[tuple[str, bytes]]:
    """(description, bytes): every structural defect of one valid packet, cheapest first."""
    body, size = valid[:-C.CRC_LEN], len(valid) - C.OVERHEAD
    crc = valid[-C.CRC_LEN:]
    yield "crc xor 0x00000001", body + bytes([crc[0] ^ 1]) + crc[1:]
    yield (f"oversize {C.MAX_PACKET + 1} bytes (trailing bytes after the CRC)",
           valid + bytes(C.MAX_PACKET + 1 - len(valid)))
    yield "size field + 1", recrc(set_u16(body, SIZE_OFFSET, size + 1))
    yield "truncated: CRC missing", body
    yield "unknown packet ID VRXI", recrc(b"VRXI" + body[C.ID_LEN:])
    yield "trailing byte after the CRC", valid + b"\0"
    for variant in VARIANTS:
        for order in BYTE_ORDERS:
            if (variant, order) != (DEFAULT_VARIANT, DEFAULT_BYTE_ORDER):
                yield f"crc variant {variant} {order}-endian", recrc(body, variant, order)
    yield "crc zero", body + bytes(C.CRC_LEN)
    yield "crc xor 0x80000000", body + crc[:3] + bytes([crc[3] ^ 0x80])
    yield "size field - 1", recrc(set_u16(body, SIZE_OFFSET, size - 1))
    yield "size field 0", recrc(set_u16(body, SIZE_OFFSET, 0))
    yield f"size field {C.MAX_PAYLOAD + 1}", recrc(set_u16(body, SIZE_OFFSET, C.MAX_PAYLOAD + 1))
    yield "size field 0xFFFF", recrc(set_u16(body, SIZE_OFFSET, 0xFFFF))
    grown = body + bytes(C.MAX_PAYLOAD + 1 - size)
    yield (f"oversize: payload {C.MAX_PAYLOAD + 1} bytes, size field and CRC matching",
           recrc(set_u16(grown, SIZE_OFFSET, C.MAX_PAYLOAD + 1)))
    for total in (1472, 9000, LARGE_DATAGRAM):
        yield f"oversize {total} bytes (random trailing bytes)", valid + rng.randbytes(total - len(valid))
    for cut in (0, 1, C.ID_LEN, C.PREFIX_LEN - 1, C.PREFIX_LEN, C.OVERHEAD - 1, len(valid) - 1, len(valid) // 2):
        if cut < len(valid):
            yield f"truncated to {cut} bytes", valid[:cut]
    yield "truncated payload, CRC recomputed", recrc(body[:-1])
    yield "4 trailing bytes after the CRC", valid + b"\xde\xad\xbe\xef"
    for raw_id in (b"VRPX", b"vrpi", b"\0\0\0\0", b"XXXX", b"VR\xffI"):
        yield f"unknown packet ID {raw_id!r}", recrc(raw_id + body[C.ID_LEN:])
    yield "crc 0xFFFFFFFF", body + b"\xff" * C.CRC_LEN


def random_bytes(valid: bytes, rng: random.Random) -> tuple[str, bytes]:
    """1 to 8 random byte changes; the CRC is left stale or fixed up (half of the time each)."""
    fix = rng.random() < 0.5
    span = len(valid) - C.CRC_LEN if fix else len(valid)
    data = bytearray(valid)
    changes = set()
    for _ in range(rng.randint(1, 8)):
        pos = rng.randrange(span)
        how = rng.randrange(3)
        if how == 0:
            data[pos] ^= 1 << rng.randrange(8)
        elif how == 1:
            data[pos] = rng.choice((0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF))
        else:
            data[pos] = rng.randrange(256)
        changes.add(pos)
    if data[:span] == valid[:span]:   # the changes undid each other: keep one for real
        data[pos] ^= 0x01
    if fix:
        end = crc_span(bytes(data), struct.unpack_from("<H", data, SIZE_OFFSET)[0])
        data[end:end + C.CRC_LEN] = crc_bytes(bytes(data[:end]))
    where = ",".join(str(p) for p in sorted(changes))
    return f"random bytes at {where}" + (" (CRC fixed)" if fix else ""), bytes(data)
