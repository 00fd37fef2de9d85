"""The fast path: EG-Link bytes to a plain dict, with the illegal reasons and warnings.

No scapy objects, a handful of struct calls per packet. The rules follow interpretation.md and
are the contract that the Lua dissector is held to through tests/vectors.
"""
from __future__ import annotations

import struct
from typing import Any, NamedTuple, Optional

from . import constants as C
from . import protocol as P
from .crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, check_byte_order, crc_function

_HEADER = P.HEADER
_HEADER_FIELDS = tuple((f.name, f.code) for f in P.HEADER_FIELDS)
# Payload layouts as (field, struct code), derived from vm110.protocol; "Ns" fields are bytes.
LAYOUTS = P.LAYOUTS
VRPI_LAYOUT = LAYOUTS[C.PacketType.VRPI]


_Parts = tuple[tuple[str, struct.Struct, int], ...]


def _compile(layout: tuple[tuple[str, str], ...]) -> tuple[struct.Struct, tuple[str, ...], _Parts]:
    """One Struct and the names for the whole layout, plus (name, struct, offset) for partial decoding."""
    parts, offset = [], 0
    for name, code in layout:
        part = struct.Struct("<" + code)
        parts.append((name, part, offset))
        offset += part.size
    whole = struct.Struct("<" + "".join(code for _, code in layout))
    return whole, tuple(name for name, _ in layout), tuple(parts)


_COMPILED = {ptype: _compile(layout) for ptype, layout in LAYOUTS.items()}
_TYPES = {t.value.encode(): t for t in C.PacketType}
_DIRECTIONS = {raw: t.direction.value for raw, t in _TYPES.items()}
_OUTPUTS = frozenset(raw for raw, t in _TYPES.items() if t.direction is C.Direction.OUTPUT)

# Problem and warning strings built once: decode() runs per packet on days-long captures.
_UNKNOWN_ID, _BAD_CRC, _REVISION, _SIZE_MISMATCH, _SIZE_TOO_LARGE, _TRUNCATED = (
    p.value for p in (C.Problem.UNKNOWN_ID, C.Problem.BAD_CRC, C.Problem.REVISION,
                      C.Problem.SIZE_MISMATCH, C.Problem.SIZE_TOO_LARGE, C.Problem.TRUNCATED))
W = C.WarningCode
_HEADER_SPARE = f"{W.SPARE_NONZERO.value}:spare"
_ORIGIN = f"{W.ORIGIN_NONZERO.value}:origin"
_EXTRA = W.EXTRA_PAYLOAD.value
_VRPI, _VRPO = C.PacketType.VRPI, C.PacketType.VRPO
_TAIL = P.VRPO_TAIL


class _Checks(NamedTuple):
    """The value checks of one packet type, from the flags of its fields (vm110.protocol)."""

    spare: tuple[tuple[str, str], ...]                        # (field, warning)
    enum: tuple[tuple[str, frozenset[int], str], ...]         # (field, values, warning)
    range: tuple[tuple[str, int, int, str], ...]              # (field, low, high, warning)
    gate: Optional[str]                                       # 0 here: no RU armed
    disarmed: tuple[tuple[str, str], ...]                     # (field, warning)


def _checks(packet: P.Packet) -> _Checks:
    fields = packet.fields
    return _Checks(
        tuple((f.name, f"{W.SPARE_NONZERO.value}:{f.name}") for f in fields if f.spare),
        tuple((f.name, frozenset(int(v) for v in f.enum.values), f"{W.UNKNOWN_ENUM.value}:{f.name}")
              for f in fields if f.enum),
        tuple((f.name, f.range[0], f.range[1], f"{W.OUT_OF_RANGE.value}:{f.name}") for f in fields if f.range),
        packet.ru_gate,
        tuple((f.name, f"{W.DISARMED_RU_DATA.value}:{f.name}") for f in fields if f.ru and packet.ru_gate))


_CHECKS = {ptype: _checks(packet) for ptype, packet in P.PACKETS.items()}


def crc_span(data: bytes, size: int) -> int:
    """Offset of the CRC: after `size` payload bytes, or the last 4 bytes of a short packet."""
    return min(C.PREFIX_LEN + size, len(data) - C.CRC_LEN)


def decode(data: bytes | bytearray | memoryview, crc: str = DEFAULT_VARIANT,
           crc_order: str = DEFAULT_BYTE_ORDER) -> dict[str, Any]:
    """Decode one EG-Link UDP payload. Never raises on any input bytes (also a bytearray or a
    memoryview, as a socket's recv_into or scapy's raw() may give them).

    Returns canonical field names (those of the scapy layers and of `vm110.<name>` in Wireshark),
    the generated `direction`, `crc.calculated`, `crc.status` and (VRPI) `es_relays_open`, plus `problems`
    (reasons the packet is illegal) and `warnings` ("code" or "code:field").
    """
    crc_fn = crc_function(crc)
    order = check_byte_order(crc_order)
    if not isinstance(data, bytes):
        data = bytes(data)
    out: dict[str, Any] = {}
    problems: list[str] = []
    warnings: list[str] = []
    out["problems"], out["warnings"] = problems, warnings
    n = len(data)

    if n < C.PREFIX_LEN:
        _decode_partial_header(data, out)
        problems.append(_TRUNCATED)
        if "type" in out and data[:C.ID_LEN] not in _TYPES:
            problems.insert(0, _UNKNOWN_ID)
        return out

    raw_id, revision, origin, serial, size, spare = _HEADER.unpack_from(data)
    ptype = _TYPES.get(raw_id)
    out.update(type=raw_id.decode("latin-1"), revision=revision, origin=origin, serial=serial,
               size=size, spare=spare)
    if ptype is None:
        problems.append(_UNKNOWN_ID)
    else:
        out["direction"] = _DIRECTIONS[raw_id]

    end = crc_span(data, size)
    if n >= C.OVERHEAD:
        stored = int.from_bytes(data[end:end + C.CRC_LEN], order)
        calculated = crc_fn(data[:end])
        out["crc"], out["crc.calculated"] = stored, calculated
        out["crc.status"] = C.CRC_GOOD if stored == calculated else C.CRC_BAD
        if stored != calculated:
            problems.append(_BAD_CRC)
    if revision != C.SUPPORTED_REVISION:
        problems.append(_REVISION)
    if n != C.OVERHEAD + size:
        problems.append(_SIZE_MISMATCH)
    if size > C.MAX_PAYLOAD:
        problems.append(_SIZE_TOO_LARGE)

    if spare:
        warnings.append(_HEADER_SPARE)
    if origin and raw_id in _OUTPUTS:
        warnings.append(_ORIGIN)
    if n < C.OVERHEAD:
        problems.append(_TRUNCATED)  # no room for a CRC: nothing after the header
        return out
    if ptype is None or revision != C.SUPPORTED_REVISION:
        return out  # unknown layout: the header is all there is to decode

    payload = data[C.PREFIX_LEN:end]
    low, high = P.PAYLOAD_BOUNDS[ptype]
    if len(payload) < low:
        problems.append(_TRUNCATED)
    _decode_payload(ptype, payload, out)
    if len(payload) > high:
        warnings.append(_EXTRA)
    _check_values(ptype, out, warnings)
    return out


def _decode_partial_header(data: bytes, out: dict[str, Any]) -> None:
    if len(data) >= C.ID_LEN:
        raw_id = data[:C.ID_LEN]
        out["type"] = raw_id.decode("latin-1")
        if raw_id in _TYPES:
            out["direction"] = _TYPES[raw_id].direction.value
    offset = C.ID_LEN
    for name, code in _HEADER_FIELDS:
        width = struct.calcsize(code)
        if offset + width > len(data):
            break
        out[name] = struct.unpack_from("<" + code, data, offset)[0]
        offset += width


def _decode_payload(ptype: C.PacketType, payload: bytes, out: dict[str, Any]) -> None:
    whole, names, parts = _COMPILED[ptype]
    if len(payload) >= whole.size:
        out.update(zip(names, whole.unpack_from(payload)))
    else:
        for name, part, offset in parts:
            if offset + part.size > len(payload):
                break
            out[name] = part.unpack_from(payload, offset)[0]
    if ptype is _VRPO and len(payload) >= whole.size:
        out[_TAIL.name] = payload[whole.size:whole.size + _TAIL.size]
    if ptype is _VRPI and "bu_state" in out:
        out["es_relays_open"] = out["bu_state"] < C.ES_RELAYS_CLOSED_FROM


def _check_values(ptype: C.PacketType, out: dict[str, Any], warnings: list[str]) -> None:
    checks = _CHECKS[ptype]
    get = out.get
    for name, warning in checks.spare:
        value = get(name)
        if value and (not isinstance(value, bytes) or any(value)):
            warnings.append(warning)
    for name, allowed, warning in checks.enum:
        value = get(name)
        if value is not None and value not in allowed:
            warnings.append(warning)
    for name, low, high, warning in checks.range:
        value = get(name)
        if value is not None and not low <= value <= high:
            warnings.append(warning)
    if checks.gate is not None and get(checks.gate) == 0:
        for name, warning in checks.disarmed:
            if get(name):
                warnings.append(warning)
