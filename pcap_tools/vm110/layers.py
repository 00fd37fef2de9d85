# scapy.contrib.description = VM-110 EG-Link (TS-0006)
# scapy.contrib.status = loads
"""scapy layers for the EG-Link: `VM110` (packet ID, header, CRC trailer) and one class per payload.

The CRC trails the payload on the wire. scapy dissects fields front to back, so `pre_dissect`
moves the trailer in front of the payload and `post_build` puts it back; `size` and `crc` are
computed only when left unset, so that wrong values can be crafted on purpose.

CRC variant and stored byte order come from `conf.contribs["VM110"]` (as scapy's CAN layer does
with its settings), or temporarily from `crc_settings()`.

As scapy's contrib layers do, importing the module binds the layers to their UDP ports (5825 and
5827, either direction), and `from vm110.layers import *` gives the layers and the helpers of
`__all__`; `ls(VRPI)`, `sniff(offline=..., prn=...)` and `answers()` work as for any layer.
"""
from __future__ import annotations

import contextlib
import itertools
import struct
from typing import Any, Callable, Iterator, Optional

from scapy.config import conf
from scapy.fields import (
    ByteEnumField, ByteField, ConditionalField, Field, LEIntEnumField, LEIntField, LEShortEnumField, LEShortField,
    LESignedShortField, StrFixedLenEnumField, XByteField, XLEIntField, XLEShortField, XStrFixedLenField,
    XStrLenField,
)
from scapy.layers.inet import UDP
from scapy.packet import Packet, bind_layers, split_layers

from . import constants as C
from . import protocol as P
from .crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, check_byte_order, crc_bytes, crc_function
from .decode import crc_span

__all__ = ["PAYLOAD_CLASSES", "VM110", "VRAI", "VRAO", "VRCI", "VRCO", "VRPI", "VRPO", "bind_ports",
           "crc_settings", "unbind_ports"]

conf.contribs.setdefault("VM110", {"crc_variant": DEFAULT_VARIANT, "crc_order": DEFAULT_BYTE_ORDER})


def _settings() -> tuple[str, str]:
    cfg = conf.contribs["VM110"]
    return cfg["crc_variant"], cfg["crc_order"]


@contextlib.contextmanager
def crc_settings(variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> Iterator[None]:
    """Build and dissect with another CRC variant or stored byte order inside a `with` block."""
    crc_function(variant)
    check_byte_order(order)
    cfg = conf.contribs["VM110"]
    saved = dict(cfg)
    cfg.update(crc_variant=variant, crc_order=order)
    try:
        yield
    finally:
        cfg.clear()
        cfg.update(saved)


class StoredCRC(int):
    """A dissected CRC: written back in the byte order it was read in, whatever the settings are
    by then (a packet read inside `crc_settings(..., "big")` and written after it keeps its bytes)."""

    order: str


class CRCField(Field[Optional[int], bytes]):
    """32-bit CRC stored in the configured byte order (a dissected one: in its own)."""

    def __init__(self, name: str, default: Optional[int]) -> None:
        super().__init__(name, default, "<I")

    @staticmethod
    def _struct(order: str) -> struct.Struct:
        return struct.Struct("<I" if order == "little" else ">I")

    def addfield(self, pkt: Packet, s: bytes, val: Optional[int]) -> bytes:
        order = val.order if isinstance(val, StoredCRC) else _settings()[1]
        # Packed by scapy's own Field ("<I"), so that a value beyond 32 bits is the ValueError of
        # every other field (it was a bare struct.error); reversed for a big-endian trailer.
        packed = super().addfield(pkt, b"", 0 if val is None else val)
        return s + (packed if order == "little" else packed[::-1])

    def getfield(self, pkt: Packet, s: bytes) -> tuple[bytes, int]:
        order = _settings()[1]
        crc = StoredCRC(self._struct(order).unpack_from(s)[0])
        crc.order = order
        return s[4:], crc

    def i2repr(self, pkt: Optional[Packet], x: Optional[int]) -> str:
        return "None" if x is None else f"0x{x:08X}"


PACKET_IDS = {t.value.encode(): C.PACKET_DESCRIPTIONS[t] for t in C.PacketType}

# scapy field classes per wire kind: (plain, hexadecimal, with value names).
_SCAPY_FIELDS: dict[str, tuple[type, type, Optional[type]]] = {
    "u8": (ByteField, XByteField, ByteEnumField),
    "u16": (LEShortField, XLEShortField, LEShortEnumField),
    "u32": (LEIntField, XLEIntField, LEIntEnumField),
    "s16": (LESignedShortField, LESignedShortField, None),
}


_UNSET = object()


def scapy_field(f: P.Field, default: object = _UNSET) -> Field:
    """The scapy field of a declared field (vm110.protocol), shown as Wireshark shows it."""
    value = f.default if default is _UNSET else default
    if f.kind == "bytes":
        return XStrFixedLenField(f.name, bytes(value) if isinstance(value, bytes) else None, f.size)
    plain, hexa, named = _SCAPY_FIELDS[f.kind]
    if f.enum is not None and named is not None:
        return named(f.name, value, {int(k): v for k, v in f.enum.values.items()})
    return (hexa if f.base == "HEX" else plain)(f.name, value)


def _length(n: int) -> Callable[[Packet], int]:
    return lambda _pkt: n


class CondWholeField(ConditionalField):
    """A payload field that a payload cut short (illegal: truncated) may lack: dissected when its
    bytes are all there, else None. None here and in every field after it is the cut end of a
    payload, neither shown nor built (a dissected one builds as it was read; set by hand, it
    crafts a payload cut short); a None before a field that is set builds as scapy builds None, 0,
    so that no field after it moves."""

    def __init__(self, fld: Field, size: int, later: tuple[str, ...]) -> None:
        # A payload field's default is never None: None is a value set, by dissection or by hand.
        names = (fld.name, *later)
        super().__init__(fld, lambda pkt: any(pkt.fields.get(n, 0) is not None for n in names))
        self.name, self.size = fld.name, size   # (name: read on every build, not through the delegation)

    def getfield(self, pkt: Packet, s: bytes) -> tuple[bytes, Any]:
        return (s, None) if len(s) < self.size else super().getfield(pkt, s)


def fields_of(ptype: C.PacketType) -> list[Any]:
    """`fields_desc` of a payload layer, from the declaration."""
    packet = P.PACKETS[ptype]
    # Bytes beyond the layout's maximum are not part of the tail: they dissect as a Raw payload.
    tail = [] if packet.tail is None else [
        (XStrLenField(packet.tail.name, b"", length_from=_length(packet.tail.size)), 0)]
    fields = [(scapy_field(f), f.size) for f in packet.fields] + tail
    names = tuple(fld.name for fld, _ in fields)
    return [CondWholeField(fld, size, names[i + 1:]) for i, (fld, size) in enumerate(fields)]


def _header_fields() -> list[Any]:
    """Packet ID, the declared header, and the CRC trailer (dissected and built out of wire order)."""
    # size is computed when left unset (None), like the CRC
    defaults: dict[str, object] = {"revision": C.SUPPORTED_REVISION, "size": None}
    return [
        # (scapy's stubs say str keys; its code compares the raw bytes, which the keys are)
        StrFixedLenEnumField("type", b"VRPI", PACKET_IDS, length=C.ID_LEN),  # type: ignore[arg-type]
        *(scapy_field(f, defaults.get(f.name, _UNSET)) for f in P.HEADER_FIELDS),
        CRCField("crc", None),
    ]


_WIDTHS = (C.ID_LEN, *(f.size for f in P.HEADER_FIELDS), C.CRC_LEN)   # of VM110's fields, in its order


class VM110(Packet):
    name = "VM-110 EG-Link"
    fields_desc = _header_fields()

    def pre_dissect(self, s: bytes) -> bytes:
        s = bytes(s)    # (a memoryview, as socket.recv_into fills one, cannot be joined: vm110.decode takes it too)
        if len(s) < C.OVERHEAD:
            return s
        end = crc_span(s, P.SIZE.unpack_from(s, P.SIZE_OFFSET)[0])
        return s[:C.PREFIX_LEN] + s[end:end + C.CRC_LEN] + s[C.PREFIX_LEN:end] + s[end + C.CRC_LEN:]

    def do_dissect(self, s: bytes) -> bytes:
        if len(s) >= C.OVERHEAD:
            return super().do_dissect(s)
        # Cut short before a CRC (illegal: truncated): the fields that fit whole, as vm110.decode and
        # the dissector show them, the others None; the rest is padding. It builds as it was read
        # until a field is changed, then whole. Without a whole packet ID it is no EG-Link: Raw.
        whole = sum(1 for end in itertools.accumulate(_WIDTHS) if end <= len(s))
        if not whole:
            raise struct.error(f"{len(s)} bytes: no packet ID")
        read = s[:sum(_WIDTHS[:whole])]
        for f in self.fields_desc[:whole]:
            s, self.fields[f.name] = f.getfield(self, s)
        self.fields.update((f.name, None) for f in self.fields_desc[whole:])
        self.raw_packet_cache, self.raw_packet_cache_fields, self.explicit = read, {}, 1
        return s

    def post_dissect(self, s: bytes) -> bytes:
        if self.crc is not None:
            self.raw_packet_cache = None  # the cached bytes are in dissection order, not wire order
        return s

    def extract_padding(self, s: bytes) -> tuple[bytes, bytes]:
        size = (self.size or 0) if self.crc is not None else 0    # no CRC: cut short, no payload
        return s[:size], s[size:]

    def post_build(self, p: bytes, pay: bytes) -> bytes:
        if self.size is None:
            p = p[:P.SIZE_OFFSET] + P.SIZE.pack(len(pay) & 0xFFFF) + p[P.SIZE_OFFSET + P.SIZE.size:]
        body = p[:C.PREFIX_LEN] + pay
        trailer = p[C.PREFIX_LEN:C.PREFIX_LEN + C.CRC_LEN]
        if self.crc is None:
            trailer = crc_bytes(body, *_settings())
        return body + trailer

    def crc_ok(self) -> bool:
        """Whether the stored CRC matches the packet under the configured variant."""
        raw = bytes(self)
        if len(raw) < C.OVERHEAD:
            return False    # no CRC to match
        end = crc_span(raw, P.SIZE.unpack_from(raw, P.SIZE_OFFSET)[0])
        variant, order = _settings()
        stored = int.from_bytes(raw[end:end + C.CRC_LEN], check_byte_order(order))
        return stored == crc_function(variant)(raw[:end])

    def hashret(self) -> bytes:
        return self.payload.hashret()

    def answers(self, other: Packet) -> int:
        return isinstance(other, VM110) and self.payload.answers(other.payload)

    def mysummary(self) -> str:
        return self.sprintf("VM110 %type% serial=%serial%")


class _Payload(Packet):
    """A payload layer. Cut short (illegal: truncated), it carries the fields that fit whole, as
    `vm110.decode` and the dissector show them, the others None; the bytes of a field cut in two
    stay a Raw payload. With no field whole, the payload is Raw (as scapy's layers fall back)."""

    ptype: C.PacketType

    def do_dissect(self, s: bytes) -> bytes:
        fields = P.PACKETS[self.ptype].fields
        if len(s) >= P.PACKETS[self.ptype].min_size:
            return super().do_dissect(s)
        ends = list(itertools.takewhile(lambda end: end <= len(s), itertools.accumulate(f.size for f in fields)))
        if not ends:
            raise struct.error(f"{self.ptype.value} payload of {len(s)} bytes: no field whole")
        rest = super().do_dissect(s[:ends[-1]]) + s[ends[-1]:]
        for f in self.fields_desc[len(ends):]:
            self.fields[f.name] = None
        return rest

    def answers(self, other: Packet) -> int:
        # Only an acknowledgement answers, its command: scapy's default would pair any two packets
        # of one class (a VRCI with its own retransmission, a VRPI with the next).
        return 0

    def _summary(self, text: str) -> str:
        """`text` after the type and the header's serial: scapy shows only the top layer's summary,
        and the serial is what a capture's packets are followed by."""
        serial = f" serial={self.underlayer.serial}" if isinstance(self.underlayer, VM110) else ""
        return f"{self.ptype.value}{serial} {text}"


def _same_id(ack: Packet, command: Packet) -> bool:
    """An acknowledgement's ID names its command; an ID left unset (crafted None) names none."""
    return ack.command_id is not None and ack.command_id == command.command_id


class _CommandPair(_Payload):
    """Commands and their acknowledgements pair up by command ID (TS-0006 4.3 to 4.6)."""

    pair = b""

    def hashret(self) -> bytes:
        # A command ID left unset (crafted None) pairs with nothing: no ack names it.
        if self.command_id is None:
            return self.pair
        return self.pair + struct.pack("<H", self.command_id)

    def mysummary(self) -> str:
        return self._summary(self.sprintf("command_id=%command_id%"))


class VRPI(_Payload):
    name = "VRPI (VisionRemote Periodic Input)"
    ptype = C.PacketType.VRPI
    fields_desc = fields_of(ptype)

    def mysummary(self) -> str:
        return self._summary(self.sprintf("%bu_state% armed_ru=%armed_ru% %ru_state%"))


class VRPO(_Payload):
    name = "VRPO (VisionRemote Periodic Output)"
    ptype = C.PacketType.VRPO
    fields_desc = fields_of(ptype)

    def mysummary(self) -> str:
        data = self.periodic_data or b""     # (None: crafted cut short)
        return self._summary(self.sprintf("#%packet_number%") + f" {len(data)} bytes")


class VRCI(_CommandPair):
    name = "VRCI (VisionRemote Command Input)"
    pair = b"CI"
    ptype = C.PacketType.VRCI
    fields_desc = fields_of(ptype)


class VRCO(_CommandPair):
    name = "VRCO (VisionRemote Command Output)"
    pair = b"CO"
    ptype = C.PacketType.VRCO
    fields_desc = fields_of(ptype)


class VRAO(_CommandPair):
    name = "VRAO (VisionRemote Acknowledge Output)"
    pair = VRCI.pair
    ptype = C.PacketType.VRAO
    fields_desc = fields_of(ptype)

    def answers(self, other: Packet) -> int:
        return isinstance(other, VRCI) and _same_id(self, other)


class VRAI(_CommandPair):
    name = "VRAI (VisionRemote Acknowledge Input)"
    pair = VRCO.pair
    ptype = C.PacketType.VRAI
    fields_desc = fields_of(ptype)

    def answers(self, other: Packet) -> int:
        return isinstance(other, VRCO) and _same_id(self, other)


PAYLOAD_CLASSES: dict[C.PacketType, type[Packet]] = {
    C.PacketType.VRPI: VRPI, C.PacketType.VRPO: VRPO, C.PacketType.VRCI: VRCI,
    C.PacketType.VRCO: VRCO, C.PacketType.VRAI: VRAI, C.PacketType.VRAO: VRAO,
}
# Revision 0 is the layout of TS-0006 (3.2): any other revision's payload stays raw, as in the dissector.
for _ptype, _cls in PAYLOAD_CLASSES.items():
    bind_layers(VM110, _cls, type=_ptype.value.encode(), revision=C.SUPPORTED_REVISION)

_bound_inputs: list[int] = []   # a UDP port stays bound while an input port bound here covers it


def _covered() -> set[int]:
    return {port for first in _bound_inputs for port in (first, first + C.OUTPUT_PORT_OFFSET)}


def bind_ports(input_port: int = C.INPUT_PORT) -> None:
    """Decode UDP on `input_port` and `input_port + 2` (both directions) as EG-Link; ValueError for
    an input port whose output port would be no UDP port."""
    if isinstance(input_port, bool) or not isinstance(input_port, int) or not (
            0 < input_port <= 0xFFFF - C.OUTPUT_PORT_OFFSET):
        raise ValueError(f"input port {input_port!r}: an integer from 1 to {0xFFFF - C.OUTPUT_PORT_OFFSET}")
    before = _covered()
    if input_port not in _bound_inputs:
        _bound_inputs.append(input_port)
    for port in sorted(_covered() - before):
        bind_layers(UDP, VM110, sport=port)
        bind_layers(UDP, VM110, dport=port)


def unbind_ports(input_port: int) -> None:
    """Undo `bind_ports` for one input port and its output port, except a port that another bound
    input port also covers (a second base unit on 5823 sends its output to 5825)."""
    if input_port not in _bound_inputs:
        return
    before = _covered()
    _bound_inputs.remove(input_port)
    for port in sorted(before - _covered()):
        split_layers(UDP, VM110, sport=port)
        split_layers(UDP, VM110, dport=port)


bind_ports()
