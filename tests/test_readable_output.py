"""Readable output (issue 15): `vm110 decode` names enumerated values as the dissector does and
shows times as ISO 8601 UTC and seconds from the capture's start; the analysis summary and synth
do the same. The expectations come from tshark (the dissector's value strings, its own UTC and
relative time columns) and from fixed dates, not from the code under test."""
from __future__ import annotations

import datetime
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import tshark_runner as T
from vm110 import cli
from vm110.layers import VM110, VRPI
from vm110.timefmt import since, stamp, utc_iso

CAPTURES = Path(__file__).resolve().parent.parent / "captures"
ENUMS = ("bu_state", "eg_link", "ec_link", "c_link", "ru_state", "ru_cable", "ru_docked", "ru_disabled",
         "encoder_switch")


def vm110(capsys, *args: str) -> str:
    """Standard output of `vm110 ARGS`, run in-process (exit code 0 required)."""
    assert cli.main(list(args)) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("seconds, text", [
    (0, "1970-01-01T00:00:00.000000Z"),
    (1_750_000_000, "2025-06-15T15:06:40.000000Z"),          # the synthesised captures' start (README)
    (1_750_000_000.125, "2025-06-15T15:06:40.125000Z"),
    (1_750_000_000.9999996, "2025-06-15T15:06:41.000000Z"),   # rounded to the µs, carried into the second
    (951_782_400.5, "2000-02-29T00:00:00.500000Z"),
    (-1.5, "1969-12-31T23:59:58.500000Z"),
    (1e300, "1e+300 s"), (float("nan"), "nan s"), (float("inf"), "inf s"),   # no date: the raw value
])
def test_utc_iso(seconds, text):
    assert utc_iso(seconds) == text


@pytest.mark.parametrize("seconds, start, text", [
    (12.5, 2.25, "+10.250000"), (1.0, 1.0, "+0.000000"), (0.5, 1.0, "-0.500000"), (None, 0.0, "-"),
    (float("nan"), 0.0, "-"),
])
def test_since(seconds, start, text):
    assert since(seconds, start) == text


def test_stamp():
    assert stamp(1_750_000_001.5, 1_750_000_000) == "2025-06-15T15:06:41.500000Z (+1.500000 s)"
    assert stamp(None, 0) == "-"


def tshark_view(pcap: Path) -> tuple[dict[int, tuple[str, str]], dict[int, dict[str, str]]]:
    """Per frame: tshark's UTC and relative time, and the dissector's text of each enum field."""
    with T.HOST.workspace(pcap.parent) as ws:
        cols = ws.run(["-r", str(pcap), "-t", "ud", "-T", "fields", "-e", "frame.number", "-e", "_ws.col.Time",
                       "-e", "frame.time_relative"]).stdout
        frames, _ = T.dissect_pdml(ws, pcap)
    times = {int(n): (t, r) for n, t, r in (line.split("\t") for line in cols.splitlines())}
    enums = {f.number: {i.name[len("vm110."):]: T.showname_value(i) for i in f.items if i.name[6:] in ENUMS}
             for f in frames}
    return times, enums


def iso_of_tshark(text: str) -> str:
    """tshark's "2025-06-15 15:06:40.000000" (-t ud) as ISO 8601 UTC."""
    return text.replace(" ", "T") + "Z"


@pytest.mark.tshark
def test_decode_shows_the_dissector_s_names_and_tshark_s_times(capsys, tmp_path):
    odd = tmp_path / "odd.pcap"       # values beyond the enumerations: "Unknown (0x..)" in both
    T.write_pcap(odd, [bytes(VM110(serial=1) / VRPI(bu_state=0x07, ru_cable=5, eg_link=9, armed_ru=0x0C07)),
                       bytes(VM110(serial=2) / VRPI(bu_state=0x11, ru_state=3, armed_ru=0x0C07))], [0, 1_250_000])
    for pcap in (CAPTURES / "bu-watchdog.pcap", odd):
        times, enums = tshark_view(pcap)
        lines = vm110(capsys, "decode", str(pcap)).splitlines()[:-1]
        records = [json.loads(line) for line in vm110(capsys, "decode", str(pcap), "--json").splitlines()]
        assert len(lines) == len(records) == len(times)
        states = set()
        for line, record in zip(lines, records):
            frame = record["frame"]
            utc, relative = times[frame]
            words = line.split()
            assert words[:3] == [str(frame), iso_of_tshark(utc), f"+{float(relative):.6f}"]
            assert record["time_utc"] == iso_of_tshark(utc) and record["time_relative"] == pytest.approx(float(relative))
            for name, shown in enums[frame].items():          # "Armed (0x11)", "Unknown (0x07)"
                assert record["names"][name] == shown.rsplit(" (", 1)[0]
                if name in ("bu_state", "ru_state"):
                    assert f"{name}={shown}" in line
                    states.add(shown)
        assert len(states) >= 2                               # the capture changes state: not one name twice


def test_the_summary_shows_start_and_end_in_utc_and_relays_relative(capsys):
    out = vm110(capsys, "analyze", str(CAPTURES / "bu-watchdog.pcap"))
    # README (captures): from 2025-06-15 15:06:40 UTC, 15 s; the relays open at 7.0 s for 1.125 s.
    assert "Time: 2025-06-15T15:06:40.000000Z to 2025-06-15T15:06:54.900000Z (UTC)" in out
    relays = next(line for line in out.splitlines() if line.startswith("ES-Link relays open"))
    assert "2025-06-15T15:06:47.0000" in relays and "(+7.0000" in relays and "for 1.125 s" in relays
    assert "1750000" not in out                               # no raw epoch seconds anywhere


def relays_capture(path: Path, opened_us: int, closed_us: int) -> Path:
    """VRPI every 125 ms for 1 s, the BU in "External link error" (ES-Link relays open) from
    `opened_us` until the packet at `closed_us`, armed before and after."""
    times = sorted({*range(0, 1_000_000, 125_000), opened_us, closed_us})
    T.write_pcap(path, [bytes(VM110(origin=0x0101, serial=i) / VRPI(
        bu_state=0x02 if opened_us <= t < closed_us else 0x11, armed_ru=0x0C07, ru_state=3))
        for i, t in enumerate(times)], times)
    return path


def test_finding_items_keep_seconds_to_the_ms(capsys, tmp_path):
    """Relays open for 0.237654 s (the capture's own times): the finding's item line says 0.238 s
    as the relays line does (it said 0.2); the JSON keeps every digit."""
    pcap = relays_capture(tmp_path / "relays.pcap", 250_000, 487_654)
    out = vm110(capsys, "analyze", str(pcap), "--json", str(tmp_path / "r.json"))
    item = next(line for line in out.splitlines() if "duration_s" in line)
    relays = next(line for line in out.splitlines() if line.startswith("ES-Link relays open"))
    assert "duration_s 0.238, states External link error " in item and "for 0.238 s" in relays, (item, relays)
    report = json.loads((tmp_path / "r.json").read_text())
    (finding,) = [f for f in report["verdict"]["findings"] if f["rule"] == "relays_open"]
    assert finding["items"][0]["duration_s"] == pytest.approx(0.237654, abs=1e-6)


def test_relays_still_open_at_the_end_say_so(capsys, tmp_path):
    """The BU stops at 0.5 s and is still stopped when the capture ends at 0.875 s (spec 4.1.1: the
    relays are open below 0x10). Its item and its relays line said "duration_s 0.375" and "for
    0.375 s", read as relays that closed again (trial); the JSON knew (`open_at_end`), they did not."""
    times = list(range(0, 1_000_000, 125_000))
    T.write_pcap(tmp_path / "stopped.pcap", [bytes(VM110(origin=0x0101, serial=i) / VRPI(
        bu_state=0x01 if t >= 500_000 else 0x11, armed_ru=0x0C07, ru_state=4 if t >= 500_000 else 3))
        for i, t in enumerate(times)], times)
    out = vm110(capsys, "analyze", str(tmp_path / "stopped.pcap"), "--json", str(tmp_path / "r.json"))
    item = next(line for line in out.splitlines() if "duration_s" in line)
    relays = next(line for line in out.splitlines() if line.startswith("ES-Link relays open"))
    assert "duration_s 0.375, states Stopped, open_at_end True " in item, item
    assert relays.endswith("for 0.375 s Stopped, still open at the end"), relays
    (finding,) = [f for f in json.loads((tmp_path / "r.json").read_text())["verdict"]["findings"]
                  if f["rule"] == "relays_open"]
    assert finding["items"][0]["open_at_end"] is True


def test_an_items_lists_read_as_words(capsys):
    """An illegal packet's reasons were printed as Python's ['bad_crc'] (trial); they read as words."""
    out = vm110(capsys, "analyze", str(CAPTURES / "illegal.pcap"), "--list")
    reasons = [line.split(", reasons ", 1)[1].split("  [")[0] for line in out.splitlines() if ", reasons " in line]
    assert reasons and all(r and "[" not in r and "'" not in r for r in reasons), reasons
    assert "bad_crc" in reasons


def test_restart_s_relays_duration_reads_the_same_twice(capsys):
    """The trial's case: restart.pcapng's relays-open episodes (the watchdog's, the rebooted BU's
    Initial state), each in its finding and its section."""
    out = vm110(capsys, "analyze", str(CAPTURES / "restart.pcapng")).splitlines()
    items = [line for line in out if "duration_s" in line]
    seconds = re.findall(r" for ([\d.]+) s ", next(line for line in out if line.startswith("ES-Link relays open")))
    assert len(items) == len(seconds) == 2, (items, seconds)
    for item, s in zip(items, seconds):
        assert f"duration_s {s}, states " in item and len(s.split(".")[1]) == 3, (item, s)


def test_the_summary_names_ms_for_ack_latency(capsys):
    """retransmit.pcap's VRCI are acknowledged up to 1599.991 ms after their first transmission
    (its truth file): the column that shows 1600.0 says it is in ms."""
    truth = json.loads((CAPTURES / "retransmit.pcap.truth.json").read_text())
    latencies = [c["latency_first_ms"] for c in truth["commands"]["VRCI"]["list"] if c["latency_first_ms"] is not None]
    lines = vm110(capsys, "analyze", str(CAPTURES / "retransmit.pcap")).splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("acks "))
    header = re.split(r"\s{2,}", lines[at].strip())
    assert header[-3:] == ["lat p50 ms", "lat p95 ms", "lat max ms"]
    vrci = dict(zip(header, re.split(r"\s{2,}", next(line for line in lines[at:] if line.startswith("VRCI")).strip())))
    assert vrci["lat max ms"] == f"{max(latencies):.1f}" == "1600.0"


def test_the_commands_tables_fit_an_80_column_terminal(capsys):
    """The field engineer's terminal: the commands table was 135 columns wide and wrapped, its
    numbers under no heading. overlap.pcapng has 100 VRCI transmissions (its truth file)."""
    truth = json.loads((CAPTURES / "overlap.pcapng.truth.json").read_text())
    lines = vm110(capsys, "analyze", str(CAPTURES / "overlap.pcapng")).splitlines()
    at, end = lines.index(next(ln for ln in lines if ln.startswith("commands "))), len(lines) - 1
    tables = lines[at:end]
    assert lines[end].startswith("VRPO bursts: ") and len(tables) == 6 and max(map(len, tables)) <= 80, tables
    heads = [re.split(r"\s{2,}", tables[i].strip()) for i in (0, 3)]
    vrci = {**dict(zip(heads[0], tables[1].split())), **dict(zip(heads[1], tables[4].split()))}
    assert (vrci["tx"], vrci["orphan acks"]) == (str(truth["commands"]["VRCI"]["transmissions"]), "0")


def test_synth_says_when_its_capture_lies(capsys, tmp_path):
    out = vm110(capsys, "synth", "normal", "--duration", "1", "--out", str(tmp_path / "n.pcap"))
    assert "from 2025-06-15T15:06:40.000000Z to 2025-06-15T15:06:40.9" in out


def test_simulate_logs_wall_clock_utc_beside_the_node_s_seconds():
    """Over loopback only (unicast to the discard port): each event line starts with the UTC time,
    then the node's seconds from its start; the two clocks advance alike."""
    run = [sys.executable, "-m", "vm110", "simulate", "bu", "--peer", "127.0.0.1:9", "--listen", "127.0.0.1:0",
           "--source", "127.0.0.1:0", "--duration", "1.8", "--command-every", "0.5"]
    before = datetime.datetime.now(datetime.timezone.utc)
    lines = subprocess.run(run, capture_output=True, text=True, timeout=60, check=True).stdout.splitlines()
    events = [line.split() for line in lines if line[:1].isdigit()]
    assert len(events) >= 2 and all(e[2:4] == ["bu", "command_sent"] for e in events), lines
    stamps = [datetime.datetime.strptime(e[0], "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=datetime.timezone.utc)
              for e in events]
    assert before <= stamps[0] <= datetime.datetime.now(datetime.timezone.utc)
    wall, node = (stamps[1] - stamps[0]).total_seconds(), float(events[1][1]) - float(events[0][1])
    assert node == pytest.approx(0.5, abs=0.01) and wall == pytest.approx(node, abs=0.4), lines   # a busy machine


def test_the_crc_line_says_how_many_packets_carried_no_crc(capsys, tmp_path):
    """A capture taken with a short snaplen (tcpdump -s 96): the summary said "3 valid, 0 invalid"
    of three VRPI of which two were cut before their CRC and never checked (trial); the report's
    crc.valid counts them (they do not fail), crc.unchecked says so, and now the summary and the
    HTML report too. The HTML left out "(auto)": that the capture chose the variant."""
    from scapy.layers.inet import IP, UDP
    from scapy.layers.l2 import Ether
    from test_analysis_craft import vrpi
    from test_reader import pcap
    frames = [bytes(Ether() / IP(src="10.0.0.10", dst="239.255.42.20") / UDP(sport=5825, dport=5825) / vrpi(i))
              for i in range(3)]
    path = tmp_path / "snap96.pcap"
    path.write_bytes(pcap([(1.0, frames[0][:96], len(frames[0])), (1.125, frames[1]),
                           (1.25, frames[2][:96], len(frames[2]))], snaplen=96))
    out = vm110(capsys, "analyze", str(path), "--html", str(tmp_path / "r.html"))
    line = "CRC mpeg2/little (auto): 3 valid, 0 invalid (2 of them unchecked: too short to carry a CRC)"
    headline = re.search(r'<p><span class="(?:ok|fail)">.*?</p>', (tmp_path / "r.html").read_text())
    assert line in out and headline and line in headline.group()


def test_packet_ids_off_the_network_reach_no_terminal_in_the_summary(capsys, tmp_path):
    """Any host on the link can send a datagram whose packet ID is ESC [ 2 J: analyze's summary
    (and the monitor's, the same code) printed it as it came, and the terminal cleared its screen.
    It gives such characters as their escapes; the JSON keeps the bytes as they came."""
    from vm110.capture.writer import PcapWriter, UdpFlow
    capture = tmp_path / "esc.pcap"
    flow = UdpFlow("10.0.0.10", 5825, "239.255.42.20", 5825)
    with open(capture, "wb") as f, PcapWriter(f) as w:
        w.write_many([(1_750_000_000_000_000, flow.frame(b"\x1b[2J" + bytes(30)))])
    out = vm110(capsys, "analyze", str(capture), "--json", str(tmp_path / "r.json"))
    assert "type \\x1b[2J," in out and all(line.isprintable() for line in out.splitlines())
    items = json.loads((tmp_path / "r.json").read_text())["verdict"]["findings"][0]["items"]
    assert items[0]["type"] == "\x1b[2J"


def test_the_summary_gives_every_detail_of_an_item(capsys, tmp_path):
    """A VRCI acknowledged 2.5 s after it was sent has failed; the summary's item left out its
    latency and the acknowledgement's frame (the JSON and the HTML had them), so it read as one never
    acknowledged. The damage's item left out its byte offset and read `frame 34 at +3.875000 s: `."""
    from test_analysis_craft import BU, CTRL, Traffic, payload, vrpi
    from vm110 import constants as C
    from vm110.layers import VRAO, VRCI
    tr = Traffic()
    for k in range(33):
        tr.add(k * 0.125, vrpi(k))
    tr.add(0.5 + 0.0001, payload(VRCI, 100, 0x0101, command_id=7), src=BU)
    tr.add(3.0 + 0.0001, payload(VRAO, 1, command_id=7), src=CTRL, sport=C.OUTPUT_PORT)
    tr.frames.sort(key=lambda f: f[0])
    path = tmp_path / "late.pcap"
    tr.write(path)
    data = path.read_bytes()
    last = len(data) - 16 - (len(tr.frames[-1][4]) + 42)         # the last record: header, Ether/IP/UDP, EG-Link
    path.write_bytes(data[:last + 20])                            # cut in its frame
    assert cli.main(["analyze", str(path)]) == 2
    lines = capsys.readouterr().out.splitlines()
    ack = 1 + 25 + 1                              # after the VRCI and the 25 VRPI up to 3.0 s
    failed = lines[lines.index("  error   1 command failed (no acknowledgement within the limit)") + 1]
    assert f", type VRCI, command_id 7, latency_ms 2500.000, ack_frame {ack}  [" in failed, failed
    damaged = next(line for line in lines if line.startswith("            frame 34 at"))   # the last one read
    assert damaged == f"            frame 34 at +3.875000 s: offset {last}  [frame.number == 34]"


def test_one_of_a_kind_is_said_in_the_singular(tmp_path):
    """One packet lost, one frame of a tunnel, one IP fragment: the summary said `lost 1 in 1 gaps`
    and the findings `1 frames of tunnels`, `1 IP fragments`."""
    from scapy.layers.inet import GRE, IP, UDP
    from scapy.layers.l2 import Ether
    from test_reader import pcap
    from vm110 import constants as C
    from vm110.analysis import analyze, summary
    from test_analysis_craft import vrpi
    udp = IP(src="10.0.0.10", dst=C.MULTICAST_GROUP) / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT)
    records = [(1_700_000_000 + k * 0.125, Ether() / udp / vrpi(k)) for k in range(8) if k != 4]
    records.append((1_700_000_001.0, Ether() / IP(src="10.0.0.30", dst="10.0.0.40") / GRE() / udp / vrpi(0)))
    records.append((1_700_000_001.1, Ether() / IP(src="10.0.0.10", dst=C.MULTICAST_GROUP, flags="MF", proto=17)
                    / bytes(16)))
    path = tmp_path / "ones.pcap"
    path.write_bytes(pcap(records))
    report = analyze(str(path))
    messages = {f["rule"]: f["message"] for f in report["verdict"]["findings"]}
    assert messages["tunnels"].startswith("1 frame of tunnels not unwrapped")
    assert messages["ip_fragments"].startswith("1 IP fragment not analysed")
    [serials] = [line for line in summary.render(report).splitlines() if line.startswith("  serials: ")]
    assert serials.startswith("  serials: received 7, lost 1 in 1 gap, duplicates 0")
