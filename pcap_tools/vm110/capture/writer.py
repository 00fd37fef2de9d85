"""Write pcap and pcapng files fast: Ethernet/IPv4/UDP frames built with struct, no scapy.

`UdpFlow` builds the frames of one sender (its addresses are fixed, only the payload, the IP
identification and the checksums change); the writers add records with microsecond timestamps.
IP header and UDP checksums are valid: a one's-complement sum equals the big integer of the
bytes modulo 0xFFFF (2**16 is 1 modulo 0xFFFF), which `int.from_bytes` computes in C.
"""
from __future__ import annotations

import ipaddress
import struct
from typing import BinaryIO, Literal, Optional

LINKTYPE_ETHERNET = 1
SNAPLEN = 65535
ETH_MIN_FRAME = 60            # without the FCS, which taps do not deliver
ETHERTYPE_IPV4 = 0x0800
IPPROTO_UDP = 17
IP_HEADER_LEN = 20
UDP_HEADER_LEN = 8
Format = Literal["pcap", "pcapng"]
FORMATS: tuple[Format, ...] = ("pcap", "pcapng")

_ETH_IP = struct.Struct("!6s6sHBBHHHBBH4s4sHHHH")   # Ethernet + IPv4 + UDP headers in one go
_PCAP_GLOBAL = struct.Struct("<IHHiIII")
_PCAP_RECORD = struct.Struct("<IIII")
_PCAP_MAGIC_US = 0xA1B2C3D4
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
        self._macs = (dst_mac or _mac_for(dst_ip), src_mac or _mac_for(src_ip))
        self._ports = (src_port, dst_port)
        self._ttl = ttl
        self._ip_id = 0
        # Constant parts of both checksums, folded once: the IP header without length and id,
        # and the UDP pseudo-header plus ports.
        ip_const = int.from_bytes(struct.pack("!BBHHHBBH4s4s", 0x45, 0, 0, 0, 0, ttl, IPPROTO_UDP, 0,
                                              self._src, self._dst), "big")
        self._ip_const = ip_const % _ONES
        self._udp_const = (int.from_bytes(self._src + self._dst, "big") + IPPROTO_UDP + src_port
                           + dst_port) % _ONES

    def frame(self, payload: bytes) -> bytes:
        """One Ethernet frame carrying `payload`, padded to the Ethernet minimum."""
        udp_len = UDP_HEADER_LEN + len(payload)
        total = IP_HEADER_LEN + udp_len
        ip_id = self._ip_id
        self._ip_id = (ip_id + 1) & 0xFFFF
        s = (self._ip_const + total + ip_id) % _ONES
        ip_sum = _ONES - s if s else 0
        padded = payload + b"\0" if len(payload) & 1 else payload
        s = (self._udp_const + 2 * udp_len + int.from_bytes(padded, "big")) % _ONES
        udp_sum = _ONES - s if s else _ONES    # a computed 0 goes on the wire as 0xFFFF
        head = _ETH_IP.pack(self._macs[0], self._macs[1], ETHERTYPE_IPV4, 0x45, 0, total, ip_id, 0,
                            self._ttl, IPPROTO_UDP, ip_sum, self._src, self._dst, self._ports[0],
                            self._ports[1], udp_len, udp_sum)
        frame = head + payload
        if len(frame) < ETH_MIN_FRAME:
            frame += bytes(ETH_MIN_FRAME - len(frame))
        return frame


class _Writer:
    _FLUSH_EVERY = 4096

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._parts: list[bytes] = []
        self.count = 0

    def write(self, t_us: int, frame: bytes) -> None:
        self._parts.append(self._record(t_us, frame))
        self.count += 1
        if len(self._parts) >= self._FLUSH_EVERY:
            self.flush()

    def flush(self) -> None:
        self._stream.write(b"".join(self._parts))
        self._parts.clear()

    def close(self) -> None:
        self.flush()
        self._stream.flush()

    def _record(self, t_us: int, frame: bytes) -> bytes:
        raise NotImplementedError

    def __enter__(self) -> "_Writer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PcapWriter(_Writer):
    """Classic pcap, microsecond timestamps, little-endian."""

    def __init__(self, stream: BinaryIO, linktype: int = LINKTYPE_ETHERNET, snaplen: int = SNAPLEN) -> None:
        super().__init__(stream)
        stream.write(_PCAP_GLOBAL.pack(_PCAP_MAGIC_US, 2, 4, 0, 0, snaplen, linktype))

    def _record(self, t_us: int, frame: bytes) -> bytes:
        sec, usec = divmod(t_us, 1_000_000)
        return _PCAP_RECORD.pack(sec, usec, len(frame), len(frame)) + frame


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + bytes(-len(value) % 4)


def _block(block_type: int, body: bytes) -> bytes:
    length = 12 + len(body)
    return struct.pack("<II", block_type, length) + body + struct.pack("<I", length)


class PcapngWriter(_Writer):
    """pcapng: one section, one Ethernet interface (microsecond resolution, the default)."""

    _SHB, _IDB, _EPB = 0x0A0D0D0A, 0x00000001, 0x00000006
    _END_OF_OPTIONS = b"\0\0\0\0"

    def __init__(self, stream: BinaryIO, linktype: int = LINKTYPE_ETHERNET, snaplen: int = SNAPLEN,
                 application: str = "vm110") -> None:
        super().__init__(stream)
        shb = struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1) + _option(4, application.encode()) + self._END_OF_OPTIONS
        idb = struct.pack("<HHI", linktype, 0, snaplen)
        stream.write(_block(self._SHB, shb) + _block(self._IDB, idb))

    def _record(self, t_us: int, frame: bytes) -> bytes:
        body = struct.pack("<IIIII", 0, t_us >> 32, t_us & 0xFFFFFFFF, len(frame), len(frame))
        return _block(self._EPB, body + frame + bytes(-len(frame) % 4))


def open_writer(stream: BinaryIO, fmt: Format = "pcap") -> _Writer:
    """A writer of the given format on an open binary stream."""
    if fmt == "pcap":
        return PcapWriter(stream)
    if fmt == "pcapng":
        return PcapngWriter(stream)
    raise ValueError(f"unknown capture format {fmt!r}; choose from {', '.join(FORMATS)}")
