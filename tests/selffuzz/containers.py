"""Where the records, their length fields and their packet data lie in a pcap or pcapng file.

Parsing is tolerant: it stops at the first record that does not fit, so it also works on files an
earlier mutation already damaged (the mutators then only see the intact part).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Optional

PCAP_MAGICS = {b"\xd4\xc3\xb2\xa1": "<", b"\x4d\x3c\xb2\xa1": "<", b"\xa1\xb2\xc3\xd4": ">", b"\xa1\xb2\x3c\x4d": ">"}
SHB = 0x0A0D0D0A
EPB, SPB = 6, 3
BYTE_ORDER_MAGIC = 0x1A2B3C4D


@dataclass(frozen=True)
class Record:
    """One pcap record or pcapng block (`data` < 0: a block without packet data)."""

    start: int
    end: int
    data: int
    caplen: int
    endian: str
    length_fields: tuple[int, ...]    # offsets of 32-bit fields that state a length
    time_fields: tuple[int, ...]      # offsets of the 32-bit timestamp words (pcap: seconds first)


@dataclass(frozen=True)
class Layout:
    format: str                       # "pcap" or "pcapng"
    blocks: tuple[Record, ...]        # pcap: the records; pcapng: every block

    @property
    def packets(self) -> tuple[Record, ...]:
        return tuple(b for b in self.blocks if b.data >= 0)


def parse(data: bytes) -> Optional[Layout]:
    """The layout of the intact part of `data`, None when it is neither pcap nor pcapng."""
    if data[:4] in PCAP_MAGICS and len(data) >= 24:
        return Layout("pcap", tuple(_pcap_records(data, PCAP_MAGICS[data[:4]])))
    if len(data) >= 12 and struct.unpack_from("<I", data)[0] == SHB:
        return Layout("pcapng", tuple(_pcapng_blocks(data)))
    return None


def _pcap_records(data: bytes, endian: str) -> list[Record]:
    out, pos = [], 24
    while pos + 16 <= len(data):
        caplen = struct.unpack_from(endian + "I", data, pos + 8)[0]
        end = pos + 16 + caplen
        if end > len(data):
            break
        out.append(Record(pos, end, pos + 16, caplen, endian, (pos + 8, pos + 12), (pos, pos + 4)))
        pos = end
    return out


def _pcapng_blocks(data: bytes) -> list[Record]:
    out, pos, endian = [], 0, "<"
    while pos + 12 <= len(data):
        if struct.unpack_from("<I", data, pos)[0] == SHB and pos + 12 <= len(data):
            magic = data[pos + 8:pos + 12]
            endian = "<" if struct.unpack("<I", magic)[0] == BYTE_ORDER_MAGIC else ">"
        btype, total = struct.unpack_from(endian + "II", data, pos)
        if total < 12 or total % 4 or pos + total > len(data):
            break
        ends = (pos + 4, pos + total - 4)
        if btype == EPB and total >= 32:
            caplen = struct.unpack_from(endian + "I", data, pos + 20)[0]
            if 28 + caplen > total - 4:
                break
            out.append(Record(pos, pos + total, pos + 28, caplen, endian, (*ends, pos + 20, pos + 24),
                              (pos + 12, pos + 16)))
        elif btype == SPB and total >= 16:
            caplen = min(struct.unpack_from(endian + "I", data, pos + 8)[0], total - 16)
            out.append(Record(pos, pos + total, pos + 12, caplen, endian, (*ends, pos + 8), ()))
        else:
            out.append(Record(pos, pos + total, -1, 0, endian, ends, ()))
        pos += total
    return out


def rebuild(data: bytes, record: Record, layout: Layout, packet: bytes) -> bytes:
    """`data` with the packet data of `record` replaced by `packet`, its length fields made true."""
    e = record.endian
    if layout.format == "pcap":
        head = bytearray(data[record.start:record.data])
        struct.pack_into(e + "II", head, 8, len(packet), len(packet))
        return data[:record.start] + bytes(head) + packet + data[record.end:]
    if record.data - record.start != 28:        # only EPBs are rebuilt (SPBs carry no caplen)
        return data
    padded = packet + bytes(-len(packet) % 4)
    total = 28 + len(padded) + 4
    head = bytearray(data[record.start:record.data])
    struct.pack_into(e + "I", head, 4, total)
    struct.pack_into(e + "II", head, 20, len(packet), len(packet))
    # options dropped: they are not what these mutations are about
    return data[:record.start] + bytes(head) + padded + struct.pack(e + "I", total) + data[record.end:]
