"""Link-layer and network numbers the capture reader understands (pcap LINKTYPE_* values)."""
from __future__ import annotations

from typing import Iterable

from ..words import plural

LINKTYPE_NULL = 0            # BSD loopback: 4-byte address family in the writer's byte order
LINKTYPE_ETHERNET = 1
LINKTYPE_IEEE802_11 = 105    # 802.11 frames without a radio header
LINKTYPE_IEEE802_11_RADIOTAP = 127
LINKTYPE_RAW = 101           # raw IPv4 or IPv6, version from the first nibble
LINKTYPE_LOOP = 108          # OpenBSD loopback: address family in network byte order
LINKTYPE_LINUX_SLL = 113
LINKTYPE_IPV4 = 228
LINKTYPE_IPV6 = 229
LINKTYPE_LINUX_SLL2 = 276
DLT_RAW_ALIASES = (12, 14)   # DLT_RAW as some platforms number it in pcap files
READ = "Ethernet, Linux cooked, raw IP, loopback and 802.11"

NAMES = {
    LINKTYPE_NULL: "null", LINKTYPE_ETHERNET: "ethernet", LINKTYPE_RAW: "raw",
    LINKTYPE_LOOP: "loop", LINKTYPE_LINUX_SLL: "linux-sll", LINKTYPE_IPV4: "ipv4",
    LINKTYPE_IPV6: "ipv6", LINKTYPE_LINUX_SLL2: "linux-sll2",
    LINKTYPE_IEEE802_11: "ieee802-11", LINKTYPE_IEEE802_11_RADIOTAP: "radiotap",
    **dict.fromkeys(DLT_RAW_ALIASES, "raw"),
}



def unread(count: int, link_types: Iterable[str], instead: str) -> str:
    """What to say of `count` frames of the link types (of a reader's `link_types`) not read, and
    what reads them `instead`."""
    numbers = sorted((t for t in link_types if t.isdigit()), key=int)
    kinds = f"link types {', '.join(numbers[:-1])} and {numbers[-1]}" if len(numbers) > 1 else \
        f"link type {''.join(numbers) or 'unknown'}"
    return f"{plural(count, 'frame')} of {kinds} not read (this reader reads {READ}; {instead})"


ETHERTYPE_IPV4 = 0x0800
ETHERTYPE_IPV6 = 0x86DD
ETHERTYPE_VLANS = (0x8100, 0x88A8, 0x9100)   # 802.1Q, 802.1ad (QinQ), legacy QinQ
ETH_HEADER_LEN = 14
VLAN_TAG_LEN = 4
SLL_HEADER_LEN = 16
SLL2_HEADER_LEN = 20
NULL_HEADER_LEN = 4
RADIOTAP_MIN_LEN = 8          # version, pad, length, the first presence word
RADIOTAP_TSFT = 0x1           # presence bits: TSFT (8 bytes, aligned to 8), Flags (1 byte)
RADIOTAP_FLAGS = 0x2
RADIOTAP_EXT = 0x80000000     # another presence word follows
RADIOTAP_DATAPAD = 0x20       # Flags: the 802.11 header is padded to 32 bits
WLAN_HEADER_LEN = 24          # 802.11 data frame header with three addresses
LLC_SNAP = b"\xaa\xaa\x03"
SNAP_OUIS = (b"\x00\x00\x00", b"\x00\x00\xf8")   # RFC 1042, 802.1H bridge tunnel: an EtherType follows
LLC_SNAP_LEN = 8
AF_INET = 2
AF_INET6 = (10, 24, 28, 30)  # Linux, NetBSD/OpenBSD, FreeBSD, macOS

IPPROTO_UDP = 17
# Tunnels the reader does not unwrap (counted and said): IP in IP, IPv6 in IP, GRE (ERSPAN too),
# EtherIP; and over UDP, VXLAN, VXLAN-GPE and GENEVE by their ports.
TUNNEL_PROTOCOLS = frozenset((4, 41, 47, 97))
TUNNEL_PORTS = frozenset((4789, 4790, 6081))
IPV4_MIN_HEADER = 20
IPV4_SRC = 12                 # offset of the source address in the IPv4 header
IPV4_FRAGMENT_MASK = 0x3FFF   # MF flag and fragment offset
IPV6_HEADER_LEN = 40
IPV6_FRAGMENT = 44
IPV6_EXTENSIONS = (0, 43, 60)  # hop-by-hop, routing, destination options: skipped over
UDP_HEADER_LEN = 8
