"""Capture synthesis speed: `vm110 synth day` (the simulators on the virtual clock, frames, pcap,
ground truth) in packets per second, against baselines measured in the same run:

- scapy: `wrpcap` of the same frames, already built as scapy packets (writing only);
- writer: `vm110.capture.writer` writing the same frames, already built (the floor of any synthesis).

Target (issue 5): at least 100,000 packets/s synthesised, i.e. a 24-hour capture (about 1.5 million
packets) in seconds. The verdict is on CPU time of the synthesis (best of BENCH_SYNTH_REPEAT runs),
because other jobs on the machine slow the wall clock down; wall time is reported next to it.
"""
from __future__ import annotations

import io
import os
import sys
import tempfile
import time

from scapy.layers.l2 import Ether
from scapy.utils import RawPcapReader, wrpcap

from vm110.capture.writer import PcapWriter
from vm110.synth import synthesize

HOURS = float(os.environ.get("BENCH_SYNTH_HOURS", "4"))
REPEAT = int(os.environ.get("BENCH_SYNTH_REPEAT", "3"))
SCAPY_SAMPLE = 20_000
TARGET = 100_000


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn()
    return result, time.perf_counter() - wall, time.process_time() - cpu


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "day.pcap")
        runs = [timed(lambda: synthesize("day", out, seed=1, duration_s=HOURS * 3600)) for _ in range(REPEAT)]
        packets = runs[0][0]["capture"]["packets"]
        wall, cpu = min(run[1] for run in runs), min(run[2] for run in runs)
        with RawPcapReader(out) as reader:
            frames = [(raw, meta.sec * 1_000_000 + meta.usec) for raw, meta in reader]

        def write_all() -> None:
            writer = PcapWriter(io.BytesIO())
            writer.write_many([(t_us, raw) for raw, t_us in frames])
            writer.close()
        _, writer_wall, _ = timed(write_all)

        sample = [Ether(raw) for raw, _ in frames[:SCAPY_SAMPLE]]
        for packet, (_, t_us) in zip(sample, frames):
            packet.time = t_us / 1e6
        _, scapy_wall, scapy_cpu = timed(lambda: wrpcap(os.path.join(tmp, "scapy.pcap"), sample))

    rate = packets / wall
    rate_cpu = packets / cpu
    scapy_rate = len(sample) / scapy_wall
    writer_rate = packets / writer_wall
    print(f"synthesised {packets} packets ({HOURS:g} h of 'day') in {wall:.2f} s wall, {cpu:.2f} s CPU "
          f"(best of {REPEAT})")
    print(f"  synthesis        {rate:>10,.0f} packets/s wall  {rate_cpu:>10,.0f} packets/s CPU")
    print(f"  scapy wrpcap     {scapy_rate:>10,.0f} packets/s (pre-built packets, {len(sample)} of them)")
    print(f"  writer only      {writer_rate:>10,.0f} packets/s (pre-built frames)")
    print(f"  ratio synthesis / scapy wrpcap: {rate / scapy_rate:.2f}  "
          f"(CPU: {rate_cpu / (len(sample) / scapy_cpu):.2f})")
    print(f"  ratio synthesis / writer only:  {rate / writer_rate:.3f}")
    print(f"  24 h (~1.5 M packets): about {1_500_000 / rate:.0f} s at this rate ({1_500_000 / rate_cpu:.0f} s of CPU)")
    verdict = "met" if rate_cpu >= TARGET else "NOT met"
    print(f"  target >= {TARGET:,} packets/s (CPU): {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
