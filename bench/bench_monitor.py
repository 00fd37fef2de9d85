"""Benchmark of `vm110 monitor --read FILE` (as fast as it goes) on synthesised captures.

Prints, all measured in this run:
- packets/s of the monitor on a capture of PACKETS packets (target >= 20,000 on one core), as a
  ratio against two baselines: `vm110 analyze` on the same file, and a plain loop reading its
  datagrams (`CaptureReader`);
- the monitor's resident memory at 15, 30 and 60 minutes of capture time of the 1-hour `day`
  capture (from its --json-lines snapshots, taken as the capture time passes) and the growth
  from 15 to 60 minutes (target: flat, a few MiB of noise at most).
Each timing is the best of REPEAT runs, interleaved. Captures are cached in out/bench/.
"""
from __future__ import annotations

import json
import os
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
PACKETS_PER_S = 18.6          # of the `day` scenario
REPEAT = 2
TARGET_PPS = 20_000


def capture(name: str, seconds: float) -> Path:
    path = OUT / f"monitor-{name}.pcap"
    if not path.exists():
        OUT.mkdir(parents=True, exist_ok=True)
        synthesize("day", str(path), 1, seconds, "pcap")
    return path


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main_bench() -> None:
    big = capture(f"{PACKETS}", PACKETS / PACKETS_PER_S)
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
    print(f"monitor --read: {packets} packets in {best['monitor']:.2f} s = {pps:,.0f} packets/s "
          f"(target >= {TARGET_PPS:,}: {'ok' if pps >= TARGET_PPS else 'MISSED'})")
    print(f"  monitor / analyze (same file): {best['monitor'] / best['analyze']:.2f}  "
          f"(analyze {best['analyze']:.2f} s)")
    print(f"  monitor / plain read loop:     {best['monitor'] / best['read']:.2f}  (read {best['read']:.2f} s)")

    hour = capture("hour", 3600.0)
    with tempfile.TemporaryDirectory(prefix="vm110-bench-") as tmp:
        lines = Path(tmp) / "live.jsonl"
        subprocess.run([sys.executable, "-m", "vm110", "monitor", "--read", str(hour), "--idle", "0", "--no-dashboard",
                        "--json-lines", str(lines), *quiet], check=False, stdout=subprocess.DEVNULL)
        snaps = [o for o in map(json.loads, lines.read_text().splitlines()) if o["type"] == "snapshot"]
    start = snaps[0]["time"]
    at = {}
    for minute in (15, 30, 60):
        near = [s for s in snaps if s["time"] - start <= minute * 60]
        at[minute] = near[-1]["memory_kb"] / 1024
    print("monitor memory over a 1-hour capture (RSS, MiB): "
          + ", ".join(f"{m} min {v:.1f}" for m, v in at.items())
          + f"; growth 15 -> 60 min: {at[60] - at[15]:+.1f} MiB")


if __name__ == "__main__":
    main_bench()
