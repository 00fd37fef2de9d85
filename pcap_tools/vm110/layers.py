"""scapy layers for the EG-Link: `VM110` (packet ID, header, CRC trailer) and one class per payload.

The CRC trails the payload on the wire. scapy dissects fields front to back, so `pre_dissect`
moves the trailer in front of the payload and `post_build` puts it back; `size` and `crc` are
computed only when left unset, so that wrong values can be crafted on purpose.

CRC variant and stored byte order come from `conf.contribs["VM110"]` (as scapy's CAN layer does
with its settings), or temporarily from `crc_settings()`.
"""
from __future__ import annotations

import contextlib
import struct
from typing import Iterator, Optional

from scapy.config import conf
from scapy.fields import (
    ByteEnumField, ByteField, Field, LEIntField, LEShortField, LESignedShortField,
    StrFixedLenEnumField, XLEShortField, XStrFixedLenField, XStrLenField,
)
from scapy.layers.inet import UDP
from scapy.packet import Packet, bind_layers, split_layers

from . import constants as C
from .crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, check_byte_order, crc_bytes, crc_function
from .decode import crc_span

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


class CRCField(Field[Optional[int], bytes]):
    """32-bit CRC stored in the configured byte order."""

    def __init__(self, name: str, default: Optional[int]) -> None:
        super().__init__(name, default, "<I")

    def _struct(self) -> struct.Struct:
        return struct.Struct("<I" if _settings()[1] == "little" else ">I")

    def addfield(self, pkt: Packet, s: bytes, val: Optional[int]) -> bytes:
        return s + self._struct().pack(self.i2m(pkt, val) or 0)

    def getfield(self, pkt: Packet, s: bytes) -> tuple[bytes, int]:
        return s[4:], self._struct().unpack_from(s)[0]

    def i2repr(self, pkt: Optional[Packet], x: Optional[int]) -> str:
        return "None" if x is None else f"0x{x:08X}"


PACKET_IDS = {t.value.encode(): C.PACKET_DESCRIPTIONS[t] for t in C.PacketType}


def _names(table: dict) -> dict[int, str]:
    return {int(k): v for k, v in table.items()}


class VM110(Packet):
    name = "VM-110 EG-Link"
    fields_desc = [
        StrFixedLenEnumField("type", b"VRPI", PACKET_IDS, length=C.ID_LEN),
        LEShortField("revision", C.SUPPORTED_REVISION),
        LEShortField("origin", 0),
        LEShortField("serial", 0),
        LEShortField("size", None),
        LEIntField("spare", 0),
        CRCField("crc", None),  # the trailer, dissected and built out of wire order
    ]

    def pre_dissect(self, s: bytes) -> bytes:
        if len(s) < C.OVERHEAD:
            return s
        size = struct.unpack_from("<H", s, 10)[0]
        end = crc_span(s, size)
        return s[:C.PREFIX_LEN] + s[end:end + C.CRC_LEN] + s[C.PREFIX_LEN:end] + s[end + C.CRC_LEN:]

    def post_dissect(self, s: bytes) -> bytes:
        self.raw_packet_cache = None  # the cached bytes are in dissection order, not wire order
        return s

    def extract_padding(self, s: bytes) -> tuple[bytes, bytes]:
        size = self.size or 0
        return s[:size], s[size:]

    def post_build(self, p: bytes, pay: bytes) -> bytes:
        if self.size is None:
            p = p[:10] + struct.pack("<H", len(pay) & 0xFFFF) + p[12:]
        body = p[:C.PREFIX_LEN] + pay
        trailer = p[C.PREFIX_LEN:C.PREFIX_LEN + C.CRC_LEN]
        if self.crc is None:
            trailer = crc_bytes(body, *_settings())
        return body + trailer

    def crc_ok(self) -> bool:
        """Whether the stored CRC matches the packet under the configured variant."""
        raw = bytes(self)
        end = crc_span(raw, struct.unpack_from("<H", raw, 10)[0])
        variant, order = _settings()
        return int.from_bytes(raw[end:end + C.CRC_LEN], order) == crc_function(variant)(raw[:end])

    def hashret(self) -> bytes:
        return self.payload.hashret()

    def answers(self, other: Packet) -> int:
        return isinstance(other, VM110) and self.payload.answers(other.payload)

    def mysummary(self) -> str:
        return self.sprintf("VM110 %type% serial=%serial%")


def _command_fields() -> list[Field]:
    return [
        LEShortField("command_id", 0),
        LEIntField("command_spare", 0),
        XStrFixedLenField("command_data", b"\x00" * C.COMMAND_DATA_LEN, C.COMMAND_DATA_LEN),
    ]


class _CommandPair(Packet):
    """Commands and their acknowledgements pair up by command ID (TS-0006 4.3 to 4.6)."""

    pair = b""

    def hashret(self) -> bytes:
        return self.pair + struct.pack("<H", self.command_id)

    def mysummary(self) -> str:
        return self.sprintf(f"{self.__class__.__name__} command_id=%command_id%")


class VRPI(Packet):
    name = "VRPI (VisionRemote Periodic Input)"
    fields_desc = [
        ByteEnumField("bu_state", C.BuState.INITIAL, _names(C.BU_STATE_NAMES)),
        ByteField("vlaps", 0),
        ByteField("unarmed_rus", 0),
        ByteEnumField("eg_link", C.LinkStatus.UNUSED, _names(C.LINK_STATUS_NAMES)),
        ByteEnumField("ec_link", C.LinkStatus.UNUSED, _names(C.LINK_STATUS_NAMES)),
        ByteEnumField("c_link", C.LinkStatus.UNUSED, _names(C.LINK_STATUS_NAMES)),
        XLEShortField("armed_ru", 0),
        ByteEnumField("ru_state", C.RuState.INITIAL, _names(C.RU_STATE_NAMES)),
        ByteField("ru_battery", 0),
        ByteField("ru_rssi", 0),
        ByteEnumField("ru_cable", C.RuCable.WIRELESS, _names(C.RU_CABLE_NAMES)),
        ByteEnumField("ru_docked", C.RuDocked.NOT_DOCKED, _names(C.RU_DOCKED_NAMES)),
        ByteEnumField("ru_disabled", C.RuDisabled.ENABLED, _names(C.RU_DISABLED_NAMES)),
        *(LESignedShortField(f"joystick{i}", 0) for i in range(1, C.JOYSTICKS + 1)),
        *(LESignedShortField(f"switch{i}", 0) for i in range(1, C.SWITCHES + 1)),
        ByteField("encoder", 0),
        ByteEnumField("encoder_switch", C.EncoderSwitch.RELEASED, _names(C.ENCODER_SWITCH_NAMES)),
        XStrFixedLenField("vrpi_spare", b"\x00" * C.VRPI_SPARE_LEN, C.VRPI_SPARE_LEN),
    ]

    def mysummary(self) -> str:
        return self.sprintf("VRPI %bu_state% armed_ru=%armed_ru% %ru_state%")


class VRPO(Packet):
    name = "VRPO (VisionRemote Periodic Output)"
    fields_desc = [
        LEShortField("packet_number", 0),
        # Bytes beyond the layout's 488 are not periodic data: they dissect as a Raw payload.
        XStrLenField("periodic_data", b"", length_from=lambda _: C.VRPO_MAX_DATA),
    ]

    def mysummary(self) -> str:
        return self.sprintf("VRPO #%packet_number%") + f" {len(self.periodic_data)} bytes"


class VRCI(_CommandPair):
    name = "VRCI (VisionRemote Command Input)"
    pair = b"CI"
    fields_desc = _command_fields()


class VRCO(_CommandPair):
    name = "VRCO (VisionRemote Command Output)"
    pair = b"CO"
    fields_desc = _command_fields()


class VRAO(_CommandPair):
    name = "VRAO (VisionRemote Acknowledge Output)"
    pair = VRCI.pair
    fields_desc = [LEShortField("command_id", 0)]

    def answers(self, other: Packet) -> int:
        return isinstance(other, VRCI) and other.command_id == self.command_id


class VRAI(_CommandPair):
    name = "VRAI (VisionRemote Acknowledge Input)"
    pair = VRCO.pair
    fields_desc = [LEShortField("command_id", 0)]

    def answers(self, other: Packet) -> int:
        return isinstance(other, VRCO) and other.command_id == self.command_id


PAYLOAD_CLASSES: dict[C.PacketType, type[Packet]] = {
    C.PacketType.VRPI: VRPI, C.PacketType.VRPO: VRPO, C.PacketType.VRCI: VRCI,
    C.PacketType.VRCO: VRCO, C.PacketType.VRAI: VRAI, C.PacketType.VRAO: VRAO,
}
for _ptype, _cls in PAYLOAD_CLASSES.items():
    bind_layers(VM110, _cls, type=_ptype.value.encode())

_bound_ports: list[int] = []


def bind_ports(input_port: int = C.INPUT_PORT) -> None:
    """Decode UDP on `input_port` and `input_port + 2` (both directions) as EG-Link."""
    ports = (input_port, input_port + C.OUTPUT_PORT_OFFSET)
    for port in ports:
        if port not in _bound_ports:
            bind_layers(UDP, VM110, sport=port)
            bind_layers(UDP, VM110, dport=port)
            _bound_ports.append(port)


def unbind_ports(input_port: int) -> None:
    """Undo `bind_ports` for one input port and its output port."""
    for port in (input_port, input_port + C.OUTPUT_PORT_OFFSET):
        if port in _bound_ports:
            split_layers(UDP, VM110, sport=port)
            split_layers(UDP, VM110, dport=port)
            _bound_ports.remove(port)


bind_ports()
