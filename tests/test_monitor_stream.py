"""The stream reader reads what the file reader reads, whatever the pieces the bytes come in:
the same frames, times, datagrams, counters and damage, for every bundled capture, cut short,
and with bytes flipped."""
from __future__ import annotations

import random
import tempfile
from pathlib import Path

import pytest

from vm110.analysis import analyze, engine
from vm110.analysis.commands import Retiring
from vm110.analysis.incremental import Analysis
from vm110.analysis.report import Options
from vm110.capture.reader import CaptureError, CaptureReader
from vm110.capture.stream import StreamReader
from vm110.cli import main

ROOT = Path(__file__).resolve().parent.parent
CAPTURES = sorted(p for p in (ROOT / "captures").iterdir() if p.suffix in (".pcap", ".pcapng"))


def facts(reader) -> tuple:
    # The reader's generic walk leaves the first and last times of a chunk cut by damage unset
    # (the engine's own walks set them, as the stream does): compared where nothing is damaged,
    # and the reports below compare them against the engine.
    times = (reader.first_ts, reader.last_ts) if reader.problem is None else ()
    return (reader.frames, reader.non_udp, reader.fragments, sorted(reader.snap_truncated), reader.problem,
            reader.damage, *times, sorted(reader.link_types))


def by_file(path: Path):
    reader = CaptureReader(str(path))
    got = [(ts, frame, (src, sport, dport, payload)) for ts, src, sport, dport, payload, frame in reader]
    return got, facts(reader)


def by_stream(data: bytes, rng: random.Random):
    reader = StreamReader("x")
    got = []
    pos = 0
    while pos < len(data):
        step = rng.choice((1, 3, 17, 100, 1500, 65536))
        for ts, frame, _, _, dgram in reader.feed(data[pos:pos + step]):
            if dgram is not None:
                got.append((ts, frame, dgram))
        pos += step
    reader.close()
    return got, facts(reader)


def variants(data: bytes, rng: random.Random):
    yield "whole", data
    yield "cut", data[:rng.randrange(100, len(data))]
    flipped = bytearray(data)
    for _ in range(8):
        flipped[rng.randrange(24, len(data))] ^= 1 << rng.randrange(8)
    yield "flipped", bytes(flipped)


@pytest.mark.parametrize("capture", CAPTURES, ids=lambda p: p.name)
def test_stream_reads_what_the_file_reader_reads(capture, tmp_path):
    rng = random.Random(capture.name)
    for name, data in variants(capture.read_bytes(), rng):
        path = tmp_path / f"{name}{capture.suffix}"
        path.write_bytes(data)
        try:
            expected = by_file(path)
        except CaptureError:
            with pytest.raises(CaptureError):
                by_stream(data, rng)
            continue
        assert by_stream(data, rng) == expected, name


# Seeds that once found a difference (a datagram the snaplen cut short taken as legal) among others.
@pytest.mark.parametrize("seed,capture", [("5", "normal.pcap"), ("3", "bu-watchdog.pcap"), ("2", "vrco.pcap"),
                                          ("0", "loss.pcapng"), ("0", "illegal.pcap"), ("0", "restart.pcapng")])
def test_monitor_reports_damaged_captures_as_analyze_does(seed, capture, tmp_path, capsys):
    rng = random.Random(f"{seed}{capture}")
    source = ROOT / "captures" / capture
    for name, data in variants(source.read_bytes(), rng):
        if name == "whole":
            continue
        path = tmp_path / f"{name}{source.suffix}"
        path.write_bytes(data)
        a, m = tmp_path / "a.json", tmp_path / "m.json"
        code = main(["analyze", str(path), "--quiet", "--json", str(a)])
        if code == 2:                              # not a capture any more: both refuse it
            assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--json", str(m)]) == 2
            continue
        main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json", str(m)])
        assert a.read_bytes() == m.read_bytes(), name


class _RetiringAnalysis(Analysis):
    """The analysis fed a packet at a time, retiring finished commands after each batch as
    eagerly as `vm110 monitor` may (by the time before which every event is applied)."""

    def __init__(self, opt) -> None:
        super().__init__(opt)
        self.spool = tempfile.TemporaryFile()   # noqa: SIM115 -- closed in finish()
        self.retiring = Retiring(self.tracker, self.spool)

    def feed(self, rec, sources) -> None:
        for a in range(len(rec)):                  # a packet at a time: the most chances to go wrong
            super().feed(rec[a:a + 1], sources)
            self.retiring.retire(min(float(rec["ts"][a]), self.applied_until()))

    def finish(self) -> None:
        if not self.finished:
            self.retiring.restore()
            self.spool.close()
        super().finish()


@pytest.mark.parametrize("scope", ["sender", "auto"])     # (auto: the look holds the commands back a while)
@pytest.mark.parametrize("capture", ["overlap.pcapng", "loss.pcapng", "restart.pcapng", "vrco.pcap", "glink.pcapng"])
def test_retired_commands_give_the_same_report(capture, scope, monkeypatch):
    path = str(ROOT / "captures" / capture)
    options = Options(serial_scope=scope)
    expected = analyze(path, crc="mpeg2", crc_order="little", options=options)
    made: list = []

    def factory(opt):
        made.append(_RetiringAnalysis(opt))
        return made[-1]
    monkeypatch.setattr(engine, "Analysis", factory)
    monkeypatch.setenv(engine.WORKERS_ENV, "1")
    got = analyze(path, crc="mpeg2", crc_order="little", options=options)
    assert made and made[-1].retiring.retired > 0          # it did retire commands
    assert got == expected


def test_monitor_retires_commands_beside_a_sender_stuck_on_one_serial(tmp_path, monkeypatch):
    """A base unit stuck on one serial is never all decided (a restart candidate every 10 s,
    rules.md rule 5): `vm110 monitor` retired finished commands only once every packet was, so
    beside it a run of days kept every command in memory. It retires what is finished before the
    first undecided packet; the report is analyze's all the same."""
    from test_analysis_craft import CTRL, Traffic, payload, vrpi
    from vm110 import constants as C
    from vm110.layers import VRAI, VRCO
    tr = Traffic()
    bu = [(i * 0.125 + 0.06, None) for i in range(480)]
    for k in range(20):                                      # a VRCO every 2.5 s, acknowledged
        tr.add(1.0 + k * 2.5, payload(VRCO, k, command_id=k + 1), src=CTRL, sport=C.OUTPUT_PORT)
        bu.append((1.05 + k * 2.5, k + 1))
    for serial, (t, acked) in enumerate(sorted(bu)):
        tr.add(t, vrpi(serial) if acked is None else payload(VRAI, serial, 0x0101, command_id=acked))
    for i in range(480):
        tr.add(i * 0.125, vrpi(777, origin=0x0102), src="10.0.0.11")         # stuck on serial 777
    tr.frames.sort(key=lambda f: f[0])
    path = tmp_path / "stuck.pcap"
    tr.write(path)
    retired: list[int] = []
    real = Retiring.retire

    def watch(self, now, upto=None):
        real(self, now, upto)
        retired.append(self.retired)
    monkeypatch.setattr(Retiring, "retire", watch)
    a, m = tmp_path / "a.json", tmp_path / "m.json"
    assert main(["analyze", str(path), "--quiet", "--json", str(a)]) == 0
    assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json", str(m)]) == 0
    assert max(retired, default=0) >= 10
    assert a.read_bytes() == m.read_bytes()
