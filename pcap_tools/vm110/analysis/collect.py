"""What an engine extracts from a capture: the file-level facts (frames, traffic around EG-Link,
CRC counts, illegal packets, damage) and, for each legal packet, one RECORD.

Both engines (fast and tshark) fill a `Collected`, which hands the records a batch at a time to
its `Analysis` (`flush`); everything after that (serials, timing, commands, bursts, state,
verdict) is computed by the same code, so the two engines can only differ in what they read,
never in how it is judged. Records are not kept: memory does not grow with the packets.
"""
from __future__ import annotations

import math
import struct
from collections import Counter
from array import array
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from .. import constants as C
from .. import protocol as P
from ..capture import linktypes as L
from ..capture.reader import PCAP_RECORD_LEN, PcapLayout

TYPES = tuple(C.PacketType)
CODE = {t: i for i, t in enumerate(TYPES)}               # packet type -> small integer code
CODE_OF_ID = {t.value.encode(): i for i, t in enumerate(TYPES)}
VRPI_CODE, VRPO_CODE = CODE[C.PacketType.VRPI], CODE[C.PacketType.VRPO]
# The leading VRPI bytes that make up the state timeline (fields declared `state` in vm110.protocol).
STATE_FIELDS = tuple(f.name for f in P.state_fields())
STATE = struct.Struct("<" + "".join(f.code for f in P.state_fields()))
STATE_LEN = STATE.size
MAX_EXAMPLES = 1000                                       # illegal packets listed in a report


def sender_id(direction: str, origin: int, src: str) -> str:
    return f"{direction} {src} origin 0x{origin:04x}"


# One legal packet: time, frame, source (index into `Collected.sources`), source port, and the
# first PREFIX bytes of the EG-Link packet (ID, header, first payload bytes), zero-padded. The
# numpy view names the header fields at their declared offsets; `aux` is the first payload field of
# the other types (packet number, command ID), `state` the VRPI state bytes.
PREFIX = C.PREFIX_LEN + STATE_LEN
# (the source index in 32 bits: a capture may hold more than 65,536 source addresses, spoofed or not)
RECORD = struct.Struct(f"<dIIH{PREFIX}s")
_AT = struct.calcsize("<dIIH")                            # where the packet starts in a RECORD
_KEYS = [f for f in P.HEADER_FIELDS if f.name in ("origin", "serial", "size")]   # what the analysis reads
_NUMPY = {"H": "<u2", "I": "<u4"}
RECORD_DTYPE = np.dtype({
    "names": ["ts", "frame", "src", "sport", "packet", "pid", *(f.name for f in _KEYS), "aux", "state"],
    "formats": ["<f8", "<u4", "<u4", "<u2", f"V{PREFIX}", "<u4", *(_NUMPY[f.code] for f in _KEYS),
                "<u2", f"V{STATE_LEN}"],
    "offsets": [0, 8, 12, 16, _AT, _AT, *(_AT + P.HEADER_OFFSETS[f.name] for f in _KEYS),
                _AT + C.PREFIX_LEN, _AT + C.PREFIX_LEN],
    "itemsize": RECORD.size,
})
if any(p.fields[0].code != "H" for t, p in P.PACKETS.items() if t is not C.PacketType.VRPI):
    raise AssertionError("RECORD `aux` reads a 16-bit first payload field (packet number, command ID)")


_PIDS = np.array(sorted(int.from_bytes(t.value.encode(), "little") for t in TYPES), dtype=np.uint32)
_CODE_OF_PID = np.array([CODE_OF_ID[int(p).to_bytes(4, "little")] for p in _PIDS], dtype=np.uint8)


def code_of(pid) -> np.ndarray:
    """Type codes of legal packets from their packet IDs (RECORD `pid`)."""
    return _CODE_OF_PID[np.searchsorted(_PIDS, pid)]


# The bytes `located_rows` picks, relative to a located EG-Link packet: the pcap record header's
# time (it starts _BEFORE bytes earlier: record header, Ethernet, IPv4, UDP), the IPv4 source,
# the UDP source port, and the first PREFIX bytes of the packet.
_IP = PCAP_RECORD_LEN + L.ETH_HEADER_LEN          # where IPv4 starts, from the record start
_BEFORE = _IP + L.IPV4_MIN_HEADER + L.UDP_HEADER_LEN
_PICK = np.concatenate([np.arange(0, 8), np.arange(_IP + L.IPV4_SRC, _IP + L.IPV4_SRC + 4),
                        np.arange(_IP + L.IPV4_MIN_HEADER, _IP + L.IPV4_MIN_HEADER + 2),
                        np.arange(_BEFORE, _BEFORE + PREFIX)]) - _BEFORE
_PICKED = np.dtype([("sec", "<u4"), ("frac", "<u4"), ("src", "<u4"), ("sport", ">u2"), ("packet", f"V{PREFIX}")])
_ROWS = 4096           # records gathered at a time
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


_SRC_BITS = 30           # source indexes: one per packet at most, 2**30 of them far beyond any capture


def sender_keys(rec: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """One integer per record naming its sender: direction, source index, port, origin."""
    return ((_INPUT[codes].astype(np.int64) << (32 + _SRC_BITS)) | (rec["src"].astype(np.int64) << 32)
            | (rec["sport"].astype(np.int64) << 16) | rec["origin"].astype(np.int64))


def key_sender(key: int) -> tuple[str, int, int, int]:
    """(direction, origin, source index, port) of a sender key."""
    direction = (C.Direction.INPUT if key >> (32 + _SRC_BITS) else C.Direction.OUTPUT).value
    return direction, key & 0xFFFF, (key >> 32) & ((1 << _SRC_BITS) - 1), (key >> 16) & 0xFFFF


@dataclass
class Collected:
    path: str
    engine: str
    analysis: Any = None                  # the Analysis the records are fed to
    format: str = ""
    link_types: list = field(default_factory=list)
    frames: int = 0
    udp: int = 0
    non_udp: int = 0
    fragments: int = 0
    unread: int = 0                       # frames of a link type the reader cannot read
    tunnelled: int = 0                    # frames of a tunnel the reader does not unwrap
    other_udp: int = 0
    snap_truncated: int = 0
    problem: Optional[str] = None
    damage: Optional[int] = None          # file offset where reading stopped for `problem`
    dropped: Optional[dict] = None        # what the capture says it dropped (capture.drops); None: nothing
    first_ts: Optional[float] = None
    last_ts: Optional[float] = None
    earliest_ts: float = math.inf         # the span of the records' times, in any order (capinfos')
    latest_ts: float = -math.inf
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
    records: bytearray = field(default_factory=bytearray)  # RECORD per legal packet not yet fed
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

    def located_rows(self, data: bytes, offsets: array, frames: array, layout: PcapLayout) -> np.ndarray:
        """RECORDs of EG-Link packets located in a chunk of a little-endian Ethernet pcap (offsets
        into `data`, which runs at least PREFIX bytes past the last). Before each lie its pcap
        record header (time) and the Ethernet/IPv4/UDP headers (source address and port) at fixed
        distances: the common frame of the fused loop. One numpy gather for the whole chunk."""
        out = np.zeros(len(offsets), dtype=RECORD_DTYPE)
        if not len(out):
            return out
        at = np.frombuffer(offsets, dtype=np.int64)
        raw = np.frombuffer(data, dtype=np.uint8)
        rows = np.concatenate([raw[at[k:k + _ROWS, None] + _PICK].view(_PICKED).ravel()     # small index arrays
                               for k in range(0, len(at), _ROWS)])
        out["frame"] = np.frombuffer(frames, dtype=np.uint32)
        out["ts"] = rows["sec"] + rows["frac"] * layout.scale
        for i in np.flatnonzero(rows["frac"] >= layout.units).tolist():   # damage: as Wireshark reads it
            out["ts"][i] = layout.time(int(rows["sec"][i]), int(rows["frac"][i]))
        out["sport"] = rows["sport"]
        out["packet"] = rows["packet"]
        values, which = np.unique(rows["src"], return_inverse=True)
        index = np.array([self.source(int(v).to_bytes(4, "little")) for v in values.tolist()], dtype=np.uint32)
        out["src"] = index[which.ravel()]
        return out

    def flush(self, located: Optional[np.ndarray] = None) -> None:
        """Feed the records gathered so far (and `located` ones) to the analysis, in frame order."""
        rec = np.frombuffer(bytes(self.records), dtype=RECORD_DTYPE)
        self.records.clear()          # in place: the engines' loops hold it
        if located is not None and len(located):
            rec = np.insert(located, np.searchsorted(located["frame"], rec["frame"]), rec) if len(rec) else located
        if len(rec):
            self.analysis.feed(rec, self.sources)
