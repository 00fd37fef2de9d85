"""`tshark -z vm110,stat` (dissector/vm110.lua) against the synthesizer's ground truth, per sender:
packets by type, lost, duplicates, out of order, wraps, retransmissions, acked and unacknowledged
commands; interval min/avg/max against the legal packets' timestamps read from the capture."""
from __future__ import annotations

import json
import re
from collections import defaultdict
from pathlib import Path

import pytest
from scapy.layers.inet import IP, UDP
from scapy.utils import rdpcap

import tshark_runner as T
from vm110.decode import decode

pytestmark = pytest.mark.tshark

CAPTURES = [T.REPO / "captures" / name for name in ("loss.pcapng", "retransmit.pcap", "glink.pcapng")]
_SENDER = re.compile(r"^Sender (.+)$")
_PACKETS = re.compile(r"^  Packets: (.*)$")
_SERIAL = re.compile(r"^  Serial: lost (\d+), duplicates (\d+), out of order (\d+), wraps (\d+)$")
_COMMANDS = re.compile(r"^  Commands: acked (\d+), unacknowledged (\d+), retransmissions (\d+)$")
_INTERVAL = re.compile(r"^  (VRPI|VRPO) interval \(ms\): min ([\d.]+), avg ([\d.]+), max ([\d.]+) \((\d+) intervals\)$")


def parse(text: str) -> dict:
    out, current = {}, None
    for line in text.splitlines():
        if m := _SENDER.match(line):
            current = out[m.group(1)] = {"intervals": {}}
        elif m := _PACKETS.match(line):
            current["by_type"] = {k: int(v) for k, v in (p.split() for p in m.group(1).split(", "))}
        elif m := _SERIAL.match(line):
            current["serial"] = dict(zip(("lost", "duplicates", "out_of_order", "wraps"), map(int, m.groups())))
        elif m := _COMMANDS.match(line):
            current["commands"] = dict(zip(("acked", "unacked", "retransmissions"), map(int, m.groups())))
        elif m := _INTERVAL.match(line):
            current["intervals"][m.group(1)] = (*map(float, m.groups()[1:4]), int(m.group(5)))
    return out


def expected_intervals(capture: Path) -> dict:
    """(sender, type) -> (min, avg, max, count) in ms between legal periodic packets, by vm110.decode."""
    times = defaultdict(list)
    for pkt in rdpcap(str(capture)):
        if UDP not in pkt:
            continue
        d = decode(bytes(pkt[UDP].payload)[:pkt[UDP].len - 8])
        if d.get("type") in ("VRPI", "VRPO") and not d["problems"]:
            direction = "Input" if d["type"].endswith("I") else "Output"
            sender = f"{direction} {pkt[IP].src}:{pkt[UDP].sport} origin 0x{d['origin']:04x}"
            times[(sender, d["type"])].append(int(round(float(pkt.time) * 1e6)))
    out = {}
    for key, ts in times.items():
        iv = [(b - a) / 1000 for a, b in zip(ts, ts[1:])]
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
            proc = ws.run(["-r", str(local), "-q", "-z", "vm110,stat"])
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
        assert g["serial"] == {k: sender["serial"][k] for k in ("lost", "duplicates", "out_of_order", "wraps")}, sid
        mine = [c for c in commands if c["sender"] == sid]
        assert g["commands"] == {"acked": sum(c["ack_frame"] is not None for c in mine),
                                 "unacked": sum(c["ack_frame"] is None for c in mine),
                                 "retransmissions": sum(len(c["frames"]) - 1 for c in mine)}, sid
        for kind in ("VRPI", "VRPO"):
            want = intervals.get((sid, kind))
            if want is None:
                assert kind not in g["intervals"]
                continue
            assert g["intervals"][kind][3] == want[3]
            assert g["intervals"][kind][:3] == pytest.approx(want[:3], abs=1.5e-3)


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


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_gui_menu_shows_the_statistics(tshark, tmp_path):
    """Statistics menu entry: the Qt GUI shows a Lua menu of group MENU_STAT_UNSORTED in Statistics
    (one of MENU_STAT_GENERIC not at all, seen in Wireshark 4.0), and its window has the text of
    `-z vm110,stat`."""
    capture = CAPTURES[1]
    try:
        with tshark.workspace(tmp_path) as ws:
            local = ws.dir / capture.name
            local.write_bytes(capture.read_bytes())
            stub = ws.dir / "gui_stub.lua"
            stub.write_text(GUI_STUB)
            stat = ws.run(["-r", str(local), "-q", "-z", "vm110,stat"]).stdout
            gui = ws.run(["-X", f"lua_script:{stub}", "-X", f"lua_script:{ws.plugin()}", "-r", str(local), "-q",
                          "-z", "vm110gui"], plugin=False)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in gui.stdout + gui.stderr, gui.stderr
    menu, window, text = gui.stdout.split("\n", 2)
    assert menu == "MENU VM-110 EG-Link Stream Statistics MENU_STAT_UNSORTED"
    assert window == "WINDOW VM-110 EG-Link Stream Statistics"
    assert text == stat and "Sender Input 10.0.0.10:5825 origin 0x0101" in text
