"""Mutations that know the EG-Link: the fields of packets found inside the records (size, packet
ID, serial, VRPO packet number, command ID, header words), with the CRC recomputed or left stale,
and datagrams shortened or lengthened with the IP/UDP/record lengths kept consistent, so that the
mutated packets get past the outer layers and reach the EG-Link decoding and stream analysis."""
from __future__ import annotations

import random
import struct
from dataclasses import dataclass
from typing import Callable, Optional

from vm110 import constants as C
from vm110.crc import DEFAULT_BYTE_ORDER, crc_function

from . import containers

IDS = tuple(t.value.encode() for t in C.PacketType)
NEAR_IDS = (b"VRPX", b"vrpi", b"VRP\0", b"\0\0\0\0", b"VRCA")
ID_LEN, HEADER = 4, 16              # packet ID, then revision, origin, serial, size, spare
FIELDS = {"revision": (4, "H"), "origin": (6, "H"), "serial": (8, "H"), "size": (10, "H"), "spare": (12, "I"),
          "packet_number": (16, "H"), "command_id": (16, "H")}
_CRC = crc_function()


@dataclass(frozen=True)
class Datagram:
    """An EG-Link packet inside a record: absolute offsets in the file."""

    record: containers.Record
    start: int           # first byte of the packet ID
    end: int             # one past the CRC
    ip: Optional[int]    # IPv4 header, when the packet came in one


def find(data: bytes, layout: containers.Layout) -> list[Datagram]:
    """The UDP payloads that start with an EG-Link packet ID."""
    out = []
    for rec in layout.packets:
        frame = data[rec.data:rec.data + rec.caplen]
        ip = _ipv4(frame)
        if ip is None:
            continue
        ihl = (frame[ip] & 0x0F) * 4
        udp = ip + ihl
        if len(frame) < udp + 8 + ID_LEN:
            continue
        ulen = struct.unpack_from("!H", frame, udp + 4)[0]
        payload = udp + 8
        end = min(len(frame), udp + max(ulen, 8))
        if frame[payload:payload + ID_LEN] in IDS:
            out.append(Datagram(rec, rec.data + payload, rec.data + end, rec.data + ip))
    return out


def _ipv4(frame: bytes) -> Optional[int]:
    """Offset of a UDP-carrying IPv4 header behind Ethernet (with or without one VLAN tag)."""
    for offset in (14, 18):
        if len(frame) >= offset + 20 and frame[offset] >> 4 == 4 and frame[offset + 9] == 17 \
                and frame[offset - 2:offset] == b"\x08\x00":
            return offset
    return None


def _with_crc(packet: bytes) -> bytes:
    body = packet[:-C.CRC_LEN]
    return body + _CRC(body).to_bytes(C.CRC_LEN, DEFAULT_BYTE_ORDER)


def _field_value(rng: random.Random, old: int, bits: int) -> int:
    top = (1 << bits) - 1
    return rng.choice([0, 1, top, top >> 1, (old + 1) & top, (old - 1) & top, old ^ (1 << rng.randrange(bits)),
                       rng.randrange(top + 1)])


def mutate_field(data: bytes, layout: containers.Layout, rng: random.Random) -> tuple[bytes, str]:
    """One header or payload field of a few EG-Link packets; CRC recomputed or left stale."""
    grams = find(data, layout)
    if not grams:
        return data, "no EG-Link packet found"
    name = rng.choice([*FIELDS, "packet_id"])
    fix_crc = rng.random() < 0.6
    out = bytearray(data)
    picked = rng.sample(grams, min(len(grams), rng.choice([1, 2, 5, 20])))
    for g in picked:
        packet = bytearray(out[g.start:g.end])
        if name == "packet_id":
            packet[:ID_LEN] = rng.choice([*IDS, *NEAR_IDS])
        else:
            offset, code = FIELDS[name]
            if len(packet) < offset + struct.calcsize(code):
                continue
            old = struct.unpack_from("<" + code, packet, offset)[0]
            struct.pack_into("<" + code, packet, offset, _field_value(rng, old, 8 * struct.calcsize(code)))
        if fix_crc and len(packet) >= HEADER + C.CRC_LEN:
            packet = bytearray(_with_crc(bytes(packet)))
        out[g.start:g.end] = packet
    return bytes(out), f"eglink {name} of {len(picked)} packet(s), CRC {'recomputed' if fix_crc else 'stale'}"


def resize(data: bytes, layout: containers.Layout, rng: random.Random) -> tuple[bytes, str]:
    """One EG-Link datagram cut or extended, with IP, UDP and record lengths telling the truth."""
    grams = [g for g in find(data, layout) if g.ip is not None]
    if not grams:
        return data, "no EG-Link datagram found"
    g = rng.choice(grams)
    packet = data[g.start:g.end]
    new_len = rng.choice([rng.randrange(len(packet)), len(packet) + rng.randint(1, 600), rng.randint(0, HEADER + 8)])
    new = packet[:new_len] + rng.randbytes(max(0, new_len - len(packet)))
    if rng.random() < 0.5 and len(new) >= HEADER + C.CRC_LEN:
        new = _with_crc(new)
    rec = g.record
    ip = bytearray(data[g.ip:g.start])
    ihl = (ip[0] & 0x0F) * 4
    struct.pack_into("!H", ip, 2, len(ip) + len(new))
    struct.pack_into("!HH", ip, ihl + 4, 8 + len(new), 0)      # UDP length; checksum 0: none
    struct.pack_into("!H", ip, 10, 0)
    struct.pack_into("!H", ip, 10, _ip_checksum(bytes(ip[:ihl])))
    frame = data[rec.data:g.ip] + bytes(ip) + new
    return containers.rebuild(data, rec, layout, frame), f"eglink datagram {len(packet)} -> {len(new)} bytes"


def _ip_checksum(header: bytes) -> int:
    total = sum(struct.unpack(f"!{len(header) // 2}H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


MUTATIONS: tuple[Callable[[bytes, containers.Layout, random.Random], tuple[bytes, str]], ...] = (mutate_field, resize)
