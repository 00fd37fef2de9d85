"""Write pcap and pcapng files fast: Ethernet/IPv4/UDP frames built with struct, no scapy.

`UdpFlow` builds the frames of one sender (its addresses are fixed, only the payload, the IP
identification and the checksums change); the writers add records with microsecond timestamps.
IP header and UDP checksums are valid: a one's-complement sum equals the big integer of the
bytes modulo 0xFFFF (2**16 is 1 modulo 0xFFFF), which `int.from_bytes` computes in C.
"""
from __future__ import annotations

import ipaddress
import struct
from typing import Iterable, Literal, Optional, Protocol

LINKTYPE_ETHERNET = 1
SNAPLEN = 65535
ETH_MIN_FRAME = 60            # without the FCS, which taps do not deliver
ETHERTYPE_IPV4 = 0x0800
IPPROTO_UDP = 17
IP_HEADER_LEN = 20
UDP_HEADER_LEN = 8
Format = Literal["pcap", "pcapng"]
FORMATS: tuple[Format, ...] = ("pcap", "pcapng")

ETH_HEADER_LEN = 14
# Ethernet + IPv4 + UDP headers in one go: the constant runs as bytes, the rest as numbers.
_HEAD = struct.Struct("!16sHH4sH12sHH")
_PAD_BELOW = ETH_MIN_FRAME - ETH_HEADER_LEN - IP_HEADER_LEN - UDP_HEADER_LEN    # payload sizes to pad
_PCAP_GLOBAL = struct.Struct("<IHHiIII")
_PCAP_RECORD = struct.Struct("<IIII")
_PCAP_MAGIC_US = 0xA1B2C3D4
_US = 1_000_000
_ONES = 0xFFFF


def multicast_mac(group: str) -> bytes:
    """The Ethernet address of an IPv4 multicast group (RFC 1112: 01:00:5e + low 23 bits)."""
    low = int(ipaddress.IPv4Address(group)) & 0x7FFFFF
    return bytes((0x01, 0x00, 0x5E)) + low.to_bytes(3, "big")


def host_mac(ip: str) -> bytes:
    """A locally administered unicast address derived from the IPv4 address (02:00:a.b.c.d)."""
    return b"\x02\x00" + ipaddress.IPv4Address(ip).packed


def _mac_for(ip: str) -> bytes:
    return multicast_mac(ip) if ipaddress.IPv4Address(ip).is_multicast else host_mac(ip)


class UdpFlow:
    """Frames from one (source IP, port) to one (destination IP, port)."""

    def __init__(self, src_ip: str, src_port: int, dst_ip: str, dst_port: int, ttl: int = 1,
                 src_mac: Optional[bytes] = None, dst_mac: Optional[bytes] = None) -> None:
        self._src, self._dst = ipaddress.IPv4Address(src_ip).packed, ipaddress.IPv4Address(dst_ip).packed
        # The constant runs of the headers, packed once: MACs, EtherType, version/IHL and TOS;
        # flags/fragment, TTL and protocol; addresses and ports.
        self._head = (dst_mac or _mac_for(dst_ip)) + (src_mac or _mac_for(src_ip)) + struct.pack(
            "!HBB", ETHERTYPE_IPV4, 0x45, 0)
        self._ttl_proto = struct.pack("!HBB", 0, ttl, IPPROTO_UDP)
        self._addresses = self._src + self._dst + struct.pack("!HH", src_port, dst_port)
        self._ip_id = 0
        self._shapes: dict[int, tuple[int, int, int, int, bool, bytes]] = {}    # by payload size
        # Constant parts of both checksums, folded once: the IP header without length and id,
        # and the UDP pseudo-header plus ports.
        ip_const = int.from_bytes(struct.pack("!BBHHHBBH4s4s", 0x45, 0, 0, 0, 0, ttl, IPPROTO_UDP, 0,
                                              self._src, self._dst), "big")
        self._ip_const = ip_const % _ONES
        self._udp_const = (int.from_bytes(self._src + self._dst, "big") + IPPROTO_UDP + src_port
                           + dst_port) % _ONES

    def frame(self, payload: bytes) -> bytes:
        """One Ethernet frame carrying `payload`, padded to the Ethernet minimum."""
        try:
            total, udp_len, ip_base, udp_base, odd, pad = self._shapes[len(payload)]
        except KeyError:
            total, udp_len, ip_base, udp_base, odd, pad = self._shape(len(payload))
        ip_id = self._ip_id
        self._ip_id = (ip_id + 1) & 0xFFFF
        s = (ip_base + ip_id) % _ONES
        ip_sum = _ONES - s if s else 0
        words = int.from_bytes(payload, "big")
        if odd:
            words <<= 8                        # an odd payload is summed with a zero byte after it
        s = (udp_base + words) % _ONES
        udp_sum = _ONES - s if s else _ONES    # a computed 0 goes on the wire as 0xFFFF
        return _HEAD.pack(self._head, total, ip_id, self._ttl_proto, ip_sum, self._addresses, udp_len,
                          udp_sum) + payload + pad

    def _shape(self, size: int) -> tuple[int, int, int, int, bool, bytes]:
        """What depends on the payload size alone: IP total and UDP lengths, the constant parts
        of both checksums with them, odd length, padding to the Ethernet minimum."""
        udp_len = UDP_HEADER_LEN + size
        total = IP_HEADER_LEN + udp_len
        shape = self._shapes[size] = (total, udp_len, self._ip_const + total, self._udp_const + 2 * udp_len,
                                      bool(size & 1), bytes(max(0, _PAD_BELOW - size)))
        return shape


class ByteSink(Protocol):
    """Where a writer puts its bytes: a binary file, or anything with the same two methods."""

    def write(self, data: bytes, /) -> object: ...

    def flush(self) -> object: ...


class _Writer:
    _FLUSH_EVERY = 4096

    def __init__(self, stream: ByteSink) -> None:
        self._stream = stream
        self._parts: list[bytes] = []
        self.count = 0

    def write(self, t_us: int, frame: bytes) -> None:
        self.write_many(((t_us, frame),))

    def write_many(self, frames: Iterable[tuple[int, bytes]]) -> None:
        """Write (timestamp µs, frame) pairs, in order."""
        parts = self._parts
        before = len(parts)
        parts.extend(self._records(frames))
        self.count += len(parts) - before
        if len(parts) >= self._FLUSH_EVERY:
            self.flush()

    def flush(self) -> None:
        self._stream.write(b"".join(self._parts))
        self._parts.clear()

    def close(self) -> None:
        self.flush()
        self._stream.flush()

    def _records(self, frames: Iterable[tuple[int, bytes]]) -> list[bytes]:
        raise NotImplementedError

    def __enter__(self) -> "_Writer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PcapWriter(_Writer):
    """Classic pcap, microsecond timestamps, little-endian."""

    def __init__(self, stream: ByteSink, linktype: int = LINKTYPE_ETHERNET, snaplen: int = SNAPLEN) -> None:
        super().__init__(stream)
        stream.write(_PCAP_GLOBAL.pack(_PCAP_MAGIC_US, 2, 4, 0, 0, snaplen, linktype))

    def _records(self, frames: Iterable[tuple[int, bytes]]) -> list[bytes]:
        pack = _PCAP_RECORD.pack
        return [pack(t // _US, t % _US, len(frame), len(frame)) + frame for t, frame in frames]


def build_option(code: int, value: bytes) -> bytes:
    """A pcapng option, padded to 32 bits."""
    return struct.pack("<HH", code, len(value)) + value + bytes(-len(value) % 4)


def build_block(block_type: int, body: bytes) -> bytes:
    """A pcapng block: type, total length, body, total length."""
    length = 12 + len(body)
    return struct.pack("<II", block_type, length) + body + struct.pack("<I", length)


class PcapngWriter(_Writer):
    """pcapng: one section, one Ethernet interface (microsecond resolution, the default)."""

    _SHB, _IDB, _EPB = 0x0A0D0D0A, 0x00000001, 0x00000006
    _END_OF_OPTIONS = b"\0\0\0\0"
    # An Enhanced Packet Block up to its data: type, length, interface 0, timestamp, lengths.
    _EPB_HEAD = struct.Struct("<IIIIIII")
    _EPB_TAIL = struct.Struct("<I")
    _EPB_OVERHEAD = _EPB_HEAD.size + _EPB_TAIL.size
    _PADS = tuple(bytes(-n % 4) for n in range(4))

    def __init__(self, stream: ByteSink, linktype: int = LINKTYPE_ETHERNET, snaplen: int = SNAPLEN,
                 application: str = "vm110") -> None:
        super().__init__(stream)
        shb = struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1) + build_option(4, application.encode()) + self._END_OF_OPTIONS
        idb = struct.pack("<HHI", linktype, 0, snaplen)
        stream.write(build_block(self._SHB, shb) + build_block(self._IDB, idb))

    def _records(self, frames: Iterable[tuple[int, bytes]]) -> list[bytes]:
        head, tail, pads, epb, overhead = (self._EPB_HEAD.pack, self._EPB_TAIL.pack, self._PADS, self._EPB,
                                           self._EPB_OVERHEAD)
        records = []
        for t, frame in frames:
            size = len(frame)
            pad = pads[size & 3]
            length = overhead + size + len(pad)
            records.append(head(epb, length, 0, t >> 32, t & 0xFFFFFFFF, size, size) + frame + pad + tail(length))
        return records


def format_of(path: str) -> Format:
    """The format a file name asks for: pcapng when it ends in .pcapng (any case), else pcap."""
    return "pcapng" if path.lower().endswith(".pcapng") else "pcap"


def open_writer(stream: ByteSink, fmt: Format = "pcap") -> _Writer:
    """A writer of the given format on an open binary stream."""
    if fmt == "pcap":
        return PcapWriter(stream)
    if fmt == "pcapng":
        return PcapngWriter(stream)
    raise ValueError(f"unknown capture format {fmt!r}; choose from {', '.join(FORMATS)}")
