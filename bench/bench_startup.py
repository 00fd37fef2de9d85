"""Fixed costs before any packet.

Command start-up: how long `vm110 COMMAND --help` takes before the command could do any work,
against two baselines measured in the same run:

- interpreter: `python -c pass` (the floor: no command starts faster);
- all loaded: `python -c` importing every command's module, which every command did before it
  loaded only its own (its libraries with it: scapy, numpy, DuckDB, the fuzzer).

`analyze --engine tshark` of CAPTURES small captures (the sampler of `vm110 craft`), against the
floor of any tshark engine: `tshark -r` with the plugin, once per capture. (The plugin check,
`tshark -G protocols`, ran once more per capture before it was kept for the process.)

CPU time of the child (user + system, best of BENCH_STARTUP_REPEAT runs): other jobs on the machine
slow the wall clock down; the wall time of the same run is printed next to it.
"""
from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vm110.cli import COMMANDS
from vm110.plugin import plugin_path

REPEAT = int(os.environ.get("BENCH_STARTUP_REPEAT", "5"))
CAPTURES = 4
ALL = "; ".join(f"import vm110.commands.{m}" for m in COMMANDS.values())


def cost(argv: list[str]) -> tuple[float, float]:
    """Best CPU and wall seconds of running `argv` (output discarded)."""
    best_cpu = best_wall = float("inf")
    for _ in range(REPEAT):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        wall = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        wall = time.perf_counter() - wall
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        best_cpu, best_wall = min(best_cpu, cpu), min(best_wall, wall)
    return best_cpu, best_wall


def main() -> int:
    floor_cpu, floor_wall = cost([sys.executable, "-c", "pass"])
    all_cpu, all_wall = cost([sys.executable, "-c", ALL])
    print(f"start-up, CPU seconds (best of {REPEAT}); wall in brackets")
    print(f"  interpreter alone      {floor_cpu:6.3f}  ({floor_wall:.3f})")
    print(f"  every command loaded   {all_cpu:6.3f}  ({all_wall:.3f})")
    print(f"  {'command':<22} {'CPU':>6}  {'/ all loaded':>12}  {'/ interpreter':>13}")
    for argv in [["--help"], *([name, "--help"] for name in COMMANDS)]:
        cpu, wall = cost([sys.executable, "-m", "vm110", *argv])
        print(f"  {' '.join(argv):<22} {cpu:6.3f}  {cpu / all_cpu:12.2f}  {cpu / floor_cpu:13.1f}  ({wall:.3f})")
    if shutil.which("tshark") is None:
        print("analyze --engine tshark: no tshark here, not measured")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        sampler = Path(tmp) / "sampler.pcap"
        subprocess.run([sys.executable, "-m", "vm110", "craft", "--out", str(sampler)], capture_output=True, check=True)
        captures = [str(sampler)] * CAPTURES
        tshark_cpu, _ = cost(["sh", "-c", 'for c; do tshark -X "lua_script:$0" -r "$c" > /dev/null; done',
                              str(plugin_path()), *captures])
        engine_cpu, engine_wall = cost([sys.executable, "-m", "vm110", "analyze", "--engine", "tshark", "--quiet",
                                        *captures])
    print(f"analyze --engine tshark, {CAPTURES} small captures: {engine_cpu:.3f} CPU s ({engine_wall:.3f} wall); "
          f"tshark -r each with the plugin {tshark_cpu:.3f}: {engine_cpu / tshark_cpu:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
