"""Serial classification, jitter and bursts against plain reference implementations, CRC and
serial-scope auto-detection, wraps, and the robustness cases of issue 6 through `analyze`."""
from __future__ import annotations

import itertools
import math
import random
import struct
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from test_analysis_craft import BU_ORIGIN, T0, Traffic, payload, vrpi
from vm110 import constants as C
from vm110.analysis import analyze, bursts, serials, timing
from vm110.analysis.report import Options
from vm110.layers import VRAO, VRCI, VRPI, VRPO

MOD = C.SERIAL_MODULUS


def reference_serials(seq: list) -> dict:
    """Unwrapping version of interpretation.md's rules, written independently."""
    high, seen, lost = None, set(), set()
    dup = ooo = wraps = 0
    for s in seq:
        if high is None:
            high = s
            seen.add(s)
            continue
        d = (s - high) % MOD
        if 0 < d < MOD // 2:
            new = high + d
            lost.update(range(high + 1, new))
            wraps += new // MOD - high // MOD
            high = new
            seen.add(new)
        else:
            u = high - (MOD - d) % MOD
            if d == 0 or u in seen:
                dup += 1
            else:
                ooo += 1
                lost.discard(u)
                seen.add(u)
    return {"lost": len(lost), "duplicates": dup, "out_of_order": ooo, "wraps": wraps}


@given(st.integers(0, MOD - 1), st.lists(st.integers(-3, 6), max_size=300), st.integers(0, 2**32))
def test_serials_match_the_reference(start, steps, seed):
    seq, s = [start], start
    rng = random.Random(seed)
    for step in steps:
        if step < 0 and len(seq) > 1:
            seq.append(seq[rng.randrange(len(seq))])          # a repeat or a late one
        else:
            s = (s + max(step, 1)) % MOD
            seq.append(s)
    # 1 ms apart: every repeat lies within the duplicate window, every late packet fills a gap
    # opened within it, and no jump is too large for the time (docs/rules.md).
    got = serials.classify(seq, [i / 1000 for i in range(len(seq))])
    ref = reference_serials(seq)
    assert {k: getattr(got, k) for k in ref} == ref


def test_serial_wrap_and_loss_across_it():
    got = serials.classify([65533, 65534, 65535, 0, 1], [0.0, 0.1, 0.2, 0.3, 0.4])
    assert (got.lost, got.wraps, got.gaps) == (0, 1, [])
    got = serials.classify([65534, 1, 0, 2], [0.0, 0.1, 0.2, 0.3])
    assert (got.gaps, got.lost_serials, got.out_of_order_serials, got.wraps) == ([(65534, 2, 0.1, 1)], [65535], [0], 1)


def test_late_serials_are_counted_on_the_gap_they_fill():
    """A late packet counts on the gap it fills (by the packet that opened it), whichever gap that
    is: later gaps may be open already."""
    seq = [0, 1, 4, 5, 8, 2, 9, 10, 12, 11]   # gaps 2-3 (then 2 late), 6-7 (lost), 11 (then late)
    got = serials.classify(seq, [i / 1000 for i in range(len(seq))])
    assert got.gaps == [(1, 2, 0.002, 2), (5, 2, 0.004, 4), (10, 1, 0.008, 8)]
    assert got.gap_late == {2: 1, 8: 1} and sorted(got.lost_serials) == [3, 6, 7]


def test_lost_items_are_the_gaps_still_missing_serials(tmp_path):
    """The `lost` finding's items add up to its count: a gap whose serials all came later is no
    item (those packets are out of order), one partly filled says how many came late."""
    traffic = Traffic()
    for i, s in enumerate([0, 1, 4, 5, 8, 2, 9, 10, 12, 11, 13]):
        traffic.add(i * 0.125, vrpi(s))
    traffic.write(tmp_path / "late.pcap")
    report = analyze(str(tmp_path / "late.pcap"))
    [lost] = [f for f in report["verdict"]["findings"] if f["rule"] == "lost"]
    items = [{k: i[k] for k in ("frame", "after", "count", "late") if k in i} for i in lost["items"]]
    assert items == [{"frame": 3, "after": 1, "count": 2, "late": 1}, {"frame": 5, "after": 5, "count": 2}]
    assert lost["count"] == report["totals"]["lost"] == 3 == sum(i["count"] - i.get("late", 0) for i in lost["items"])
    assert report["totals"]["out_of_order"] == 2


def test_a_gap_left_behind_a_whole_cycle_stays_lost():
    seq = [0, 2] + list(range(3, MOD)) + [0, 1, 2]        # 1 missing; 65536 later, 1 comes round again
    got = serials.classify(seq, [i / 1000 for i in range(len(seq))])
    assert (got.lost_serials, got.out_of_order, got.duplicates) == ([1], 0, 0)


def reference_jitter(times: list, period: float) -> list:
    j, out = 0.0, []
    for a, b in itertools.pairwise(times):
        delta = round((b - a) * 1e6) / 1000.0           # intervals to the microsecond
        k = max(1, math.floor(delta / period + 0.5))
        j = j + (abs(delta - k * period) - j) / 16
        out.append(j)
    return out


def test_jitter_block_recurrence_equals_the_plain_loop():
    rng = random.Random(5)
    times, t = [], 1.7e9
    for _ in range(5000):
        t = round(t + rng.choice([0.125, 0.125, 0.25, 0.6]) + rng.gauss(0, 0.004), 6)   # captures: us
        times.append(t)
    want = reference_jitter(times, 125.0)
    got = timing.jitter_of_intervals(timing.intervals_ms(times), 125.0)
    assert max(abs(a - b) for a, b in zip(got, want)) < 1e-6
    assert timing.jitter_summary(timing.intervals_ms(times), 125.0)["final"] == pytest.approx(want[-1], abs=1e-9)


def test_percentiles_are_linear_between_ranks():
    assert timing.summary([1.0, 2.0, 3.0, 4.0]) == {"min": 1.0, "mean": 2.5, "p50": 2.5, "p95": 3.85,
                                                    "p99": pytest.approx(3.97), "p999": pytest.approx(3.997),
                                                    "max": 4.0}


def burst_count(times: list, numbers: list, sizes: list, data_size: int = 0, cuts: Sequence[int] = ()) -> tuple:
    """(complete, positions of the first packet of each incomplete burst, of every burst) of one
    sender's VRPO packets, fed to the incremental burst assembly at once (or in batches that end
    before the positions `cuts`)."""
    from vm110.analysis.periodic import Floats
    packets = Floats()
    b = bursts.Bursts(packets, C.VRPO_BURST_GAP_MS, 0, data_size)
    bounds = [0, *sorted(set(cuts) - {0, len(times)}), len(times)]
    for lo, hi in itertools.pairwise(bounds):
        packets.extend(np.asarray(times[lo:hi], dtype=np.float64))
        b.feed(np.asarray(times[lo:hi], dtype=np.float64), np.asarray(numbers[lo:hi]), np.asarray(sizes[lo:hi]),
               range(lo, hi), True)
    b.finish()
    return b.complete, sorted(w for w, _ in b.incomplete), np.array(b.firsts, dtype=np.int64)


def test_bursts():
    full, tail = 2 + C.VRPO_MAX_DATA, 2 + 100
    times = [0.0, 0.001, 0.002, 0.1, 0.101, 0.2, 0.201, 0.202, 0.3]
    numbers = [0, 1, 2, 0, 2, 1, 0, 2, 0]
    sizes = [full, full, tail, full, tail, full, full, tail, tail]
    complete, incomplete, starts = burst_count(times, numbers, sizes)
    assert (complete, incomplete, list(starts)) == (3, [3], [0, 3, 5, 8])   # 0.2: reordered, still whole
    assert burst_count([0.0, 0.1], [0, 1], [tail, tail])[:2] == (1, [1])
    # interpretation.md: "a burst ends with a packet of fewer than 488 bytes": a complete burst takes
    # no more packets, even closer than the burst gap.
    def judged(*args: list) -> tuple:
        complete, incomplete, starts = burst_count(*args)
        return complete, incomplete, list(starts)
    assert judged([0.0, 0.01], [0, 0], [tail, tail]) == (2, [], [0, 1])
    assert judged([0.0, 0.01], [0, 1], [2 + 300, tail]) == (1, [1], [0, 1])
    # reordered and complete, then a part whose first was lost
    assert judged([0.0, 0.001, 0.002], [1, 0, 1], [tail, full, tail]) == (1, [2], [0, 2])
    assert burst_count([0.0, 0.001], [0, 1], [full, full], data_size=2 * C.VRPO_MAX_DATA)[:2] == (1, [])


def test_bursts_of_full_packets_infer_the_data_size():
    """docs/rules.md, "VRPO bursts": with the data size inferred (0), a burst of 488-byte packets is
    complete when the sender sent no shorter packet and no longer complete such burst before it;
    a packet that restarts the numbering begins the next burst even within the gap."""
    full, tail = 2 + C.VRPO_MAX_DATA, 2 + 100

    def judged(times: list, numbers: list, sizes: list) -> tuple:
        complete, incomplete, starts = burst_count(times, numbers, sizes)
        return complete, incomplete, list(starts)
    # 976 bytes a cycle; the third lost its second packet
    assert judged([0.0, 0.001, 0.1, 0.101, 0.2, 0.3, 0.301], [0, 1, 0, 1, 0, 0, 1], [full] * 7) == \
        (3, [4], [0, 2, 4, 5])
    # 488 bytes every 15 ms: the numbering restarts within the gap
    assert judged([0.0, 0.015, 0.03], [0, 0, 0], [full] * 3) == (3, [], [0, 1, 2])
    # 976 bytes every 15 ms: each burst over when the next restarts it
    assert judged([0.0, 0.001, 0.015, 0.016, 0.03], [0, 1, 0, 1, 0], [full] * 5) == (2, [4], [0, 2, 4])
    # a sender that has split with a short last packet: a lone full packet lost its tail
    assert judged([0.0, 0.001, 0.1], [0, 1, 0], [full, tail, full]) == (1, [2], [0, 2])
    # the first burst's lost tail is not seen; later bursts set the size
    assert judged([0.0, 0.1, 0.101, 0.2], [0, 0, 1, 0], [full] * 4) == (2, [3], [0, 1, 3])
    # the inferred size reached: a packet that does not go on from it begins the next burst (its
    # parts out of order, 15 ms after); one that goes on shows the size was inferred too small
    assert judged([0.0, 0.001, 0.1, 0.101, 0.115, 0.116], [0, 1, 0, 1, 1, 0], [full] * 6) == (3, [], [0, 2, 4])
    assert judged([0.0, 0.1, 0.101], [0, 0, 1], [full] * 3) == (2, [], [0, 1])
    # exactly the gap apart on an epoch clock (0.01999998 s in floats): two bursts, as in the dissector
    assert judged([1_700_000_000.05, 1_700_000_000.07], [0, 1], [full] * 2) == (1, [1], [0, 1])
    # a configured size judges alone: 976 configured, 488 alone is incomplete
    assert burst_count([0.0, 0.1], [0, 0], [full, full], data_size=2 * C.VRPO_MAX_DATA)[:2] == (0, [0, 1])


@given(st.lists(st.tuples(st.sampled_from([0.0005, 0.005, 0.015, 0.05, 0.1]), st.integers(0, 2), st.booleans()),
                max_size=40),
       st.lists(st.integers(0, 40), max_size=6), st.sampled_from([0, 2 * C.VRPO_MAX_DATA]))
@settings(max_examples=300, deadline=None)
def test_bursts_judge_alike_in_any_batches(steps, cuts, data_size):
    """Fed in any batches (bursts of one packet judged a batch at a time), the bursts are those fed
    a packet at a time (every packet through `Open`)."""
    times = list(np.cumsum([s for s, _, _ in steps]))
    numbers = [n for _, n, _ in steps]
    sizes = [2 + (C.VRPO_MAX_DATA if f else 100) for _, _, f in steps]
    one = burst_count(times, numbers, sizes, data_size, range(len(times)))
    got = burst_count(times, numbers, sizes, data_size, cuts)
    assert got[:2] == one[:2] and list(got[2]) == list(one[2])


def test_crc_auto_finds_another_variant_and_byte_order(tmp_path):
    tr = Traffic()
    for i in range(20):
        tr.add(i * 0.125, payload(VRPI, i, BU_ORIGIN, variant="bzip2", order="big", bu_state=C.BuState.ARMED))
    tr.write(tmp_path / "b.pcap")
    report = analyze(str(tmp_path / "b.pcap"))
    assert (report["crc"]["variant"], report["crc"]["byte_order"], report["crc"]["valid"]) == ("bzip2", "big", 20)
    assert report["illegal"]["total"] == 0 and report["senders"][0]["serial"]["received"] == 20
    forced = analyze(str(tmp_path / "b.pcap"), crc="mpeg2", crc_order="little")
    assert forced["crc"]["invalid"] == 20 and forced["illegal"]["by_reason"] == {"bad_crc": 20}


def test_serial_scope_auto_detects_per_type_counters(tmp_path):
    tr = Traffic()
    for i in range(40):
        tr.add(i * 0.125, vrpi(i))
        if i % 4 == 1:
            tr.add(i * 0.125 + 0.01, payload(VRCI, i // 4, BU_ORIGIN, command_id=i // 4))   # own counter
    tr.write(tmp_path / "t.pcap")
    report = analyze(str(tmp_path / "t.pcap"))
    ser = report["senders"][0]["serial"]
    assert (ser["scope"], ser["lost"], ser["out_of_order"], ser["duplicates"]) == ("type", 0, 0, 0)
    forced = analyze(str(tmp_path / "t.pcap"), options=Options(serial_scope="sender"))["senders"][0]["serial"]
    # One counter: VRCI k repeats VRPI k's serial 0.375 k + 0.135 s later: a duplicate within the
    # 1000 ms window (k <= 2), an unconfirmed restart candidate (out of order) after it.
    assert forced["scope"] == "sender" and (forced["duplicates"], forced["out_of_order"], forced["restarts"]) == (3, 7, 0)
    # Why, in the report's words: the anomalies of each reading (rules.md), the one counter's
    # those of the forced report (5 s of packets: the end of the capture decided on all 50).
    # The choice starts at the first VRCI (frame 3): its 48 packets from there, by hand, with one
    # counter started afresh at it: VRPI 2 opens a gap, VRCI 1 comes late into it, VRCI 2 is a
    # duplicate of VRPI 2 (0.885 s), VRCI 3 ... 9 unconfirmed candidates: 10 anomalies.
    assert ser["scope_reason"] == ("auto, on all its 48 packets from its first VRCI (frame 3): "
                                   "10 anomalies with one counter, 0 with one per type")
    assert forced["scope_reason"] == "set by --serial-scope"


def test_a_per_type_sender_first_heard_with_one_type_is_counted_per_type(tmp_path):
    """A base unit numbering per type that sends VRPI alone for its first 15 s, then commands:
    the look at 10 s saw VRPI only and took one counter for good (trial), so each command showed
    as out of order (and a VRAI could pass for a duplicate: a false failed command). One type has
    one counter under either scope: the choice starts at the first VRCI (frame 123), and the
    report says so."""
    from vm110.analysis import report_html, summary
    tr = Traffic()
    for i in range(160):
        tr.add(i * 0.125, vrpi(i))
        if i >= 120 and i % 8 == 1:
            tr.add(i * 0.125 + 0.01, payload(VRCI, i // 8, BU_ORIGIN, command_id=i // 8))   # own counter
    tr.write(tmp_path / "t.pcap")
    report = analyze(str(tmp_path / "t.pcap"))
    ser = report["senders"][0]["serial"]
    # From frame 123 on (5 VRCI, VRPI 122 ... 159), one counter started afresh at VRCI 15: a
    # restart at VRPI 122, then VRCI 16 ... 19 each an unconfirmed candidate; per type none. The
    # capture ends before the look at 10 s: the end decides.
    why = "auto, on all its 43 packets from its first VRCI (frame 123): 5 anomalies with one counter, 0 with one per type"
    assert (ser["scope"], ser["scope_reason"]) == ("type", why)
    assert (ser["out_of_order"], ser["duplicates"], ser["lost"], ser["restarts"]) == (0, 0, 0, 0)
    assert f"(serial scope type: {why})" in summary.render(report)
    assert f"type ({why})" in report_html.render([report])
    vrpi_only = Traffic()
    for i in range(40):
        vrpi_only.add(i * 0.125, vrpi(i))
    vrpi_only.write(tmp_path / "one.pcap")
    ser = analyze(str(tmp_path / "one.pcap"))["senders"][0]["serial"]
    assert (ser["scope"], ser["scope_reason"]) == ("sender", "auto: VRPI only, one counter under either scope")


def _serial_counts(ser: dict) -> tuple:
    return ser["scope"], ser["lost"], ser["duplicates"], ser["out_of_order"], ser["restarts"]


def test_auto_finds_a_per_type_base_unit_on_a_lossy_mirror(tmp_path):
    """Trial: a base unit numbering per type (TS-0006 read as interpretation.md allows), VRPI
    alone for its first 10 s, then a command every 2 s sent three times (its acks lost), seen
    through a mirror port that loses, repeats and reorders: per-type counters, and the real
    losses, copies and the late packet, nothing more."""
    from vm110 import encode
    lost_vrpi, lost_vrci = {100, 101, 102, 150}, {13}            # a burst of 3, then one; a retry
    copies, swapped = {("VRPI", 90), ("VRPI", 120), ("VRCI", 6)}, 180   # VRPI 181 comes before 180
    sent = [(0.125 * k, "VRPI", k) for k in range(240)]
    sent += [(10.01 + 2 * j + 0.1 * r, "VRCI", 3 * j + r) for j in range(10) for r in range(3)]
    tr = Traffic()
    for when, kind, n in sorted(sent):
        if n in (lost_vrpi if kind == "VRPI" else lost_vrci):
            continue
        t = when
        if kind == "VRPI":
            data = encode.packet(C.PacketType.VRPI, encode.vrpi_payload({}), origin=BU_ORIGIN, serial=5000 + n)
            t += {swapped: 0.126, swapped + 1: -0.124}.get(n, 0.0)
        else:
            data = encode.packet(C.PacketType.VRCI, encode.command_payload(n // 3 + 1), origin=BU_ORIGIN, serial=n)
        tr.add(t, data)
        if (kind, n) in copies:
            tr.add(t + 0.0002, data)
    tr.frames.sort(key=lambda f: f[0])
    tr.write(tmp_path / "lossy.pcap")
    ser = analyze(str(tmp_path / "lossy.pcap"))["senders"][0]["serial"]
    assert _serial_counts(ser) == ("type", len(lost_vrpi) + len(lost_vrci), len(copies), 1, 0)
    assert ser["scope_reason"].startswith("auto, on the ") and "from its first VRCI" in ser["scope_reason"]


def test_auto_keeps_one_counter_for_a_controller_losing_around_each_command(tmp_path):
    """Trial: a controller numbering every packet on one counter, VRPO in bursts of 4 every
    100 ms and a VRCO every second sent three times, that loses the packet before and after each
    VRCO and every tenth besides. Per type, the two losses around a VRCO are one gap of the VRPO
    counter, and each VRCO but the first opens a gap of its own counter: one anomaly fewer than
    with one counter, not the 4 fewer that per-type counters need. One counter, and the real
    losses."""
    from vm110 import encode
    kinds = sorted([(0.1 * b + 0.0005 * i, "VRPO", i) for b in range(300) for i in range(4)]
                   + [(5.03 + j + 0.1 * r, "VRCO", j + 1) for j in range(25) for r in range(3)])
    serial = {k: 100 + n for n, k in enumerate(kinds)}
    lost = {serial[k] + d for k in kinds if k[1] == "VRCO" for d in (-1, 1)}
    lost |= {s for s in serial.values() if s % 10 == 7}
    tr = Traffic()
    for k in kinds:
        t, kind, n = k
        if serial[k] in lost:
            continue
        body = encode.vrpo_payload(n, b"x" * 10) if kind == "VRPO" else encode.command_payload(n)
        tr.add(t, encode.packet(C.PacketType(kind), body, serial=serial[k]), src="10.0.0.20", sport=C.OUTPUT_PORT)
    tr.write(tmp_path / "ctl.pcap")
    ser = analyze(str(tmp_path / "ctl.pcap"))["senders"][0]["serial"]
    kept = sorted(set(serial.values()) - lost)
    assert _serial_counts(ser) == ("sender", sum(kept[0] < s < kept[-1] for s in lost), 0, 0, 0)
    assert ser["scope_reason"].endswith("(not 4 fewer: cannot tell, one counter assumed)")


def test_the_scope_reason_names_the_packets_the_choice_was_made_on(tmp_path):
    """Trial: a controller of some 100 000 packets read "auto, on its 4096 packets from its first
    VRCO", as if it had sent no more; and a capture cut just after a base unit's first VRCI read
    "on all its 1 packets ...: all VRCI: one type cannot tell", of a sender of two types."""
    from vm110 import encode
    tr = Traffic()
    # VRPI every 2 ms, a VRCI (its own counter) after every 1000th from the 500th: from the first
    # VRCI (frame 502) the 4096th packet decides, on VRCI 0 ... 4 among them. One counter from
    # VRCI 0: VRPI 501 a restart (confirmed by 502), VRCI 1 ... 4 unconfirmed candidates; per type none.
    for k in range(4700):
        tr.add(0.002 * k, encode.packet(C.PacketType.VRPI, encode.vrpi_payload({}), origin=BU_ORIGIN, serial=k))
        if k % 1000 == 500:
            tr.add(0.002 * k + 0.001, encode.packet(C.PacketType.VRCI, encode.command_payload(k // 1000),
                                                    origin=BU_ORIGIN, serial=k // 1000))
    tr.write(tmp_path / "many.pcap")
    ser = analyze(str(tmp_path / "many.pcap"))["senders"][0]["serial"]
    assert (ser["scope"], ser["received"]) == ("type", 4705)
    assert ser["scope_reason"] == ("auto, on the first 4096 packets from its first VRCI (frame 502): "
                                   "5 anomalies with one counter, 0 with one per type")
    cut = Traffic()
    for k in range(8):
        cut.add(0.125 * k, vrpi(100 + k))
    cut.add(1.0, payload(VRCI, 0, BU_ORIGIN, command_id=1))               # the last packet
    cut.write(tmp_path / "cut.pcap")
    ser = analyze(str(tmp_path / "cut.pcap"))["senders"][0]["serial"]
    assert (ser["scope"], ser["scope_reason"]) == (
        "sender", "auto, on its 1 packet from its first VRCI (frame 9): VRCI only from there: cannot tell, one counter assumed")


def _per_type_bu_beside(tmp_path: Path, other: Callable[[Traffic, int], object]) -> str:
    """5 s of a base unit numbering VRPI and VRCI each on its own (VRPI 20 lost), and beside it
    what `other` adds every 125 ms (`i`: the 125 ms step): the capture's path."""
    tr = Traffic()
    for i in range(40):
        if i != 20:
            tr.add(i * 0.125, vrpi(i))
        if i % 8 == 1:
            tr.add(i * 0.125 + 0.01, payload(VRCI, 300 + i // 8, BU_ORIGIN, command_id=i // 8))
        other(tr, i)
    tr.write(tmp_path / "t.pcap")
    return str(tmp_path / "t.pcap")


def test_the_report_says_why_its_findings_have_no_filter(tmp_path):
    """A base unit counting per type and another on one counter: no dissector preference judges
    both (its serial scope is one for all), so the findings carry no filter; the report gave no
    word of why (trial). `verdict.no_filters` says it, and the summary."""
    from vm110.analysis import summary

    def one_counter(tr: Traffic, i: int) -> None:
        tr.add(i * 0.125 + 0.05, vrpi(7000 + 2 * i, origin=0x0202), src="10.0.0.11")
        if i % 8 == 3:                                                        # one counter: VRPI's next serial
            tr.add(i * 0.125 + 0.06, payload(VRCI, 7001 + 2 * i, 0x0202, command_id=i // 8), src="10.0.0.11")
    path = _per_type_bu_beside(tmp_path, one_counter)
    report = analyze(path)
    assert [s["serial"]["scope"] for s in report["senders"]] == ["type", "sender"]
    assert "wireshark_prefs" not in report["verdict"]
    assert not [f["rule"] for f in report["verdict"]["findings"] if "filter" in f]
    why = ("some senders' serials are counted per sender and others' per type, and the dissector's "
           "vm110.serial_scope is one for all (--serial-scope sender or type gives the filters)")
    assert report["verdict"]["no_filters"] == why
    assert f"  No Wireshark filter for the rules: {why}" in summary.render(report).splitlines()
    typed = analyze(path, options=Options(serial_scope="type"))
    assert "no_filters" not in typed["verdict"] and typed["verdict"]["wireshark_prefs"] == ["vm110.serial_scope:type"]


def test_a_sender_of_one_packet_type_leaves_the_scope_preference_to_the_others(tmp_path):
    """A base unit counting per type and a second one sending VRPI alone: the report gave no
    Wireshark preferences and no rule filters (trial: "scopes differ"), though the VRPI-only unit
    has one counter under either scope and `vm110.serial_scope:type` judges both as the report."""
    path = _per_type_bu_beside(tmp_path, lambda tr, i: tr.add(i * 0.125 + 0.05, vrpi(7000 + i, origin=0x0202),
                                                                src="10.0.0.11"))
    report = analyze(path)
    assert [s["serial"]["scope"] for s in report["senders"]] == ["type", "sender"]
    assert report["verdict"]["wireshark_prefs"] == ["vm110.serial_scope:type"]
    unacked = next(f for f in report["verdict"]["findings"] if f["rule"] == "unacked")
    assert unacked["filter"] == "vm110.expert.never_acked"
    # What the preference asks for: every sender counted per type judges as the report did.
    typed = analyze(path, options=Options(serial_scope="type"))
    judged = [[{k: v for k, v in s["serial"].items() if not k.startswith("scope")} for s in r["senders"]]
              for r in (typed, report)]
    assert judged[0] == judged[1]


def _vrpi_traffic(n: int = 12) -> Traffic:
    tr = Traffic()
    for i in range(n):
        tr.add(i * 0.125, vrpi(i))
    return tr


def test_file_cut_in_a_record_is_reported_and_the_rest_analysed(tmp_path):
    path = tmp_path / "cut.pcap"
    _vrpi_traffic().write(path)
    data = path.read_bytes()
    path.write_bytes(data[:-30])
    report = analyze(str(path))
    assert report["capture"]["packets"] == 11 and report["senders"][0]["by_type"] == {"VRPI": 11}
    assert "cut in the middle" in report["capture"]["problem"]
    assert report["verdict"]["findings"][0]["rule"] == "damaged" and not report["verdict"]["ok"]


def test_snaplen_truncated_eglink_packet_is_illegal_truncated(tmp_path):
    path = tmp_path / "snap.pcap"
    _vrpi_traffic(3).write(path)
    data = bytearray(path.read_bytes())
    # Cut the second record's frame to 60 bytes as a snaplen would (records start after the 24-byte header).
    first_len = struct.unpack_from("<I", data, 24 + 8)[0]
    second = 24 + 16 + first_len
    incl = struct.unpack_from("<I", data, second + 8)[0]
    struct.pack_into("<I", data, second + 8, 60)
    del data[second + 16 + 60:second + 16 + incl]
    path.write_bytes(bytes(data))
    report = analyze(str(path))
    assert report["capture"]["snaplen_truncated"] == 1
    assert report["illegal"]["by_reason"] == {"truncated": 1}
    assert report["senders"][0]["serial"]["lost"] == 1


def test_timestamps_going_backwards(tmp_path):
    tr = _vrpi_traffic(6)
    t, *rest = tr.frames[3]
    tr.frames[3] = (t - 1.0, *rest)                   # one packet stamped a second early
    tr.write(tmp_path / "back.pcap")
    report = analyze(str(tmp_path / "back.pcap"))
    p = report["periodic"][0]
    assert p["time_backwards"] == 1 and report["capture"]["time_backwards"] == 1
    assert p["interval_ms"]["min"] == -875.0 and [{k: v[k] for k in ("start", "gap_ms")} for v in p["watchdog"]["violations"]] == [
        {"start": T0 + 3 * 0.125 - 1.0, "gap_ms": 1125.0}]
    assert report["senders"][0]["serial"]["lost"] == 0


def test_findings_come_errors_first_then_warnings_then_notes(tmp_path, capsys):
    """A packet lost in IP fragments never reassembled (one of them lost): the warning that
    fragments were not analysed, a note of the capture as a whole, came before the error that the
    packet was lost, in the JSON, the summary and the HTML; a reader stopping at the first lines of
    a long list saw warnings and took the capture for sound. Errors come first, as report.md says."""
    from scapy.layers.inet import IP, UDP, fragment
    from scapy.layers.l2 import Ether
    from test_reader import pcap
    from vm110.analysis import summary
    frames = [Ether() / IP(src="10.0.0.10", dst=C.MULTICAST_GROUP) / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT)
              / vrpi(i) for i in range(12)]
    records = [(T0 + i * 0.125, f) for i, f in enumerate(frames) if i != 5]
    records[5:5] = [(T0 + 5 * 0.125, Ether() / part) for part in fragment(frames[5][IP], fragsize=24)[:-1]]
    path = tmp_path / "fragment.pcap"
    path.write_bytes(pcap(records))
    report = analyze(str(path))
    findings = report["verdict"]["findings"]
    assert [(f["rule"], f["severity"]) for f in findings] == [("lost", "error"), ("ip_fragments", "warning")]
    lines = summary.render(report).splitlines()
    assert lines[3].startswith("  error   1 packet lost") and lines[5].startswith("  warning ")


def test_empty_capture(tmp_path):
    Traffic().write(tmp_path / "empty.pcap")
    report = analyze(str(tmp_path / "empty.pcap"))
    assert report["capture"]["packets"] == 0 and report["senders"] == [] and report["periodic"] == []
    assert not report["verdict"]["ok"] and report["verdict"]["findings"][0]["rule"] == "no_eglink"


def test_command_id_wrap_and_ack_matching(tmp_path):
    tr = Traffic()
    for s, cid in enumerate((65534, 65535, 0, 1)):
        tr.add(s * 0.2, payload(VRCI, s, BU_ORIGIN, command_id=cid))
        tr.add(s * 0.2 + 0.05, payload(VRAO, s, command_id=cid), src="10.0.0.20", sport=C.OUTPUT_PORT)
    tr.write(tmp_path / "wrap.pcap")
    vrci = analyze(str(tmp_path / "wrap.pcap"))["commands"]["VRCI"]
    assert (vrci["commands"], vrci["acked"], vrci["command_id_wraps"], vrci["acks_without_command"]) == (4, 4, 1, 0)
    assert vrci["ack_latency_ms"]["max"] == 50.0


def test_command_ids_counted_from_0_again_are_no_wrap(tmp_path):
    """A controller numbering 0, 1, 2, 0, 1, 2 never passed 65535 (a trial saw 2 wraps counted)."""
    tr = Traffic()
    for s, cid in enumerate((0, 1, 2, 0, 1, 2, 65534, 65535, 3)):
        tr.add(s * 3.0, payload(VRCI, s, BU_ORIGIN, command_id=cid))       # beyond the reuse gap: new
    tr.write(tmp_path / "ids.pcap")
    vrci = analyze(str(tmp_path / "ids.pcap"))["commands"]["VRCI"]
    assert (vrci["commands"], vrci["command_id_wraps"]) == (9, 1)           # 65535 -> 3 only


def test_vrpo_on_another_port_found_by_its_header(tmp_path):
    tr = Traffic()
    for i in range(5):
        tr.add(i * 0.1, payload(VRPO, i, packet_number=0, periodic_data=b"abc"), src="10.9.9.9", sport=7000)
    tr.add(0.55, b"VRPO-not-really", src="10.9.9.9", sport=7000)
    tr.write(tmp_path / "port.pcap")
    report = analyze(str(tmp_path / "port.pcap"))
    assert report["capture"]["eglink_packets"] == 5 and report["capture"]["other_udp_packets"] == 1
    assert report["senders"][0]["src"] == "10.9.9.9:7000" and report["vrpo_bursts"]["complete"] == 5


@pytest.mark.parametrize("few", [1, 2, 32])
def test_grouping_many_senders(monkeypatch, few):
    import numpy as np
    from vm110.analysis import collect
    monkeypatch.setattr(collect, "FEW_SENDERS", few)
    key = np.array([5, 3, 5, 9, 3, 1, 7, 1, 2, 8, 2], dtype=np.int64)
    groups = {v: rows.tolist() for v, rows in collect._groups(key)}
    assert groups == {5: [0, 2], 3: [1, 4], 9: [3], 1: [5, 7], 7: [6], 2: [8, 10], 8: [9]}


def test_corrupt_record_header_stops_the_reading_with_a_finding(tmp_path):
    path = tmp_path / "corrupt.pcap"
    _vrpi_traffic(8).write(path)
    data = bytearray(path.read_bytes())
    pos = 24
    for _ in range(5):
        pos += 16 + struct.unpack_from("<I", data, pos + 8)[0]
    struct.pack_into("<I", data, pos + 8, 0x7FFFFFFF)        # the sixth record claims 2 GB
    path.write_bytes(bytes(data))
    report = analyze(str(path))
    assert report["capture"]["packets"] == 5 and report["senders"][0]["serial"]["received"] == 5
    assert report["capture"]["problem"].startswith(f"corrupt record header at byte {pos}")


def test_vlan_and_ipv6_frames_in_an_ethernet_pcap(tmp_path):
    from scapy.layers.inet import IP, UDP
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import Dot1Q, Ether
    from scapy.utils import wrpcap
    frames = []
    for i in range(6):
        data = vrpi(i)
        head = Ether() / Dot1Q(vlan=3) / IP(src="10.0.0.10") if i % 2 else Ether() / IP(src="10.0.0.10")
        frames.append(head / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / data)
        frames.append(Ether() / IPv6(src="fd00::10") / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / vrpi(i, 0x0202))
    for i, f in enumerate(frames):
        f.time = T0 + i * 0.0625
    wrpcap(str(tmp_path / "mixed-l2.pcap"), frames)
    report = analyze(str(tmp_path / "mixed-l2.pcap"))
    assert [(s["src"], s["by_type"], s["serial"]["lost"]) for s in report["senders"]] == [
        (f"10.0.0.10:{C.INPUT_PORT}", {"VRPI": 6}, 0), (f"[fd00::10]:{C.INPUT_PORT}", {"VRPI": 6}, 0)]


@pytest.mark.parametrize("endian", ["<", ">"])
def test_pcapng_interfaces_and_odd_blocks_through_the_engine(tmp_path, endian):
    from scapy.layers.inet import IP, UDP
    from scapy.layers.l2 import Ether
    from test_reader import block, option
    e = endian
    shb = block(0x0A0D0D0A, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1), e)
    idb_eth = block(1, struct.pack(e + "HHI", 1, 0, 65535), e)
    idb_raw = block(1, struct.pack(e + "HHI", 101, 0, 65535) + option(9, b"\x09", e) + option(0, b"", e), e)

    def epb(iface, ticks, frame):
        return block(6, struct.pack(e + "IIIII", iface, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), len(frame))
                     + frame, e)

    def ip(serial):
        return bytes(IP(src="10.0.0.10", dst="239.255.42.20") / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT)
                     / vrpi(serial))
    blocks = [shb, idb_eth, idb_raw]
    for i in range(6):
        t_us = 1_700_000_000_000_000 + i * 125_000
        if i == 2:
            blocks.append(block(0x1234, b"skip me", e))                               # unknown: skipped
        if i == 3:
            frame = bytes(Ether(type=0x0800) / ip(i))
            blocks.append(block(3, struct.pack(e + "I", len(frame)) + frame, e))   # simple packet block
        elif i % 2:
            blocks.append(epb(1, t_us * 1000, ip(i)))                               # raw IP, nanoseconds
        else:
            blocks.append(epb(0, t_us, bytes(Ether(type=0x0800) / ip(i))))
    path = tmp_path / "ifaces.pcapng"
    path.write_bytes(b"".join(blocks))
    report = analyze(str(path))
    assert report["capture"]["packets"] == 6 and report["capture"]["link_types"] == ["ethernet", "raw"]
    snd = report["senders"][0]["serial"]
    assert (snd["received"], snd["lost"], snd["out_of_order"]) == (6, 0, 0)
    assert report["periodic"][0]["interval_ms"]["min"] == 0.0       # the simple packet block: previous time
    assert report["periodic"][0]["interval_ms"]["max"] == 250.0


@pytest.mark.parametrize("linktype,endian", [(101, "<"), (1, ">"), (113, "<")])
def test_other_pcap_layouts_through_the_engine(tmp_path, linktype, endian):
    from scapy.layers.inet import IP, UDP
    from scapy.layers.l2 import CookedLinux, Ether
    from test_reader import pcap
    wrap = {101: lambda p: p, 1: lambda p: Ether() / p, 113: lambda p: CookedLinux(proto=0x0800) / p}[linktype]
    records = [(1_700_000_000 + i * 0.125, wrap(IP(src="10.0.0.10", dst="239.255.42.20")
                                                 / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / vrpi(i if i != 3 else 9)))
               for i in range(8)]
    path = tmp_path / "other.pcap"
    path.write_bytes(pcap(records, linktype=linktype, endian=endian))
    report = analyze(str(path))
    ser = report["senders"][0]["serial"]
    assert (ser["received"], ser["lost"], ser["out_of_order"]) == (8, 2, 4)   # 9 after 2; 4..7 late; 3, 8 lost


def test_frames_of_a_link_type_the_reader_does_not_read_are_said(tmp_path):
    """A site capture in PPI (192, Ethernet inside), which Wireshark and --engine tshark read: the
    fast engine gave "no EG-Link packets in the capture" and nothing else, read as a dead link
    (trial). The report now counts the frames it could not read and says which link type."""
    from scapy.layers.inet import IP, UDP
    from scapy.layers.l2 import Ether
    from test_reader import pcap
    ppi = struct.pack("<BBHI", 0, 0, 8, 1)                        # version, flags, length, DLT Ethernet
    records = [(1_700_000_000 + i * 0.125, ppi + bytes(Ether() / IP(src="10.0.0.10", dst="239.255.42.20")
                                                        / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / vrpi(i)))
               for i in range(8)]
    path = tmp_path / "ppi.pcap"
    path.write_bytes(pcap(records, linktype=192))
    report = analyze(str(path))
    assert report["capture"]["unread_frames"] == 8
    [unread] = [f for f in report["verdict"]["findings"] if f["rule"] == "unread_link_type"]
    assert (unread["severity"], unread["count"]) == ("warning", 8)
    assert unread["message"].startswith("8 frames of link type 192 not read") and "--engine tshark" in unread["message"]


def test_frames_of_link_types_not_read_are_told_in_words():
    """Report trial: "1 frames of link type 192", and "link type 147, 192" for two of them."""
    from vm110.capture.linktypes import unread
    assert unread(1, {"192"}, "x").startswith("1 frame of link type 192 not read")
    assert unread(3, {"192", "Ethernet", "147", "1000"}, "x").startswith("3 frames of link types 147, 192 and 1000 not")


@pytest.mark.parametrize("fmt", ["pcap", "pcapng"])
def test_damaged_files_never_raise(tmp_path, fmt):
    """Random byte damage and cuts: a report (that renders as JSON, HTML and summary) or a
    CaptureError, nothing else."""
    from vm110.analysis import report_html, report_json, summary
    from vm110.capture.reader import CaptureError
    from vm110.synth import synthesize
    clean = tmp_path / f"clean.{fmt}"
    synthesize("illegal", str(clean), 2, 3.0, fmt)
    data = clean.read_bytes()
    rng = random.Random(11)
    for case in range(40):
        damaged = bytearray(data)
        for _ in range(rng.choice([1, 5, 50])):
            damaged[rng.randrange(len(damaged))] = rng.randrange(256)
        if case % 3 == 0:
            del damaged[rng.randrange(len(damaged)):]
        path = tmp_path / f"d{case}.{fmt}"
        path.write_bytes(bytes(damaged))
        try:
            report = analyze(str(path))
        except CaptureError:
            continue
        assert report["capture"]["packets"] >= 0 and isinstance(report["verdict"]["ok"], bool)
        report_json.write(str(tmp_path / "r.json"), report)
        assert "<svg" in report_html.render([report]) and "VERDICT" in summary.render(report)


@pytest.mark.parametrize("name", ["loss.pcapng", "restart.pcapng", "illegal.pcap"])
def test_reading_in_a_second_process_gives_the_same_report(name, monkeypatch):
    """Large files are read by a child process that sends its batches to the analysing parent
    (engine.pipelined): the report is the one of a single process, damage and all."""
    from vm110.analysis import engine
    path = str(Path(__file__).resolve().parent.parent / "captures" / name)
    monkeypatch.setenv(engine.WORKERS_ENV, "1")
    alone = analyze(path)
    monkeypatch.setenv(engine.WORKERS_ENV, "2")
    monkeypatch.setattr(engine, "PIPELINE_MIN_BYTES", 0)
    assert engine.pipelined(path)
    together = analyze(path)
    assert {**together, "tool": None} == {**alone, "tool": None}


def test_a_damaged_file_read_in_a_second_process(tmp_path, monkeypatch):
    from vm110.analysis import engine
    path = tmp_path / "cut.pcap"
    _vrpi_traffic().write(path)
    path.write_bytes(path.read_bytes()[:-30])
    monkeypatch.setattr(engine, "PIPELINE_MIN_BYTES", 0)
    monkeypatch.setenv(engine.WORKERS_ENV, "2")
    report = analyze(str(path))
    assert report["capture"]["packets"] == 11 and report["totals"]["damaged"] == 1
    (tmp_path / "junk.pcap").write_bytes(b"\xd4\xc3\xb2\xa1" + bytes(10))
    with pytest.raises(Exception, match="pcap file header cut short"):
        analyze(str(tmp_path / "junk.pcap"))


def test_more_than_65536_source_addresses_each_name_their_sender():
    """A capture of more than 65,536 source addresses (spoofed, or a whole site mirrored) ended in
    "cannot analyse: OverflowError: Python integer 65536 out of bounds for uint16": the records held
    the source index in 16 bits. Each record now names its source, and each key its sender."""
    from vm110.analysis import collect
    from vm110 import encode as E
    got = collect.Collected(path="x", engine="fast")
    packets = {C.Direction.INPUT: E.packet(C.PacketType.VRPI, E.payload(C.PacketType.VRPI, {}), origin=0x0101),
               C.Direction.OUTPUT: E.packet(C.PacketType.VRPO, E.vrpo_payload(0, b"a"), origin=0x0202)}
    for i in range(70_000):
        direction = C.Direction.INPUT if i % 2 else C.Direction.OUTPUT
        got.add_legal(float(i), i + 1, i.to_bytes(4, "big"), 40_000 + i % 7, packets[direction])
    rec = np.frombuffer(bytes(got.records), dtype=collect.RECORD_DTYPE)
    assert rec["src"].tolist() == list(range(70_000)) and rec["frame"][-1] == 70_000
    keys = collect.sender_keys(rec, collect.code_of(rec["pid"]))
    assert len(set(keys.tolist())) == 70_000
    for i in (0, 65_535, 65_536, 69_999):
        direction = C.Direction.INPUT if i % 2 else C.Direction.OUTPUT
        assert collect.key_sender(int(keys[i])) == (direction.value, 0x0101 if i % 2 else 0x0202, i, 40_000 + i % 7)
