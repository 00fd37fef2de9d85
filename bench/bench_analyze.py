"""Benchmark of `vm110 analyze` (fast engine) on synthesised captures of 1,000,000 and 2,000,000 packets.

Prints, all measured in this run:
- analysis time / time scapy's RawPcapReader needs merely to iterate the same file (target <= 1.0);
- analysis time / `tshark -T fields` with the Lua dissector, both on the first 100,000 packets
  (tshark with a Lua dissector needs minutes for the whole file);
- peak memory of a child process running `vm110 analyze --json` on 1 M packets (target <= 300 MiB)
  and on 2 M, and their difference (target: about 24 MiB at most; the analysis keeps per packet
  only the time of a periodic packet, everything else is bounded by senders, commands and findings);
- a gzip-compressed capture (`.pcap.gz`, as dumpcap --compress gzip writes): analysis time of the
  same capture compressed / uncompressed (the reader decompresses it as it reads, nothing on disk);
- what a sender costs: `vm110 analyze --json` (the command, in a fresh process) of SENDERS VRPI
  packets each from a sender of its own (a hostile or mirrored capture: every source address is
  one), against the same packets from two senders; the ratio, and the cost of each sender above.
Each timing is the median of REPEAT runs, interleaved, so that a busy machine hurts both sides alike.
The capture is cached in out/bench/ (synthesis is deterministic; delete it to rebuild).
"""
from __future__ import annotations

import argparse
import gzip
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scapy.utils import RawPcapReader

from vm110 import constants as C
from vm110 import encode as E
from vm110.analysis import analyze
from vm110.capture.writer import UdpFlow, open_writer
from vm110.plugin import plugin_path
from vm110.synth import synthesize

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "bench"
PACKETS_PER_S = 18.6          # of the `day` scenario
REPEAT = 3
TSHARK_PACKETS = 100_000
SENDERS = 20_000


def capture(packets: int) -> Path:
    path = OUT / f"analyze-{packets}.pcap"
    if not path.exists():
        OUT.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        truth = synthesize("day", str(path), 1, packets / PACKETS_PER_S, "pcap")
        print(f"synthesised {truth['capture']['packets']} packets in {time.perf_counter() - start:.1f} s")
    return path


def prefix(path: Path, count: int) -> Path:
    """The first `count` records of a little-endian pcap."""
    out = path.with_name(f"{path.stem}-first{count}.pcap")
    if not out.exists():
        data = path.read_bytes()
        pos = 24
        for _ in range(count):
            pos += 16 + struct.unpack_from("<I", data, pos + 8)[0]
        out.write_bytes(data[:pos])
    return out


def senders_capture(count: int, own: bool) -> Path:
    """`count` VRPI packets 1 ms apart, each from a sender of its own (`own`), or from two."""
    path = OUT / f"senders-{count}-{'own' if own else 'two'}.pcap"
    if not path.exists():
        OUT.mkdir(parents=True, exist_ok=True)
        packet = E.packet(C.PacketType.VRPI, E.payload(C.PacketType.VRPI, {}), origin=0x0101)
        with open(path, "wb") as out, open_writer(out, "pcap") as writer:
            for i in range(count):
                n = i if own else i % 2
                source = f"10.{(n >> 16) & 255}.{(n >> 8) & 255}.{n & 255}"
                flow = UdpFlow(source, C.INPUT_PORT, C.MULTICAST_GROUP, C.INPUT_PORT)
                writer.write(1_700_000_000_000_000 + i * 1000, flow.frame(packet))
    return path


def gzipped(path: Path) -> Path:
    out = path.with_name(path.name + ".gz")
    if not out.exists():
        with open(path, "rb") as src, gzip.open(out, "wb", compresslevel=6) as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    return out


def best(fn, repeat: int = REPEAT) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def scapy_iterate(path: Path) -> None:
    with RawPcapReader(str(path)) as reader:
        for _ in reader:
            pass


# Runs the CLI in a fresh process and prints its VmHWM (peak RSS of this process's own memory map:
# unlike ru_maxrss it does not inherit the RSS of the parent that spawned it).
# The analysing process's own peak (VmHWM) and its reading child's (ru_maxrss of the children):
# both count, so the figure is their sum (an upper bound: forked pages are shared at first).
_CHILD = """
import resource, sys
from vm110.cli import main
code = main(sys.argv[1:])
hwm = next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM:'))
kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print('PEAK', hwm, kids, code, file=sys.stderr)
"""


def child_peak(path: Path) -> tuple[float, float, float]:
    """(wall seconds, peak RSS MiB of the analysing process plus its reading child, of the child)
    of `vm110 analyze --json` in a fresh process."""
    with tempfile.TemporaryDirectory(prefix="vm110-bench-") as tmp:   # a regular file: --json refuses devices
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", _CHILD, "analyze", str(path), "--quiet",
                               "--json", os.path.join(tmp, "report.json")], capture_output=True, text=True)
        wall = time.perf_counter() - start
    line = next((ln for ln in done.stderr.splitlines() if ln.startswith("PEAK ")), None)
    if line is None or line.split()[3] not in ("0", "1"):
        raise SystemExit(f"vm110 analyze failed: {done.stderr[-500:]}")
    _, hwm, kids, _ = line.split()
    return wall, (int(hwm) + int(kids)) / 1024.0, int(kids) / 1024.0


def tshark_fields(path: Path) -> None:
    subprocess.run(["tshark", "-r", str(path), "-X", f"lua_script:{plugin_path()}", "-T", "fields",
                    "-e", "frame.number", "-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status",
                    "-e", "vm110.command_id"], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def per_sender(count: int) -> None:
    own, two = senders_capture(count, True), senders_capture(count, False)
    times: dict[Path, list[float]] = {own: [], two: []}
    for _ in range(REPEAT):
        for path in times:
            times[path].append(child_peak(path)[0])
    own_s, two_s = statistics.median(times[own]), statistics.median(times[two])
    print(f"vm110 analyze --json of {count} packets, each from a sender of its own: {own_s:.2f} s; "
          f"from two senders: {two_s:.2f} s")
    print(f"RATIO {count} senders / 2 senders = {own_s / two_s:.2f} "
          f"({(own_s - two_s) / count * 1e6:.0f} us a sender)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--packets", type=int, default=1_000_000)
    parser.add_argument("--senders", type=int, default=SENDERS, help="packets (and senders) of the per-sender row")
    parser.add_argument("--senders-only", action="store_true", help="only the per-sender row")
    args = parser.parse_args()
    per_sender(args.senders)
    if args.senders_only:
        return
    path = capture(args.packets)
    double = capture(2 * args.packets)
    peaks = [(n, *child_peak(p)) for n, p in ((args.packets, path), (2 * args.packets, double))]
    scapy_times, analysis_times = [], []
    for _ in range(REPEAT):
        scapy_times.append(best(lambda: scapy_iterate(path), 1))
        analysis_times.append(best(lambda: analyze(str(path)), 1))
    report = analyze(str(path))
    packets = report["capture"]["packets"]
    scapy_s = statistics.median(scapy_times)
    analysis_s = statistics.median(analysis_times)
    print(f"capture: {packets} packets, {path.stat().st_size / 2**20:.1f} MiB ({path})")
    print(f"scapy RawPcapReader, iterate only: {scapy_s:.2f} s ({scapy_s / packets * 1e6:.2f} us/packet)")
    print(f"vm110 analyze, fast engine:        {analysis_s:.2f} s ({analysis_s / packets * 1e6:.2f} us/packet, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    print(f"RATIO analysis / scapy iterate = {analysis_s / scapy_s:.2f} (target <= 1.0)")
    packed = gzipped(path)
    plain_times, gzip_times = [], []
    for _ in range(REPEAT):
        plain_times.append(best(lambda: analyze(str(path)), 1))
        gzip_times.append(best(lambda: analyze(str(packed)), 1))
    plain_s, gzip_s = statistics.median(plain_times), statistics.median(gzip_times)
    print(f"vm110 analyze of it gzip-compressed ({packed.stat().st_size / 2**20:.1f} MiB): {gzip_s:.2f} s, "
          f"uncompressed {plain_s:.2f} s")
    print(f"RATIO analysis gzip / uncompressed = {gzip_s / plain_s:.2f}")
    for n, wall, peak, reader in peaks:
        print(f"PEAK MEMORY of `vm110 analyze --json` on {n} packets = {peak:.0f} MiB, reading child included "
              f"({reader:.0f} MiB of it; {wall:.2f} s wall)")
    print(f"PEAK MEMORY {2 * args.packets} - {args.packets} packets = {peaks[1][2] - peaks[0][2]:.0f} MiB "
          f"(target: about 24 at most; {peaks[0][2]:.0f} MiB for {args.packets}: target <= 300)")
    if shutil.which("tshark") and plugin_path().is_file():
        small = prefix(path, min(TSHARK_PACKETS, packets))
        tshark_s = best(lambda: tshark_fields(small), 1)
        ours = best(lambda: analyze(str(small)))
        print(f"tshark -T fields with the Lua dissector, first {min(TSHARK_PACKETS, packets)} packets: "
              f"{tshark_s:.2f} s; "
              f"vm110 analyze: {ours:.2f} s")
        print(f"RATIO analysis / tshark -T fields = {ours / tshark_s:.3f}")
    else:
        print("tshark or dissector/vm110.lua missing: no tshark ratio")


if __name__ == "__main__":
    main()
