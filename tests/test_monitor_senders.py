"""`vm110 monitor` runs for days: what it keeps per sender is bounded, whatever the traffic (a
controller restarting on a new port every few seconds, spoofed senders, a capture cut by its
snaplen), and what it lets go is said (docs/monitor.md, "Memory for long runs")."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tracemalloc
from collections import Counter
from pathlib import Path

from test_analysis_tshark import snapped
from vm110 import constants as C
from vm110 import encode as E
from vm110.analysis import analyze, shelf
from vm110.analysis.report import Options
from vm110.analysis.sender import Sender
from vm110.capture.writer import PcapWriter, UdpFlow
from vm110.cli import main
from vm110.monitor import live as L
from vm110.monitor.session import Session, Settings
from vm110.monitor.sources import Source

PER_SECOND = 100                # new senders per second of capture time
SECONDS, MEASURED = 30, 10      # 3,000 senders; the monitor's memory at 1,000 and at 3,000
CAP = 256                       # the live view's (1024 in use: a smaller one is reached sooner)
T0 = 1_700_000_000.0


def _monitor_files(snapshot: tracemalloc.Snapshot) -> int:
    return sum(s.size for s in snapshot.filter_traces([tracemalloc.Filter(True, "*vm110/monitor/*")]).statistics(
        "filename"))


def test_memory_stays_flat_with_many_senders(monkeypatch):
    """3,000 senders, each heard once (a VRPO, then silent), through the monitor's intake as from
    a capture: the monitor's own memory after 3,000 is that after 1,000 (it kept about 10 KiB a
    sender); the live view keeps the MAX_SENDERS heard last, counts the others, and every watchdog
    it raised is cleared or still active."""
    monkeypatch.setattr(L, "MAX_SENDERS", CAP)
    session = Session(Source(), Options(), Settings(name="many", port=5825, crc="mpeg2", crc_order="little",
                                                    lines=False))
    told = Counter()        # (watchdog findings by event: the findings themselves are not kept)
    emit = session.emit

    def counted(f: dict) -> None:
        if f["rule"] == "watchdog":
            told[f["event"]] += 1
        emit(f)
    session.live.emit = counted
    payload = E.packet(C.PacketType.VRPO, E.vrpo_payload(0, bytes(16)))
    sizes = {}
    tracemalloc.start()
    try:
        frame = 0
        for second in range(SECONDS):
            batch = []          # (a second's packets read at once, as from a capture)
            for i in range(second * PER_SECOND, (second + 1) * PER_SECOND):
                frame += 1
                ts = T0 + second + (i % PER_SECOND) / PER_SECOND
                # 100 ports a host: restarts on new ports, and new hosts.
                src = bytes((10, 1, (i // 100) >> 8 & 255, (i // 100) & 255))
                batch.append((ts, frame, 1, b"", (src, 10000 + i % 100, 5825, payload)))
            session._packets(batch)
            session._periodic()
            if second + 1 in (MEASURED, SECONDS):
                sizes[second + 1] = _monitor_files(tracemalloc.take_snapshot())
    finally:
        tracemalloc.stop()
    live = session.live
    assert len(live.senders) == CAP
    assert live.dropped == SECONDS * PER_SECOND - CAP
    view = session.snapshot(T0 + SECONDS)
    assert view["senders_dropped"] == live.dropped and len(view["senders"]) == CAP
    assert sizes[SECONDS] - sizes[MEASURED] < 1 << 20, sizes     # (1 MiB: noise; 2,000 senders were ~20 MiB)
    assert told["raised"] == told["cleared"] + len(session.active) and len(session.active) <= CAP
    session.close()


def test_each_second_looks_at_the_senders_in_view_not_at_every_sender(monkeypatch):
    """Trial: each look at the time (up to ten a second) asked the analysis about every sender
    ever heard (whether it had settled, and each one's serial verdicts): with 20,000 senders a
    look took 50 ms, and it grew with every new one. Now a look, and the end of a second, touch
    only the senders in the live view and those heard since the last look; a gap waiting for
    its duplicate window is still told once the window has passed."""
    monkeypatch.setattr(L, "MAX_SENDERS", CAP)
    session = Session(Source(), Options(serial_scope="sender"),
                      Settings(name="many", port=5825, crc="mpeg2", crc_order="little", lines=False))
    told: list = []
    emit = session.emit
    session.live.emit = lambda f: (told.append(f), emit(f))
    payload = [E.packet(C.PacketType.VRPO, E.vrpo_payload(0, bytes(16)), serial=n) for n in (1, 2, 5)]
    senders, frame = 2000, 0
    for second in range(senders // PER_SECOND):
        batch = []
        for i in range(second * PER_SECOND, (second + 1) * PER_SECOND):
            frame += 1
            src = bytes((10, 2, (i // 100) >> 8 & 255, (i // 100) & 255))
            batch.append((T0 + second + (i % PER_SECOND) / PER_SECOND, frame, 1, b"",
                          (src, 10000 + i % 100, 5825, payload[0])))
        session._packets(batch)
        session._periodic()
    # One more sender, whose serials 3 and 4 go missing: a gap told once its window has passed.
    last = T0 + senders // PER_SECOND
    session._packets([(last + k * 0.1, frame + 1 + k, 1, b"", (bytes((10, 3, 0, 1)), 20000, 5825, p))
                      for k, p in enumerate(payload)])
    touched: set = set()
    look = Sender.__getattribute__

    def spy(self, name):
        touched.add(id(self))
        return look(self, name)
    monkeypatch.setattr(Sender, "__getattribute__", spy)
    for t in (last + 0.5, last + 1.0, last + 1.5, last + 2.5):
        session._tick(t)
        session._second(t, int(t))
        assert len(touched) <= CAP + 1, t        # (the view, and the sender heard last)
        touched.clear()
    monkeypatch.undo()
    assert len(session.analysis.senders) == senders + 1
    lost = [f for f in told if f["rule"] == "lost"]
    assert [(f["item"]["serial"], f["item"]["count"]) for f in lost] == [(5, 2)]
    session.close()


def test_more_base_units_in_one_read_than_the_live_view_holds(monkeypatch):
    """Trial: a read of more base units than the live view holds (a fuzzer's burst of spoofed VRPI,
    a capture file read at once) ended the monitor with a KeyError: the state of each one's last
    VRPI was put on senders that had left the view later in the same read."""
    monkeypatch.setattr(L, "MAX_SENDERS", CAP)
    session = Session(Source(), Options(), Settings(name="burst", port=5825, crc="mpeg2", crc_order="little",
                                                    lines=False))
    vrpi = E.vrpi_payload({"bu_state": 0x11})
    session._packets([(T0 + i / 1000, i + 1, 1, b"", (bytes((10, 4, i >> 8, i & 255)), 7000,
                                                     5825, E.packet(C.PacketType.VRPI, vrpi, serial=i)))
                      for i in range(CAP + 10)])
    live = session.live
    assert len(live.senders) == CAP and live.dropped == 10
    assert {s.state["bu_state"] for s in live.senders.values()} == {C.BuState(0x11).name.replace("_", " ").title()}
    session.close()


def test_frames_cut_by_the_snaplen_are_counted_not_kept(tmp_path):
    """Trial: a link watched through `tcpdump -s 64 -w - | vm110 monitor --read -` (each EG-Link
    datagram cut short) kept the number of every such frame for as long as it ran. Now the monitor
    counts each once judged and lets it go; the report's `snaplen_truncated` is still analyze's."""
    path = tmp_path / "cut.pcap"
    snapped(Path(__file__).resolve().parent.parent / "captures" / "normal.pcap", path, 60)
    expected = analyze(str(path))["capture"]["snaplen_truncated"]
    session = Session(Source(), Options(), Settings(name=str(path), port=5825, crc="mpeg2", crc_order="little",
                                                    lines=False))
    data = path.read_bytes()
    for pos in range(0, len(data), 4096):
        session._packets(session.reader.feed(data[pos:pos + 4096]))
        assert len(session.reader.snap_truncated) == 0, pos
    session.intake.sync(session.reader)
    assert session.intake.got.snap_truncated == expected > 300
    session.close()


def test_warnings_held_behind_the_dashboard_are_bounded(capsys):
    """Trial: each warning that came while the dashboard was up (an evidence window that could not
    be written, every few minutes of a disk full for a weekend) was kept until the dashboard ended,
    then all said at once. Now the first hundred are kept and the rest counted."""
    session = Session(Source(), Options(), Settings(name="x", port=5825, crc="mpeg2", crc_order="little",
                                                    dashboard=True))
    assert session.board is not None
    session.board.on = True             # (as after its first drawing)
    for n in range(1000):
        session.warn(f"evidence not written: cannot write w{n}.pcapng: No space left on device")
    capsys.readouterr()
    session._end()
    err = capsys.readouterr().err.splitlines()
    assert err == [f"vm110 monitor: evidence not written: cannot write w{n}.pcapng: No space left on device"
                   for n in range(100)] + ["vm110 monitor: and 900 more warning(s), not kept"]
    session.close()


def test_many_senders_heard_are_counted_and_said(tmp_path, monkeypatch, capsys):
    """Trial: every sender heard is kept to the end for the report (some 10 kB each): a fuzzer or
    a device on a new port for every packet grew the monitor's memory, the snapshots' `memory_kb`
    rising with nothing to say why. Now each snapshot counts the senders heard, as many as the
    report lists, and passing SENDERS_SAID (then each tenfold) is said on standard error."""
    import json

    from test_analysis_craft import Traffic, vrpi
    from vm110.cli import main
    from vm110.monitor import session
    monkeypatch.setattr(session, "SENDERS_SAID", 10, raising=False)
    tr = Traffic()
    for k in range(40):
        tr.add(k * 0.01, vrpi(0, origin=k + 1))          # 40 base units (origins) in the first second
    tr.add(1.5, vrpi(1, origin=1))
    tr.add(2.5, vrpi(2, origin=1))
    tr.write(tmp_path / "many.pcap")
    lines, report = tmp_path / "l.jsonl", tmp_path / "a.json"
    main(["monitor", "--read", str(tmp_path / "many.pcap"), "--idle", "0", "--no-dashboard", "--quiet",
          "--crc", "mpeg2", "--crc-order", "little", "--json-lines", str(lines)])
    err = capsys.readouterr().err.splitlines()
    main(["analyze", str(tmp_path / "many.pcap"), "--quiet", "--json", str(report)])
    heard = len(json.loads(report.read_text())["senders"])
    assert heard == 40
    snaps = [json.loads(ln) for ln in lines.read_text().splitlines() if '"snapshot"' in ln]
    assert [s["senders_heard"] for s in snaps] == [heard, heard]
    said = (f"vm110 monitor: {heard} senders heard (an address, port and origin each: a fuzzer, spoofed packets, "
            "or a device on a new port for every packet?): each is kept for the report, those heard least recently "
            "in a temporary file, some 4 kB of disk each (docs/monitor.md, \"Memory for long runs\")")
    assert [ln for ln in err if "senders heard" in ln] == [said]


US = 1_000_000
GROUP = "239.255.42.20"


def _write(path: Path, packets: list[tuple[float, str, int, bytes]]) -> None:
    """(time s, source address, source port, EG-Link packet), to the input port, in time order."""
    packets.sort(key=lambda p: p[0])
    with open(path, "wb") as out, PcapWriter(out) as w:
        w.write_many((int(T0 * US) + round(t * US), UdpFlow(ip, port, GROUP, C.INPUT_PORT).frame(data))
                     for t, ip, port, data in packets)


def _coming_and_going(path: Path) -> None:
    """Senders that come and go: a controller on a new source port for each VRPO (300 ms apart, a
    restart on a new port of the one before), spoofed senders heard once, base units heard for 10 s,
    silent for 50 s, then back (on their port, their serials on after a gap and a copy; or on a
    new port, starting afresh), and commands some of them acknowledge."""
    vrpo, vrpi = E.vrpo_payload(0, bytes(16)), E.vrpi_payload({"bu_state": 0x11})
    packets = [(0.3 * n, "10.0.0.20", 20000 + n, E.packet(C.PacketType.VRPO, vrpo, serial=100 + n))
               for n in range(300)]
    packets += [(0.5 * k + 0.01, f"10.9.0.{k + 1}", 7000, E.packet(C.PacketType.VRPI, vrpi, origin=k, serial=k))
                for k in range(200)]
    for b in range(8):
        ip = f"10.0.1.{b + 1}"
        for n in range(100):
            kind, pay = (C.PacketType.VRPI, vrpi) if n % 2 else (C.PacketType.VRPO, vrpo)
            packets.append((0.1 * n + 0.003 * b, ip, 6000, E.packet(kind, pay, origin=b, serial=n)))
            back = 60 + 0.1 * n + 0.003 * b
            if b % 2:
                packets.append((back, ip, 6001, E.packet(kind, pay, origin=b, serial=n)))
            elif n != 7:
                packets.append((back, ip, 6000, E.packet(kind, pay, origin=b, serial=105 + n)))
                if n == 9:
                    packets.append((back + 0.001, ip, 6000, E.packet(kind, pay, origin=b, serial=105 + n)))
    for c in range(10):
        t = 3.0 + 10 * c
        packets.append((t, "10.0.0.30", 5000, E.packet(C.PacketType.VRCI, E.command_payload(c), serial=c)))
        if t < 10 or t > 60:
            packets.append((t + 0.02, "10.0.1.1", 6100, E.packet(C.PacketType.VRAO, E.ack_payload(c), serial=c)))
    _write(path, packets)


def test_senders_set_aside_and_back_leave_the_report_that_of_analyze(tmp_path, monkeypatch):
    """The monitor keeps in memory the senders heard last (shelf.KEEP; 16 here) and sets the others
    aside in a file: each one heard again, or taken over on a new port, comes back as it was, and
    the report is analyze's to the byte."""
    path = tmp_path / "coming.pcap"
    _coming_and_going(path)
    monkeypatch.setattr(shelf, "KEEP", 16)
    monkeypatch.setattr(L, "MAX_SENDERS", 8)      # (below KEEP, as in use: the live view asks of those in memory)
    moved = Counter()
    put, get = shelf.Shelf.put, shelf.Shelf.get
    monkeypatch.setattr(shelf.Shelf, "put", lambda self, *a: (moved.update(["out"]), put(self, *a))[1])
    monkeypatch.setattr(shelf.Shelf, "get", lambda self, *a: (moved.update(["back"]), get(self, *a))[1])
    a, m = tmp_path / "analyze.json", tmp_path / "monitor.json"
    assert main(["analyze", str(path), "--quiet", "--json", str(a)]) in (0, 1)
    assert not moved                                  # (analyze keeps them all)
    assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json", str(m)]) in (0, 1)
    assert moved["out"] > 400 and moved["back"] > moved["out"]     # (the report reads each back)
    assert a.read_bytes() == m.read_bytes()


def test_senders_heard_in_turn_come_and_go_in_the_same_place_of_the_file(tmp_path, monkeypatch):
    """More senders than shelf.KEEP, each heard every second (spoofed base units in turn, for days):
    each goes to the file and comes back again and again. Each time it takes its place there again
    (a new one only when it has outgrown it twice over): the file does not grow by a copy each time,
    and the report is still analyze's."""
    path = tmp_path / "turns.pcap"
    vrpi = E.vrpi_payload({"bu_state": 0x11})
    _write(path, [(r + 0.02 * k, f"10.5.0.{k + 1}", 7000, E.packet(C.PacketType.VRPI, vrpi, origin=k, serial=r))
                  for r in range(60) for k in range(40)])
    monkeypatch.setattr(shelf, "KEEP", 16)
    monkeypatch.setattr(L, "MAX_SENDERS", 8)
    sizes: list = []
    put = shelf.Shelf.put

    def counted(self, *args):
        stub = put(self, *args)
        sizes.append(os.fstat(self.fd).st_size)
        return stub
    monkeypatch.setattr(shelf.Shelf, "put", counted)
    a, m = tmp_path / "analyze.json", tmp_path / "monitor.json"
    assert main(["analyze", str(path), "--quiet", "--json", str(a)]) in (0, 1)
    assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json", str(m)]) in (0, 1)
    assert len(sizes) > 24 * 50                       # (all but the KEEP heard last leave at every turn)
    # After the first 10 turns, the file grows as the senders' states grow, not by a copy (some 5 kB
    # each, 5.7 MB in all) each time one leaves.
    left = len(sizes) - 24 * 10
    assert sizes[-1] - sizes[24 * 10] < left * 2048 / 4, (left, sizes[24 * 10], sizes[-1])
    assert a.read_bytes() == m.read_bytes()


def test_memory_stays_flat_however_many_senders_come_and_go(tmp_path):
    """Trial: `vm110 monitor --read` of a capture of 20,000 senders (a fuzzer, a device on a new
    port per packet) peaked at 445 MB, some 10 kB kept per sender ever heard. Now the senders heard
    before the last shelf.KEEP go to a file: from 2,500 senders to 5,000 its memory (the
    --json-lines snapshots' resident size) grows by a few hundred bytes a sender, not 19 MB."""
    path, lines = tmp_path / "many.pcap", tmp_path / "lines.json"
    vrpo = E.vrpo_payload(0, bytes(16))
    _write(path, [(i / PER_SECOND, f"10.1.{i // 100 >> 8}.{i // 100 & 255}", 10000 + i % 100,
                   E.packet(C.PacketType.VRPO, vrpo, serial=i)) for i in range(5000)])
    run = subprocess.run([sys.executable, "-m", "vm110", "monitor", "--read", str(path), "--idle", "0", "--quiet",
                          "--no-dashboard", "--json-lines", str(lines)], capture_output=True, timeout=120)
    assert run.returncode in (0, 1), run.stderr
    memory = {s["senders_heard"]: s["memory_kb"] for s in map(json.loads, lines.read_text().splitlines())
              if s.get("type") == "snapshot"}
    low, high = min(n for n in memory if n >= 2500), max(memory)
    assert high >= 4900
    assert memory[high] - memory[low] < 8 * 1024, (memory[low], memory[high])
