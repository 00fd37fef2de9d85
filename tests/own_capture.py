"""An EG-Link capture writer that shares nothing with vm110's encoder: every byte laid out from
TS-0006 (section 3: packet ID, 12-byte header, payload, CRC) and interpretation.md (CRC-32/MPEG-2:
poly 0x04C11DB7, init 0xFFFFFFFF, MSB first, no reflection, no final XOR, stored little-endian),
wrapped in Ethernet/IPv4/UDP of any source address and port, written as a classic pcap."""
from __future__ import annotations

import ipaddress
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

PAYLOAD_SIZE = {b"VRPI": 46, b"VRCI": 22, b"VRCO": 22, b"VRAO": 2, b"VRAI": 2}


def crc_mpeg2(data: bytes) -> int:
    """Bit by bit, as TS-0006 3.3 describes it (checked against 0x0376E6E7 for b"123456789")."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1) & 0xFFFFFFFF
    return crc


def packet(kind: bytes, serial: int, payload: bytes, origin: int = 0, revision: int = 0,
           size: int | None = None, crc_xor: int = 0) -> bytes:
    """ID + header (revision, origin, serial, size, spare, all little-endian) + payload + CRC."""
    head = kind + struct.pack("<HHHHI", revision, origin, serial & 0xFFFF,
                              len(payload) if size is None else size, 0)
    body = head + payload
    return body + struct.pack("<I", crc_mpeg2(body) ^ crc_xor)


def vrpi(serial: int, origin: int) -> bytes:
    # BU state Disarmed (0x10), no armed RU: every RU field zero
    return packet(b"VRPI", serial, bytes([0x10, 0, 0, 1, 1, 1]) + bytes(40), origin)


def vrpo(serial: int, number: int, data_len: int) -> bytes:
    return packet(b"VRPO", serial, struct.pack("<H", number) + bytes((number + i) & 0xFF for i in range(data_len)))


def command(kind: bytes, serial: int, cid: int, origin: int = 0) -> bytes:
    return packet(kind, serial, struct.pack("<HI", cid & 0xFFFF, 0) + bytes(16), origin)


def ack(kind: bytes, serial: int, cid: int, origin: int = 0) -> bytes:
    return packet(kind, serial, struct.pack("<H", cid & 0xFFFF), origin)


@dataclass(frozen=True)
class Frame:
    time_us: int
    payload: bytes
    src: str
    sport: int
    dport: int


def _checksum(header: bytes) -> int:
    total = sum(struct.unpack(f"!{len(header) // 2}H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def _ethernet(f: Frame) -> bytes:
    udp = struct.pack("!HHHH", f.sport, f.dport, 8 + len(f.payload), 0) + f.payload
    if ":" in f.src:                      # IPv6: the UDP checksum is mandatory there (RFC 8200)
        src, dst = ipaddress.IPv6Address(f.src).packed, ipaddress.IPv6Address("ff02::1").packed
        pseudo = src + dst + struct.pack("!IxxxB", len(udp), 17) + udp
        udp = udp[:6] + struct.pack("!H", _checksum(pseudo + b"\0" * (len(pseudo) % 2)) or 0xFFFF) + udp[8:]
        ip6 = struct.pack("!IHBB16s16s", 6 << 28, len(udp), 17, 1, src, dst)
        return bytes.fromhex("333300000001 020000000001 86dd") + ip6 + udp
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 1, 17, 0,
                     bytes(int(x) for x in f.src.split(".")), bytes([239, 255, 42, 20]))
    ip = ip[:10] + struct.pack("!H", _checksum(ip)) + ip[12:]
    return (bytes.fromhex("01005e7f2a14 020000000001 0800") + ip + udp).ljust(60, b"\0")


@dataclass(frozen=True)
class Raw:
    """A frame as it is on the wire (not EG-Link over IPv4/UDP), `snap` bytes of it captured."""
    time_us: int
    data: bytes
    snap: int = 65535


def write(path: Path, frames: Iterable[Frame | Raw]) -> None:
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for f in frames:
        data, snap = (f.data, f.snap) if isinstance(f, Raw) else (_ethernet(f), 65535)
        sec, usec = divmod(1_800_000_000_000_000 + f.time_us, 1_000_000)
        out.append(struct.pack("<IIII", sec, usec, min(snap, len(data)), len(data)) + data[:snap])
    path.write_bytes(b"".join(out))


# --- Adversarial traffic -------------------------------------------------------------------------
@dataclass
class Sender:
    src: str
    sport: int
    origin: int
    serial: int                 # the next serial (16-bit, wraps)

    def next_serial(self) -> int:
        s = self.serial
        self.serial = (self.serial + 1) & 0xFFFF
        return s


def traffic(rnd, seconds: float = 6.0) -> list[Frame]:
    """A base unit and a controller (plus a second base unit and controller behind the same
    addresses on other ports): VRPI every 125 ms, VRPO every 100 ms (some split into bursts),
    commands from both sides (several open at once, IDs reused), acks; serials near the wrap,
    numbered in the order each sender sends; some senders restart (serials afresh, or a new port)."""
    bus = [Sender("10.0.0.10", 5825, 0x0101, rnd.choice([65500, 0, rnd.randrange(65536)])),
           Sender("10.0.0.10", 40001, 0x0202, rnd.choice([65520, rnd.randrange(65536)]))]
    ctls = [Sender("10.0.0.20", 5827, 0, rnd.choice([65510, rnd.randrange(65536)])),
            Sender("10.0.0.20", 40003, 0, rnd.randrange(65536))]
    planned: list[tuple[int, int, Sender, object]] = []
    end = int(seconds * 1e6)

    def emit(t: int, s: Sender, payload_of) -> None:
        planned.append((max(0, t), len(planned), s, payload_of))

    for bu in bus:
        for t in range(rnd.randrange(125_000), end, 125_000):
            emit(t + rnd.randrange(3000), bu, lambda sn, o=bu.origin: vrpi(sn, o))
    for ctl in ctls:
        t = rnd.randrange(100_000)
        data = rnd.choice([100, 488, 600, 976, 1100])
        while t < end:
            count = -(-data // 488)
            for n in range(count):
                size = min(488, data - 488 * n)
                emit(t + 300 * n, ctl, lambda sn, n=n, size=size: vrpo(sn, n, size))
            t += 100_000 + rnd.randrange(-5000, 5000)
    # commands: each resent every 100 ms until acked (the ack may be lost, late or never sent)
    restarts = {id(s): rnd.randrange(end) for s in bus + ctls if rnd.random() < 0.3}
    cid = {id(s): rnd.choice([65534, rnd.randrange(65536)]) for s in bus + ctls}
    for _ in range(rnd.randrange(2, 12)):
        sender = rnd.choice(bus + ctls)
        if rnd.random() < 0.2:                 # the other base unit's command of the same ID
            other = bus[0] if sender is bus[1] else bus[1]
            cid[id(other)] = cid[id(sender)]
        kind, ack_kind = (b"VRCI", b"VRAO") if sender in bus else (b"VRCO", b"VRAI")
        peer = rnd.choice(ctls if sender in bus else bus)
        if rnd.random() < 0.7:
            cid[id(sender)] = (cid[id(sender)] + 1) & 0xFFFF
        c = cid[id(sender)]
        t0 = rnd.randrange(end)
        sends = rnd.randrange(1, 6)
        if rnd.random() < 0.2:                 # its sender restarts while the command is open
            restarts[id(sender)] = t0 + rnd.randrange(1, 250_000)
        for k in range(sends):
            emit(t0 + 100_000 * k + rnd.randrange(-2000, 2000), sender,
                 lambda sn, c=c, o=sender.origin, kind=kind: command(kind, sn, c, o))
        if rnd.random() < 0.8:
            t_ack = t0 + 100_000 * (sends - 1) + rnd.randrange(-30_000, 60_000)
            emit(t_ack, peer, lambda sn, c=c, o=peer.origin, k=ack_kind: ack(k, sn, c, o))
    planned.sort(key=lambda p: (p[0], p[1]))
    moved: dict[int, int] = {}
    rebooting: dict[int, int] = {}
    events = []
    for t, _, s, payload_of in planned:
        at = restarts.get(id(s))
        if at is not None and t >= at:
            del restarts[id(s)]
            s.serial = rnd.choice([0, 1, rnd.randrange(65536)])
            if rnd.random() < 0.35:    # one packet at once, then silent past the 10 s a candidate holds commands
                events.append(Frame(t, payload_of(s.next_serial()), s.src, s.sport, 5825 if s in bus else 5827))
                rebooting[id(s)] = t + 10_000_000 + rnd.randrange(2_000_000)
                continue
            rebooting[id(s)] = t + rnd.choice([0, 100_000, 400_000, 3_000_000])
            if rnd.random() < 0.5:
                moved[id(s)] = 50_000 + rnd.randrange(1000)
        if t < rebooting.get(id(s), -1):
            continue
        events.append(Frame(t, payload_of(s.next_serial()), s.src, moved.get(id(s), s.sport),
                            5825 if s in bus else 5827))
    return impair(rnd, events, end)


def impair(rnd, events: list[Frame], end: int) -> list[Frame]:
    out: list[Frame] = []
    for f in events:
        r = rnd.random()
        if r < 0.03:
            continue                                       # lost
        out.append(f)
        if r < 0.06:
            late = rnd.choice([0, 0, 0, 900_000, 1_500_000])         # a mirror's copy, or one held back
            out.append(Frame(f.time_us + late + rnd.randrange(0, 2000), f.payload, f.src, f.sport, f.dport))
        elif r < 0.075:
            bad = bytearray(f.payload)
            bad[-1] ^= 0x5A
            out[-1] = Frame(f.time_us, bytes(bad), f.src, f.sport, f.dport)          # bad CRC
        elif r < 0.085:
            out[-1] = Frame(f.time_us, f.payload[:-3], f.src, f.sport, f.dport)     # cut short
        elif r < 0.09:
            out.append(Frame(f.time_us + 10, b"hello, not EG-Link", f.src, f.sport, f.dport))
        elif r < 0.095:
            out.append(Frame(f.time_us + 10, packet(b"VRXX", 1, b"ab"), f.src, f.sport, f.dport))
    # reorder: swap some neighbours (their timestamps stay in order)
    for i in range(len(out) - 1):
        if rnd.random() < 0.03:
            a, b = out[i], out[i + 1]
            out[i] = Frame(a.time_us, b.payload, b.src, b.sport, b.dport)
            out[i + 1] = Frame(b.time_us, a.payload, a.src, a.sport, a.dport)
    out.sort(key=lambda f: f.time_us)
    return out
