"""The port picker of the tests that run real sockets: runs started side by side never share a port."""
from __future__ import annotations

import concurrent.futures

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
