"""Loopback helpers shared by the tests and the benchmarks that run real sockets."""
from __future__ import annotations

import random
import socket

LOOPBACK = "127.0.0.1"
_SPAN = 12_000          # ports picked from just below the kernel's ephemeral range
# (not the random module's state, which a test may seed: two workers seeded alike picked one port)
_PICK = random.SystemRandom()


def _ephemeral_low() -> int:
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_ports(count: int) -> list[int]:
    """`count` distinct UDP ports free on loopback right now (bound together, then released).

    Picked below the ephemeral range, never by bind(0): a port the kernel hands out is handed out
    again to any socket that binds port 0 meanwhile (another test worker's, a resolver's), and a test
    that comes back to its ports later (a fuzz finding replayed on its stored target) found one taken."""
    high = _ephemeral_low()
    low = max(1024, high - _SPAN)
    socks: list[socket.socket] = []
    try:
        while len(socks) < count:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                s.bind((LOOPBACK, _PICK.randrange(low, high)))
            except OSError:
                s.close()
                continue
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
