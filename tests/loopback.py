"""Loopback helpers shared by the tests and the benchmarks that run real sockets."""
from __future__ import annotations

import errno
import os
import random
import socket
import threading
from typing import Callable, TypeVar

T = TypeVar("T")

LOOPBACK = "127.0.0.1"
_SPAN = 12_000          # ports picked from just below the kernel's ephemeral range
# (not the random module's state, which a test may seed: two workers seeded alike picked one port)
_PICK = random.SystemRandom()
_LOCK = threading.Lock()
_GIVEN: set[int] = set()


def _ephemeral_low() -> int:
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _own_range() -> range:
    """This process's share of the span: each pytest-xdist worker has its own slice."""
    high = _ephemeral_low()
    low = max(1024, high - _SPAN)
    try:
        worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:])
        workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    except ValueError:
        worker, workers = 0, 1
    share = (high - low) // workers
    start = low + (worker % workers) * share
    return range(start, start + share)


def free_ports(count: int) -> list[int]:
    """`count` distinct UDP ports free on loopback right now, none handed out before in this process.

    Picked below the ephemeral range, never by bind(0): a port the kernel hands out is handed out
    again to any socket that binds port 0 meanwhile (another test worker's, a resolver's), and a test
    that comes back to its ports later (a fuzz finding replayed on its stored target) found one taken.
    Ports are released before the caller binds them: each worker draws from its own slice, and a
    port is never drawn twice, so that runs started side by side (threads of one test, two workers)
    cannot take each other's ports in that window."""
    ports = _own_range()
    socks: list[socket.socket] = []
    try:
        with _LOCK:
            while len(socks) < count:
                if len(_GIVEN) >= len(ports) // 2:
                    _GIVEN.clear()      # (a long run: the ports of the oldest tests are long closed)
                port = _PICK.choice(ports)
                if port in _GIVEN:
                    continue
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                try:
                    s.bind((LOOPBACK, port))
                except OSError:
                    s.close()
                    continue
                _GIVEN.add(port)
                socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def on_free_ports(count: int, start: Callable[[list[int]], T], attempts: int = 3) -> T:
    """`start(ports)` on `count` free ports; on other ones when it fails because a port was bound
    meanwhile (free_ports releases them before `start` binds them: a process outside this one, even
    outside the suite, can take one in that window)."""
    for attempt in range(1, attempts + 1):
        try:
            return start(free_ports(count))
        except Exception as exc:     # (the caller's own error, which names the bind's failure)
            if attempt == attempts or os.strerror(errno.EADDRINUSE) not in str(exc):
                raise
    raise AssertionError("unreachable")
