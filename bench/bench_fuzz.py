"""Benchmark of the controller fuzzer: cases per second against the reference controller over loopback.

Prints, measured in this run:
- fuzzer: cases/s for N single-packet cases of the random phase (random bytes, fields, structure:
  case generation through the scapy layers, base-unit VRPI stream, rate limit lifted, every
  controller packet judged by the oracles);
- baseline: the same packets, built beforehand, sent with a bare `sendto` loop to the same controller;
- the ratio fuzzer / baseline (the price of building, judging and bookkeeping per case);
- for information, the whole random phase including its timing sequences (VRPI gaps, withheld
  VRAI, retransmissions), whose waiting is part of the case, not overhead.
The real run is rate-limited (default 100 case packets/s).
Then, against the C controller of tests/targets: cases/s blind and with --coverage, and --rate 5000;
and blind against its build without a sanitizer, with core files on and with none (--no-core, as
where core_pattern pipes to apport), when gdb runs it for the stack of a crash: what gdb costs.
"""
from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "targets"))

from loopback import free_ports
from vm110 import constants as C
from vm110.fuzz import cases
from vm110.fuzz import mutate as M
from vm110.fuzz.corpus import Entry, Packet
from vm110.fuzz.guided import GuidedConfig
from vm110.fuzz.oracles import Limits
from vm110.fuzz.runner import RunConfig, Runner, start_target
from vm110.fuzz.session import Session, Settings

SEED = 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=2000)
    args = parser.parse_args()
    rx, listen = free_ports(2)
    controller = subprocess.Popen([sys.executable, "-m", "vm110", "simulate", "controller", "--listen",
                                   f"127.0.0.1:{rx}", "--peer", f"127.0.0.1:{listen}", "--source", "127.0.0.1:0",
                                   "--quiet"], stdout=subprocess.DEVNULL)
    first = len(cases.sweep(SEED))
    schedule = [cases.generate(SEED, i) for i in range(first, first + args.cases)]
    todo = [c for c in schedule if c.family != "random-sequence"]
    try:
        session = Session(Settings(target=("127.0.0.1", rx), listen=("127.0.0.1", listen), rate=1e9,
                                   limits=Limits()))
        start_target(session)
        start = time.perf_counter()
        packets = []
        for case in todo:
            sent = session.run_steps(case.index, [(s.build, s.delay_ms, s.expect_ack) for s in case.steps])
            packets += [p.data for p in sent]
        fuzz_s = time.perf_counter() - start
        session.pump(time.time() + Limits().ack_timeout_ms / 1000 + 0.2)   # let the oracles judge the last ones
        findings = len(session.monitor.triggers)
        start = time.perf_counter()
        for case in schedule:
            session.run_steps(case.index, [(s.build, s.delay_ms, s.expect_ack) for s in case.steps],
                              case.pause_vrpi_ms, case.withhold_vrai_ms, case.stream, case.settle_ms)
        schedule_s = time.perf_counter() - start
        session.close()

        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        start = time.perf_counter()
        for data in packets:
            sock.sendto(data, ("127.0.0.1", rx))
        raw_s = time.perf_counter() - start
        sock.close()
    finally:
        controller.terminate()
        controller.wait(5)
    fuzz_rate, raw_rate = len(todo) / fuzz_s, len(packets) / raw_s
    print(f"fuzzer:   {len(todo)} cases ({len(packets)} packets) in {fuzz_s:.2f} s = {fuzz_rate:,.0f} cases/s"
          f" ({findings} oracle triggers at this unlimited rate)")
    print(f"baseline: {len(packets)} pre-built packets by raw sendto in {raw_s:.3f} s = {raw_rate:,.0f} packets/s")
    print(f"ratio fuzzer/baseline: {fuzz_rate / raw_rate:.3f} (default --rate caps a run at 100 case packets/s)")
    print(f"whole random phase with its timing sequences: {len(schedule)} cases in {schedule_s:.1f} s = "
          f"{len(schedule) / schedule_s:,.0f} cases/s")


def c_target(seconds: float) -> None:
    """Blind and --coverage on the same C controller (tests/targets, built with afl-clang-fast and
    not crashing): cases/s of the random phase (blind) and of the guided loop (clear the map, send,
    wait until the map settles, read and classify it), rate limit lifted; then whether --rate 5000
    is honoured (packets/s reached, never above)."""
    import build as targets
    if targets.missing_tools("afl-correct"):
        print("C target: afl-clang-fast or gdb missing (make setup installs them): skipped")
        return
    exe = targets.build("afl-correct", Path(tempfile.gettempdir()) / "vm110-bench-targets")
    rx, listen = free_ports(2)
    settings = Settings(target=("127.0.0.1", rx), listen=("127.0.0.1", listen), rate=1e9, limits=Limits())
    results = {}
    for mode in ("blind", "coverage"):
        cfg = RunConfig(settings=settings, duration_s=seconds, out=Path(tempfile.mkdtemp(prefix="vm110-bench-")),
                        target_cmd=f"{exe} {rx} {listen}", coverage=GuidedConfig(65536) if mode == "coverage" else None)
        runner = Runner(cfg)
        guided, session = runner.guided, runner.session
        if guided is not None:
            guided.open(cfg.target_cmd)
            guided.sweep = 0
            guided.corpus.append(Entry([Packet(M.build(C.PacketType.VRCI, 0, M.default_fields(C.PacketType.VRCI)))]))
        start_target(session)
        n = _cases(session, guided, seconds)
        results[mode] = n / seconds
        extra = f", {guided.edges()} edges, corpus {len(guided.corpus)}" if guided else ""
        print(f"C target {mode:8s}: {n} cases in {seconds:.0f} s = {n / seconds:,.0f} cases/s{extra}")
        if mode == "blind":
            session.settings.rate = 5000.0
            count, start = 2000, time.perf_counter()
            vrpi = M.build(C.PacketType.VRPI, 0, M.ARMED_VRPI)
            for _ in range(count):
                session.send_case_packet(0, lambda serial, p=vrpi: (p, p), 0.0, False)
            print(f"--rate 5000: {count} packets at {count / (time.perf_counter() - start):,.0f} packets/s")
        session.close()
        if guided:
            guided.close()
    print(f"coverage/blind cases/s: {results['coverage'] / results['blind']:.2f}")


def _cases(session: Session, guided, seconds: float) -> int:
    """Cases of the random phase (or the guided loop) run for `seconds`."""
    first = len(cases.sweep(SEED))
    n, end = 0, time.time() + seconds
    while time.time() < end:
        index = first + n
        case = guided.next_case(index) if guided else cases.generate(SEED, index)
        if case.family == "random-sequence":
            n += 1
            continue
        if guided:
            guided.before_case()
        sent = session.run_steps(index, [(st.build, st.delay_ms, st.expect_ack) for st in case.steps],
                                 case.pause_vrpi_ms, case.withhold_vrai_ms, case.stream, case.settle_ms)
        if guided:
            guided.after_case(session, case, sent)
        session.monitor.triggers.clear()
        n += 1
    return n


def gdb_cost(seconds: float) -> None:
    """Blind cases/s against the plain build with core files on (it runs alone) and with none (gdb
    runs it), interleaved, best of 2."""
    import build as targets
    if targets.missing_tools("plain-correct"):
        print("gdb: gcc or gdb missing (make setup installs them): skipped")
        return
    exe = targets.build("plain-correct", Path(tempfile.gettempdir()) / "vm110-bench-targets")
    rates: dict[bool, float] = {}
    for core in (True, False, True, False):
        rx, listen = free_ports(2)
        settings = Settings(target=("127.0.0.1", rx), listen=("127.0.0.1", listen), rate=1e9, limits=Limits())
        out = Path(tempfile.mkdtemp(prefix="vm110-bench-"))
        runner = Runner(RunConfig(settings=settings, duration_s=seconds, out=out, target_cmd=f"{exe} {rx} {listen}",
                                  core=core))
        assert runner.supervisor is not None and bool(runner.supervisor.gdb) != core, runner.supervisor.core_files()
        start_target(runner.session)
        rates[core] = max(rates.get(core, 0.0), _cases(runner.session, None, seconds) / seconds)
        runner.session.close()
    print(f"plain build, core files on: {rates[True]:,.0f} cases/s; --no-core, under gdb: {rates[False]:,.0f} cases/s")
    print(f"gdb/alone cases/s: {rates[False] / rates[True]:.2f}")


if __name__ == "__main__":
    main()
    c_target(5.0)
    gdb_cost(5.0)
