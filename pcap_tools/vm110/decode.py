"""The fast path: EG-Link bytes to a plain dict, with the illegal reasons and warnings.

No scapy objects, a handful of struct calls per packet. The rules follow interpretation.md and
are the contract that the Lua dissector is held to through tests/vectors.
"""
from __future__ import annotations

import struct
from typing import Any

from . import constants as C
from .crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, check_byte_order, crc_function

_HEADER = struct.Struct("<4sHHHHI")
_HEADER_FIELDS = (("revision", "H"), ("origin", "H"), ("serial", "H"), ("size", "H"), ("spare", "I"))

# Payload layouts as (field, struct code); "Ns" fields are bytes.
VRPI_LAYOUT: tuple[tuple[str, str], ...] = (
    ("bu_state", "B"), ("vlaps", "B"), ("unarmed_rus", "B"),
    ("eg_link", "B"), ("ec_link", "B"), ("c_link", "B"),
    ("armed_ru", "H"), ("ru_state", "B"), ("ru_battery", "B"), ("ru_rssi", "B"),
    ("ru_cable", "B"), ("ru_docked", "B"), ("ru_disabled", "B"),
    *((f"joystick{i}", "h") for i in range(1, C.JOYSTICKS + 1)),
    *((f"switch{i}", "h") for i in range(1, C.SWITCHES + 1)),
    ("encoder", "B"), ("encoder_switch", "B"), ("vrpi_spare", f"{C.VRPI_SPARE_LEN}s"),
)
COMMAND_LAYOUT = (("command_id", "H"), ("command_spare", "I"), ("command_data", f"{C.COMMAND_DATA_LEN}s"))
ACK_LAYOUT = (("command_id", "H"),)
VRPO_LAYOUT = (("packet_number", "H"),)  # periodic_data is the rest of the payload

LAYOUTS = {
    C.PacketType.VRPI: VRPI_LAYOUT,
    C.PacketType.VRPO: VRPO_LAYOUT,
    C.PacketType.VRCI: COMMAND_LAYOUT,
    C.PacketType.VRCO: COMMAND_LAYOUT,
    C.PacketType.VRAI: ACK_LAYOUT,
    C.PacketType.VRAO: ACK_LAYOUT,
}


def _compile(layout: tuple[tuple[str, str], ...]) -> tuple[struct.Struct, tuple[tuple[str, struct.Struct, int], ...]]:
    """One Struct for the whole layout, plus (name, struct, offset) for partial decoding."""
    parts, offset = [], 0
    for name, code in layout:
        part = struct.Struct("<" + code)
        parts.append((name, part, offset))
        offset += part.size
    return struct.Struct("<" + "".join(code for _, code in layout)), tuple(parts)


_COMPILED = {ptype: _compile(layout) for ptype, layout in LAYOUTS.items()}
_TYPES = {t.value.encode(): t for t in C.PacketType}
_ENUM_VALUES = {name: frozenset(int(v) for v in names) for name, names in C.ENUM_FIELDS.items()}
_SPARE_FIELDS = ("vrpi_spare", "command_spare")


def crc_span(data: bytes, size: int) -> int:
    """Offset of the CRC: after `size` payload bytes, or the last 4 bytes of a short packet."""
    return min(C.PREFIX_LEN + size, len(data) - C.CRC_LEN)


def decode(data: bytes, crc: str = DEFAULT_VARIANT, crc_order: str = DEFAULT_BYTE_ORDER) -> dict[str, Any]:
    """Decode one EG-Link UDP payload. Never raises on any input bytes.

    Returns canonical field names (those of the scapy layers and of `vm110.<name>` in Wireshark),
    the generated `direction`, `crc.calculated`, `crc.status` and (VRPI) `es_relays_open`, plus `problems`
    (reasons the packet is illegal) and `warnings` ("code" or "code:field").
    """
    crc_fn = crc_function(crc)
    order = check_byte_order(crc_order)
    out: dict[str, Any] = {}
    problems: list[str] = []
    warnings: list[str] = []
    out["problems"], out["warnings"] = problems, warnings
    n = len(data)

    if n < C.PREFIX_LEN:
        _decode_partial_header(data, out)
        problems.append(C.Problem.TRUNCATED.value)
        if "type" in out and data[:C.ID_LEN] not in _TYPES:
            problems.insert(0, C.Problem.UNKNOWN_ID.value)
        return out

    raw_id, revision, origin, serial, size, spare = _HEADER.unpack_from(data)
    ptype = _TYPES.get(raw_id)
    out.update(type=raw_id.decode("latin-1"), revision=revision, origin=origin, serial=serial,
               size=size, spare=spare)
    if ptype is None:
        problems.append(C.Problem.UNKNOWN_ID.value)
    else:
        out["direction"] = ptype.direction.value

    end = crc_span(data, size)
    if n >= C.OVERHEAD:
        stored = int.from_bytes(data[end:end + C.CRC_LEN], order)
        calculated = crc_fn(data[:end])
        out["crc"], out["crc.calculated"] = stored, calculated
        out["crc.status"] = C.CRC_GOOD if stored == calculated else C.CRC_BAD
        if stored != calculated:
            problems.append(C.Problem.BAD_CRC.value)
    else:
        end = n
    if revision != C.SUPPORTED_REVISION:
        problems.append(C.Problem.REVISION.value)
    if n != C.OVERHEAD + size:
        problems.append(C.Problem.SIZE_MISMATCH.value)
    if size > C.MAX_PAYLOAD:
        problems.append(C.Problem.SIZE_TOO_LARGE.value)

    if spare:
        warnings.append(f"{C.WarningCode.SPARE_NONZERO.value}:spare")
    if ptype is not None and ptype.direction is C.Direction.OUTPUT and origin:
        warnings.append(f"{C.WarningCode.ORIGIN_NONZERO.value}:origin")
    if ptype is None or revision != C.SUPPORTED_REVISION:
        return out  # unknown layout: the header is all there is to decode

    payload = data[C.PREFIX_LEN:end]
    low, high = C.PAYLOAD_BOUNDS[ptype]
    if len(payload) < low:
        problems.append(C.Problem.TRUNCATED.value)
    _decode_payload(ptype, payload, out)
    if len(payload) > high:
        warnings.append(C.WarningCode.EXTRA_PAYLOAD.value)
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
    whole, parts = _COMPILED[ptype]
    if len(payload) >= whole.size:
        out.update(zip((name for name, _, _ in parts), whole.unpack_from(payload)))
    else:
        for name, part, offset in parts:
            if offset + part.size > len(payload):
                break
            out[name] = part.unpack_from(payload, offset)[0]
    if ptype is C.PacketType.VRPO and len(payload) >= whole.size:
        out["periodic_data"] = payload[whole.size:whole.size + C.VRPO_MAX_DATA]
    if ptype is C.PacketType.VRPI and "bu_state" in out:
        out["es_relays_open"] = out["bu_state"] < C.ES_RELAYS_CLOSED_FROM


def _check_values(ptype: C.PacketType, out: dict[str, Any], warnings: list[str]) -> None:
    for name in _SPARE_FIELDS:
        value = out.get(name)
        if value and (not isinstance(value, bytes) or any(value)):
            warnings.append(f"{C.WarningCode.SPARE_NONZERO.value}:{name}")
    if ptype is not C.PacketType.VRPI:
        return
    for name, allowed in _ENUM_VALUES.items():
        if name in out and out[name] not in allowed:
            warnings.append(f"{C.WarningCode.UNKNOWN_ENUM.value}:{name}")
    for name, (low, high) in C.RANGES.items():
        if name in out and not low <= out[name] <= high:
            warnings.append(f"{C.WarningCode.OUT_OF_RANGE.value}:{name}")
    if out.get("armed_ru") == 0:
        for name in C.RU_FIELDS:
            if out.get(name):
                warnings.append(f"{C.WarningCode.DISARMED_RU_DATA.value}:{name}")
