"""The incremental analysis: however the packets are cut into batches, the report is the same
(restart candidates, scope warm-up, new-port restarts and command events cross batch borders)."""
from __future__ import annotations

import itertools
import json
import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from vm110 import constants as C
from vm110.analysis import engine, serials, timing
from vm110.analysis.incremental import Analysis
from vm110.analysis.periodic import Floats
from vm110.analysis.report import Options, build

CAPTURES = sorted(p for p in (Path(__file__).resolve().parent.parent / "captures").iterdir()
                  if p.suffix in (".pcap", ".pcapng"))


class _Recorder:
    """Stands in for the Analysis: keeps what the engine feeds it."""

    def __init__(self, opt) -> None:
        self.opt, self.batches, self.sources = opt, [], {}

    def feed(self, rec, sources) -> None:
        self.batches.append(rec.copy())
        self.sources = sources


def _records(path, monkeypatch):
    monkeypatch.setattr(engine, "Analysis", _Recorder)
    got = engine.FastEngine().collect(str(path), Options())
    rec = got.analysis
    return got, np.concatenate(rec.batches) if rec.batches else None, rec.sources


def _report(got, rec, sources, cuts) -> str:
    analysis = Analysis(Options())
    for a, b in itertools.pairwise(cuts):
        analysis.feed(rec[a:b], sources)
    got.analysis = analysis
    return json.dumps(build(got), sort_keys=True)


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_batches_of_any_size_give_the_same_report(path, monkeypatch):
    got, rec, sources = _records(path, monkeypatch)
    if rec is None:
        pytest.skip("no legal packets")
    whole = _report(got, rec, sources, [0, len(rec)])
    rng = random.Random(len(rec))
    for size in (1, 7, 500):
        if size == 1 and len(rec) > 5000:
            continue
        assert _report(got, rec, sources, list(range(0, len(rec), size)) + [len(rec)]) == whole, size
    cuts = sorted({0, len(rec), *(rng.randrange(len(rec)) for _ in range(40))})
    assert _report(got, rec, sources, cuts) == whole


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-3, 40), min_size=1, max_size=200), st.integers(0, 2**32))
def test_a_counter_fed_in_pieces_equals_one_pass(steps, seed):
    rng = random.Random(seed)
    seq, times, s, t = [], [], rng.randrange(serials.MOD), 0.0
    for step in steps:
        t += rng.choice([0.001, 0.01, 0.5, 1.5])
        if step < 0 and seq:
            seq.append(seq[rng.randrange(len(seq))])
        elif step > 30:
            s = rng.randrange(serials.MOD)                  # a jump: a restart candidate
            seq.append(s)
        else:
            s = (s + max(step, 1)) % serials.MOD
            seq.append(s)
        times.append(t)
    want = serials.classify(seq, times)
    counter = serials.Counter()
    cuts = sorted({0, len(seq), *(rng.randrange(len(seq)) for _ in range(5))})
    held = 0
    for _a, b in itertools.pairwise(cuts):
        done = counter.feed(seq[held:b], times[held:b], list(range(held, b)), final=b == len(seq))
        held += done
    got = counter.result()
    assert held == len(seq)
    for name in ("received", "duplicates", "out_of_order", "wraps", "lost_serials", "duplicate_serials",
                 "out_of_order_serials", "gaps", "gap_late", "duplicates_located", "out_of_order_located", "restarts",
                 "last"):
        assert getattr(got, name) == getattr(want, name), name


@pytest.mark.parametrize("before", [None, 0.5])
def test_floats_intervals_across_blocks(monkeypatch, before):
    monkeypatch.setattr(Floats, "BLOCK", 4)
    times = np.cumsum(np.random.default_rng(1).random(23)) + 1.7e9
    f = Floats()
    for a in range(0, len(times), 5):
        f.extend(times[a:a + 5])
    full = times if before is None else np.concatenate(([1.7e9 + before], times))
    assert np.array_equal(f.intervals_ms(None if before is None else 1.7e9 + before), timing.intervals_ms(full))
    assert f.last() == times[-1] and f[9] == times[9] and len(f) == len(times)


def test_a_stream_of_a_few_packets_holds_a_few_values_not_a_block(monkeypatch):
    """Every periodic stream took a whole block (65,536 values: 512 KiB of address space, a page or
    more of it touched) at its first packet: a hostile capture of 20,000 senders heard once took
    10 GiB of address space and 80 MiB more memory. The last block now grows as it fills."""
    few = Floats()
    few.extend(np.array([1.7e9, 1.7e9 + 0.125]))
    assert sum(b.nbytes for b in few.blocks) <= Floats.FIRST * 8
    monkeypatch.setattr(Floats, "BLOCK", 100)       # (growth across a block's end: 16, 32, 64, 100)
    times = np.cumsum(np.random.default_rng(2).random(437)) + 1.7e9
    f = Floats()
    for a, b in zip([0, 1, 3, 20, 21, 99, 250], [1, 3, 20, 21, 99, 250, 437]):
        f.extend(times[a:b])
        assert [f[i] for i in range(b)] == times[:b].tolist() and f.last() == times[b - 1]
    assert [len(block) for block in f.blocks] == [100, 100, 100, 100, 64]
    assert np.array_equal(f.intervals_ms(), timing.intervals_ms(times))


def test_copies_of_an_undecided_candidate_across_many_batches(tmp_path, monkeypatch):
    """A restart candidate repeated for thousands of packets stays undecided over many batches;
    it is decided once (not re-judged per batch), as in one pass."""
    import time
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for i in range(20):
        tr.add(i * 0.125, vrpi(100 + i))
    copy = vrpi(40000)
    for k in range(6000):
        tr.add(2.5 + k * 0.3, copy)                     # a copy every 300 ms: duplicates and candidates
    tr.add(2.5 + 6000 * 0.3, vrpi(40001))             # confirms the first: a restart
    tr.write(tmp_path / "copies.pcap")
    got, rec, sources = _records(tmp_path / "copies.pcap", monkeypatch)
    whole = _report(got, rec, sources, [0, len(rec)])
    start = time.process_time()
    assert _report(got, rec, sources, list(range(0, len(rec), 20)) + [len(rec)]) == whole
    assert time.process_time() - start < 20
    serial = json.loads(whole)["senders"][0]["serial"]
    assert serial["restart_events"][0]["to"] == 40000 and serial["duplicates"] > 4000


def test_many_senders_cost_little_each(tmp_path, monkeypatch):
    """Every source port is a sender: a capture of one packet per port keeps a few entries per
    counter, not the 65536 times of a full one."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for k in range(3000):
        tr.add(k * 0.001, vrpi(k % 7), sport=10000 + k)
    tr.write(tmp_path / "ports.pcap")
    _got, rec, sources = _records(tmp_path / "ports.pcap", monkeypatch)
    analysis = Analysis(Options())
    analysis.feed(rec, sources)
    analysis.finish()
    counters = [c for s in analysis.senders.values() for c in s.counters.values()]
    assert len(counters) == 3000 and all(c.accepted_at.all is None and c.gap_at.all is None for c in counters)


def _held_rows(monkeypatch) -> list[int]:
    """The rows the senders hold undecided after each dispatch, from now on."""
    from vm110.analysis import sender
    held: list[int] = []
    real = sender.Sender._dispatch

    def watch(self, rows, events, final):
        real(self, rows, events, final)
        held.append(sum(len(rows_) for rows_ in self.pending.values()))
    monkeypatch.setattr(sender.Sender, "_dispatch", watch)
    return held


def test_copies_within_the_window_are_not_held(tmp_path, monkeypatch):
    """Copies of an undecided candidate within its duplicate window are judged at once in a
    stream too: the same report as one pass, and nothing of them waits with the candidate."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for i in range(96):                                  # 12 s: past the scope's warm-up
        tr.add(i * 0.125, vrpi(500 + i))
    for k in range(3001):
        tr.add(15.0 + k * 0.0002, vrpi(0))               # the candidate and 3000 copies, 0.6 s
    tr.add(15.7, vrpi(1))                                # confirms it
    tr.write(tmp_path / "flood.pcap")
    got, rec, sources = _records(tmp_path / "flood.pcap", monkeypatch)
    whole = _report(got, rec, sources, [0, len(rec)])
    held = _held_rows(monkeypatch)
    assert _report(got, rec, sources, list(range(0, len(rec), 50)) + [len(rec)]) == whole
    assert max(held) == 1                                # the candidate alone
    assert json.loads(whole)["senders"][0]["serial"]["duplicates"] == 3000


def test_a_sender_stuck_on_one_serial_keeps_one_row(tmp_path, monkeypatch):
    """A device stuck on one serial (a monitor runs for days): the candidate's copies after the
    duplicate window are duplicates too (rules.md rule 5), judged at once; they were kept, one
    row each, for as long as the candidate stayed undecided."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for i in range(96):
        tr.add(i * 0.125, vrpi(500 + i))
    for k in range(2000):
        tr.add(15.0 + k * 0.125, vrpi(0))               # the candidate, then copies for 250 s
    tr.write(tmp_path / "stuck.pcap")
    got, rec, sources = _records(tmp_path / "stuck.pcap", monkeypatch)
    held = _held_rows(monkeypatch)
    report = json.loads(_report(got, rec, sources, list(range(0, len(rec), 50)) + [len(rec)]))
    assert max(held) == 1
    serial = report["senders"][0]["serial"]
    assert (serial["duplicates"], serial["out_of_order"], serial["restarts"]) == (1999, 1, 0)


def _controller(tr, seconds: float, vrcos: dict[float, int]) -> None:
    """A controller sending VRPO every 100 ms and, at the given times, VRCOs never acknowledged."""
    from test_analysis_craft import CTRL, payload
    from vm110.layers import VRCO, VRPO
    serial = 0
    for i in range(round(seconds * 10)):
        tr.add(0.01 + i * 0.1, payload(VRPO, serial, packet_number=0, periodic_data=b"x" * 10), src=CTRL,
               sport=C.OUTPUT_PORT)
        serial += 1
        cid = vrcos.get(round(0.02 + i * 0.1, 2))
        if cid is not None:
            tr.add(0.02 + i * 0.1, payload(VRCO, serial, command_id=cid), src=CTRL, sport=C.OUTPUT_PORT)
            serial += 1
    tr.frames.sort(key=lambda f: f[0])


def _monitor_tells_at_the_limit(tmp_path, tr, command_id: int, *options: str) -> dict:
    """`vm110 monitor --read` tells the VRCO `command_id` failed within 1.5 s of its limit; its
    final report."""
    from vm110.cli import main
    tr.write(tmp_path / "capture.pcap")
    lines, report = tmp_path / "live.jsonl", tmp_path / "report.json"
    assert main(["monitor", "--read", str(tmp_path / "capture.pcap"), "--idle", "0", "--no-dashboard", "--quiet",
                 "--json-lines", str(lines), "--json", str(report), "--crc", "mpeg2", "--crc-order", "little",
                 *options]) == 0
    [failed] = [o for o in map(json.loads, lines.read_text().splitlines())
                if o["type"] == "finding" and o["rule"] == "failed" and o["item"]["command_id"] == command_id]
    give_up = Options().vrco_give_up_ms / 1000
    assert give_up <= failed["at"] - failed["item"]["time"] <= give_up + 1.5
    return json.loads(report.read_text())


def _bu_serial(report: dict) -> dict:
    [bu] = [s["serial"] for s in report["senders"] if s["id"].endswith(":5825 origin 0x0101")]
    return bu


def test_a_sender_heard_once_holds_nothing_back(tmp_path):
    """A sender heard once (a stray packet, a controller that crashed within seconds) never ended
    its serial-scope choice, which only its own next packet ended: every command event after its
    packets waited for the end of the input, so `vm110 monitor` told a command that failed at
    +15 s at the end of the capture (+39.9 s). The choice ends once the analysis clock passes its
    look (10 s after the stray's second packet type; the controller's, 10 s after its first VRCO)."""
    from test_analysis_craft import BU_ORIGIN, Traffic, payload, vrpi
    from vm110.layers import VRCI
    tr = Traffic()
    tr.add(0.05, vrpi(7), sport=40000)                   # heard once, never again
    tr.add(0.06, payload(VRCI, 8, BU_ORIGIN, command_id=3), sport=40000)
    for i in range(320):
        tr.add(i * 0.125, vrpi(100 + i))
    _controller(tr, 40, {0.02: 8, 12.02: 9})
    _monitor_tells_at_the_limit(tmp_path, tr, 9)


def test_a_sender_silent_after_a_restart_candidate_holds_nothing_back(tmp_path):
    """A base unit whose last packet is a restart candidate (a serial no rule explains), silent
    for good after it: the candidate waited for the counter's next packet, and every command event
    after it, any sender's, with it, so `vm110 monitor` told the controller's VRCO that failed at
    +14 s at the end of the input (+40 s), and a monitor running for days never. They wait for it
    10 s at most on the analysis clock (rules.md rule 5); it is out of order at the end."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for i in range(8):
        tr.add(i * 0.125, vrpi(100 + i))
    tr.add(1.0, vrpi(5000))                              # the candidate, then silence for good
    _controller(tr, 40, {0.02: 8, 12.02: 9})
    bu = _bu_serial(_monitor_tells_at_the_limit(tmp_path, tr, 9))
    assert (bu["out_of_order"], bu["restarts"]) == (1, 0)                # (the candidate, undecided to the end)


def test_a_sender_stuck_on_one_serial_holds_no_failed_command_to_the_end(tmp_path):
    """A base unit stuck on one serial: its copy 1 s after the first (past the duplicate window) is
    a restart candidate, and every later copy a duplicate of it (rules.md rule 5), so the
    candidate waits to the end. Its command events, any sender's, waited with it: `vm110 monitor`
    told the controller's VRCO that failed at +27 s at the end of the input (+60 s). They wait
    10 s at most (until +11 s), so it is told at its limit."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for i in range(480):
        tr.add(i * 0.125, vrpi(777))
    _controller(tr, 60, {25.02: 3})
    bu = _bu_serial(_monitor_tells_at_the_limit(tmp_path, tr, 3, "--serial-scope", "sender"))
    assert (bu["out_of_order"], bu["duplicates"], bu["restarts"]) == (1, 478, 0)


def test_a_candidate_decided_after_the_scope_look_however_the_batches_are_cut(tmp_path, monkeypatch):
    """A per-type base unit whose VRCI counter restarts just before its scope look (10.56 s; the
    look at 11.06 s, which chooses `type`) and is confirmed after it (12.06 s): one restart, the
    same however the batches are cut (the candidate is undecided when the look's rows are
    judged, its decider in the same batch or a later one)."""
    from test_analysis_craft import BU_ORIGIN, Traffic, payload, vrpi
    from vm110.layers import VRCI
    tr = Traffic()
    for k in range(240):                                 # 30 s of VRPI, serials of their own
        tr.add(k * 0.125, vrpi(k))
    for n, (t, serial) in enumerate([*((1.0 + k * 0.5, k) for k in range(18)), (10.5, 0), (12.0, 1), (14.0, 2)]):
        tr.add(t + 0.06, payload(VRCI, serial, BU_ORIGIN, command_id=n + 1))
    tr.frames.sort(key=lambda f: f[0])
    tr.write(tmp_path / "restart.pcap")
    got, rec, sources = _records(tmp_path / "restart.pcap", monkeypatch)
    whole = _report(got, rec, sources, [0, len(rec)])
    serial = json.loads(whole)["senders"][0]["serial"]
    assert (serial["scope"], serial["out_of_order"], serial["restarts"]) == ("type", 0, 1)
    for size in (1, 7, 100):
        assert _report(got, rec, sources, list(range(0, len(rec), size)) + [len(rec)]) == whole, size


def test_the_serial_scope_is_chosen_alike_however_the_batches_are_cut(tmp_path, monkeypatch):
    """A base unit counting each packet type on its own, with one VRCI in its first 10 s: too few
    anomalies there to tell the scopes apart. The warm-up took the rows of the batch that reached
    10 s: one batch (analyze of a small file) chose per-type counters on all 20 s, batches of 20
    (as the monitor feeds) chose one counter on 10 s and found the VRPIs out of order. A look that
    cannot tell is made again on twice the time, on the same rows whatever the batches."""
    from test_analysis_craft import Traffic, payload, vrpi
    from vm110.layers import VRCI
    tr = Traffic()
    for k in range(160):                                  # 20 s of VRPI, serials of their own
        tr.add(k * 0.125, vrpi(k))
    for n, t in enumerate((5.0, 12.0, 14.0, 16.0, 18.0)):  # and VRCIs counted on their own
        tr.add(t + 0.06, payload(VRCI, n, 0x0101, command_id=n + 1))
    tr.frames.sort(key=lambda f: f[0])
    tr.write(tmp_path / "types.pcap")
    got, rec, sources = _records(tmp_path / "types.pcap", monkeypatch)
    whole = _report(got, rec, sources, [0, len(rec)])
    assert json.loads(whole)["senders"][0]["serial"]["scope"] == "type"
    assert _report(got, rec, sources, list(range(0, len(rec), 20)) + [len(rec)]) == whole


def test_a_sender_on_a_new_port_after_every_pause_keeps_its_host_short(tmp_path, monkeypatch):
    """Trial: a base unit that comes back on a new source port after every pause (a device opening
    a port per burst, for days) made each new sender scan every sender of its host ever heard, taken
    over or not: the monitor's time per sender grew with their number (10 000 ports: 136 s, twice
    5 000's). A sender taken over is never linked again (rules.md): it leaves its host's list."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    for k in range(300):
        tr.add(k * 0.3, vrpi(k), sport=10000 + k)        # silent 300 ms >= 250 ms: a restart each
    tr.write(tmp_path / "ports.pcap")
    got, rec, sources = _records(tmp_path / "ports.pcap", monkeypatch)
    analysis = Analysis(Options())
    analysis.feed(rec, sources)
    assert [len(same) for same in analysis.hosts.values()] == [1]
    got.analysis = analysis
    assert build(got)["totals"]["restarts"] == 299
