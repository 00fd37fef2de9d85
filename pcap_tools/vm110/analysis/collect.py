"""What an engine extracts from a capture: compact per-sender arrays, tallies and examples.

Both engines (fast and tshark) fill a `Collected`; everything after that (serials, timing,
commands, bursts, state, verdict) is computed from it by the same code, so the two engines can
only differ in what they read, never in how it is judged.
"""
from __future__ import annotations

import ipaddress
import struct
from array import array
from collections import Counter
from dataclasses import dataclass, field
from typing import Optional

from .. import constants as C

TYPES = tuple(C.PacketType)
CODE = {t: i for i, t in enumerate(TYPES)}               # packet type -> small integer code
CODE_OF_ID = {t.value.encode(): i for i, t in enumerate(TYPES)}
VRPI_CODE, VRPO_CODE = CODE[C.PacketType.VRPI], CODE[C.PacketType.VRPO]
# VRPI bytes that make up the state timeline: bu_state .. ru_disabled.
STATE_LEN = 14
STATE = struct.Struct("<BBBBBBHBBBBBB")
STATE_FIELDS = ("bu_state", "vlaps", "unarmed_rus", "eg_link", "ec_link", "c_link", "armed_ru",
                "ru_state", "ru_battery", "ru_rssi", "ru_cable", "ru_docked", "ru_disabled")
MAX_EXAMPLES = 1000                                       # illegal packets listed in a report


def address(src: bytes, port: int) -> str:
    """"ip:port" of a packed source address (IPv6 in brackets)."""
    if len(src) == 4:
        return f"{src[0]}.{src[1]}.{src[2]}.{src[3]}:{port}"
    return f"[{ipaddress.IPv6Address(src)}]:{port}"


def sender_id(direction: str, origin: int, src: str) -> str:
    return f"{direction} {src} origin 0x{origin:04x}"


@dataclass
class Sender:
    """Legal packets of one sender in arrival order, one entry per packet in each array but
    `state`, which has one per VRPI."""

    direction: str
    origin: int
    src: str
    ts: array = field(default_factory=lambda: array("d"))
    serial: array = field(default_factory=lambda: array("H"))
    code: array = field(default_factory=lambda: array("B"))
    frame: array = field(default_factory=lambda: array("I"))
    aux: array = field(default_factory=lambda: array("H"))     # command ID or VRPO packet number
    size: array = field(default_factory=lambda: array("H"))    # payload size
    state: array = field(default_factory=lambda: array("I"))   # VRPI only: index into states

    @property
    def id(self) -> str:
        return sender_id(self.direction, self.origin, self.src)


@dataclass
class Collected:
    path: str
    engine: str
    format: str = ""
    link_types: list = field(default_factory=list)
    frames: int = 0
    udp: int = 0
    non_udp: int = 0
    fragments: int = 0
    other_udp: int = 0
    snap_truncated: int = 0
    problem: Optional[str] = None
    first_ts: Optional[float] = None
    last_ts: Optional[float] = None
    eglink: int = 0
    ports: tuple = ()
    crc_variant: str = ""
    crc_order: str = ""
    crc_auto: bool = True
    crc_counts: Counter = field(default_factory=Counter)   # (variant, order) -> packets validated
    crc_checked: int = 0                                   # EG-Link packets long enough for a CRC
    illegal: int = 0
    illegal_reasons: Counter = field(default_factory=Counter)
    illegal_examples: list = field(default_factory=list)   # (frame, ts, src, type, reasons)
    senders: dict = field(default_factory=dict)            # key -> Sender
    states: list = field(default_factory=list)             # state id -> STATE_LEN bytes

    def add_illegal(self, frame: int, ts: float, src: str, ptype: str, reasons: list) -> None:
        self.illegal += 1
        self.illegal_reasons.update(reasons)
        if len(self.illegal_examples) < MAX_EXAMPLES:
            self.illegal_examples.append((frame, ts, src, ptype, tuple(sorted(reasons))))
