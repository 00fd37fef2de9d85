"""UDP sockets for a node on the wall clock: multicast as the specification says, or unicast.

Each node has a receiving socket (bound to `listen`, joined to `group` when one is given) and a
sending socket (bound to `source`, so that packets leave from the node's port, e.g. the BU's
inputs from IP:5825) that sends to `dest`. Impairments are applied before sending; delayed
copies wait in a queue that the runner flushes (`next_due`, `flush`). A mirror copy (meant for the
tap only) goes out like a duplicate: on a socket there is no way to show it to a capture alone.
A node restarting on a new source port gets a new sending socket (`restart_source`).
"""
from __future__ import annotations

import errno
import heapq
import ipaddress
import socket
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Optional

from .. import constants as C
from ..errors import CliError
from .impair import Impairer
from .node import Meta

IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)   # Linux: only the groups this socket joined
Address = tuple[str, int]


@dataclass
class UdpConfig:
    listen: Address                 # bind of the receiving socket
    dest: Address                   # where packets go (the group, or a unicast peer)
    source: Address = ("0.0.0.0", 0)
    group: Optional[str] = None     # multicast group to join on `iface` for receiving
    iface: str = "0.0.0.0"          # interface address: membership and outgoing multicast
    ttl: int = C.MULTICAST_TTL


def parse_address(text: str, default_port: Optional[int] = None) -> Address:
    """"HOST:PORT" (or "HOST" with a default port) to a tuple; CliError when malformed."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, ""
    try:
        ipaddress.IPv4Address(host)
        number = int(port) if port else default_port
    except ValueError:
        raise CliError(f"bad address {text!r}: expected IPv4:PORT") from None
    if number is None or not 0 <= number <= 65535:
        raise CliError(f"bad address {text!r}: expected IPv4:PORT")
    return host, number


def multicast_config(role: str, group: str = C.MULTICAST_GROUP, port: int = C.INPUT_PORT,
                     iface: str = "0.0.0.0") -> UdpConfig:
    """The specification's set-up for `bu` or `controller`: inputs on `port`, outputs on `port + 2`."""
    out_port = port + C.OUTPUT_PORT_OFFSET
    send_port, recv_port = (port, out_port) if role == "bu" else (out_port, port)
    return UdpConfig(listen=("0.0.0.0", recv_port), dest=(group, send_port), source=(iface, send_port),
                     group=group, iface=iface)


def _in_use_hint(exc: OSError) -> str:
    """Both ends on one address meet each other's ports (each sends from the port the other listens
    on): the way out, as the README shows it."""
    if exc.errno != errno.EADDRINUSE:
        return ""
    return (" (held by another program; on one machine each simulator needs an address of its own, as in "
            "the README's \"Simulators and synthesis\": 127.0.0.10 and 127.0.0.20)")


def _no_device_hint(exc: OSError, iface: str) -> str:
    """Joining the group names no interface to join it on ("No such device"): an --iface that is no
    address of this machine, or, without one, no route for multicast to pick one by."""
    if exc.errno != errno.ENODEV:
        return ""
    if iface != "0.0.0.0":
        return f" (--iface {iface} is not the address of an interface of this machine)"
    return (" (no route for multicast: give --iface with the address of the EG-Link interface, "
            "or add a route, e.g. ip route add 224.0.0.0/4 dev IFACE)")


class UdpTransport:
    """The sockets of one node. `open()` binds them; `rx_address` is where peers must send."""

    def __init__(self, config: UdpConfig, impairer: Optional[Impairer] = None) -> None:
        self.config = config
        self.impairer = impairer
        self.rx: Optional[socket.socket] = None
        self.tx: Optional[socket.socket] = None
        self._queue: list[tuple[int, int, bytes]] = []
        self._seq = 0
        # Told of every packet the network refused (reason, µs, destination): lost, as UDP loses it, but said.
        self.on_send_error: Optional[Callable[[str, int, Address], None]] = None
        # Told how many copies of each packet the impairment let go (type name, copies; 0: dropped on purpose).
        self.on_impaired: Optional[Callable[[str, int], None]] = None

    def open(self) -> "UdpTransport":
        """Bind both sockets; CliError naming the one that failed (a message naming the listening
        address when the source port was the one in use sent the user to the wrong port)."""
        cfg = self.config
        try:
            self.rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if cfg.group:
                # (a group's port is shared with the other listeners of the group; a unicast one is
                # ours alone: a simulator left running on it would take half of our packets)
                self.rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.rx.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
                self.rx.bind(("0.0.0.0" if cfg.listen[0] in ("", "0.0.0.0") else cfg.listen[0], cfg.listen[1]))
                membership = socket.inet_aton(cfg.group) + socket.inet_aton(cfg.iface)
                self.rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
            else:
                self.rx.bind(cfg.listen)
            self.rx.setblocking(False)
        except OSError as exc:
            self.close()
            group = f" (group {cfg.group})" if cfg.group else ""
            raise CliError(f"cannot receive on {cfg.listen[0]}:{cfg.listen[1]}{group}: {exc.strerror or exc}"
                           + _in_use_hint(exc) + _no_device_hint(exc, cfg.iface)) from None
        try:
            self.tx = self._sending_socket()
        except OSError as exc:
            self.close()
            raise CliError(f"cannot send from {cfg.source[0]}:{cfg.source[1]} to {cfg.dest[0]}:{cfg.dest[1]}: "
                           f"{exc.strerror or exc}" + _in_use_hint(exc)) from None
        return self

    def _sending_socket(self) -> socket.socket:
        cfg = self.config
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            tx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if ipaddress.IPv4Address(cfg.dest[0]).is_multicast:
                tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, cfg.ttl)
                tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                tx.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
                if cfg.iface != "0.0.0.0":
                    tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cfg.iface))
            tx.bind(cfg.source)
            tx.setblocking(False)
        except OSError:
            tx.close()
            raise
        return tx

    def restart_source(self, port: Optional[int]) -> tuple[int, int]:
        """At a restart: send from `port` from now on (0: a new ephemeral port), as a restarted
        program would, or go on from the same one (None); the ports sent from before and after."""
        before = self.tx_address[1]
        if port is None:
            return before, before
        self.config.source = (self.config.source[0], port)
        try:
            tx = self._sending_socket()
        except OSError as exc:
            raise CliError(f"cannot send from {self.config.source[0]}:{port} after the restart: "
                           f"{exc.strerror or exc}") from None
        if self.tx is not None:
            self.tx.close()
        self.tx = tx
        return before, tx.getsockname()[1]

    @property
    def rx_address(self) -> Address:
        assert self.rx is not None, "open() first"
        return self.rx.getsockname()

    @property
    def tx_address(self) -> Address:
        assert self.tx is not None, "open() first"
        return self.tx.getsockname()

    def set_dest(self, dest: Address) -> None:
        """Point the node at its peer (tests bind port 0 first, then wire the two ends)."""
        self.config.dest = dest

    # --- sending ------------------------------------------------------------------------------
    def send(self, data: bytes, now: int, meta: Meta) -> None:
        if self.impairer is None:
            self._sendto(data, now)
            return
        copies = self.impairer.apply(data, now, meta.ptype.value)
        if self.on_impaired is not None and len(copies) != 1:
            self.on_impaired(meta.ptype.value, len(copies))
        for due, copy, _problems, _delivered in copies:
            if due <= now:
                self._sendto(copy, now)
            else:
                heapq.heappush(self._queue, (due, self._seq, copy))
                self._seq += 1

    def next_due(self) -> Optional[int]:
        return self._queue[0][0] if self._queue else None

    def held(self) -> Counter[str]:
        """The copies the impairment holds back (--delay, --jitter, --reorder) not sent yet, by packet ID."""
        return Counter(data[:C.ID_LEN].decode("latin-1") for _, _, data in self._queue)

    def flush(self, now: int) -> None:
        while self._queue and self._queue[0][0] <= now:
            self._sendto(heapq.heappop(self._queue)[2], now)

    def _sendto(self, data: bytes, now: int) -> None:
        assert self.tx is not None, "open() first"
        try:
            self.tx.sendto(data, self.config.dest)
        except OSError as exc:   # a full buffer or an unreachable peer loses the packet, like UDP does
            if exc.errno not in (errno.EAGAIN, errno.ECONNREFUSED, errno.ENOBUFS, errno.EHOSTUNREACH,
                                 errno.ENETUNREACH):
                # (any other, e.g. a broadcast --peer: EACCES; a traceback ended the run before)
                host, port = self.config.dest
                raise CliError(f"cannot send to {host}:{port}: {exc.strerror or exc}") from None
            if self.on_send_error is not None:
                self.on_send_error(exc.strerror or str(exc), now, self.config.dest)

    # --- receiving ----------------------------------------------------------------------------
    def recv_all(self) -> list[tuple[bytes, Address]]:
        """Every datagram waiting on the receiving socket."""
        assert self.rx is not None, "open() first"
        out = []
        while True:
            try:
                out.append(self.rx.recvfrom(65535))
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionRefusedError:
                continue

    def close(self) -> None:
        for sock in (self.rx, self.tx):
            if sock is not None:
                sock.close()
        self.rx = self.tx = None
