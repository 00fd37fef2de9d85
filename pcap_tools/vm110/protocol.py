"""The EG-Link packets declared once: the header and, per packet type, its fields in wire order.

Each field carries everything any part of the project needs to know about it: name (the public
interface: `<name>` in Python, `vm110.<name>` in Wireshark), wire type and size, display base,
value names, documented range, and the legality rules it takes part in. Everything else is
derived from these declarations: `vm110.decode` and `vm110.encode` (struct layouts, value
checks), the scapy layers' `fields_desc`, the analysis record (`analysis.collect`), the
simulators, and the tables of the Lua dissector (`scripts/lua-tables` writes them into
`dissector/vm110.lua`; a test fails when they are out of date).

Adding a field here is the whole edit: it then decodes, encodes, shows in the layers, is checked
(range, enum, zero while disarmed, spare) and, after `make lua-tables`, dissects in Wireshark.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Union

from . import constants as C

# Wire types: struct code, Lua reader kind ("u" unsigned LE, "s" signed LE, "b" bytes), Wireshark
# ProtoField type. "bytes" takes its size from the field.
_KINDS = {
    "u8": ("B", "u", "uint8"),
    "u16": ("H", "u", "uint16"),
    "u32": ("I", "u", "uint32"),
    "s16": ("h", "s", "int16"),
    "bytes": ("s", "b", "bytes"),
}


@dataclass(frozen=True)
class Enum:
    """Value names of an enumerated field; `name` is the table's name in the Lua dissector."""

    name: str
    values: Mapping[int, str]

    @classmethod
    def of(cls, name: str, names: Mapping[Any, str]) -> "Enum":
        """From a table keyed by IntEnum members (vm110.constants)."""
        return cls(name, {int(k): v for k, v in names.items()})


@dataclass(frozen=True)
class Field:
    name: str
    kind: str                                  # a key of _KINDS
    label: str                                 # Wireshark's field name (tree, column title)
    blurb: str                                 # Wireshark's description (status bar, tshark -G fields)
    size: int = 0                              # bytes: its length; integers: from the kind
    base: str = ""                             # "DEC" or "HEX" (default: HEX for enums, else DEC)
    enum: Optional[Enum] = None                # a value outside it: warning unknown_enum
    range: Optional[tuple[int, int]] = None    # documented range: warning out_of_range
    ru: bool = False                           # must be 0 while no RU is armed: disarmed_ru_data
    spare: bool = False                        # should be 0: spare_nonzero
    state: bool = False                        # part of the analysis state timeline (VRPI)

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"field {self.name}: unknown kind {self.kind!r}")
        if self.kind == "bytes" and self.size <= 0:
            raise ValueError(f"field {self.name}: a bytes field needs a size")
        if self.kind != "bytes":
            object.__setattr__(self, "size", struct.calcsize("<" + _KINDS[self.kind][0]))
        if not self.base:
            object.__setattr__(self, "base", "NONE" if self.kind == "bytes" else "HEX" if self.enum else "DEC")

    @property
    def code(self) -> str:
        """The struct code ("B", "h", "6s", ...)."""
        code = _KINDS[self.kind][0]
        return f"{self.size}{code}" if self.kind == "bytes" else code

    @property
    def limits(self) -> tuple[int, int]:
        """The lowest and highest value an integer field can carry."""
        bits = 8 * self.size
        return (-(1 << bits - 1), (1 << bits - 1) - 1) if self.code.islower() else (0, (1 << bits) - 1)

    @property
    def lua_kind(self) -> str:
        return _KINDS[self.kind][1]

    @property
    def protofield(self) -> str:
        return _KINDS[self.kind][2]

    @property
    def default(self) -> Union[int, bytes]:
        return bytes(self.size) if self.kind == "bytes" else 0


@dataclass(frozen=True)
class Packet:
    """One packet type: its fields in wire order and, for VRPO, the variable data after them."""

    type: C.PacketType
    description: str
    layout: str                                # layout name (shared by types with the same fields)
    fields: tuple[Field, ...]
    tail: Optional[Field] = None               # up to tail.size bytes after the fields
    ru_gate: Optional[str] = None              # the field whose 0 means "no RU armed"

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(f.code for f in self.fields))

    @property
    def min_size(self) -> int:
        return sum(f.size for f in self.fields)

    @property
    def max_size(self) -> int:
        return self.min_size + (self.tail.size if self.tail else 0)

    def span(self, name: str) -> slice:
        """Where a field lies in the payload."""
        off = self.offsets()[name]
        return slice(off, off + FIELDS[name].size)

    def offsets(self) -> dict[str, int]:
        """Field name -> offset in the payload."""
        out, off = {}, 0
        for f in self.fields:
            out[f.name] = off
            off += f.size
        return out


# --- Enums (TS-0006 4.1) ------------------------------------------------------------------------
BU_STATE = Enum.of("BU_STATE", C.BU_STATE_NAMES)
LINK_STATUS = Enum.of("LINK_STATUS", C.LINK_STATUS_NAMES)
RU_STATE = Enum.of("RU_STATE", C.RU_STATE_NAMES)
RU_DISABLED = Enum.of("RU_DISABLED", C.RU_DISABLED_NAMES)
RU_CABLE = Enum.of("RU_CABLE", C.RU_CABLE_NAMES)
RU_DOCKED = Enum.of("RU_DOCKED", C.RU_DOCKED_NAMES)
ENCODER_SWITCH = Enum.of("ENCODER_SWITCH", C.ENCODER_SWITCH_NAMES)

# --- Header (TS-0006 3): after the 4-character packet ID ---------------------------------------
HEADER_FIELDS = (
    Field("revision", "u16", "Revision",
          "Header revision; only 0 is defined (any other: illegal, only the header is decoded)"),
    Field("origin", "u16", "Origin", "Identifies the sending base unit on input packets; 0 on output packets",
          base="HEX"),
    Field("serial", "u16", "Serial",
          "The sender's 16-bit serial counter, one step per packet it sends (wraps 65535 to 0)"),
    Field("size", "u16", "Payload size",
          "Payload bytes after the 16-byte packet ID and header; the UDP payload is 20 + size (at most 492)"),
    Field("spare", "u32", "Spare", "Header spare bytes; should be 0", base="HEX", spare=True),
)

# --- Payloads (TS-0006 4) -----------------------------------------------------------------------
_PERCENT = (0, C.PERCENT_MAX)
VRPI_FIELDS = (
    Field("bu_state", "u8", "BU state", "Base unit state", enum=BU_STATE, state=True),
    Field("vlaps", "u8", "VLAPs", "Number of VLAPs (0 to 3)", range=(0, C.VLAPS_MAX), state=True),
    Field("unarmed_rus", "u8", "Unarmed RUs", "Remote units paired but not armed", state=True),
    Field("eg_link", "u8", "EG-Link status", "State of the EG-Link (this Ethernet link) as the BU sees it",
          enum=LINK_STATUS, state=True),
    Field("ec_link", "u8", "EC-Link status", "State of the EC-Link", enum=LINK_STATUS, state=True),
    Field("c_link", "u8", "C-Link status", "State of the C-Link (radio link to the remote unit)",
          enum=LINK_STATUS, state=True),
    Field("armed_ru", "u16", "Armed RU",
          "ID of the armed remote unit; 0 when none is armed (the RU fields are then 0)", base="HEX", state=True),
    Field("ru_state", "u8", "RU state", "State of the armed remote unit", enum=RU_STATE, ru=True, state=True),
    Field("ru_battery", "u8", "RU battery (%)", "Battery charge of the armed remote unit, 0 to 100 %",
          range=_PERCENT, ru=True, state=True),
    Field("ru_rssi", "u8", "RU C-Link RSSI (%)", "Radio signal strength of the armed remote unit, 0 to 100 %",
          range=_PERCENT, ru=True, state=True),
    Field("ru_cable", "u8", "RU cable", "Whether the armed remote unit is connected by cable", enum=RU_CABLE,
          ru=True, state=True),
    Field("ru_docked", "u8", "RU docked", "Whether the armed remote unit is docked", enum=RU_DOCKED, ru=True,
          state=True),
    Field("ru_disabled", "u8", "RU disabled", "Whether the armed remote unit is disabled", enum=RU_DISABLED,
          ru=True, state=True),
    *(Field(f"joystick{i}", "s16", f"Joystick {i}",
            f"Joystick axis {i} of the remote unit, -{C.JOYSTICK_LIMIT} to {C.JOYSTICK_LIMIT}",
            range=(-C.JOYSTICK_LIMIT, C.JOYSTICK_LIMIT), ru=True) for i in range(1, C.JOYSTICKS + 1)),
    *(Field(f"switch{i}", "s16", f"Switch {i}", f"Switch {i} of the remote unit, {C.SWITCH_MIN} to {C.SWITCH_MAX}",
            range=(C.SWITCH_MIN, C.SWITCH_MAX), ru=True) for i in range(1, C.SWITCHES + 1)),
    Field("encoder", "u8", "Encoder value", "Encoder position of the remote unit", ru=True),
    Field("encoder_switch", "u8", "Encoder switch", "Encoder push switch of the remote unit", enum=ENCODER_SWITCH,
          ru=True),
    Field("vrpi_spare", "bytes", "Spare", "VRPI spare bytes; should be 0", size=C.VRPI_SPARE_LEN, spare=True),
)
VRPO_FIELDS = (
    Field("packet_number", "u16", "Packet number",
          "Number of this packet within its VRPO burst (the first is 0, preference vm110.vrpo_number_start)"),
)
VRPO_TAIL = Field("periodic_data", "bytes", "Periodic data",
                  "Machine-specific display data (up to 488 bytes per packet; split bursts are reassembled)",
                  size=C.VRPO_MAX_DATA)
# One command_id field for commands and acknowledgements, so a filter shows a command with its acks.
_COMMAND_ID = Field("command_id", "u16", "Command ID",
                    "Pairs a command (VRCI, VRCO) with its acknowledgement (VRAO, VRAI); the same ID again is a resend")
COMMAND_FIELDS = (
    _COMMAND_ID,
    Field("command_spare", "u32", "Spare", "Command spare bytes; should be 0", base="HEX", spare=True),
    Field("command_data", "bytes", "Command data", "16 bytes of machine-specific command data",
          size=C.COMMAND_DATA_LEN),
)
ACK_FIELDS = (_COMMAND_ID,)

PACKETS: dict[C.PacketType, Packet] = {p.type: p for p in (
    Packet(C.PacketType.VRPI, C.PACKET_DESCRIPTIONS[C.PacketType.VRPI], "VRPI", VRPI_FIELDS, ru_gate="armed_ru"),
    Packet(C.PacketType.VRPO, C.PACKET_DESCRIPTIONS[C.PacketType.VRPO], "VRPO", VRPO_FIELDS, tail=VRPO_TAIL),
    Packet(C.PacketType.VRCI, C.PACKET_DESCRIPTIONS[C.PacketType.VRCI], "COMMAND", COMMAND_FIELDS),
    Packet(C.PacketType.VRCO, C.PACKET_DESCRIPTIONS[C.PacketType.VRCO], "COMMAND", COMMAND_FIELDS),
    Packet(C.PacketType.VRAI, C.PACKET_DESCRIPTIONS[C.PacketType.VRAI], "ACK", ACK_FIELDS),
    Packet(C.PacketType.VRAO, C.PACKET_DESCRIPTIONS[C.PacketType.VRAO], "ACK", ACK_FIELDS),
)}

# --- Derived: the header ------------------------------------------------------------------------
HEADER = struct.Struct(f"<{C.ID_LEN}s" + "".join(f.code for f in HEADER_FIELDS))   # ID + header, one read
HEADER_OFFSETS = {f.name: C.ID_LEN + struct.calcsize("<" + "".join(g.code for g in HEADER_FIELDS[:i]))
                  for i, f in enumerate(HEADER_FIELDS)}                           # from the packet start
SIZE_OFFSET = HEADER_OFFSETS["size"]
SIZE = struct.Struct("<" + HEADER_FIELDS[[f.name for f in HEADER_FIELDS].index("size")].code)
if HEADER.size != C.PREFIX_LEN:
    raise AssertionError(f"header fields make {HEADER.size - C.ID_LEN} bytes, TS-0006 says {C.HEADER_LEN}")

# --- Derived: payloads --------------------------------------------------------------------------
LAYOUTS = {t: tuple((f.name, f.code) for f in p.fields) for t, p in PACKETS.items()}
PAYLOAD_BOUNDS = {t: (p.min_size, p.max_size) for t, p in PACKETS.items()}
FIELDS: dict[str, Field] = {}            # every header and payload field by name (tails too)
for _f in (*HEADER_FIELDS, *(f for p in PACKETS.values() for f in (*p.fields, *([p.tail] if p.tail else ())))):
    if FIELDS.setdefault(_f.name, _f) != _f:
        raise AssertionError(f"two different fields named {_f.name}")
ENUM_FIELDS = {f.name: f.enum.values for f in FIELDS.values() if f.enum}
RANGES = {f.name: f.range for f in FIELDS.values() if f.range}


def state_fields() -> tuple[Field, ...]:
    """The leading VRPI fields that make up the state timeline (the analysis keeps their bytes)."""
    fields = PACKETS[C.PacketType.VRPI].fields
    lead = 0
    while lead < len(fields) and fields[lead].state:
        lead += 1
    if any(f.state for f in fields[lead:]):
        raise AssertionError("state fields must lead the VRPI payload: the analysis keeps its first bytes")
    return fields[:lead]
