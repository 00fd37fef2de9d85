"""`tshark -z vm110,stat` (dissector/vm110.lua) against the synthesizer's ground truth, per sender:
packets by type, lost, duplicates, out of order, wraps, restarts, commands acked, unacknowledged and
interrupted, retransmissions; interval min/avg/max against the timestamps of the accepted packets
(legal ones read from the capture, without the duplicates the independent reference finds)."""
from __future__ import annotations

import itertools
import json
import re
import shutil
from collections import defaultdict
from pathlib import Path

import pytest
from scapy.layers.inet import IP, UDP
from scapy.utils import rdpcap, wrpcap

import tshark_runner as T
from vm110.decode import decode

pytestmark = pytest.mark.tshark

CAPTURES = [T.REPO / "captures" / name for name in ("loss.pcapng", "retransmit.pcap", "glink.pcapng",
                                                     "restart.pcapng", "overlap.pcapng")]
_SENDER = re.compile(r"^Sender (.+)$")
_PACKETS = re.compile(r"^  Packets: (.*)$")
_SERIAL = re.compile(r"^  Serial: lost (\d+), duplicates (\d+), out of order (\d+), wraps (\d+), restarts (\d+)$")
_RESTART = re.compile(r"^  Restart in frame (\d+): serial (\d+) -> (\d+)(?:, port (\d+) -> (\d+))?$")
_COMMANDS = re.compile(r"^  Commands: (\d+), acked (\d+), unacknowledged (\d+), interrupted (\d+), "
                       r"retransmissions (\d+)$")
_SILENT = re.compile(r"^  (VRPI|VRPO) silent until the end: ([\d.]+) ms after frame (\d+)$")
_INTERVAL = re.compile(r"^  (VRPI|VRPO) interval \(ms\): min ([\d.]+), avg ([\d.]+), max ([\d.]+) \((\d+) intervals\)$")


def parse(text: str) -> dict:
    out, current = {}, None
    for line in text.splitlines():
        if m := _SENDER.match(line):
            current = out[m.group(1)] = {"intervals": {}, "restart_events": [], "silent": {}}
        elif m := _PACKETS.match(line):
            current["by_type"] = {k: int(v) for k, v in (p.split() for p in m.group(1).split(", "))}
        elif m := _SERIAL.match(line):
            current["serial"] = dict(zip(("lost", "duplicates", "out_of_order", "wraps", "restarts"),
                                         map(int, m.groups())))
        elif m := _RESTART.match(line):
            event = dict(zip(("frame", "from", "to"), map(int, m.groups()[:3])))
            if m.group(4):
                event.update(port_from=int(m.group(4)), port_to=int(m.group(5)))
            current["restart_events"].append(event)
        elif m := _COMMANDS.match(line):
            current["commands"] = dict(zip(("commands", "acked", "unacked", "interrupted", "retransmissions"),
                                           map(int, m.groups())))
        elif m := _SILENT.match(line):
            current["silent"][m.group(1)] = (float(m.group(2)), int(m.group(3)))
        elif m := _INTERVAL.match(line):
            current["intervals"][m.group(1)] = (*map(float, m.groups()[1:4]), int(m.group(5)))
    return out


def expected_intervals(capture: Path) -> dict:
    """(sender, type) -> (min, avg, max, count) in ms between accepted periodic packets: legal ones
    by vm110.decode, without the duplicates of the independent reference; a sender that restarted
    on a new port continues its predecessor's stream (rules.md)."""
    from reference.analyser import analyse as reference
    ref = reference(str(capture))
    duplicates = {fr for fr, f in ref["frames"].items() if "serial_duplicate" in f}
    times = defaultdict(list)
    for number, pkt in enumerate(rdpcap(str(capture)), start=1):
        if UDP not in pkt or number in duplicates:
            continue
        d = decode(bytes(pkt[UDP].payload)[:pkt[UDP].len - 8])
        if d.get("type") in ("VRPI", "VRPO") and not d["problems"]:
            direction = "Input" if d["type"].endswith("I") else "Output"
            sender = f"{direction} {pkt[IP].src}:{pkt[UDP].sport} origin 0x{d['origin']:04x}"
            times[(sender, d["type"])].append((round(float(pkt.time) * 1e6), number))
    for s in ref["senders"]:
        for e in s["serial"]["restart_events"]:
            if "port_from" not in e:
                continue
            before = s["id"].replace(f":{e['port_to']} ", f":{e['port_from']} ")
            for kind in ("VRPI", "VRPO"):
                earlier = [x for x in times.get((before, kind), []) if x[1] < e["frame"]]
                if earlier and times.get((s["id"], kind)):
                    times[(s["id"], kind)].insert(0, earlier[-1])
    out = {}
    for key, ts in times.items():
        iv = [(b[0] - a[0]) / 1000 for a, b in itertools.pairwise(ts)]
        if iv:
            out[key] = (min(iv), sum(iv) / len(iv), max(iv), len(iv))
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
@pytest.mark.parametrize("capture", CAPTURES, ids=lambda p: p.name)
def test_stat_matches_truth(tshark, capture, tmp_path):
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    try:
        with tshark.workspace(tmp_path) as ws:
            local = ws.dir / capture.name
            local.write_bytes(capture.read_bytes())
            proc = ws.run(["-r", str(local), "-q", "-z", "vm110,stat"], shared=True)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in proc.stdout + proc.stderr
    got = parse(proc.stdout)
    assert sorted(got) == sorted(s["id"] for s in truth["senders"])
    commands = [c for kind in truth["commands"].values() for c in kind["list"]]
    intervals = expected_intervals(capture)
    for sender in truth["senders"]:
        g, sid = got[sender["id"]], sender["id"]
        assert g["by_type"] == sender["by_type"], sid
        want = {k: sender["serial"].get(k, 0) for k in ("lost", "duplicates", "out_of_order", "wraps", "restarts")}
        assert g["serial"] == want, sid
        assert g["restart_events"] == [{k: v for k, v in e.items() if k != "time"}
                                       for e in sender["serial"].get("restart_events", [])], sid
        mine = [c for c in commands if c["sender"] == sid]
        interrupted = interrupted_commands(capture).get(sid, 0)
        assert g["commands"] == {"commands": len(mine), "acked": sum(c["ack_frame"] is not None for c in mine),
                                 "unacked": sum(c["ack_frame"] is None for c in mine) - interrupted,
                                 "interrupted": interrupted,
                                 "retransmissions": sum(len(c["frames"]) - 1 for c in mine)}, sid
        for kind in ("VRPI", "VRPO"):
            want = intervals.get((sid, kind))
            if want is None:
                assert kind not in g["intervals"]
                continue
            assert g["intervals"][kind][3] == want[3]
            assert g["intervals"][kind][:3] == pytest.approx(want[:3], abs=1.5e-3)
    until_end = {(p["sender"], p["type"]): v for p in truth["periodic"]
                 for v in p["watchdog"]["violations"] if v.get("until_end")}
    got_silent = {(sid, kind): v for sid, g in got.items() for kind, v in g["silent"].items()}
    assert sorted(got_silent) == sorted(until_end)
    for key, (gap, _frame) in got_silent.items():
        assert gap == pytest.approx(until_end[key]["gap_ms"], abs=1.5e-3)


def interrupted_commands(capture: Path) -> dict:
    """sender -> its commands interrupted by a restart, by the independent reference."""
    from reference.analyser import analyse as reference
    out: dict = defaultdict(int)
    for kind in ("VRCI", "VRCO"):
        for c in reference(str(capture))["commands"][kind]["list"]:
            if c["interrupted_by"] is not None:
                out[c["sender"]] += 1
    return out


# Stands in for Wireshark's GUI inside tshark (loaded before the plugin; each script has an
# environment of its own over _G): records the menus the plugin registers; a tap's draw then opens
# each one, and its text window prints to stdout.
GUI_STUB = """
local menus = {}
_G.gui_enabled = function() return true end
_G.register_menu = function(name, action, group) menus[#menus + 1] = { name = name, action = action, group = group } end
_G.TextWindow = { new = function(title) return { set = function(_, text) io.write("WINDOW ", title, "\\n", text) end } end }
register_stat_cmd_arg("vm110gui", function()
    local tap = Listener.new("frame", "vm110")
    function tap.draw()
        for _, m in ipairs(menus) do
            io.write("MENU ", m.name, " ", m.group == MENU_STAT_UNSORTED and "MENU_STAT_UNSORTED" or tostring(m.group), "\\n")
            m.action()
        end
    end
end)
"""


def _through_gui_stub(tshark: T.Tshark, tmp_path, stub_text: str) -> tuple:
    """(`-z vm110,stat` text, the run with the GUI stand-in `stub_text` loaded before the plugin)
    on a bundled capture; no Lua error in the latter."""
    capture = CAPTURES[1]
    try:
        with tshark.workspace(tmp_path) as ws:
            local = ws.dir / capture.name
            local.write_bytes(capture.read_bytes())
            stub = ws.dir / "gui_stub.lua"
            stub.write_text(stub_text)
            stat = ws.run(["-r", str(local), "-q", "-z", "vm110,stat"], shared=True).stdout
            gui = ws.run(["-X", f"lua_script:{stub}", "-X", f"lua_script:{ws.plugin()}", "-r", str(local), "-q",
                          "-z", "vm110gui"], plugin=False)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in gui.stdout + gui.stderr, gui.stderr
    return stat, gui


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_gui_menu_shows_the_statistics(tshark, tmp_path):
    """Statistics menu entry: the Qt GUI shows a Lua menu of group MENU_STAT_UNSORTED in Statistics
    (one of MENU_STAT_GENERIC not at all, seen in Wireshark 4.0), and its window has the text of
    `-z vm110,stat`."""
    stat, gui = _through_gui_stub(tshark, tmp_path, GUI_STUB)
    menu, window, text = gui.stdout.split("\n", 2)
    assert menu == "MENU VM-110 EG-Link Stream Statistics MENU_STAT_UNSORTED"
    assert window == "WINDOW VM-110 EG-Link Stream Statistics"
    assert text == stat and "Sender Input 10.0.0.10:5825 origin 0x0101" in text


def _sections(text: str) -> dict[str, list[str]]:
    """Sender -> its lines, with the wraps (not counted with a filter) taken out of the serial line."""
    out, current = {}, None
    for line in text.splitlines():
        if line.startswith("Sender "):
            current = out[line] = []
        elif current is not None:
            current.append(re.sub(r", wraps \d+", "", line))
    return out


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_stat_honours_a_display_filter(tshark, tmp_path):
    """`-z vm110,stat,FILTER` (as Wireshark's own statistics take one): a filter that matches every
    EG-Link packet gives the figures of the whole capture (on a restart, and on loss with late
    packets that fill gaps: lost is net of them in both); one sender's address gives that sender's
    section alone, unchanged; a time window counts exactly the packets `-Y` keeps; single pass and
    -2 agree (the figures come from the final analysis)."""
    capture = T.REPO / "captures" / "restart.pcapng"
    window = "frame.time_relative >= 5 && frame.time_relative < 15"
    try:
        with tshark.workspace(tmp_path) as ws:
            local = ws.dir / capture.name
            local.write_bytes(capture.read_bytes())
            lossy = ws.dir / "loss.pcapng"
            lossy.write_bytes((T.REPO / "captures" / "loss.pcapng").read_bytes())
            def stat(arg, *extra, pcap=local):
                proc = ws.run(["-r", str(pcap), "-q", *extra, "-z", arg], shared=True)
                assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr
                return proc.stdout
            whole = stat("vm110,stat")
            every = stat("vm110,stat,vm110")
            lossy_whole, lossy_every = stat("vm110,stat", pcap=lossy), stat("vm110,stat,vm110", pcap=lossy)
            bu = stat("vm110,stat,ip.src == 10.0.0.10")
            timed, timed2 = stat(f"vm110,stat,{window}"), stat(f"vm110,stat,{window}", "-2")
            nothing = stat("vm110,stat,vm110.type == \"VRXX\"")
            kept = ws.run(["-r", str(local), "-Y", f"vm110 && !vm110.expert.bad_crc && ({window})", "-T", "fields",
                           "-e", "vm110.type"]).stdout.split()
            bad = ws.run(["-r", str(local), "-q", "-z", "vm110,stat,vm110.nonsense == 1"], check=False)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert every.splitlines()[1] == "Display filter: vm110"
    assert _sections(every) == _sections(whole) and len(_sections(whole)) >= 2
    assert _sections(lossy_every) == _sections(lossy_whole)
    assert "out of order 0" not in lossy_whole and "lost 0" not in lossy_whole, "late packets and lost ones"
    sections = _sections(bu)
    assert list(sections) == [s for s in _sections(whole) if "10.0.0.10:" in s]
    assert all(sections[s] == _sections(whole)[s] for s in sections)
    assert timed == timed2
    counted = sum(int(n) for line in timed.splitlines() if line.startswith("  Packets: ")
                  for n in re.findall(r"\d+", line))
    assert counted == len(kept) > 0
    assert "(no EG-Link packet matches the filter)" in nothing
    assert 'vm110,stat: the display filter "vm110.nonsense == 1" does not compile' in bad.stderr


GUI_STUB_FILTERED = GUI_STUB + """
_G.get_filter = function() return 'ip.src == 10.0.0.10' end
_G.retap_packets = function() io.write("RETAP\\n") end
_G.TextWindow = { new = function(title)
    io.write("WINDOW ", title, "\\n")
    return { set = function(_, text) io.write(text) end,
             add_button = function(_, label) io.write("BUTTON ", label, "\\n") end,
             set_atclose = function() io.write("ATCLOSE\\n") end }
end }
"""


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_gui_window_takes_the_display_filter(tshark, tmp_path):
    """The Statistics menu's window takes the display filter applied in the GUI (get_filter()),
    names it in its title, offers a button to ask for another, and retaps the packets through it."""
    _, gui = _through_gui_stub(tshark, tmp_path, GUI_STUB_FILTERED)
    assert gui.stdout.splitlines() == ["MENU VM-110 EG-Link Stream Statistics MENU_STAT_UNSORTED",
                                       "WINDOW VM-110 EG-Link Stream Statistics (ip.src == 10.0.0.10)",
                                       "BUTTON Display filter...", "ATCLOSE", "RETAP"]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_appended_captures_restart_at_the_seam(tshark, tmp_path):
    """Two captures of one link appended (`mergecap -a`: the clock steps back 30 s): each sender
    restarts at its first packet of the second capture, and the serial figures are those of the two
    captures added up (rules.md, "the analysis clock"); `vm110 analyze` says the same."""
    first, second = (T.REPO / "captures" / name for name in ("loss.pcapng", "normal.pcap"))
    packets = [*rdpcap(str(first)), *rdpcap(str(second))]
    truths = [json.loads(Path(f"{c}.truth.json").read_text()) for c in (first, second)]
    seam: dict[str, tuple[int, int]] = {}    # sender -> (frame, serial) of its first packet after the seam
    offset = len(rdpcap(str(first)))
    for number, pkt in enumerate(rdpcap(str(second)), start=offset + 1):
        d = decode(bytes(pkt[UDP].payload))
        sender = f"{d['direction']} {pkt[IP].src}:{pkt[UDP].sport} origin 0x{d['origin']:04x}"
        seam.setdefault(sender, (number, d["serial"]))
    got, report = _stat_and_report(tshark, tmp_path, packets)
    assert sorted(got) == sorted(seam)
    for sender, (frame, serial) in seam.items():
        want = {k: sum(s["serial"].get(k, 0) for t in truths for s in t["senders"] if s["id"] == sender)
                for k in ("lost", "duplicates", "out_of_order")}
        assert {k: got[sender]["serial"][k] for k in want} == want, sender
        [event] = got[sender]["restart_events"]
        assert (event["frame"], event["to"]) == (frame, serial), sender
        [mine] = [s for s in report["senders"] if s["id"] == sender]
        assert {k: mine["serial"][k] for k in (*want, "restarts")} == {**want, "restarts": 1}, sender
        assert [{k: e[k] for k in ("frame", "from", "to")} for e in mine["serial"]["restart_events"]] == [event]
    # The step back begins a new VRPO burst: the last packet before the seam and the first after
    # it were one incomplete burst (less than the burst gap "apart", 30 s back).
    assert report["totals"]["vrpo_incomplete"] == sum(t["vrpo_bursts"]["incomplete"] for t in truths)
    with tshark.workspace(tmp_path / "bursts") as ws:
        def incomplete(name: str, part: list) -> int:
            wrpcap(str(ws.dir / name), part)
            return len(ws.run(["-r", str(ws.dir / name), "-2", "-Y", "vm110.expert.burst_incomplete"]).stdout.split())
        assert incomplete("both.pcap", packets) == incomplete("a.pcap", packets[:offset]) + \
            incomplete("b.pcap", packets[offset:])
        # Each stream's first packet after the seam: a negative interval, flagged (trial: the field
        # was left out, while -z vm110,stat and analyze counted it).
        done = ws.run(["-r", str(ws.dir / "both.pcap"), "-Y", "vm110.expert.time_backwards", "-T", "fields",
                       "-e", "frame.number", "-e", "vm110.analysis.interval", "-e", "vm110.analysis.flags"])
        rows = [line.split("\t") for line in done.stdout.splitlines()]
    items = [i["frame"] for f in report["verdict"]["findings"] if f["rule"] == "time_backwards" for i in f["items"]]
    assert [int(r[0]) for r in rows] == sorted(items) and len(items) == report["capture"]["time_backwards"] > 0
    assert all(float(r[1]) < 0 and "Time Backwards" in r[2] for r in rows), rows


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_ipv6_senders_are_named_as_analyze_names_them(tshark, tmp_path):
    """An IPv6 source in brackets ([fd00::2]:5827), as `vm110 analyze` writes it: the two
    outputs join by sender."""
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import Ether
    from vm110.encode import packet, vrpo_payload
    frames = []
    for n in range(5):
        frame = Ether() / IPv6(src="fd00::2", dst="ff02::1") / UDP(sport=5827, dport=5827) / packet(
            "VRPO", vrpo_payload(0, b"x"), serial=n)
        frame.time = 1_750_000_000 + n / 10
        frames.append(frame)
    got, report = _stat_and_report(tshark, tmp_path, frames)
    assert list(got) == [s["id"] for s in report["senders"]] == ["Output [fd00::2]:5827 origin 0x0000"]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_datagram_quoted_in_an_icmp_error_was_not_received(tshark, tmp_path):
    """A controller's VRPO to a base unit whose port is closed comes back quoted in an ICMP port
    unreachable. Wireshark dissects the quote, but it is no packet received (`vm110 analyze` reads
    no ICMP): it counts nowhere, with or without a filter, and is no finding (trial: each quote was
    a [Duplicate] of its VRPO, VRPO 22 and duplicates 2 where analyze counts 20 and 0)."""
    from scapy.layers.inet import ICMP
    from scapy.layers.l2 import Ether
    from vm110.encode import packet, vrpo_payload
    frames = []
    for n in range(20):
        vrpo = IP(src=T.CONTROLLER_ADDR, dst=T.BU_ADDR) / UDP(sport=5827, dport=5827) / packet(
            "VRPO", vrpo_payload(0, b"x" * 64), serial=n)
        frames.append(Ether() / vrpo)
        if n in (5, 12):
            frames.append(Ether() / IP(src=T.BU_ADDR, dst=T.CONTROLLER_ADDR) / ICMP(type=3, code=3) / vrpo)
    for n, frame in enumerate(frames):
        frame.time = 1_750_000_000 + n / 20
    got, report = _stat_and_report(tshark, tmp_path, frames)
    sender = f"Output {T.CONTROLLER_ADDR}:5827 origin 0x0000"
    assert [s["id"] for s in report["senders"]] == [sender] and report["senders"][0]["by_type"] == {"VRPO": 20}
    assert got[sender]["by_type"] == {"VRPO": 20} and got[sender]["serial"]["duplicates"] == 0
    with tshark.workspace(tmp_path / "icmp") as ws:
        capture = ws.dir / "icmp.pcap"
        wrpcap(str(capture), frames)
        assert parse(ws.run(["-r", str(capture), "-q", "-z", "vm110,stat,vm110"]).stdout)[sender]["by_type"] == \
            {"VRPO": 20}
        assert ws.run(["-r", str(capture), "-2", "-Y", "vm110.analysis.flags || icmp && vm110.analysis.interval"]).stdout == ""
        quoted = ws.run(["-r", str(capture), "-2", "-Y", "icmp && vm110", "-T", "fields", "-e", "vm110.serial"])
        assert quoted.stdout.split() == ["5", "12"]    # (still decoded)


def _stat_and_report(tshark: T.Tshark, tmp_path: Path, packets: list) -> tuple[dict, dict]:
    """`-z vm110,stat` (parsed) and `vm110 analyze`'s report of the packets written as a pcap."""
    from vm110.analysis import analyze
    try:
        with tshark.workspace(tmp_path) as ws:
            capture = ws.dir / "packets.pcap"
            wrpcap(str(capture), packets)
            proc = ws.run(["-r", str(capture), "-q", "-z", "vm110,stat"])
            return parse(proc.stdout), json.loads(json.dumps(analyze(str(capture))))
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_preference_analyze_would_refuse_is_said_and_the_default_used(tshark, tmp_path):
    """Number preferences took any value (trial): a duplicate window of 0 made every mirror copy of
    overlap.pcapng a restart (106), an input port of 65534 an output port of 65536. Each is refused
    as `vm110 analyze` refuses the matching option, said once on tshark's standard error (a dialog
    in Wireshark), and the default analyses the capture."""
    bad = {"vm110.dup_window_ms": "0", "vm110.input_port": "65534", "vm110.vrpo_number_start": "2",
           "vm110.burst_gap_ms": "3600001", "vm110.vrpo_min_ms": "300"}
    with tshark.workspace(tmp_path) as ws:
        capture = ws.dir / "overlap.pcapng"
        shutil.copyfile(T.REPO / "captures" / capture.name, capture)
        plain = ws.run(["-r", str(capture), "-q", "-z", "vm110,stat"])
        refused = ws.run(["-r", str(capture), "-q", "-z", "vm110,stat",
                          *(a for key, value in bad.items() for a in ("-o", f"{key}:{value}"))])
        fine = ws.run(["-r", str(capture), "-q", "-z", "vm110,stat", "-o", "vm110.dup_window_ms:1",
                       "-o", "vm110.input_port:65533", "-o", "vm110.vrpo_min_ms:200"])
    said = [line.split("vm110: preference ", 1)[1] for line in refused.stderr.splitlines()
            if "vm110: preference " in line]
    assert said == ["vm110.input_port = 65534 is outside 1 to 65533; 5825 is used",
                    "vm110.dup_window_ms = 0 is outside 1 to 3600000; 1000 is used",
                    "vm110.vrpo_number_start = 2 is outside 0 to 1; 0 is used",
                    "vm110.burst_gap_ms = 3600001 is outside 1 to 3600000; 20 is used",
                    "vm110.vrpo_min_ms = 300 is above vm110.vrpo_max_ms = 200; 50 and 200 are used"], refused.stderr
    assert refused.stdout == plain.stdout and parse(plain.stdout)
    assert "vm110: preference" not in fine.stderr     # (the limits themselves are taken)


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_refused_preference_is_reset_in_wireshark(tshark, tmp_path):
    """A refused value goes back to the default in Wireshark's own preferences, which the
    preferences dialog shows and saves. Trial: Edit > Preferences showed the refused 0 while 1000
    was used, and its OK wrote `vm110.dup_window_ms: 0` to the preferences file again, refused anew
    on every start. A second Lua script reads the values through Wireshark (get_preference) once
    the capture is read."""
    bad = {"vm110.dup_window_ms": ("0", 1000), "vm110.input_port": ("65534", 5825),
           "vm110.vrpo_min_ms": ("300", 50), "vm110.vrpo_max_ms": ("200", 200),
           "vm110.resend_tolerance_ms": ("0", 0)}   # (a value taken stays)
    with tshark.workspace(tmp_path) as ws:
        probe = ws.dir / "probe.lua"
        probe.write_text("local tap = Listener.new('frame')\nfunction tap.draw()\n"
                         + "".join(f"    print('{name}=' .. tostring(get_preference('{name}')))\n" for name in bad)
                         + "end\n")
        capture = ws.dir / "normal.pcap"
        shutil.copyfile(T.REPO / "captures" / capture.name, capture)
        proc = ws.run(["-X", f"lua_script:{probe}", "-r", str(capture), "-q",
                       *(a for key, (value, _) in bad.items() for a in ("-o", f"{key}:{value}"))])
    assert "vm110.dup_window_ms = 0 is outside" in proc.stderr
    shown = dict(line.split("=") for line in proc.stdout.splitlines() if line.startswith("vm110."))
    assert shown == {name: str(default) for name, (_, default) in bad.items()}
