"""Benchmark of `vm110 monitor --read FILE` (as fast as it goes) on synthesised captures.

Prints, all measured in this run:
- packets/s of the monitor on a capture of PACKETS packets of PAIRS base units and their
  controllers, as a mirror port shows them (target >= 20,000 on one core), as a
  ratio against two baselines: `vm110 analyze` on the same file, and a plain loop reading its
  datagrams (`CaptureReader`);
- the monitor's resident memory at 15, 30 and 60 minutes of capture time of the 1-hour `day`
  capture (from its --json-lines snapshots, taken as the capture time passes) and the growth
  from 15 to 60 minutes (target: flat), with the commands seen meanwhile and the growth per
  command (the report lists every command; the monitor keeps finished ones in a file).
Each timing is the best of REPEAT runs, interleaved. Captures are cached in out/bench/.
"""
from __future__ import annotations

import heapq
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vm110.capture.reader import CaptureReader
from vm110.cli import main
from vm110.synth import synthesize

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "bench"
PACKETS = int(os.environ.get("BENCH_MONITOR_PACKETS", "200000"))
PAIRS = 10                    # base units (and controllers) on the mirror port
PACKETS_PER_S = 18.6          # of the `day` scenario
REPEAT = 2
TARGET_PPS = 20_000


def capture(name: str, seconds: float) -> Path:
    path = OUT / f"monitor-{name}.pcap"
    if not path.exists():
        OUT.mkdir(parents=True, exist_ok=True)
        synthesize("day", str(path), 1, seconds, "pcap")
    return path


def mirror(pairs: int, seconds: float) -> Path:
    """What a mirror port shows of `pairs` base units with their controllers: the `day` capture
    `pairs` times, pair k from 10.0.k.10 and 10.0.k.20, shifted k * 1.7 ms, merged by time."""
    path = OUT / f"monitor-mirror{pairs}-{seconds:g}.pcap"
    if path.exists():
        return path
    one = capture(f"day-{seconds:g}", seconds)
    data = one.read_bytes()
    records, pos = [], 24
    while pos + 16 <= len(data):
        sec, usec, incl = struct.unpack_from("<III", data, pos)
        records.append((sec * 1_000_000 + usec, data[pos + 8:pos + 16 + incl]))
        pos += 16 + incl
    src_octet = 16 + 14 + 12 + 2                  # record header, Ethernet, IPv4 source: third byte

    def copy(k: int):
        shift = int(k * 1700)
        for us, rest in records:
            frame = bytearray(rest)
            frame[src_octet - 8] = k
            yield us + shift, bytes(frame)
    with open(path, "wb") as out:
        out.write(data[:24])
        for us, rest in heapq.merge(*(copy(k) for k in range(pairs)), key=lambda r: r[0]):
            out.write(struct.pack("<II", us // 1_000_000, us % 1_000_000) + rest)
    return path


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main_bench() -> None:
    big = mirror(PAIRS, PACKETS / PACKETS_PER_S / PAIRS)
    packets = sum(1 for _ in CaptureReader(str(big)))
    quiet = ["--quiet", "--crc", "mpeg2", "--crc-order", "little"]

    def monitor() -> None:
        with open(os.devnull, "w") as null:
            stdout, sys.stdout = sys.stdout, null
            try:
                main(["monitor", "--read", str(big), "--idle", "0", "--no-dashboard", *quiet])
            finally:
                sys.stdout = stdout

    def analyze() -> None:
        main(["analyze", str(big), *quiet])

    def read() -> None:
        for _ in CaptureReader(str(big)):
            pass

    runs: dict[str, list[float]] = {"monitor": [], "analyze": [], "read": []}
    for _ in range(REPEAT):
        for name, fn in (("monitor", monitor), ("analyze", analyze), ("read", read)):
            runs[name].append(timed(fn))
    best = {k: min(v) for k, v in runs.items()}
    pps = packets / best["monitor"]
    print(f"monitor --read, mirror port of {PAIRS} BUs and {PAIRS} controllers: {packets} packets in "
          f"{best['monitor']:.2f} s = {pps:,.0f} packets/s "
          f"(target >= {TARGET_PPS:,}: {'ok' if pps >= TARGET_PPS else 'MISSED'})")
    print(f"  monitor / analyze (same file): {best['monitor'] / best['analyze']:.2f}  "
          f"(analyze {best['analyze']:.2f} s)")
    print(f"  monitor / plain read loop:     {best['monitor'] / best['read']:.2f}  (read {best['read']:.2f} s)")

    hour = mirror(PAIRS, 3600.0)
    with tempfile.TemporaryDirectory(prefix="vm110-bench-") as tmp:
        lines = Path(tmp) / "live.jsonl"
        subprocess.run([sys.executable, "-m", "vm110", "monitor", "--read", str(hour), "--idle", "0", "--no-dashboard",
                        "--json-lines", str(lines), *quiet], check=False, stdout=subprocess.DEVNULL)
        snaps = [o for o in map(json.loads, lines.read_text().splitlines()) if o["type"] == "snapshot"]
    start = snaps[0]["time"]
    at, commands = {}, {}
    for minute in (15, 30, 60):
        near = [s for s in snaps if s["time"] - start <= minute * 60]
        at[minute] = near[-1]["memory_kb"] / 1024
        commands[minute] = near[-1]["commands"]["commands"]
    grew, more = at[60] - at[15], commands[60] - commands[15]
    print(f"monitor memory over a 1-hour capture of the {PAIRS}-pair mirror port (RSS, MiB): "
          + ", ".join(f"{m} min {v:.1f}" for m, v in at.items())
          + f"; growth 15 -> 60 min: {grew:+.1f} MiB")
    # The report lists every command: finished ones go to a file, so this should be about 8 bytes.
    print(f"  commands 15 -> 60 min: {more} more, {grew * 2**20 / max(more, 1):.0f} bytes of growth per command")


if __name__ == "__main__":
    main_bench()
