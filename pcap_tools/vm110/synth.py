"""Capture synthesis: a scenario on the virtual clock, written as a tap sees it, with its ground truth.

Frames are Ethernet/IPv4/UDP from each station to the multicast group (TTL 1, valid checksums,
the group's multicast MAC), timestamps in microseconds from a fixed epoch. The ground truth
(`truth_path(out)`, JSON, see /work/notes/truth-contract.md and captures/README.md) is computed
while the frames are written, from the event log, in one pass: memory stays small for long runs.
The same scenario, seed and duration give byte-identical files.
"""
from __future__ import annotations

import gc
import json
import os
from typing import Any, Optional

from . import constants as C
from .capture.writer import Format, UdpFlow, open_writer
from .sim.clock import seconds
from .sim.scenario import EPOCH_US, SCENARIOS, Scenario
from .sim.truth import GroundTruth
from .sim.virtual import Arrival, VirtualNetwork, endpoints

TRUTH_SUFFIX = ".truth.json"
# Other traffic a tap also sees: an mDNS query for _vm110._udp.local (not EG-Link).
OTHER_SOURCE, OTHER_GROUP, MDNS_PORT = "10.0.0.30", "224.0.0.251", 5353
OTHER_PAYLOAD = bytes.fromhex("000000000001000000000000") + b"\x06_vm110\x04_udp\x05local\x00" + bytes.fromhex("000c0001")


def truth_path(out: str) -> str:
    """Where the ground truth of capture `out` goes: `<out>.truth.json`."""
    return out + TRUTH_SUFFIX


def scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}") from None


def synthesize(name: str, out: str, seed: int = 1, duration_s: Optional[float] = None,
               fmt: Format = "pcap") -> dict[str, Any]:
    """Write capture `out` and its truth next to it; returns the truth."""
    sc = scenario(name)
    duration = sc.duration_s if duration_s is None else duration_s
    if duration <= 0:
        raise ValueError("duration must be positive")
    stations = sc.build(seed, duration)
    # One flow per endpoint (a station's port, then its new ports after restarts; to the group on
    # the station's own port), then the other traffic's: its arrivals carry that index.
    flows = [UdpFlow(stations[i].ip, port, C.MULTICAST_GROUP, stations[i].port, ttl=C.MULTICAST_TTL)
             for i, port in endpoints(stations)]
    others = [(t, 0, len(flows), OTHER_PAYLOAD, (), None, False)
              for t in map(seconds, sc.other_traffic) if t < seconds(duration)]
    flows.append(UdpFlow(OTHER_SOURCE, MDNS_PORT, OTHER_GROUP, MDNS_PORT, ttl=255))
    frame = [flow.frame for flow in flows]
    truth = GroundTruth(stations, EPOCH_US)
    collecting = gc.isenabled()
    gc.disable()      # millions of short-lived tuples and no cycles: the collector would only cost time
    try:
        with open(out, "wb") as stream:
            writer = open_writer(stream, fmt)
            for batch in VirtualNetwork(stations).run(duration):
                if others and others[0][0] <= batch[-1][0]:
                    batch = _interleave(batch, others)
                writer.write_many([(EPOCH_US + t, frame[i](data)) for t, _, i, data, _, _, _ in batch])
                truth.add(batch)
            writer.write_many([(EPOCH_US + t, frame[i](data)) for t, _, i, data, _, _, _ in others])   # after the end
            truth.add(others)
            writer.close()
    finally:
        if collecting:
            gc.enable()
    result = truth.report()
    with open(truth_path(out), "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1)
        fh.write("\n")
    return result


def _interleave(batch: list[Arrival], others: list[Arrival]) -> list[Arrival]:
    """Merge the other traffic that falls within `batch` into it (taking it off `others`); a
    frame at the same time as an EG-Link packet comes first."""
    merged: list[Arrival] = []
    for arrival in batch:
        while others and others[0][0] <= arrival[0]:
            merged.append(others.pop(0))
        merged.append(arrival)
    return merged


def remove_outputs(out: str) -> None:
    """Remove a half-written capture and its truth (after an error)."""
    for path in (out, truth_path(out)):
        if os.path.exists(path):
            os.remove(path)
