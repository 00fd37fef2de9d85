"""Run nodes on a virtual clock: the same node logic as on sockets, with no sleeping.

Each station is a node with the address it sends from; what it sends passes its impairments
(`sim.impair`) and the 100 Mbit/s wire, then reaches every node of the other direction and the
tap (a mirror copy reaches the tap only). The tap sits where the receivers are: it sees what they
receive, in arrival order, and remembers for each packet the sender's own account of it (`Meta`)
and why it is illegal, if it is. That record is the event log the ground truth is computed from
(`sim.truth`). A station sends from one endpoint (address, port) at a time: its port, then the
new port of each restart that changes it (`sim.lifecycle`).
"""
from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass, field
from typing import Iterator, Optional

from .clock import VirtualClock, seconds
from .impair import Impairer, Impairment
from .node import Meta, Node

WIRE_NS_PER_BYTE = 80        # 100 Mbit/s
WIRE_OVERHEAD = 66           # Ethernet preamble, headers, FCS and gap, IPv4 and UDP headers


@dataclass
class Station:
    """A node on the network: where its packets come from and what happens to them on the way."""

    node: Node
    ip: str
    port: int
    impairment: Impairment = field(default_factory=Impairment)

    @property
    def ports(self) -> list[int]:
        """The source ports it sends from, in turn."""
        return [self.port] + [r.port for r in self.node.restarts if r.port is not None]

    def sender_ids(self) -> list[str]:
        """The analysis' name of this sender on each of its ports (docs/report.md)."""
        return [f"{self.node.direction.value} {self.ip}:{port} origin 0x{self.node.origin:04x}" for port in self.ports]


def endpoints(stations: list[Station]) -> list[tuple[int, int]]:
    """(station index, port) of every endpoint, station by station: an arrival's index."""
    return [(index, port) for index, s in enumerate(stations) for port in s.ports]


# One packet as the tap saw it: (t µs on the virtual clock, sequence number of its sender, index
# of the sending endpoint (`endpoints`), bytes, illegal reasons by construction (() for a legal
# packet), the sender's `Meta`, whether the receivers got it (False: a mirror copy)). It is the
# network's own queue entry, handed over as it is: no copy per packet.
Arrival = tuple[int, int, int, bytes, tuple[str, ...], Optional[Meta], bool]   # no Meta: other traffic
BATCH = 4096                 # arrivals handed to the tap at a time


class VirtualNetwork:
    """Stations on one multicast group, run for a given time on a virtual clock."""

    def __init__(self, stations: list[Station]) -> None:
        self.stations = stations
        self.clock = VirtualClock()
        self._heap: list[Arrival] = []
        self._wire_free = [0] * len(stations)
        self._endpoints = endpoints(stations)
        self._receivers = [[other.node for other in stations if other.node.direction is not s.node.direction]
                           for s in stations]
        first = 0
        for index, station in enumerate(stations):
            node = station.node
            imp = station.impairment
            impairer = Impairer(imp, f"{node.name}:{index}", node.crc, node.crc_order) if imp.active() else None
            node.attach(self._sender(index, first, impairer))
            first += len(station.ports)

    def _sender(self, index: int, endpoint: int, impairer: Optional[Impairer]):
        heap, push, seq = self._heap, heapq.heappush, itertools.count()
        wire_free = self._wire_free
        apply = impairer.apply if impairer is not None else None
        wire_us: dict[int, int] = {}     # by packet length: time on the wire (rounded up)
        current = [endpoint]             # the endpoint it sends from, moved on by a new-port restart
        ports = [port for _, port in self._endpoints]

        def restart_source(port: Optional[int]) -> tuple[int, int]:
            before = ports[current[0]]
            if port is not None:
                current[0] += 1
            return before, ports[current[0]]
        self.stations[index].node.restart_source = restart_source

        def send(data: bytes, now: int, meta: Meta) -> None:
            start = wire_free[index]
            if now > start:  # noqa: PLR1730 (per packet: an if is cheaper than max())
                start = now
            size = len(data)
            try:
                wire_free[index] = start + wire_us[size]
            except KeyError:
                wire_us[size] = (WIRE_OVERHEAD + size) * WIRE_NS_PER_BYTE // 1000 + 1
                wire_free[index] = start + wire_us[size]
            if apply is None:
                push(heap, (start, next(seq), current[0], data, (), meta, True))
                return
            for t, copy, problems, delivered in apply(data, start, meta.ptype):     # a str: the type's name
                push(heap, (t, next(seq), current[0], copy, problems, meta, delivered))
        return send

    def run(self, duration_s: float) -> Iterator[list[Arrival]]:
        """What the tap sees until `duration_s` of virtual time, in order, in lists of up to `BATCH`."""
        end = seconds(duration_s)
        nodes = [s.node for s in self.stations]
        for node in nodes:
            node.start(0)
        heap, pop = self._heap, heapq.heappop
        # Methods bound once: the call sites below see both kinds of node, which defeats the
        # interpreter's attribute caches.
        by_station = [[(nodes.index(n), n, n.receive, n.next_due) for n in group] for group in self._receivers]
        receivers = [by_station[station] for station, _ in self._endpoints]      # by endpoint
        ticks = [(node.tick, node.next_due) for node in nodes]
        never = end + 1
        # Each node's next deadline, recomputed only when that node has run.
        dues: list[int] = [never if d is None else d for d in (node.next_due() for node in nodes)]
        # The source as a socket gives it, (address, port): a restart on a new port is a new source.
        sources = [(self.stations[station].ip, port) for station, port in self._endpoints]
        clock = self.clock
        batch: list[Arrival] = []
        append, room = batch.append, BATCH
        pair = len(nodes) == 2       # the usual case: no min() over two deadlines
        now = 0
        while True:
            if pair:
                low, other = dues
                if other < low:
                    low, first = other, 1
                else:
                    first = 0
            else:
                low = min(dues)
                first = dues.index(low)
            if low < now:  # noqa: PLR1730 (overdue, e.g. a command waiting for the previous one; per event)
                low = now
            if heap and heap[0][0] <= low:
                arrival = pop(heap)
                now = arrival[0]
                if now >= end:
                    break
                clock.t = now
                append(arrival)
                room -= 1
                if not room:
                    yield batch
                    batch = []
                    append, room = batch.append, BATCH
                _, _, index, data, problems, _, delivered = arrival
                if not delivered:
                    continue
                src = sources[index]
                for r, node, receive, next_due in receivers[index]:
                    node.vouched = problems       # it built this packet: skip the legality check
                    receive(data, now, src)
                    due = next_due()
                    dues[r] = never if due is None else due
            else:
                if low >= end:
                    break
                clock.t = now = low
                tick, next_due = ticks[first]
                tick(now)
                due = next_due()
                dues[first] = never if due is None else due
        if batch:
            yield batch
