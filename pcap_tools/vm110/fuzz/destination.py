"""Where the fuzzer may send: its packets move cranes, so only where the user clearly asked.

Loopback only, unless `--allow-remote`; a multicast group reaches every node on the segment, so it
needs `--allow-remote` too. Never the unspecified address (0.0.0.0, ::), the limited broadcast
address or the broadcast address of a local subnet, whatever the options.
"""
from __future__ import annotations

import errno
import ipaddress
import socket
from typing import Union

from ..errors import CliError

Address = Union[ipaddress.IPv4Address, ipaddress.IPv6Address]


def resolve(host: str, what: str, numeric: bool = False) -> str:
    """The one address `host` is resolved to, IPv4 first (the fuzzer speaks IPv4); CliError if none.
    `numeric`: an address only, no name looked up (for addresses read from a file)."""
    flags = socket.AI_NUMERICHOST if numeric else 0
    for family in (socket.AF_INET, socket.AF_INET6):
        try:
            infos = socket.getaddrinfo(host, None, family, socket.SOCK_DGRAM, 0, flags)
        except (OSError, UnicodeError):
            continue
        if infos:
            return str(ipaddress.ip_address(str(infos[0][4][0]).split("%", 1)[0]))
    raise CliError(f"{what}: {'not an IP address' if numeric else 'cannot resolve'}: {host[:80]!r}")


def check(address: str, what: str, allow_remote: bool) -> None:
    """CliError unless the fuzzer may send to `address` (an IP address, not a name)."""
    try:
        ip: Address = ipaddress.ip_address(address)
    except ValueError:
        raise CliError(f"{what}: {address[:80]!r} is not an IP address") from None
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    never = " (refused even with --allow-remote)"
    if ip.is_unspecified:
        raise CliError(f"{what}: {ip} is the unspecified address, not a destination{never}")
    if isinstance(ip, ipaddress.IPv4Address) and (ip == ipaddress.IPv4Address("255.255.255.255")
                                                   or is_local_broadcast(ip)):
        raise CliError(f"{what}: {ip} is a broadcast address: every host of the subnet gets it{never}")
    if ip.is_multicast and not allow_remote:
        raise CliError(f"{what}: {ip} is a multicast group: every node on the segment gets it; "
                       "add --allow-remote to send there")
    if not ip.is_loopback and not ip.is_multicast and not allow_remote:
        raise CliError(f"{what}: {ip} is not a loopback address: add --allow-remote to send to another host")


def is_local_broadcast(ip: ipaddress.IPv4Address) -> bool:
    """True when the routing table calls `ip` a broadcast address (of any local subnet, secondary
    addresses included). Asked without sending: connecting a UDP socket that lacks SO_BROADCAST
    to a broadcast address fails with EACCES."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((str(ip), 9))
        except OSError as exc:
            return exc.errno == errno.EACCES
    return False
