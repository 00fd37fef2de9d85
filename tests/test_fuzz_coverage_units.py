"""Coverage-guided pieces without a controller: the shared-memory map, AFL's hit-count classes,
the corpus on disk (hostile files skipped), AFL dictionaries, strings of a program, mutation that
keeps size and CRC right."""
from __future__ import annotations

import json
import random

import pytest
from vm110 import constants as C
from vm110.decode import decode
from vm110.errors import CliError
from vm110.fuzz import cases as K
from vm110.fuzz import mutate as M
from vm110.fuzz.corpus import CorpusDir, Entry, Packet, binary_strings, load_dictionary
from vm110.fuzz.coverage import COUNT_CLASS, ShmMap, Virgin, map_size
from vm110.fuzz.guided import entry_of, packet_id
from vm110.fuzz.havoc import Mutator
from vm110.fuzz.session import Sent


def test_hit_count_classes_are_afls():
    # AFL's classes: 0, 1, 2, 3, 4-7, 8-15, 16-31, 32-127, 128-255.
    expected = {0: 0, 1: 1, 2: 2, 3: 4, 4: 8, 7: 8, 8: 16, 15: 16, 16: 32, 31: 32, 32: 64, 127: 64, 128: 128, 255: 128}
    assert {n: COUNT_CLASS[n] for n in expected} == expected


def test_virgin_counts_new_edges_and_new_classes():
    v = Virgin(8)
    assert v.novel(bytes(8)) == 0 and not v.ever_nonzero
    assert v.novel(bytes([1, 0, 0, 5, 0, 0, 0, 0])) == 2 and v.edges == 2
    assert v.novel(bytes([1, 0, 0, 6, 0, 0, 0, 0])) == 0, "5 and 6 are one class"
    assert v.novel(bytes([2, 0, 0, 0, 0, 0, 0, 0])) == -1, "a new class of a known edge"
    assert v.novel(bytes([0, 0, 0, 0, 0, 0, 0, 9])) == 1 and v.edges == 3


def test_shm_map_clear_and_read():
    m = ShmMap(4096)
    try:
        assert m.id >= 0 and m.read() == bytes(4096)
        import ctypes
        ctypes.memset(m.addr + 100, 7, 3)
        assert m.read()[100:103] == b"\x07\x07\x07"
        m.clear()
        assert m.read() == bytes(4096)
    finally:
        m.close()


def test_map_size_from_environment():
    assert map_size({}) == 65536 and map_size({"AFL_MAP_SIZE": "262144"}) == 262144
    for bad in ("0", "-1", "1e9", "x"):
        with pytest.raises(CliError):
            map_size({"AFL_MAP_SIZE": bad})


def test_afl_dictionary(tmp_path):
    path = tmp_path / "d.dict"
    path.write_text('# comment\nmaint="MAINT:"\n"ENGAGE"\nbin="\\x00\\xffA\\"\\\\"\nkw@2="X"\n\n')
    assert load_dictionary(str(path)) == [b"MAINT:", b"ENGAGE", b'\x00\xffA"\\', b"X"]
    path.write_text('ok="A"\nbroken\n')
    with pytest.raises(CliError, match="line 2"):
        load_dictionary(str(path))


def test_program_strings_are_its_own(tmp_path):
    prog = tmp_path / "prog"
    prog.write_bytes(b"\0\0MAINT:\0ENGAGE\0a b\0%d\0_private\0xy\0")
    assert binary_strings(str(prog)) == [b"MAINT:", b"ENGAGE"]
    assert binary_strings(str(tmp_path / "missing")) == []


def test_corpus_round_trip_and_hostile_files_skipped(tmp_path):
    store = CorpusDir(tmp_path)
    vrci = M.build(C.PacketType.VRCI, 3, M.default_fields(C.PacketType.VRCI, 9))
    store.save(Entry([Packet(vrci, 5.0), Packet(b"junk", 0.0, raw=True)], dict(M.DISARMED_VRPI), origin="test"))
    (tmp_path / "id-000007.json").write_text(json.dumps({"vm110_corpus_entry": 1, "packets": [
        {"hex": "zz", "delay_ms": 0, "raw": False, "expect_ack": True}]}))
    (tmp_path / "id-000008.json").write_text("[1e999999")
    (tmp_path / "id-000009.json").write_text(json.dumps({"vm110_corpus_entry": 1, "packets": [
        {"hex": "00", "delay_ms": float("nan"), "raw": False, "expect_ack": True}]}).replace("NaN", "1e999"))
    again = CorpusDir(tmp_path)
    entries = again.load()
    assert len(entries) == 1 and entries[0].packets[0].data == vrci and entries[0].packets[1].raw
    assert entries[0].stream == {k: int(v) for k, v in M.DISARMED_VRPI.items()}
    assert len(again.skipped) == 3 and again.next == 10


def test_every_case_the_fuzzer_makes_resumes_from_the_corpus(tmp_path):
    # The sweep seeds the corpus with all its cases: waiting alone (no packet: a VRPI gap, a VRAI
    # withheld) and a 20-transmission storm were written, then refused when read back.
    count = len(K.sweep(1)) + 200
    cases = [K.generate(1, i) for i in range(count)]
    store = CorpusDir(tmp_path)
    for case in cases:
        sent = [Sent(0.0, *step.build(n), step.delay_ms, step.expect_ack) for n, step in enumerate(case.steps)]
        store.save(entry_of(case, sent, case.description))
    again = CorpusDir(tmp_path)
    entries = again.load()
    assert again.skipped == []
    assert [(len(e.packets), e.pause_vrpi_ms, e.withhold_vrai_ms) for e in entries] == [
        (len(c.steps), c.pause_vrpi_ms, c.withhold_vrai_ms) for c in cases]
    assert {0, 20} <= {len(c.steps) for c in cases}


def test_mutants_keep_size_and_crc_unless_raw():
    rng = random.Random(1)
    m = Mutator(rng, [b"MAINT:", b"ENGAGE"])
    base = Entry([Packet(M.build(C.PacketType.VRCI, 1, M.default_fields(C.PacketType.VRCI, 5))),
                  Packet(M.build(C.PacketType.VRPI, 2, M.ARMED_VRPI))])
    broken = legal_changed = 0
    for _ in range(400):
        child = m.mutate(base, base)
        assert 0 < len(child.packets) <= 8 or not child.packets
        assert child.pause_vrpi_ms == child.withhold_vrai_ms == 0, "mutants need no waiting"
        for p in child.packets:
            d = decode(p.data)
            if p.raw:
                broken += 1
                continue
            if len(p.data) >= C.OVERHEAD:
                assert d["crc.status"] == C.CRC_GOOD and d["size"] == len(p.data) - C.OVERHEAD, p.data.hex()
                legal_changed += p.data not in (base.packets[0].data, base.packets[1].data)
    assert broken > 0 and legal_changed > 200
    assert any(p.data[C.PREFIX_LEN + 6:].startswith(b"ENGAGE") for _ in range(200)
               for p in m.mutate(base, base).packets), "dictionary tokens go into command data"


def test_a_havoced_packet_id_is_shown_without_control_characters():
    """Trial: a finding's line was 'mutation of a corpus case: 5 packet(s) VRCI+V\\x7fR+\\ufffd\\x00\\x00\\ufffd',
    the NUL and DEL (and so any ESC the havoc wrote) raw on the terminal."""
    assert packet_id(b"VRCI" + bytes(20)) == "VRCI"
    assert packet_id(b"V\x7fR+") == "V\\x7fR+"
    assert packet_id(b"\xff\x00\x1b[") == "\\xff\\x00\\x1b["


class _Quiet:
    """A session with nothing to pump: the test writes the controller's hits into the map itself."""

    def pump(self, until: float) -> None:
        pass


def test_a_resumed_corpus_restores_edges_the_controllers_timers_reached(tmp_path):
    """Trial: a resumed --corpus reached 57 edges where the run that wrote it had 69 (AFL++ build of
    tests/targets/controller.c). The controller's timers and the base unit's stream and acks hit
    edges whenever they fire: inside a case in one run (counted), between cases in the next (lost,
    the map is cleared before each case). Both runs must count them."""
    import ctypes
    from vm110.fuzz.guided import Guided, GuidedConfig

    def run(timer_inside_case: bool) -> int:
        g = Guided(GuidedConfig(4096, tmp_path / "corpus"), seed=1)
        try:
            g.open(None)
            for index in range(2):
                case = g.next_case(index)
                if index == 1 and not timer_inside_case:
                    ctypes.memset(g.map.addr + 300, 1, 1)      # the VRCO timer, between cases
                g.before_case()
                ctypes.memset(g.map.addr + 100, 1, 2)          # what the case itself reaches
                if index == 0 and timer_inside_case:
                    ctypes.memset(g.map.addr + 300, 1, 1)      # the VRCO timer, during the case
                g.after_case(_Quiet(), case, [])
            return g.edges()
        finally:
            g.close()

    written = run(timer_inside_case=True)
    assert written == 3 and len(list((tmp_path / "corpus").glob("id-*.json"))) >= 1
    resumed = run(timer_inside_case=False)
    assert resumed == written


def test_coverage_report_says_where_each_bug_is_and_why_the_run_ended():
    """Trial: coverage.html listed a bug's headline, hits and file only (no case, no time, no pcap
    or display filter, as its finding and terminal line have), and nothing of a run that stopped
    early, of unreproduced triggers or of a resumed corpus."""
    from vm110.fuzz.report_html import render
    summary = {
        "target": "127.0.0.1:5825", "cases_run": 40, "duration_s": 9.5, "started": 1_700_000_000.0,
        "stopped_early": "--max-findings 1 reached", "unreproduced": [{"oracle": "stall"}],
        "findings": [{"oracle": "crash", "case_index": 33, "mutation": "mutation of a corpus case: 2 packet(s) VRCI",
                      "file": "finding-001-crash.json", "pcap": "finding-001-crash.pcap", "frame": 133,
                      "display_filter": "frame.number == 133", "time": 1_700_000_004.5}],
        "buckets": [{"headline": "crash SIGSEGV in maintenance_engage (controller.c:182)", "count": 2,
                     "file": "finding-001-crash.json", "first": 1_700_000_004.5, "last": 1_700_000_008.0}],
        "coverage": {"edges": 75, "map_size": 65536, "corpus": 21, "edges_over_time": [{"s": 1, "edges": 75}],
                     "corpus_skipped": [], "resumed": {"cases": 5, "of": 21, "edges": 60}}}
    page = render(summary)
    row = page.split("<tr><td>crash SIGSEGV", 1)[1].split("</tr>", 1)[0]
    assert "2023-11-14T22:13:24.500000Z (+4.500000 s)" in row
    assert "33: mutation of a corpus case: 2 packet(s) VRCI" in row
    assert "finding-001-crash.pcap" in row and "<code class='filter'>frame.number == 133</code>" in row
    assert "Stopped early: --max-findings 1 reached" in page
    assert "1 trigger(s) did not happen again" in page
    assert "Resumed 5 of the 21 cases of --corpus (the run ended first" in page
    # Review: a trigger the lost controller could not replay was said not to happen again when replayed.
    summary["unreproduced"] = [{"oracle": "crash", "not_replayed": "controller restarted but sent no VRPO"}]
    page = render(summary)
    assert "did not happen again" not in page and "1 trigger(s) could not be replayed" in page


def test_a_resumed_corpus_says_when_it_reaches_fewer_edges_than_the_runs_that_kept_it(tmp_path):
    """A stored case may have reached an edge through what a case not kept left behind (the C
    controller's MAINT: state): played again without it, it does not, and the run says so rather
    than showing fewer edges unexplained."""
    import ctypes
    from vm110.fuzz.guided import Guided, GuidedConfig

    def run(hits: list[list[int]]) -> dict:
        g = Guided(GuidedConfig(4096, tmp_path / "corpus"), seed=1)
        try:
            g.open(None)
            for index, edges in enumerate(hits):
                case = g.next_case(index)
                g.before_case()
                for e in edges:
                    ctypes.memset(g.map.addr + e, 1, 1)
                g.after_case(_Quiet(), case, [])
            g.before_case()
            return g.summary()
        finally:
            g.close()

    # Case 1 (nothing new, not kept) leaves a state in which case 2 reaches edge 200.
    first = run([[100, 101], [100], [100, 200]])
    assert first["edges"] == 3 and len(list((tmp_path / "corpus").glob("id-*.json"))) == 2
    again = run([[100, 101], [100]])           # case 2 played again, without that state
    assert again["resumed"] == {"cases": 2, "of": 2, "edges": 2, "stored_edges": 3}
