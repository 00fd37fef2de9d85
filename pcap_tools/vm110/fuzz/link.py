"""The fuzzer's one UDP socket: sends only to the target, receives the controller's output.

Receive times are kernel timestamps (SO_TIMESTAMPNS) where available, so that a fuzzer that was
slow to read its socket does not mistake late reading for a late controller.
"""
from __future__ import annotations

import errno
import ipaddress
import socket
import struct
import time
from typing import Optional

from .. import constants as C
from ..errors import CliError
from .destination import check, resolve

_RCVBUF = 4 << 20
_TIMESPEC = struct.Struct("@ll")
_MAX_DATAGRAM = 65535
_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)   # Linux


def parse_endpoint(text: str, what: str, numeric: bool = False) -> tuple[str, int]:
    """HOST:PORT or [IPv6]:PORT -> (address, port), the host name resolved once (`numeric`: no
    name accepted); CliError for anything else."""
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    number = port.isascii() and port.isdigit() and len(port) <= 5
    if not sep or not host or not number or not 0 < int(port) < 65536:
        raise CliError(f"{what} must be HOST:PORT, got {text[:80]!r}")
    return resolve(host, what, numeric), int(port)


def taken(address: tuple[str, int]) -> bool:
    """Whether a process of this host already receives on the unicast `address` (a bind there is
    refused as in use); False for a multicast group (shared by design) or an address not of this host."""
    if ipaddress.ip_address(address[0]).is_multicast:
        return False
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(address)
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE
    return False


class Link:
    def __init__(self, target: tuple[str, int], listen: tuple[str, int], group: Optional[str] = None,
                 allow_remote: bool = False) -> None:
        check(target[0], "the target", allow_remote)    # the last gate before a packet leaves
        self.target = target
        self.sock = sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            # (a group's port is shared with the group's other listeners; a unicast one is ours
            # alone: another process bound to it would silently take the controller's packets)
            if group is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, C.MULTICAST_TTL)
            if hasattr(socket, "SO_TIMESTAMPNS"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_TIMESTAMPNS, 1)
            if group is not None:
                sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)   # only the group joined here
                sock.bind(("", listen[1]))
                # The listen host names the interface to join on (0.0.0.0: the kernel's choice).
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                                socket.inet_aton(group) + socket.inet_aton(listen[0]))
            else:
                sock.bind(listen)
        except OSError as exc:
            sock.close()
            raise CliError(f"cannot listen on {listen[0]}:{listen[1]}: {exc.strerror or exc}") from None
        sock.setblocking(False)
        self.local = sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, data: bytes) -> float:
        """Send to the target (the only destination there is); the time it left."""
        try:
            self.sock.sendto(data, self.target)
        except OSError:
            pass   # e.g. ECONNREFUSED echoes while the controller restarts: the oracles judge that
        return time.time()

    def receive(self) -> list[tuple[float, bytes, tuple[str, int]]]:
        """Every datagram waiting: (arrival time, bytes, source)."""
        out: list[tuple[float, bytes, tuple[str, int]]] = []
        while True:
            try:
                data, ancdata, _flags, src = self.sock.recvmsg(_MAX_DATAGRAM, 64)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                continue   # ICMP errors reported on the socket
            stamp = None
            for level, kind, value in ancdata:
                if level == socket.SOL_SOCKET and kind == getattr(socket, "SO_TIMESTAMPNS", -1):
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    stamp = sec + nsec / 1e9
            out.append((stamp if stamp is not None else time.time(), data, src))

    def close(self) -> None:
        self.sock.close()
