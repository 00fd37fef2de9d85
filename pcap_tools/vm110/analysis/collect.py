"""What an engine extracts from a capture: compact per-sender arrays, tallies and examples.

Both engines (fast and tshark) fill a `Collected`; everything after that (serials, timing,
commands, bursts, state, verdict) is computed from it by the same code, so the two engines can
only differ in what they read, never in how it is judged.
"""
from __future__ import annotations

import struct
from collections import Counter
from array import array
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .. import constants as C
from ..capture import linktypes as L
from ..capture.reader import PCAP_RECORD_LEN, address

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


def sender_id(direction: str, origin: int, src: str) -> str:
    return f"{direction} {src} origin 0x{origin:04x}"


# One legal packet: time, frame, source (index into `Collected.sources`), source port, and the
# first PREFIX bytes of the EG-Link packet (ID, header, first payload bytes), zero-padded.
PREFIX = C.PREFIX_LEN + STATE_LEN
RECORD = struct.Struct(f"<dIHH{PREFIX}s")
RECORD_DTYPE = np.dtype({
    "names": ["ts", "frame", "src", "sport", "packet", "pid", "origin", "serial", "size", "aux", "state"],
    "formats": ["<f8", "<u4", "<u2", "<u2", f"V{PREFIX}", "<u4", "<u2", "<u2", "<u2", "<u2", f"V{STATE_LEN}"],
    "offsets": [0, 8, 12, 14, 16, 16, 22, 24, 26, 16 + C.PREFIX_LEN, 16 + C.PREFIX_LEN],
    "itemsize": RECORD.size,
})


@dataclass
class Sender:
    """Legal packets of one sender in arrival order (numpy arrays, one entry per packet)."""

    direction: str
    origin: int
    src: str
    ts: np.ndarray
    serial: np.ndarray
    code: np.ndarray
    frame: np.ndarray
    aux: np.ndarray       # command ID or VRPO packet number
    size: np.ndarray      # payload size
    state: np.ndarray     # VRPI: the state bytes (STATE)

    @property
    def id(self) -> str:
        return sender_id(self.direction, self.origin, self.src)


_CODE_TABLE = {t.value.encode(): i for i, t in enumerate(TYPES)}
# The bytes _gather_pcap picks, relative to a located EG-Link packet: the pcap record header's
# time (it starts _BEFORE bytes earlier: record header, Ethernet, IPv4, UDP), the IPv4 source,
# the UDP source port, and the first PREFIX bytes of the packet.
_IP = PCAP_RECORD_LEN + L.ETH_HEADER_LEN          # where IPv4 starts, from the record start
_BEFORE = _IP + L.IPV4_MIN_HEADER + L.UDP_HEADER_LEN
_PICK = np.concatenate([np.arange(0, 8), np.arange(_IP + L.IPV4_SRC, _IP + L.IPV4_SRC + 4),
                        np.arange(_IP + L.IPV4_MIN_HEADER, _IP + L.IPV4_MIN_HEADER + 2),
                        np.arange(_BEFORE, _BEFORE + PREFIX)]) - _BEFORE
_PICKED = np.dtype([("sec", "<u4"), ("frac", "<u4"), ("src", "<u4"), ("sport", ">u2"), ("packet", f"V{PREFIX}")])
_WINDOW = 1 << 22
FEW_SENDERS = 32       # up to this many, one comparison per sender beats sorting the key


def _groups(key: np.ndarray):
    """(key value, row indices in arrival order) per distinct key."""
    left = np.ones(len(key), dtype=bool)
    for _ in range(FEW_SENDERS):
        first = int(np.argmax(left))
        if not left[first]:
            return
        mine = key == key[first]
        left &= ~mine
        yield int(key[first]), np.flatnonzero(mine)
    rest = np.flatnonzero(left)
    if len(rest):
        order = rest[np.argsort(key[rest], kind="stable")]
        values, starts = np.unique(key[order], return_index=True)
        for value, a, b in zip(values.tolist(), starts, [*starts[1:], len(order)]):
            yield value, order[a:b]
_INPUT = np.array([t.direction is C.Direction.INPUT for t in TYPES])


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
    damage: Optional[int] = None          # file offset where reading stopped for `problem`
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
    records: bytearray = field(default_factory=bytearray)  # RECORD per legal packet, but:
    # legal packets found by the fused pcap loop are only located (file offset of the EG-Link
    # packet, frame) and gathered from the file afterwards, all at once (`_gather_pcap`).
    offsets: array = field(default_factory=lambda: array("Q"))
    offset_frames: array = field(default_factory=lambda: array("I"))
    pcap_scale: float = 1e-6
    sources: dict = field(default_factory=dict)            # packed source address -> index

    def add_illegal(self, frame: int, ts: float, src: str, ptype: str, reasons: list) -> None:
        self.illegal += 1
        self.illegal_reasons.update(reasons)
        if len(self.illegal_examples) < MAX_EXAMPLES:
            self.illegal_examples.append((frame, ts, src, ptype, tuple(sorted(reasons))))

    def source(self, src: bytes) -> int:
        index = self.sources.get(src)
        if index is None:
            index = self.sources[src] = len(self.sources)
        return index

    def add_legal(self, ts: float, frame: int, src: bytes, sport: int, packet: bytes) -> None:
        self.records += RECORD.pack(ts, frame, self.source(src), sport, packet)

    def _gather_pcap(self) -> np.ndarray:
        """RECORDs of the located packets, read back from the pcap a window at a time. Before
        each EG-Link packet lie its pcap record header (time) and the Ethernet/IPv4/UDP headers
        (source address and port) at fixed distances: the common frame of the fused loop."""
        offsets = np.frombuffer(self.offsets, dtype=np.uint64).astype(np.int64)
        frames = np.frombuffer(self.offset_frames, dtype=np.uint32)
        self.offsets, self.offset_frames = array("Q"), array("I")
        out = np.zeros(len(offsets), dtype=RECORD_DTYPE)
        out["frame"] = frames
        src = np.zeros(len(out), dtype=np.uint32)
        with open(self.path, "rb") as f:
            i = 0
            while i < len(offsets):
                first = int(offsets[i]) - _BEFORE
                j = max(int(np.searchsorted(offsets, first + _WINDOW - PREFIX, side="right")), i + 1)
                f.seek(first)
                want = int(offsets[j - 1]) + PREFIX - first
                window = np.frombuffer(f.read(want).ljust(want, b"\0"), dtype=np.uint8)
                rows = window[(offsets[i:j] - first)[:, None] + _PICK].view(_PICKED).ravel()
                out["ts"][i:j] = rows["sec"] + rows["frac"] * self.pcap_scale
                src[i:j] = rows["src"]
                out["sport"][i:j] = rows["sport"]
                out["packet"][i:j] = rows["packet"]
                i = j
        values, which = np.unique(src, return_inverse=True)
        index = np.array([self.source(int(v).to_bytes(4, "little")) for v in values.tolist()], dtype=np.uint16)
        out["src"] = index[which.ravel()]
        return out

    def merge(self, later: "Collected") -> None:
        """Append what another engine read from the part of the file that follows this one."""
        rec = np.frombuffer(later.records, dtype=RECORD_DTYPE)     # a bytearray: changed in place
        if len(rec):
            remap = np.zeros(len(later.sources), dtype=np.uint16)
            for src, index in later.sources.items():
                remap[index] = self.source(src)
            rec["src"] = remap[rec["src"]]
            rec["frame"] += self.frames
        self.records += later.records
        later.records = bytearray()
        self.offsets += later.offsets
        frames = np.frombuffer(later.offset_frames, dtype=np.uint32)     # an array: changed in place
        frames += self.frames
        self.offset_frames += later.offset_frames
        for f, t, s, p, r in later.illegal_examples[:max(0, MAX_EXAMPLES - len(self.illegal_examples))]:
            self.illegal_examples.append((f + self.frames, t, s, p, r))
        for name in ("udp", "non_udp", "fragments", "other_udp", "snap_truncated", "eglink", "crc_checked",
                     "illegal"):
            setattr(self, name, getattr(self, name) + getattr(later, name))
        self.crc_counts.update(later.crc_counts)
        self.illegal_reasons.update(later.illegal_reasons)
        self.frames += later.frames
        if later.frames:
            self.last_ts = later.last_ts
            self.first_ts = self.first_ts if self.first_ts is not None else later.first_ts
        if self.problem is None:
            self.problem, self.damage = later.problem, later.damage
        self.link_types = sorted(set(self.link_types) | set(later.link_types))

    def take_senders(self) -> list[Sender]:
        """The legal packets grouped by sender (direction, origin, source, port), sorted by id.
        Takes the records (they are regrouped, not kept twice). Senders are few: each is picked
        out with one vectorised comparison, which keeps the arrival order and needs no sort."""
        rec = np.frombuffer(self.records, dtype=RECORD_DTYPE)
        self.records = bytearray()
        if len(self.offsets):
            located = self._gather_pcap()
            rec = np.insert(located, np.searchsorted(located["frame"], rec["frame"]), rec) if len(rec) else located
        if not len(rec):
            return []
        pid = rec["pid"]
        code = np.zeros(len(rec), dtype=np.uint8)
        for raw, value in _CODE_TABLE.items():
            code[pid == int.from_bytes(raw, "little")] = value
        key = ((_INPUT[code].astype(np.int64) << 48) | (rec["src"].astype(np.int64) << 32)
               | (rec["sport"].astype(np.int64) << 16) | rec["origin"].astype(np.int64))
        sources = {i: s for s, i in self.sources.items()}
        out = []
        for value, rows in _groups(key):
            part = rec[rows]
            direction = (C.Direction.INPUT if value >> 48 else C.Direction.OUTPUT).value
            src = address(sources[(value >> 32) & 0xFFFF], (value >> 16) & 0xFFFF)
            out.append(Sender(direction, value & 0xFFFF, src, part["ts"], part["serial"], code[rows],
                              part["frame"], part["aux"], part["size"], part["state"]))
        return sorted(out, key=lambda s: s.id)
