"""The fuzzer's memory oracle: its rule on RSS series made here (a leak, a cache that fills, an
allocator's noise, a large controller), and end to end against tests/targets/controller.c built
with a leak of 64 KiB per VRCI (-DBUG_LEAK) and without. Everything over loopback."""
from __future__ import annotations

import concurrent.futures
import json
import random
import subprocess
import sys
from pathlib import Path

import pytest
from loopback import free_ports, on_free_ports
from test_fuzz_targets import fuzz, programs  # noqa: F401  (the fixture builds the targets)
from vm110.fuzz.memory import MAX_SERIES, Rule, Sample, Watch, asan_allowance_kib, group_rss_kib
from vm110.fuzz.runner import RunConfig, Runner
from vm110.fuzz.session import Settings

MIB = 1024


def feed(watch: Watch, series: list[float], cases_per_sample: int = 10) -> list[tuple[int, dict]]:
    """The samples (one a second) given to `watch`: (sample number, evidence) of each that fired."""
    fired = []
    for n, rss in enumerate(series):
        evidence = watch.add(Sample(float(n), int(rss), n * cases_per_sample, 2 * n * cases_per_sample))
        if evidence is not None:
            fired.append((n, evidence))
    return fired


def test_a_steady_leak_is_one_finding_with_its_growth_per_case():
    # 10 MiB warm, then 16 cases a second leaking 64 KiB each: 1 MiB a second.
    series = [10 * MIB] * 5 + [10 * MIB + 1 * MIB * k for k in range(1, 60)]
    fired = feed(Watch(Rule(growth_kib=16 * MIB)), series, cases_per_sample=16)
    # The rule: 5 samples in a row at least 10 + max(16, 5) = 26 MiB: from the 26 MiB sample (n=20) on.
    first = series.index(26 * MIB)
    assert [n for n, _ in fired] == [first + 4], "once, when the fifth sample over the threshold came"
    evidence = fired[0][1]
    assert evidence["kind"] == "growth" and evidence["warmup_kib"] == 10 * MIB
    assert evidence["kib_per_case"] == 64 and evidence["kib_per_packet"] == 32
    assert evidence["cases"] == {"first": 4 * 16 + 1, "last": (first + 4) * 16, "count": (first + 4 - 4) * 16}
    assert [s["rss_kib"] for s in evidence["series"]] == series[:first + 5]


def test_a_leak_on_a_rare_packet_kind_is_found_within_a_minute_by_default():
    """Trial: a C controller (1.6 MiB) leaking 16 KiB per packet with an unknown packet ID (TS-0006
    5.1.5: to be ignored), 7 % of the 38 cases a second at the default rate, rose 45 KiB/s: under
    the old 16 MiB default that is six minutes, and a 60 s run found nothing."""
    rng = random.Random(3)
    rss, series = 1600, []
    for _ in range(60):
        series.append(rss)
        rss += 16 * sum(rng.random() < 0.074 for _ in range(38))
    fired = feed(Watch(Rule()), series, cases_per_sample=38)
    assert len(fired) == 1
    n, evidence = fired[0]
    # Past max(1 MiB, half the warm-up level) above the warm-up level for the 5 samples up to it
    assert all(x >= max(series[:5]) + MIB for x in series[n - 4:n + 1]) and n < 60
    assert evidence["kind"] == "growth" and 0 < evidence["kib_per_case"] < 16
    # The same controller without the leak, its RSS a page up or down now and then, is no finding
    assert feed(Watch(Rule()), [1600 + 4 * rng.choice((0, 0, 0, 1, -1)) for _ in range(3000)]) == []


def test_the_finding_names_the_packet_kind_that_leaks():
    """64 KiB per packet of an unknown ID, one case in 14 (as the schedule sends them), among legal
    and illegal packets of other kinds; one rarer kind came three times beside many of them (as in
    the sweep, where the structural mutations of the three types come in the same round)."""
    rng = random.Random(5)
    kinds = ["VRPI legal", "VRCI legal", "VRAI legal", "VRCI bad_crc", "VRPI size_mismatch", "unknown_id"]
    watch, rss, evidence = Watch(Rule()), 1600, None
    for n in range(40):
        sent = [rng.choices(kinds, weights=(20, 20, 20, 15, 18, 7))[0] for _ in range(38)]
        if n in (7, 8, 9):
            sent += ["unknown_id"] * 6 + ["VRAI truncated"]
        for kind in sent:
            watch.kinds[kind] += 1
            rss += 64 * (kind == "unknown_id")
        evidence = watch.add(Sample(float(n), rss + 4 * rng.randint(-2, 2), 38 * n, 38 * n)) or evidence
    assert evidence is not None
    top, *others = evidence["suspects"]
    assert top["kind"] == "unknown_id" and 56 <= top["kib_per_packet"] <= 72 and top["share"] > 0.9
    assert all(x["share"] < 0.1 for x in others)
    assert "it goes with unknown_id packets (" in evidence["detail"]
    # A leak per second, of no packet kind, is said as none
    watch, evidence = Watch(Rule()), None
    for n in range(40):
        watch.kinds.update(rng.choices(kinds, k=38))
        evidence = watch.add(Sample(float(n), 1600 + 64 * n, 38 * n, 38 * n)) or evidence
    assert evidence is not None and evidence["suspects"] == [] and "goes with" not in evidence["detail"]


def test_a_cache_that_fills_and_stays_full_is_no_leak():
    """Past the threshold while it filled, but not rising across the last samples."""
    series = [10 * MIB] * 5 + [10 * MIB + 10 * MIB * k for k in range(1, 5)] + [50 * MIB] * 200
    assert feed(Watch(Rule()), series) == []
    # The same fill going on is one
    assert feed(Watch(Rule()), series[:9] + [50 * MIB + MIB * k for k in range(1, 6)])


def test_a_buffer_allocated_at_once_then_a_page_up_and_down_is_no_leak():
    """A correct C controller (1.6 MiB) that fills a 2 MiB table on its first command, past the
    1 MiB asked; its RSS then a page or two up and down (a stack page, a trimmed heap): never rising
    for good."""
    rng = random.Random(11)
    series = [1600] * 8 + [1600 + 2 * MIB + 4 * rng.choice((0, 0, 1, 2, -1)) for _ in range(3000)]
    assert feed(Watch(Rule()), series) == []
    # The same table still filling, 16 KiB a second, is (the growth past the threshold goes on)
    assert feed(Watch(Rule()), series[:20] + [series[19] + 16 * k for k in range(1, 10)])


def test_allocator_noise_and_a_trimmed_heap_are_no_leak():
    rng = random.Random(7)
    series = [40 * MIB + rng.randint(-3 * MIB, 3 * MIB) for _ in range(3000)]
    assert feed(Watch(Rule()), series) == []


def test_growth_must_be_a_share_of_a_large_controller_too():
    """+40 MiB on 200 MiB is below half of it; from +100 MiB (the sample n=104) on it is past it."""
    warm = [200 * MIB] * 5
    assert feed(Watch(Rule()), warm + [200 * MIB + MIB * k for k in range(1, 41)]) == []
    assert [n for n, _ in feed(Watch(Rule()), warm + [200 * MIB + MIB * k for k in range(1, 106)])] == [104 + 4]


def test_the_rss_read_moves_by_the_page_not_by_the_kernels_batch():
    """Trial: /proc/PID/stat's RSS moved in steps of 128 KiB (the kernel counts 32 pages per CPU
    before it adds them up), so a controller leaking 16 KiB a packet grew in one sample interval of
    eight and the packets it went with could not be told."""
    code = "import sys\nkept = []\nfor line in sys.stdin:\n    kept.append(b'L' * 40960)\n    print(flush=True)\n"
    with subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                          text=True, start_new_session=True) as proc:
        assert proc.stdin is not None and proc.stdout is not None
        try:
            steps = []
            for _ in range(6):
                before = group_rss_kib(proc.pid)
                proc.stdin.write("\n")
                proc.stdin.flush()
                proc.stdout.readline()
                steps.append(group_rss_kib(proc.pid) - before)
        finally:
            proc.kill()
    # 40 KiB written each time: 10 or 11 pages (and now and then a page of the interpreter's own)
    assert sorted(steps)[len(steps) // 2] in range(40, 52), steps


def test_the_hard_limit_fires_at_its_first_sample_above_once_per_controller():
    watch = Watch(Rule(limit_kib=20 * MIB, growth_kib=None))
    fired = feed(watch, [10 * MIB, 15 * MIB, 20 * MIB, 21 * MIB, 30 * MIB])
    assert [(n, e["kind"]) for n, e in fired] == [(3, "limit")]
    assert "above --target-memory 20 MiB" in fired[0][1]["detail"]


def test_the_series_of_a_long_run_stays_bounded():
    watch = Watch(Rule(growth_kib=None))
    feed(watch, [MIB + n for n in range(100_000)])
    assert len(watch.series) <= MAX_SERIES
    assert watch.series[0].rss_kib == MIB and watch.series[-1].rss_kib == MIB + 99_999
    assert watch.peak == MIB + 99_999


def test_addresssanitizers_quarantine_is_allowed_for():
    """Trial: a correct ASan build that frees a 64 KiB buffer per command rose from 5 to 28 MiB in
    25 s (freed chunks wait in the quarantine, 256 MiB by default on 64-bit Linux, with their shadow,
    an eighth more) and was reported as a leak."""
    assert asan_allowance_kib("abort_on_error=1:detect_leaks=0") == (256 * MIB + 1024) * 9 // 8
    assert asan_allowance_kib("quarantine_size_mb=16:thread_local_quarantine_size_kb=64") == (16 * MIB + 64) * 9 // 8
    assert asan_allowance_kib("quarantine_size=1048576,quarantine_size_mb=-1") == (1 * MIB + 1024) * 9 // 8
    assert asan_allowance_kib("quarantine_size_mb=0 thread_local_quarantine_size_kb=0") == 0
    churn = [5 * MIB] * 5 + [5 * MIB + MIB * k for k in range(1, 200)]
    assert feed(Watch(Rule(allowance_kib=asan_allowance_kib(""))), churn) == []
    assert feed(Watch(Rule(allowance_kib=asan_allowance_kib(""))), churn + [400 * MIB + MIB * k for k in range(5)])


def test_the_rule_of_an_asan_build_allows_for_its_quarantine(tmp_path, programs, monkeypatch):  # noqa: F811
    monkeypatch.delenv("ASAN_OPTIONS", raising=False)
    rx, listen = free_ports(2)
    for name, allowance in (("asan-churn", asan_allowance_kib("")), ("plain-correct", 0)):
        runner = Runner(RunConfig(settings=Settings(("127.0.0.1", rx), ("127.0.0.1", listen)), out=tmp_path / name,
                                  target_cmd=f"{programs(name)} {rx} {listen}"))
        try:
            assert runner.session.memory is not None and runner.session.memory.rule.allowance_kib == allowance
            assert ("AddressSanitizer's quarantine" in runner.summary()["memory"]["rule"]) == bool(allowance)
        finally:
            runner.session.close()
            if runner._log is not None:      # (run() closes it; this runner is not run)
                runner._log.close()


def _run(tmp_path: Path, exe: Path, rule: Rule, duration: float) -> dict:
    def runner(ports: list[int]) -> Runner:       # (its listen socket is bound here)
        rx, listen = ports
        return Runner(RunConfig(settings=Settings(("127.0.0.1", rx), ("127.0.0.1", listen), rate=2000),
                                duration_s=duration, out=tmp_path / f"out-{exe.name}", target_cmd=f"{exe} {rx} {listen}",
                                memory=rule, max_findings=1))
    return on_free_ports(2, runner).run()


def test_a_leaking_controller_is_found_and_a_correct_one_is_not(tmp_path, programs):  # noqa: F811
    # The rule on a faster clock (samples every 0.1 s), for a short test: at 2000 packets/s the
    # leaking ones send some 12 legal VRCI a second (0.75 MiB), and a packet of an unknown ID in
    # some 14 cases.
    rule = Rule(growth_kib=1 * MIB, period_s=0.1)
    with concurrent.futures.ThreadPoolExecutor(3) as pool:      # side by side: the test takes one run's time
        runs = [pool.submit(_run, tmp_path, programs(name), rule, seconds)
                for name, seconds in (("plain-leak", 10.0), ("plain-leak-unknown", 10.0), ("plain-correct", 3.0))]
        leaky, rare, clean = (run.result() for run in runs)
    evidence = _memory_evidence(tmp_path, "plain-leak", leaky)
    # 64 KiB per legal VRCI, and fewer legal VRCI than cases and packets
    assert 0 < evidence["kib_per_packet"] < 64 and 0 < evidence["kib_per_case"] < 64
    assert f"--seed 0 --cases {evidence['cases']['last'] + 1} " in evidence["rerun"]
    top = evidence["suspects"][0]
    assert top["kind"] == "VRCI legal" and 48 < top["kib_per_packet"] < 80, evidence["suspects"]
    # Trial: a leak per packet of an unknown ID (TS-0006 5.1.5: to be ignored) was said to be some
    # KiB per case, with nothing to say which
    evidence = _memory_evidence(tmp_path, "plain-leak-unknown", rare)
    top = evidence["suspects"][0]
    assert top["kind"] == "unknown_id" and 48 < top["kib_per_packet"] < 80, evidence["suspects"]
    assert "it goes with unknown_id packets" in evidence["detail"]
    assert "memory" not in clean["counts"] and clean["memory"]["oracle"] == "on"
    assert clean["memory"]["rss_kib"] > 0


def _memory_evidence(tmp_path: Path, name: str, summary: dict) -> dict:
    [finding] = [f for f in summary["findings"] if f["oracle"] == "memory"]
    assert summary["counts"] == {"memory": 1} and finding["rerun"].startswith("vm110 fuzz --target 127.0.0.1:")
    evidence = json.loads((tmp_path / f"out-controller-{name}/{finding['file']}").read_text())["memory"]
    assert evidence["kind"] == "growth" and evidence["rss_kib"] >= evidence["warmup_kib"] + MIB
    return evidence


def test_the_hard_limit_is_a_finding_that_replay_refuses(tmp_path, programs):  # noqa: F811
    """A correct controller over --target-memory from its start (its first sample came before the
    first case, whose triggers are forgotten: the oracle, which fires once, must not be)."""
    exe = programs("plain-correct")
    rss = _vm_rss_mib(exe)
    if rss < 1.2:
        pytest.skip(f"the controller's RSS is {rss:.2f} MiB: no --target-memory (1 MiB at least) below it")
    out = tmp_path / "out"
    result, summary = fuzz(out, exe, "--target-memory", "1", "--max-findings", "1", "--duration", "30")
    assert result.returncode == 1, result.stdout + result.stderr
    [bucket] = summary["buckets"]
    assert bucket["headline"].startswith("memory: RSS ") and "above --target-memory 1 MiB" in bucket["headline"]
    assert bucket["headline"] in result.stdout and "replay one" not in result.stdout
    assert "rerun them with vm110 fuzz --target" in result.stdout and "--target-memory 1 " in result.stdout
    evidence = json.loads((out / bucket["file"]).read_text())["memory"]
    assert evidence["kind"] == "limit" and evidence["limit_kib"] == MIB and evidence["rss_kib"] > MIB
    # Its rerun is a command line the fuzzer takes (--cases 1 at least, though it came before any case)
    assert int(evidence["rerun"].split(" --cases ")[1].split()[0]) >= 1
    again = subprocess.run([sys.executable, "-m", "vm110", "fuzz", "--replay", str(out / bucket["file"]),
                            "--target-cmd", str(exe)], capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "is a memory finding" in again.stderr and "--seed 0 --cases " in again.stderr


def _vm_rss_mib(exe: Path) -> float:
    """The controller's VmRSS as the kernel gives it, once it is listening."""
    rx, listen = free_ports(2)
    with subprocess.Popen([str(exe), str(rx), str(listen)], stderr=subprocess.PIPE, text=True) as proc:
        try:
            assert proc.stderr is not None and "listening" in proc.stderr.readline()
            status = Path(f"/proc/{proc.pid}/status").read_text()
            return int(status.split("VmRSS:")[1].split()[0]) / 1024
        finally:
            proc.terminate()


def test_the_status_line_shows_the_rss_and_the_summary_why_the_oracle_is_off(tmp_path, capsys):
    from vm110.commands.fuzz import _memory_line, _StatusLine
    _StatusLine()({"cases": 3, "rate": 1.0, "rate_now": 1.0, "findings": 0, "triggers": 0, "left_s": None, "rss_kib": 12 * MIB})
    assert "RSS 12.0 MiB" in capsys.readouterr().err
    rx, listen = free_ports(2)
    runner = Runner(RunConfig(settings=Settings(("127.0.0.1", rx), ("127.0.0.1", listen)), out=tmp_path / "out"))
    try:
        memory = runner.summary()["memory"]
    finally:
        runner.session.close()
    assert memory["oracle"] == "off" and runner.session.memory is None
    assert _memory_line(memory) == "memory oracle off: no --target-cmd: only a controller the fuzzer starts is measured"
