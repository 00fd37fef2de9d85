"""Benchmark of `vm110 fleet` on synthesised captures.

Prints, all measured in this run:
- build throughput: `vm110 fleet build --engine local -j N` against `vm110 analyze --jobs N --json`
  on the same captures with the same number of processes (target <= 1.2x), and the captures per
  hour that makes on this machine;
- the speed-up of `--engine dask` from one to two LocalCluster workers (the map only; the cluster's
  start is printed apart);
- the time of a named query (`--worst links`) over the demo fleet (`make fleet-demo`'s 40 captures);
- opening a dataset of many small captures and a named query, against DuckDB scanning the same
  parts once (the ratio should stay flat from 250 to 1,000 captures); and `vm110 fleet report`'s
  page over it, against DuckDB scanning once the parts of every table the report reads.
Each timing is the median of REPEAT runs, interleaved, so that a busy machine hurts both sides alike.
Captures are cached in out/bench/fleet/ (synthesis is deterministic; delete it to rebuild).
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vm110.fleet import demo
from vm110.fleet.build import build
from vm110.fleet.query import NAMED, Args, Fleet
from vm110.fleet.sources import MetaPattern
from vm110.fleet.work import Settings
from vm110.synth import synthesize

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "bench" / "fleet"
VM110 = [sys.executable, "-m", "vm110"]
SCENARIOS = ("normal", "loss", "retransmit", "vrco", "controller-watchdog", "disarmed")
REPEAT = 3


def captures(count: int, seconds: float) -> list[str]:
    folder = OUT / f"captures-{count}x{seconds:g}s"
    if not folder.exists():
        temp = Path(tempfile.mkdtemp(dir=OUT.parent if OUT.parent.exists() else None))
        for i in range(count):
            synthesize(SCENARIOS[i % len(SCENARIOS)], str(temp / f"c{i:03d}.pcap"), i + 1, seconds, "pcap")
            os.remove(temp / f"c{i:03d}.pcap.truth.json")
        OUT.mkdir(parents=True, exist_ok=True)
        temp.rename(folder)
    return sorted(str(p) for p in folder.glob("*.pcap"))


def timed(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def throughput(paths: list[str], jobs: int, work: Path) -> None:
    analyze_t, build_t = [], []
    for n in range(REPEAT):
        analyze_t.append(timed([*VM110, "analyze", *paths, "--jobs", str(jobs), "--quiet",
                                "--json", str(work / f"reports{n}.json")]))
        build_t.append(timed([*VM110, "fleet", "build", *paths, "--out", str(work / f"ds{n}"), "-j", str(jobs)]))
    a, b = statistics.median(analyze_t), statistics.median(build_t)
    size = sum(os.path.getsize(p) for p in paths)
    print(f"build, {len(paths)} captures ({size / len(paths) / 1024:.0f} KiB each), {jobs} processes: "
          f"fleet build {b:.2f} s, analyze --json {a:.2f} s: {b / a:.2f}x (target <= 1.2)")
    print(f"  one machine ({os.cpu_count()} CPUs, -j {jobs}): {len(paths) / b * 3600:,.0f} captures/hour of this "
          f"size, {size / b / 2**20:.1f} MiB/s")


def dask_speedup(paths: list[str], work: Path) -> None:
    from distributed import Client, LocalCluster
    times = {}
    for workers in (1, 2):
        start = time.perf_counter()
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None) as cluster, Client(cluster) as client:
            started = time.perf_counter() - start
            client.run(lambda: __import__("vm110.fleet.work"))      # imports done before the clock starts
            runs = []
            for n in range(REPEAT):
                settings = Settings(dataset=str(work / f"dask{workers}-{n}"))
                t0 = time.perf_counter()
                build(paths, settings, engine="dask", jobs=workers, scheduler=cluster.scheduler_address)
                runs.append(time.perf_counter() - t0)
        times[workers] = statistics.median(runs)
        print(f"dask, {workers} worker{'s' if workers > 1 else ''}: cluster start {started:.1f} s, "
              f"build of {len(paths)} captures {times[workers]:.2f} s")
    print(f"  speed-up 1 -> 2 workers: {times[1] / times[2]:.2f}x (on {os.cpu_count()} CPUs)")


def named_query(work: Path) -> None:
    demo.captures(str(work / "demo"))
    build([str(work / "demo" / "sites")], Settings(dataset=str(work / "demo-ds")),
          MetaPattern("sites/{site}/{machine}/*.pcap"), jobs=2)
    runs = []
    for _ in range(5):
        t0 = time.perf_counter()
        fleet = Fleet(str(work / "demo-ds"))
        result = fleet.run(NAMED["worst-links"].sql(fleet, Args()))
        runs.append(time.perf_counter() - t0)
    cli = statistics.median(timed([*VM110, "fleet", "query", str(work / "demo-ds"), "--worst", "links"])
                            for _ in range(3))
    print(f"named query --worst links over the demo fleet (40 captures, {len(result.rows)} rows): "
          f"{statistics.median(runs) * 1000:.0f} ms (open + query), {cli:.2f} s as a command")


def small_captures(count: int) -> list[str]:
    """`count` captures of six packets each (craft's sampler, a day apart), in sites/machines:
    many small files, where the per-file cost of reading the dataset shows."""
    from vm110.capture.writer import open_writer
    from vm110.commands.craft import sample_packets
    folder = OUT / f"small-{count}"
    if not folder.exists():
        temp = Path(tempfile.mkdtemp(dir=OUT.parent if OUT.parent.exists() else None))
        frames = [(f.time, bytes(f)) for f in sample_packets()]
        for i in range(count):
            where = temp / "sites" / f"s{i % 5}" / f"m{i % 50}"
            where.mkdir(parents=True, exist_ok=True)
            with open(where / f"c{i:05d}.pcap", "wb") as stream, open_writer(stream, "pcap") as writer:
                writer.write_many((round((t + i * 86400) * 1e6), data) for t, data in frames)
        OUT.mkdir(parents=True, exist_ok=True)
        temp.rename(folder)
    return [str(folder / "sites")]


def many_captures(work: Path, count: int) -> None:
    """Opening a dataset of many small captures and a named query, against DuckDB alone scanning
    the same parts once (the floor): the ratio should not grow with the number of captures."""
    import duckdb
    from vm110.fleet.dataset import view_files
    dataset = str(work / f"small-{count}")
    build(small_captures(count), Settings(dataset=dataset), MetaPattern("sites/{site}/{machine}/*.pcap"), jobs=2)
    runs, floor = [], []
    for _ in range(REPEAT):
        t0 = time.perf_counter()
        fleet = Fleet(dataset)
        fleet.run(NAMED["worst-links"].sql(fleet, Args()))
        runs.append(time.perf_counter() - t0)
        fleet.con.close()
        files = view_files(fleet.manifest, fleet.dataset)
        t0 = time.perf_counter()
        with duckdb.connect() as con:
            for table in ("captures", "senders", "streams"):            # what --worst links reads
                paths = [f for group in files[table].values() for f in group]
                con.execute(f"SELECT count(*) FROM read_parquet({paths!r})").fetchall()
        floor.append(time.perf_counter() - t0)
    a, b = statistics.median(runs), statistics.median(floor)
    print(f"open + --worst links over {count} small captures: {a:.2f} s; DuckDB alone scanning its parts once: "
          f"{b:.2f} s: {a / b:.1f}x")
    report_page(dataset, count)


def report_page(dataset: str, count: int) -> None:
    """The report's page (about 15 queries over six tables) against DuckDB alone scanning the parts
    of those tables once: the ratio is what the queries cost beyond one look at the data."""
    import duckdb
    from vm110.fleet.dataset import view_files
    from vm110.fleet.report import render
    runs, floor = [], []
    for _ in range(REPEAT):
        t0 = time.perf_counter()
        fleet = Fleet(dataset)
        render(fleet)
        runs.append(time.perf_counter() - t0)
        fleet.con.close()
        files = view_files(fleet.manifest, fleet.dataset)
        t0 = time.perf_counter()
        with duckdb.connect() as con:
            for table in ("captures", "senders", "streams", "commands", "findings", "errors"):
                paths = [f for group in files[table].values() for f in group]
                if paths:
                    con.execute(f"SELECT count(*) FROM read_parquet({paths!r})").fetchall()
        floor.append(time.perf_counter() - t0)
    a, b = statistics.median(runs), statistics.median(floor)
    print(f"open + report page over {count} small captures: {a:.2f} s; DuckDB alone scanning its tables' parts "
          f"once: {b:.2f} s: {a / b:.1f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=int, default=24)
    parser.add_argument("--seconds", type=float, default=120.0, help="length of each capture")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    paths = captures(args.captures, args.seconds)
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (wall times suffer when it is high)")
    work = Path(tempfile.mkdtemp(prefix="vm110-bench-fleet-"))
    try:
        throughput(paths, args.jobs, work)
        dask_speedup(paths, work)
        named_query(work)
        for count in (250, 1000):
            many_captures(work, count)
    finally:
        shutil.rmtree(work)          # made by this run


if __name__ == "__main__":
    main()
