"""Captures as a real site records them, laid out byte by byte from the pcap and pcapng
specifications (draft-ietf-opsawg-pcap, draft-ietf-opsawg-pcapng) and the EG-Link framing of
TS-0006, sharing no code with vm110: the analysis is held to bytes our own writer, simulators
and synthesis never produce (Linux cooked captures, VLAN tags, IPv6 multicast, several
interfaces with their own resolutions, fragments, a SPAN port's copies).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional

# -- EG-Link (TS-0006) ----------------------------------------------------------------------------


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        c = byte << 24
        for _ in range(8):
            c = ((c << 1) ^ 0x04C11DB7) if c & 0x80000000 else c << 1
        table.append(c & 0xFFFFFFFF)
    return table


_TABLE = _crc_table()


def crc_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 (TS-0006 section 3.3, interpretation.md): MSB first, init all ones, no final XOR."""
    c = 0xFFFFFFFF
    for b in data:
        c = ((c << 8) & 0xFFFFFFFF) ^ _TABLE[(c >> 24) ^ b]
    return c


def eglink(pid: bytes, serial: int, payload: bytes, origin: int = 0) -> bytes:
    """One EG-Link packet: ID, header (revision 0, origin, serial, size, spare), payload, CRC (LE)."""
    body = pid + struct.pack("<HHHHI", 0, origin, serial & 0xFFFF, len(payload), 0) + payload
    return body + struct.pack("<I", crc_mpeg2(body))


def vrpi(serial: int, origin: int = 0x0101) -> bytes:
    """A disarmed base unit's VRPI: BU state 0x10, EG-Link operational, C-Link passive."""
    return eglink(b"VRPI", serial, bytes([0x10, 0, 0, 1, 0, 6]) + bytes(40), origin)


def vrpo(serial: int, number: int = 0, data: bytes = b"\x00" * 16) -> bytes:
    return eglink(b"VRPO", serial, struct.pack("<H", number) + data)


def vrci(serial: int, command: int, origin: int = 0x0101) -> bytes:
    return eglink(b"VRCI", serial, struct.pack("<H", command) + bytes(20), origin)


def vrao(serial: int, command: int) -> bytes:
    return eglink(b"VRAO", serial, struct.pack("<H", command))


# -- the network --------------------------------------------------------------------------------

def _checksum(data: bytes) -> int:
    if len(data) % 2:
        data += b"\0"
    s = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while s >> 16:
        s = (s & 0xFFFF) + (s >> 16)
    return ~s & 0xFFFF


def _ip4(text: str) -> bytes:
    return bytes(int(p) for p in text.split("."))


def _ip6(text: str) -> bytes:
    import ipaddress
    return ipaddress.IPv6Address(text).packed


def udp(src: str, sport: int, dst: str, dport: int, payload: bytes) -> bytes:
    """A UDP datagram with its checksum over the pseudo header (IPv4 or IPv6)."""
    length = 8 + len(payload)
    if ":" in src:
        pseudo = _ip6(src) + _ip6(dst) + struct.pack("!I3xB", length, 17)
    else:
        pseudo = _ip4(src) + _ip4(dst) + struct.pack("!BBH", 0, 17, length)
    head = struct.pack("!HHHH", sport, dport, length, 0)
    csum = _checksum(pseudo + head + payload) or 0xFFFF
    return struct.pack("!HHHH", sport, dport, length, csum) + payload


def ipv4(src: str, dst: str, body: bytes, ident: int = 1, proto: int = 17,
         offset8: int = 0, more: bool = False, ttl: int = 1) -> bytes:
    flags = (0x2000 if more else 0) | offset8
    head = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(body), ident, flags, ttl, proto, 0, _ip4(src), _ip4(dst))
    return head[:10] + struct.pack("!H", _checksum(head)) + head[12:] + body


def ipv4_fragments(src: str, dst: str, datagram: bytes, mtu: int, ident: int) -> list[bytes]:
    """The IPv4 packets of one UDP datagram sent over a link of `mtu` bytes (RFC 791)."""
    step = (mtu - 20) // 8 * 8
    out = []
    for off in range(0, len(datagram), step):
        part = datagram[off:off + step]
        out.append(ipv4(src, dst, part, ident, offset8=off // 8, more=off + step < len(datagram)))
    return out


def ipv6(src: str, dst: str, body: bytes, hop: int = 1) -> bytes:
    return struct.pack("!IHBB16s16s", 0x60000000, len(body), 17, hop, _ip6(src), _ip6(dst)) + body


def ipv6_fragments(src: str, dst: str, datagram: bytes, mtu: int, ident: int) -> list[bytes]:
    """The IPv6 packets of one UDP datagram a source fragmented for a path of `mtu` bytes (RFC 8200)."""
    step = (mtu - 48) // 8 * 8
    out = []
    for off in range(0, len(datagram), step):
        part = datagram[off:off + step]
        more = off + step < len(datagram)
        frag = struct.pack("!BBHI", 17, 0, off | more, ident) + part
        out.append(struct.pack("!IHBB16s16s", 0x60000000, len(frag), 44, 1, _ip6(src), _ip6(dst)) + frag)
    return out


def multicast_mac(dst: str) -> bytes:
    if ":" in dst:
        return b"\x33\x33" + _ip6(dst)[12:]
    return b"\x01\x00\x5e" + bytes([_ip4(dst)[1] & 0x7F]) + _ip4(dst)[2:]


def ether(src_mac: bytes, dst_mac: bytes, ethertype: int, body: bytes, tags: Iterable[tuple[int, int]] = ()) -> bytes:
    """An Ethernet II frame, padded to 60 bytes; `tags` (TPID, VLAN ID) outermost first."""
    head = dst_mac + src_mac
    for tpid, vid in tags:
        head += struct.pack("!HH", tpid, vid)
    frame = head + struct.pack("!H", ethertype) + body
    return frame + bytes(max(0, 60 - len(frame)))


def sll(ethertype: int, body: bytes, src_mac: bytes, packet_type: int = 0) -> bytes:
    """Linux cooked capture v1 (LINKTYPE_LINUX_SLL, 113)."""
    return struct.pack("!HHH8sH", packet_type, 1, 6, src_mac + b"\0\0", ethertype) + body


def sll2(ethertype: int, body: bytes, src_mac: bytes, ifindex: int = 2, packet_type: int = 2) -> bytes:
    """Linux cooked capture v2 (LINKTYPE_LINUX_SLL2, 276)."""
    return struct.pack("!HHIHBB8s", ethertype, 0, ifindex, 1, packet_type, 6, src_mac + b"\0\0") + body


# -- capture files ------------------------------------------------------------------------------

@dataclass
class Record:
    ts_ns: int                  # nanoseconds since the epoch
    data: bytes                 # the frame as captured (perhaps cut)
    orig: int = -1              # length on the wire; -1: len(data)
    iface: int = 0              # pcapng interface


def pcap(records: Iterable[Record], link: int, nanos: bool = False, big: bool = False, snaplen: int = 65535) -> bytes:
    e = ">" if big else "<"
    out = [struct.pack(e + "IHHiIII", 0xA1B23C4D if nanos else 0xA1B2C3D4, 2, 4, 0, 0, snaplen, link)]
    for r in records:
        sec, ns = divmod(r.ts_ns, 1_000_000_000)
        frac = ns if nanos else ns // 1000
        orig = len(r.data) if r.orig < 0 else r.orig
        out.append(struct.pack(e + "IIII", sec, frac, len(r.data), orig) + r.data)
    return b"".join(out)


def _pad4(b: bytes) -> bytes:
    return b + bytes(-len(b) % 4)


def _block(btype: int, body: bytes, e: str = "<") -> bytes:
    length = 12 + len(body)
    return struct.pack(e + "II", btype, length) + body + struct.pack(e + "I", length)


def _option(code: int, value: bytes, e: str = "<") -> bytes:
    return struct.pack(e + "HH", code, len(value)) + _pad4(value)


@dataclass
class Interface:
    link: int
    tsresol: Optional[int] = None       # the if_tsresol byte; None: microseconds (no option)
    snaplen: int = 0

    def ticks(self, ts_ns: int) -> int:
        if self.tsresol is None:
            return ts_ns // 1000
        if self.tsresol & 0x80:
            return (ts_ns << (self.tsresol & 0x7F)) // 1_000_000_000
        power = self.tsresol
        return ts_ns * 10 ** power // 1_000_000_000 if power <= 9 else ts_ns * 10 ** (power - 9)


def pcapng(interfaces: list[Interface], records: Iterable[Record], big: bool = False,
           isb_drops: Optional[dict[int, int]] = None) -> bytes:
    e = ">" if big else "<"
    out = [_block(0x0A0D0D0A, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1), e)]
    for itf in interfaces:
        opts = b""
        if itf.tsresol is not None:
            opts += _option(9, bytes([itf.tsresol]), e)
        if opts:
            opts += struct.pack(e + "HH", 0, 0)
        out.append(_block(1, struct.pack(e + "HHI", itf.link, 0, itf.snaplen) + opts, e))
    for r in records:
        ticks = interfaces[r.iface].ticks(r.ts_ns)
        orig = len(r.data) if r.orig < 0 else r.orig
        body = struct.pack(e + "IIIII", r.iface, ticks >> 32, ticks & 0xFFFFFFFF, len(r.data), orig) + _pad4(r.data)
        out.append(_block(6, body, e))
    for iface, dropped in (isb_drops or {}).items():
        body = struct.pack(e + "III", iface, 0, 0) + _option(5, struct.pack(e + "Q", dropped), e) + struct.pack(e + "HH", 0, 0)
        out.append(_block(5, body, e))
    return b"".join(out)


# -- a site's traffic ---------------------------------------------------------------------------

BU_IP, CTRL_IP, GROUP = "10.0.0.10", "10.0.0.20", "239.255.42.20"
BU_IP6, CTRL_IP6, GROUP6 = "fd00::10", "fd00::20", "ff15::42:20"
BU_MAC, CTRL_MAC = bytes.fromhex("0050c2aa0001"), bytes.fromhex("0050c2aa0002")
T0_NS = 1_764_000_000_000_000_000


@dataclass
class Datagram:
    t: float                    # seconds after T0
    src: str
    sport: int
    dst: str
    dport: int
    payload: bytes

    @property
    def ts_ns(self) -> int:
        return T0_NS + round(self.t * 1e9)


@dataclass
class Site:
    """One base unit (VRPI every 125 ms, a command acknowledged) and one controller (VRPO every
    100 ms) for `seconds`; `lost_vrpi`: serials of VRPI the network lost (never in the capture).
    `expect` says what TS-0006 and interpretation.md make of it."""
    seconds: float = 3.0
    port: int = 5825
    lost_vrpi: tuple[int, ...] = ()
    ipv6: bool = False
    vrpo_data: int = 16
    datagrams: list[Datagram] = field(default_factory=list)

    def __post_init__(self) -> None:
        bu, ctrl, group = (BU_IP6, CTRL_IP6, GROUP6) if self.ipv6 else (BU_IP, CTRL_IP, GROUP)
        p_in, p_out = self.port, self.port + 2
        n_vrpi, n_vrpo = int(self.seconds / 0.125), int(self.seconds / 0.1)
        # The operator's command at 0.55 s, resent at 0.65 s, acknowledged at 0.70 s.
        sent_bu = sorted([(k * 0.125, "VRPI") for k in range(n_vrpi)] + [(0.55, "VRCI"), (0.65, "VRCI")])
        sent_ctrl = sorted([(0.01 + k * 0.1, "VRPO") for k in range(n_vrpo)] + [(0.70, "VRAO")])
        build = {"VRPI": vrpi, "VRCI": lambda s: vrci(s, 7), "VRPO": lambda s: vrpo(s, 0, bytes(self.vrpo_data)),
                 "VRAO": lambda s: vrao(s, 7)}
        for sent, src, port in ((sent_bu, bu, p_in), (sent_ctrl, ctrl, p_out)):
            for serial, (t, kind) in enumerate(sent, start=1):
                if not (kind == "VRPI" and serial in self.lost_vrpi):
                    self.datagrams.append(Datagram(t, src, port, group, port, build[kind](serial)))
        self.vrpi_count, self.vrpo_count = n_vrpi - len(self.lost_vrpi), n_vrpo
        self.datagrams.sort(key=lambda d: d.t)

    def expect(self) -> dict:
        return {"VRPI": self.vrpi_count, "VRCI": 2, "VRPO": self.vrpo_count, "VRAO": 1,
                "lost": len(self.lost_vrpi), "retransmissions": 1, "acked": 1, "commands": 1}


def frames(site: Site, frame: Callable[[Datagram, bytes], bytes]) -> list[Record]:
    """One record per datagram: `frame(datagram, ip_packet)` wraps the IP packet."""
    out = []
    for d in site.datagrams:
        body = udp(d.src, d.sport, d.dst, d.dport, d.payload)
        packet = ipv6(d.src, d.dst, body) if ":" in d.src else ipv4(d.src, d.dst, body)
        out.append(Record(d.ts_ns, frame(d, packet)))
    return out


def src_mac(d: Datagram) -> bytes:
    return BU_MAC if d.payload[3:4] == b"I" else CTRL_MAC


def on_ethernet(tags: Iterable[tuple[int, int]] = ()) -> Callable[[Datagram, bytes], bytes]:
    tags = tuple(tags)

    def wrap(d: Datagram, packet: bytes) -> bytes:
        et = 0x86DD if ":" in d.src else 0x0800
        return ether(src_mac(d), multicast_mac(d.dst), et, packet, tags)
    return wrap


def on_sll(d: Datagram, packet: bytes) -> bytes:
    return sll(0x86DD if ":" in d.src else 0x0800, packet, src_mac(d), packet_type=2)


def on_sll2(d: Datagram, packet: bytes) -> bytes:
    return sll2(0x86DD if ":" in d.src else 0x0800, packet, src_mac(d))
