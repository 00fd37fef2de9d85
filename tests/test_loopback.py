"""The port picker of the tests that run real sockets: runs started side by side never share a port."""
from __future__ import annotations

import concurrent.futures
import errno
import os
import socket

import pytest

import loopback


def test_ports_handed_out_side_by_side_are_distinct(monkeypatch):
    monkeypatch.setattr(loopback, "_GIVEN", set())     # (this worker's earlier tests' ports aside)
    # CI: three fuzz runs of one test, started in threads, each took two ports; one run's Link found
    # its listen port taken ("Address already in use") by another's in the window between pick and bind.
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        drawn = [p for ports in pool.map(loopback.free_ports, [2] * 400) for p in ports]
    assert len(set(drawn)) == len(drawn) == 800
    assert all(p in loopback._own_range() for p in drawn)


def test_each_worker_draws_from_its_own_slice(monkeypatch):
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "3")
    slices = []
    for worker in ("gw0", "gw1", "gw2"):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", worker)
        slices.append(set(loopback._own_range()))
    assert all(len(s) >= 1000 for s in slices)
    assert not (slices[0] & slices[1]) and not (slices[1] & slices[2]) and not (slices[0] & slices[2])
    assert max(max(s) for s in slices) < loopback._ephemeral_low()


def test_a_start_that_finds_a_port_taken_meanwhile_gets_other_ports():
    """on_free_ports: a port taken between free_ports() and the caller's bind (by any process on
    the machine) costs another draw, not the test; any other error is the caller's."""
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tried: list[list[int]] = []

    def start(ports: list[int]) -> list[int]:
        tried.append(ports)
        if len(tried) == 1:
            taken.bind((loopback.LOOPBACK, ports[0]))      # taken meanwhile
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((loopback.LOOPBACK, ports[0]))
            except OSError as exc:
                raise RuntimeError(f"cannot listen on {ports[0]}: {exc.strerror}") from None
        return ports
    try:
        assert loopback.on_free_ports(2, start) == tried[1] and len(tried) == 2 and tried[0] != tried[1]
    finally:
        taken.close()

    def broken(ports: list[int]) -> None:
        tried.append(ports)
        raise RuntimeError("no such controller")
    tried.clear()
    with pytest.raises(RuntimeError, match="no such controller"):
        loopback.on_free_ports(1, broken)
    assert len(tried) == 1

    def always(ports: list[int]) -> None:
        raise OSError(errno.EADDRINUSE, os.strerror(errno.EADDRINUSE))
    with pytest.raises(OSError):
        loopback.on_free_ports(1, always, attempts=2)
