"""Capture synthesis: a scenario on the virtual clock, written as a tap sees it, with its ground truth.

Frames are Ethernet/IPv4/UDP from each station to the multicast group (TTL 1, valid checksums,
the group's multicast MAC), timestamps in microseconds from a fixed epoch. The ground truth
(`truth_path(out)`, JSON, the keys marked ✓ in docs/report.md, see captures/README.md) is computed
while the frames are written, from the event log, in one pass: memory stays small for long runs.
The same scenario, seed and duration give byte-identical files.
"""
from __future__ import annotations

import gc
import json
import math
from typing import Any, Optional

from . import constants as C
from .capture.writer import ByteSink, Format, UdpFlow, open_writer
from .fileio import atomic_writer, check_distinct, check_target, write_text
from .sim.clock import seconds
from .sim.reading import Reading
from .sim.scenario import EPOCH_US, SCENARIOS, Scenario
from .sim.truth import GroundTruth
from .sim.virtual import Arrival, VirtualNetwork, endpoints

TRUTH_SUFFIX = ".truth.json"
RATE_SAMPLE_S = 10.0      # traffic run to measure a scenario's output rate
# Other traffic a tap also sees: an mDNS query for _vm110._udp.local (not EG-Link).
OTHER_SOURCE, OTHER_GROUP, MDNS_PORT = "10.0.0.30", "224.0.0.251", 5353
OTHER_PAYLOAD = (bytes.fromhex("000000000001000000000000") + b"\x06_vm110\x04_udp\x05local\x00"
                 + bytes.fromhex("000c0001"))


def truth_path(out: str) -> str:
    """Where the ground truth of capture `out` goes: `<out>.truth.json`."""
    return out + TRUTH_SUFFIX


def scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}") from None


def synthesize(name: str, out: str, seed: int = 1, duration_s: Optional[float] = None,
               fmt: Format = "pcap", reading: Optional[Reading] = None) -> dict[str, Any]:
    """Write capture `out` and its truth next to it; returns the truth. Both devices speak
    `reading` (default: interpretation.md's), and the truth is the one `analyze` gives under it.

    Each file goes through a temporary file renamed into place when complete, the truth before the
    capture: a failure at any point leaves the files that were there as they were (CliError)."""
    sc = scenario(name)
    duration = sc.duration_s if duration_s is None else duration_s
    if not 0 < duration < math.inf:
        raise ValueError("duration must be positive and finite")
    check_target(truth_path(out))      # up front: not after the whole run
    # (both names one file through a link: the second written would replace the first)
    check_distinct({"--out": out, "its truth": truth_path(out)}, [])
    with atomic_writer(out) as stream:
        result = write_capture(stream, sc, seed, duration, fmt, reading)
        write_text(truth_path(out), _truth_text(result))
    return result


def output_rate(name: str, seed: int = 1, fmt: Format = "pcap") -> float:
    """Bytes per second of traffic that `synthesize` writes (capture and truth), from a short run."""
    sink = _Counter()
    result = write_capture(sink, scenario(name), seed, RATE_SAMPLE_S, fmt)
    return (sink.size + len(_truth_text(result))) / RATE_SAMPLE_S


def write_capture(stream: ByteSink, sc: Scenario, seed: int, duration: float, fmt: Format,
                  reading: Optional[Reading] = None) -> dict[str, Any]:
    """Run `sc` and write its capture to `stream`; returns the truth. Both devices speak `reading`
    (default: interpretation.md's)."""
    reading = reading or Reading()
    stations = sc.stations(seed, duration, reading)
    for station in stations:          # (the truth is made of the packets; a log grows with the run)
        station.node.keep_log = False
    # One flow per endpoint (a station's port, then its new ports after restarts; to the group on
    # the station's own port), then the other traffic's: its arrivals carry that index.
    flows = [UdpFlow(stations[i].ip, port, C.MULTICAST_GROUP, stations[i].port, ttl=C.MULTICAST_TTL)
             for i, port in endpoints(stations)]
    others: list[Arrival] = [(t, 0, len(flows), OTHER_PAYLOAD, (), None, False)
              for t in map(seconds, sc.other_traffic) if t < seconds(duration)]
    flows.append(UdpFlow(OTHER_SOURCE, MDNS_PORT, OTHER_GROUP, MDNS_PORT, ttl=255))
    frame = [flow.frame for flow in flows]
    truth = GroundTruth(stations, EPOCH_US, reading)
    collecting = gc.isenabled()
    gc.disable()      # millions of short-lived tuples and no cycles: the collector would only cost time
    try:
        writer = open_writer(stream, fmt)
        for arrivals in VirtualNetwork(stations).run(duration):
            batch = _interleave(arrivals, others) if others and others[0][0] <= arrivals[-1][0] else arrivals
            writer.write_many([(EPOCH_US + t, frame[i](data)) for t, _, i, data, _, _, _ in batch])
            truth.add(batch)
        writer.write_many([(EPOCH_US + t, frame[i](data)) for t, _, i, data, _, _, _ in others])   # after the end
        truth.add(others)
        writer.close()
    finally:
        if collecting:
            gc.enable()
    return truth.report()


def _truth_text(truth: dict[str, Any]) -> str:
    return json.dumps(truth, indent=1) + "\n"


class _Counter:
    """A binary stream that only counts what is written to it."""

    def __init__(self) -> None:
        self.size = 0

    def write(self, data: bytes) -> int:
        self.size += len(data)
        return len(data)

    def flush(self) -> None:
        pass


def _interleave(batch: list[Arrival], others: list[Arrival]) -> list[Arrival]:
    """Merge the other traffic that falls within `batch` into it (taking it off `others`); a
    frame at the same time as an EG-Link packet comes first."""
    merged: list[Arrival] = []
    for arrival in batch:
        while others and others[0][0] <= arrival[0]:
            merged.append(others.pop(0))
        merged.append(arrival)
    return merged
