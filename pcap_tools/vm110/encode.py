"""The fast way back: field values to EG-Link bytes, the inverse of `vm110.decode`.

struct and the zlib-backed CRC only, no scapy objects: the simulators and the capture synthesis
build hundreds of thousands of packets per second with it. The scapy layers stay the tool for
crafting odd packets by hand; tests hold both to the same bytes.
"""
from __future__ import annotations

import struct
from typing import Any, Mapping, Optional, Union

from . import constants as C
from .crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, check_byte_order, crc_function
from . import protocol as P

_HEADER = P.HEADER
_PAYLOAD_STRUCTS = {ptype: packet.struct for ptype, packet in P.PACKETS.items()}
# (name, value when missing) per field, in wire order.
_PAYLOAD_FIELDS = {ptype: tuple((f.name, f.default) for f in packet.fields) for ptype, packet in P.PACKETS.items()}
_TAILS = {ptype: packet.tail.name for ptype, packet in P.PACKETS.items() if packet.tail}

PacketId = Union[C.PacketType, str, bytes]


def _raw_id(ptype: PacketId) -> bytes:
    if isinstance(ptype, bytes):
        return ptype
    return (ptype.value if isinstance(ptype, C.PacketType) else ptype).encode("latin-1")


def packet(ptype: PacketId, payload: bytes = b"", *, origin: int = 0, serial: int = 0,
           revision: int = C.SUPPORTED_REVISION, spare: int = 0, size: Optional[int] = None,
           crc: Optional[int] = None, variant: str = DEFAULT_VARIANT,
           order: str = DEFAULT_BYTE_ORDER) -> bytes:
    """Packet ID + header + payload + CRC. `size` and `crc` are computed unless given."""
    body = _HEADER.pack(_raw_id(ptype), revision, origin, serial & 0xFFFF,
                        len(payload) if size is None else size, spare) + payload
    value = crc_function(variant)(body) if crc is None else crc
    return body + value.to_bytes(C.CRC_LEN, check_byte_order(order))


def payload(ptype: Union[C.PacketType, str], fields: Mapping[str, Any]) -> bytes:
    """The payload of a known type from canonical field names; missing fields are zero."""
    ptype = C.PacketType(ptype)
    values = [fields.get(name, default) for name, default in _PAYLOAD_FIELDS[ptype]]
    body = _PAYLOAD_STRUCTS[ptype].pack(*values)
    tail = _TAILS.get(ptype)
    if tail is not None:
        body += bytes(fields.get(tail, b""))
    return body


def encode(fields: Mapping[str, Any], variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> bytes:
    """Inverse of `vm110.decode.decode` for well-formed packets of a known type.

    Takes the canonical names (`type`, header fields, payload fields); `size` and `crc` are
    computed when absent, so passing wrong ones on purpose crafts illegal packets.
    """
    return packet(fields["type"], payload(fields["type"], fields), origin=fields.get("origin", 0),
                  serial=fields.get("serial", 0), revision=fields.get("revision", C.SUPPORTED_REVISION),
                  spare=fields.get("spare", 0), size=fields.get("size"), crc=fields.get("crc"),
                  variant=variant, order=order)


# The hot paths of the simulators: one struct call for the payload. Their argument lists name
# the fields; tests/test_encode.py holds them to `payload` (the declaration) byte for byte.
_VRPO_NUMBER = struct.Struct("<H")
_ACK = P.PACKETS[C.PacketType.VRAO].struct
_COMMAND = P.PACKETS[C.PacketType.VRCI].struct


def vrpo_payload(packet_number: int, data: bytes) -> bytes:
    return _VRPO_NUMBER.pack(packet_number) + data


def command_payload(command_id: int, data: bytes = b"") -> bytes:
    return _COMMAND.pack(command_id & 0xFFFF, 0, data.ljust(C.COMMAND_DATA_LEN, b"\0")[:C.COMMAND_DATA_LEN])


def ack_payload(command_id: int) -> bytes:
    return _ACK.pack(command_id & 0xFFFF)


def vrpi_payload(fields: Mapping[str, Any]) -> bytes:
    return payload(C.PacketType.VRPI, fields)
