"""Both engines give the same report: the fast one (own reader and decoder) and the tshark one
(the Lua dissector through pyshark), on every bundled capture and on crafted and synthesised ones."""
from __future__ import annotations

import gzip
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time

import pytest

import tshark_runner as T
from longrun import runner_params
from test_analysis_engine import build_mixed
from test_analysis_truth import ALL_CAPTURES, CAPTURES
from vm110 import constants as C
from vm110.analysis import analyze
from vm110.analysis import tshark_packets
from vm110.analysis.findings import located_item
from vm110.synth import synthesize

VM110 = [sys.executable, "-m", "vm110"]

pytestmark = pytest.mark.tshark


def comparable(report: dict) -> dict:
    """Everything but the engine's name and the CRC candidates the tshark engine did not need to try."""
    out = json.loads(json.dumps(report))
    del out["tool"]
    del out["crc"]["candidates"]
    return out


def assert_same(path: str) -> None:
    fast, slow = comparable(analyze(path)), comparable(analyze(path, engine="tshark"))
    for key in fast:
        assert slow[key] == fast[key], key
    assert slow == fast


@pytest.mark.parametrize("capture", ALL_CAPTURES, ids=lambda p: p.name)
def test_engines_agree_on_bundled_captures(capture):
    assert_same(str(capture))


def test_engines_agree_on_a_gzip_compressed_capture(tmp_path):
    """tshark reads a gzip-compressed capture itself; the fast engine now too."""
    path = tmp_path / "normal.pcap.gz"
    path.write_bytes(gzip.compress((CAPTURES / "normal.pcap").read_bytes()))
    assert analyze(str(path))["capture"]["eglink_packets"] > 0
    assert_same(str(path))


def test_the_user_s_wireshark_preferences_change_no_number(tmp_path, monkeypatch):
    """A user who switched the CRC check and the heuristic off in Wireshark (its preferences file):
    the tshark engine then counted no bad CRC and no packet on another port, 14 illegal packets
    in illegal.pcap instead of 22 (trial-readme). It pins them: the numbers are the fast engine's."""
    config = tmp_path / ".config" / "wireshark"
    config.mkdir(parents=True)
    (config / "preferences").write_text("vm110.check_crc: FALSE\nvm110.heuristic: FALSE\n")
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    monkeypatch.delenv("WIRESHARK_CONFIG_DIR", raising=False)
    assert_same(str(CAPTURES / "illegal.pcap"))


def test_the_user_s_enabled_protocols_change_no_number(tmp_path, monkeypatch):
    """A user who disabled vm110 in Wireshark (Analyze > Enabled Protocols: disabled_protos in
    their configuration): the tshark engine found no EG-Link packet in normal.pcap (no_eglink),
    where the fast engine found them all (trial-fleet). It reads with an empty configuration."""
    config = tmp_path / "wireshark"
    config.mkdir()
    (config / "disabled_protos").write_text("vm110\n")
    monkeypatch.setenv("WIRESHARK_CONFIG_DIR", str(config))
    assert_same(str(CAPTURES / "normal.pcap"))
    assert os.environ["WIRESHARK_CONFIG_DIR"] == str(config)


def test_an_installed_plugin_that_differs_is_not_used_silently(tmp_path, monkeypatch):
    """The user's installed vm110.lua loads first and the package's stands aside (its line on
    tshark's standard error, which the engine hid): an older installed copy decoded the capture,
    unsaid (trial-readme). A copy that differs is one line, exit 2; the same copy is used."""
    plugins = tmp_path / ".local" / "lib" / "wireshark" / "plugins"
    plugins.mkdir(parents=True)
    ours = (CAPTURES.parent / "dissector" / "vm110.lua").read_text()
    monkeypatch.setenv("HOME", str(tmp_path))
    capture = str(CAPTURES / "normal.pcap")
    command = [*VM110, "analyze", capture, "--engine", "tshark", "--quiet"]
    (plugins / "vm110.lua").write_text(ours.replace('PLUGIN_VERSION = "', 'PLUGIN_VERSION = "0.0.1-old-'))
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert f"the plugin tshark loads first, {plugins / 'vm110.lua'} (version 0.0.1-old-" in done.stderr
    (plugins / "vm110.lua").write_text(ours)
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_the_plugin_is_checked_once_per_process_while_nothing_changes(tmp_path, monkeypatch):
    """A run of several captures ran `tshark -G protocols` again for each; a plugin file changed
    (or another tshark, or another home) is checked again."""
    from vm110.analysis import tshark_engine
    from vm110.plugin import PLUGIN_ENV
    runs = []
    real = tshark_engine.list_protocols
    monkeypatch.setattr(tshark_engine, "list_protocols", lambda *a: runs.append(a) or real(*a))
    monkeypatch.setattr(tshark_engine, "_CHECKED", set())
    plugin = tmp_path / "vm110.lua"
    shutil.copyfile(CAPTURES.parent / "dissector" / "vm110.lua", plugin)
    monkeypatch.setenv(PLUGIN_ENV, str(plugin))
    from vectorlib import load_vectors, packet_bytes
    capture = str(tmp_path / "one.pcap")
    T.write_pcap(tmp_path / "one.pcap", [packet_bytes(load_vectors()[0])])
    first = analyze(capture, "tshark")
    assert first["totals"]["packets"] == 1 and analyze(capture, "tshark") == first and len(runs) == 1
    plugin.write_text(plugin.read_text() + "\n-- changed\n")
    analyze(capture, "tshark")
    monkeypatch.setenv("HOME", str(tmp_path))
    analyze(capture, "tshark")
    assert len(runs) == 3


@pytest.mark.parametrize("wrap", ["sll2-vlan", "ipv6-atomic-fragment", "port-7000", "radiotap"])
def test_engines_agree_on_unusual_wrappings(wrap, tmp_path):
    """The bundled traffic as a cooked capture of a tagged interface, over IPv6 in atomic fragments
    (RFC 6946: whole datagrams), on ports 7000/7002, which Wireshark gives to AFS, and over the air
    (802.11 QoS data with radiotap: TS-0006 5.3, G-Link is WiFi): the reader found no EG-Link
    packet in the first two and the last, the tshark engine only some in the third."""
    from scapy.layers.dot11 import Dot11, Dot11QoS, RadioTap
    from scapy.layers.inet import IP, UDP
    from scapy.layers.inet6 import IPv6, IPv6ExtHdrFragment
    from scapy.layers.l2 import LLC, SNAP, CookedLinuxV2, Dot1Q, Ether
    from scapy.utils import rdpcap, wrpcap
    frames = []
    for i, p in enumerate(rdpcap(str(CAPTURES / "normal.pcap"))[:80]):
        udp = p[UDP]
        inner = UDP(sport=udp.sport, dport=udp.dport) / bytes(udp.payload)[:udp.len - 8]
        if wrap == "sll2-vlan":
            f = CookedLinuxV2(proto=0x8100) / Dot1Q(vlan=7) / IP(src=p[IP].src, dst=p[IP].dst) / inner
        elif wrap == "radiotap":
            f = (RadioTap() / Dot11(type=2, subtype=8, FCfield=0x02) / Dot11QoS() / LLC(dsap=0xAA, ssap=0xAA, ctrl=3)
                 / SNAP(code=0x0800) / IP(src=p[IP].src, dst=p[IP].dst) / inner)
        elif wrap == "port-7000":
            inner[UDP].sport, inner[UDP].dport = udp.sport + 1175, udp.dport + 1175
            f = Ether() / IP(src=p[IP].src, dst=p[IP].dst) / inner
        else:
            f = (Ether() / IPv6(src=f"fe80::{p[IP].src.split('.')[-1]}", dst="ff02::1")
                 / IPv6ExtHdrFragment(offset=0, m=0, id=i) / inner)
        f.time = p.time
        frames.append(f)
    path = tmp_path / f"{wrap}.pcap"
    wrpcap(str(path), frames, linktype={"sll2-vlan": 276, "radiotap": 127}.get(wrap, 1))
    assert analyze(str(path))["capture"]["eglink_packets"] == 80
    assert_same(str(path))


def test_engines_agree_on_the_crafted_capture(tmp_path):
    build_mixed(tmp_path / "mixed.pcap")
    assert_same(str(tmp_path / "mixed.pcap"))


def test_engines_agree_on_a_synthesised_capture(tmp_path):
    out = tmp_path / "retransmit.pcapng"
    synthesize("retransmit", str(out), 3, None, "pcapng")
    assert_same(str(out))


def test_engines_agree_on_another_crc_variant(tmp_path):
    from test_analysis_craft import BU_ORIGIN, Traffic, payload
    from vm110 import constants as C
    from vm110.layers import VRPI
    tr = Traffic()
    for i in range(10):
        tr.add(i * 0.125, payload(VRPI, i, BU_ORIGIN, variant="iso-hdlc", order="big", bu_state=C.BuState.ARMED,
                                  crc=0 if i == 4 else None))
    tr.write(tmp_path / "iso.pcap")
    report = analyze(str(tmp_path / "iso.pcap"), engine="tshark")
    assert (report["crc"]["variant"], report["crc"]["byte_order"], report["crc"]["valid"]) == ("iso-hdlc", "big", 9)
    assert_same(str(tmp_path / "iso.pcap"))


def test_engines_count_the_same_packets_for_each_crc_candidate(tmp_path):
    """With some packets failing the default CRC, the tshark engine counts each candidate in one
    Python pass; it left out a packet the heuristic finds on another port, which the fast engine
    counts (self-fuzz, seed 301: 189 against 190)."""
    from test_analysis_craft import BU_ORIGIN, Traffic, payload
    from vm110.layers import VRPI
    tr = Traffic()
    for i in range(10):
        tr.add(i * 0.125, payload(VRPI, i, BU_ORIGIN, bu_state=C.BuState.ARMED, crc=0 if i in (3, 6) else None),
               sport=C.INPUT_PORT if i != 8 else 6000)
    tr.write(tmp_path / "heuristic.pcap")
    fast, slow = analyze(str(tmp_path / "heuristic.pcap")), analyze(str(tmp_path / "heuristic.pcap"), engine="tshark")
    assert fast["capture"]["eglink_packets"] == 10 and fast["crc"]["valid"] == 8
    assert slow["crc"]["candidates"] == fast["crc"]["candidates"]
    assert_same(str(tmp_path / "heuristic.pcap"))


def test_a_datagram_on_an_eglink_port_from_a_lower_port_is_eglink_in_both_engines(tmp_path):
    """Wireshark gives a datagram to its lower port's dissector first: one from port 5683 (CoAP) to
    the controller's 5827 went to CoAP when it was no legal EG-Link packet (the heuristic, tried
    first, wants one), and the tshark engine lost it where the fast engine counts it truncated
    (self-fuzz: a damaged source port). On every Wireshark: CoAP's without the plugin, EG-Link's
    with it as the tshark engine runs it (the heuristic tried first)."""
    from test_analysis_craft import CTRL, Traffic, payload
    from vm110.layers import VRPO
    tr = Traffic()
    for i in range(8):
        data = payload(VRPO, i, packet_number=0, periodic_data=b"a")
        tr.add(i * 0.1, data[:-6] if i == 5 else data, src=CTRL, sport=C.OUTPUT_PORT if i != 5 else 5683,
               dport=C.OUTPUT_PORT)
    tr.write(tmp_path / "coap.pcap")
    fast = analyze(str(tmp_path / "coap.pcap"))
    assert (fast["illegal"]["total"], fast["capture"]["eglink_packets"]) == (1, 8)
    assert comparable(analyze(str(tmp_path / "coap.pcap"), engine="tshark")) == comparable(fast)
    for tshark in T.RUNNERS:
        with tshark.workspace(tmp_path / tshark.name) as ws:
            tr.write(ws.dir / "coap.pcap")
            path = str(ws.dir / "coap.pcap")
            shown = ["-r", path, "-Y", "frame.number == 6", "-T", "fields", "-e", "frame.protocols"]
            plain = ws.run(shown, plugin=False).stdout.strip()
            ours = ws.run(["-o", "udp.try_heuristic_first:TRUE", *shown]).stdout.strip()
        assert plain.endswith(":coap") and ours.endswith(":vm110"), (tshark.name, plain, ours)


def test_engines_agree_on_mixed_traffic(tmp_path):
    from scapy.layers.inet import IP, TCP, UDP, fragment
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import ARP, Dot1Q, Ether
    from test_analysis_craft import vrpi
    from test_reader import pcap
    from vm110 import constants as C
    port = C.INPUT_PORT
    records = []
    for i in range(8):
        head = Ether() / Dot1Q(vlan=5) if i % 2 else Ether()
        records.append((1_700_000_000 + i * 0.125, head / IP(src="10.0.0.10", dst="239.255.42.20")
                        / UDP(sport=port, dport=port) / vrpi(i if i != 5 else 40)))
        records.append((1_700_000_000 + i * 0.125 + 0.01, Ether() / IPv6(src="fd00::7", dst="ff02::1")
                        / UDP(sport=port, dport=port) / vrpi(i, 0x0303)))
    frags = fragment(IP(src="10.0.0.1", dst="10.0.0.2") / UDP(sport=1, dport=2) / bytes(3000), fragsize=1000)
    records += [(1_700_000_002.0, Ether() / ARP()), (1_700_000_002.1, Ether() / IP() / TCP()),
                *((1_700_000_002.2 + i / 100, Ether() / f) for i, f in enumerate(frags))]
    (tmp_path / "mixed.pcap").write_bytes(pcap(records))
    assert_same(str(tmp_path / "mixed.pcap"))


def test_auto_crc_needs_no_tshark_run_per_candidate(monkeypatch):
    """A capture with bad CRCs once took a tshark run per CRC candidate (8; the self-fuzzer saw
    26 s on overlap.pcapng): the candidates are counted in one Python pass instead."""
    from vm110.analysis import tshark_engine
    runs = []
    real = tshark_engine.TsharkEngine._packets

    def counted(self, path, variant, order):
        runs.append((variant, order))
        return real(self, path, variant, order)

    monkeypatch.setattr(tshark_engine.TsharkEngine, "_packets", counted)
    report = analyze(str(CAPTURES / "illegal.pcap"), "tshark")
    assert runs == [("mpeg2", "little")] and report["crc"]["invalid"] > 0
    assert report["crc"]["candidates"]["mpeg2/little"] == report["crc"]["valid"]


def test_the_tshark_engine_hands_sigchld_back():
    """pyshark leaves SIGCHLD routed to its idle event loop; later child processes of the same
    process then fill that loop's wakeup pipe (Python reports every failed write)."""
    analyze(str(CAPTURES / "normal.pcap"), engine="tshark")
    assert signal.getsignal(signal.SIGCHLD) == signal.SIG_DFL
    assert signal.set_wakeup_fd(-1) == -1                 # no wakeup fd was left installed


def _tshark_wrapper(path, then: str):
    """A `tshark` that reads a file as tshark does and then runs the shell text `then`."""
    real = shutil.which("tshark")
    path.write_text(f'#!/bin/bash\ncase " $* " in *" -r "*) ;; *) exec {real} "$@" ;; esac\n{real} "$@"\n{then}\n')
    path.chmod(0o755)
    return str(path)


def test_a_tshark_that_exits_while_python_is_busy_is_a_clean_read(tmp_path, monkeypatch):
    """The flake "Unknown child process pid ..., will report returncode 255", made certain: tshark's
    output ends, Python is slow (a loaded machine) and tshark exits meanwhile. pyshark killed it
    then, and killing polls first, reaping tshark behind asyncio's child watcher (exit 255): a
    clean read reported as a crash. tshark is now reaped by the watcher."""
    class Busy(tshark_packets._Capture):
        async def _cleanup_subprocess(self, process):
            time.sleep(0.1)
            await super()._cleanup_subprocess(process)

    monkeypatch.setattr(tshark_packets, "_Capture", Busy)
    wrapper = _tshark_wrapper(tmp_path / "tshark", "exec >&-; sleep 0.02")    # output ends before exit
    read = tshark_packets.packets(str(CAPTURES / "normal.pcap"), [], tshark_path=wrapper)
    assert sum(1 for _ in read) == analyze(str(CAPTURES / "normal.pcap"))["capture"]["packets"]


def test_a_failing_tshark_is_told_after_its_packets(tmp_path):
    wrapper = _tshark_wrapper(tmp_path / "tshark", 'echo "tshark: a damaged record" >&2; exit 2')
    seen = 0
    with pytest.raises(tshark_packets.TsharkStopped, match="a damaged record"):
        for _ in tshark_packets.packets(str(CAPTURES / "normal.pcap"), [], tshark_path=wrapper):
            seen += 1
    assert seen == analyze(str(CAPTURES / "normal.pcap"))["capture"]["packets"]


def snapped(source, target, snaplen: int) -> None:
    """A copy of a little-endian pcap as a capture with `snaplen` would have written it."""
    data = source.read_bytes()
    out, pos = [data[:16] + struct.pack("<I", snaplen) + data[20:24]], 24
    while pos < len(data):
        ts_sec, ts_frac, incl, orig = struct.unpack_from("<IIII", data, pos)
        kept = min(incl, snaplen)
        out.append(struct.pack("<IIII", ts_sec, ts_frac, kept, orig) + data[pos + 16:pos + 16 + kept])
        pos += 16 + incl
    target.write_bytes(b"".join(out))


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_datagram_the_snaplen_cut_is_truncated_alone(tshark, tmp_path):
    """Cut by the capture, a datagram is illegal as `truncated` and nothing else (its CRC and size
    are not there to judge): in the dissector's experts as in the report and `vm110 decode`. The
    dissector said bad CRC and size mismatch, 371 times each, on normal.pcap cut at 80 bytes."""
    cut = tmp_path / "snap80.pcap"
    snapped(CAPTURES / "normal.pcap", cut, 80)
    report = analyze(str(cut))
    assert report["illegal"]["by_reason"] == {"truncated": report["capture"]["snaplen_truncated"]} != {}
    with tshark.workspace(tmp_path / "ws") as ws:
        local = ws.dir / cut.name
        local.write_bytes(cut.read_bytes())
        experts = ws.run(["-r", str(local), "-T", "fields", "-e", "_ws.expert.message", "-Y", "vm110.expert.truncated"])
    lines = experts.stdout.splitlines()
    assert len(lines) == report["illegal"]["total"]
    assert all(line == "Truncated: cut short by the capture (snaplen)" for line in lines), lines[:3]
    decoded = subprocess.run([*VM110, "decode", str(cut)], capture_output=True, text=True, check=True).stdout
    assert decoded.count("ILLEGAL(truncated)") == report["illegal"]["total"] and "bad_crc" not in decoded


def test_only_eg_link_datagrams_the_snaplen_cut_are_counted(tmp_path):
    """capture.snaplen_truncated counts EG-Link datagrams (docs/report.md): the fast engine and the
    monitor counted every UDP datagram the snaplen cut (318 on illegal.pcap cut at 50 bytes, 4 of
    them mDNS, where the finding's items and the tshark engine gave 314)."""
    whole, cut = tmp_path / "whole.pcap", tmp_path / "snap50.pcap"
    other = [T.Datagram(bytes(60), sport=5353, dport=5353), T.Datagram(b"VRPI" + bytes(60), sport=6000, dport=6001)]
    T.write_pcap(whole, [b"VRPI" + bytes(60), *other, b"VRCO" + bytes(60), *other])
    snapped(whole, cut, 50)
    fast, slow = analyze(str(cut)), analyze(str(cut), engine="tshark")
    assert fast["capture"]["snaplen_truncated"] == slow["capture"]["snaplen_truncated"] == 2
    assert fast["illegal"]["by_reason"] == {"truncated": 2}
    live = tmp_path / "monitor.json"
    subprocess.run([*VM110, "monitor", "--read", str(cut), "--idle", "0", "--no-dashboard", "--json", str(live)],
                   capture_output=True, check=True, timeout=60)
    assert json.loads(live.read_text())["capture"]["snaplen_truncated"] == 2


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_datagram_cut_inside_its_header_is_truncated_alone(tshark, tmp_path):
    """The same below 16 bytes: an unknown packet ID cut to 8 bytes is truncated only. The dissector
    said "unknown packet ID, truncated" there (and "truncated" alone from 16 bytes on; trial)."""
    whole, cut = tmp_path / "whole.pcap", tmp_path / "snap50.pcap"
    T.write_pcap(whole, [b"VRXX" + bytes(60), b"VRPI" + bytes(60)])
    snapped(whole, cut, 50)                   # 14 + 20 + 8 header bytes, 8 of the datagram
    assert analyze(str(cut))["illegal"]["by_reason"] == {"truncated": 2}
    decoded = subprocess.run([*VM110, "decode", str(cut)], capture_output=True, text=True, check=True).stdout
    assert decoded.count("ILLEGAL(truncated)") == 2
    with tshark.workspace(tmp_path / "ws") as ws:
        local = ws.dir / cut.name
        local.write_bytes(cut.read_bytes())
        info = ws.run(["-r", str(local), "-T", "fields", "-e", "_ws.col.Info"]).stdout.splitlines()
    assert [line.split(" [")[-1] for line in info] == ["Illegal: truncated]"] * 2, info


@pytest.mark.parametrize("tshark", runner_params(T.RUNNERS))
def test_every_filter_a_report_gives_shows_its_frames(tshark, tmp_path):
    """The display filter of each finding item, pasted into Wireshark (tshark -Y here, 4.0, 4.4
    and 4.6), selects the item's frames: exactly them, or a range holding them all."""
    checked = 0
    for name in ("restart.pcapng", "retransmit.pcap", "illegal.pcap"):
        capture = CAPTURES / name
        items = [i for f in analyze(str(capture))["verdict"]["findings"] for i in f.get("items", [])]
        several = [i for i in items if len(i.get("frames", [])) > 1][:12]
        try:
            with tshark.workspace(tmp_path / name) as ws:
                local = ws.dir / name
                local.write_bytes(capture.read_bytes())
                for item in several + items[:4]:
                    check_filter(ws, local, item)
                    checked += 1
        except T.TsharkUnavailable as exc:
            pytest.fail(str(exc))
    assert checked > 12


def check_filter(ws: T.Workspace, capture, item: dict) -> None:
    """The item's filter in tshark (with the plugin, as Wireshark has it) shows exactly its frames."""
    done = ws.run(["-r", str(capture), "-Y", item["filter"], "-T", "fields", "-e", "frame.number"], check=False)
    assert done.returncode == 0, (item["filter"], done.stderr)
    shown = [int(n) for n in done.stdout.split()]
    assert shown == sorted(item.get("frames", [item["frame"]])), item


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_long_command_s_filter_shows_its_frames_only(tshark, tmp_path):
    """A command resent 70 times among the BU's status: its item's filter was a frame range, then
    narrowed by the command's ID alone, which still showed a VRCO and VRAI with that ID (trial). Within
    the range here: another kind, another sender and a mirror copy with the same ID; and the item of
    such a command acknowledged after its limit, which holds the ack too."""
    from test_analysis_craft import BU_ORIGIN, CTRL, Traffic, payload, vrpi
    from vm110.layers import VRAI, VRAO, VRCI, VRCO
    tr = Traffic()
    for k in range(70):
        tr.add(1.0 + k * 0.1, payload(VRCI, 100 + 2 * k, BU_ORIGIN, command_id=7))
        tr.add(1.0 + k * 0.1 + 0.05, vrpi(101 + 2 * k))
    tr.add(1.501, payload(VRCI, 110, BU_ORIGIN, command_id=7))                       # a mirror copy
    tr.add(2.02, payload(VRCO, 1, command_id=7), src=CTRL, sport=C.OUTPUT_PORT)
    tr.add(2.03, payload(VRAI, 1, BU_ORIGIN, command_id=7))
    tr.add(2.04, payload(VRCI, 5, BU_ORIGIN, command_id=7), src="10.0.0.11")          # another BU
    tr.add(8.1, payload(VRAO, 3, command_id=7), src=CTRL, sport=C.OUTPUT_PORT)        # acks that one
    tr.frames.sort(key=lambda f: f[0])
    capture = tmp_path / "long.pcap"
    tr.write(capture)
    findings = {f["rule"]: f["items"] for f in analyze(str(capture))["verdict"]["findings"]}
    [unacked] = [i for i in findings["unacked"] if len(i["frames"]) > 64]
    [failed] = [i for i in findings["failed"] if len(i["frames"]) > 64]
    assert len(unacked["frames"]) == 70 and failed["frames"] == unacked["frames"] and failed["ack_frame"] is None
    # The same command acknowledged late (a failed item with its ack): its transmissions and the ack.
    acked = located_item(unacked["frames"] + [len(tr.frames)], unacked["time"], unacked["sender"], type="VRCI",
                         command_id=7, ack_frame=len(tr.frames))
    with tshark.workspace(tmp_path / "ws") as ws:
        local = ws.dir / capture.name
        local.write_bytes(capture.read_bytes())
        for item in (unacked, failed, acked):
            check_filter(ws, local, item)


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_tunnels_are_a_warning_with_a_filter_that_shows_them(tshark, tmp_path):
    """A capture mirrored through a tunnel (GRE, VXLAN, IP in IP): the fast engine said only "no
    EG-Link packets" (trial), which reads as a dead link. It now counts the tunnels' frames and
    says they were not unwrapped, with a filter that shows exactly them; the tshark engine, which
    unwraps them as Wireshark does, finds the EG-Link packets in them."""
    from scapy.layers.inet import IP, UDP
    from scapy.layers.l2 import GRE, Ether
    from scapy.layers.vxlan import VXLAN
    from scapy.utils import rdpcap, wrpcap
    from vm110.analysis.findings import TUNNEL_FILTER
    frames, tunnelled = [], []
    for i, p in enumerate(rdpcap(str(CAPTURES / "normal.pcap"))[:30]):
        outer = Ether() / IP(src="192.168.1.1", dst="192.168.1.2")
        how = i % 4
        f = (outer / GRE(proto=0x6558) / p if how == 0 else outer / UDP(sport=40000, dport=4789) / VXLAN(vni=5) / p
             if how == 1 else outer / p[IP] if how == 2 else p)
        f.time = p.time
        frames.append(f)
        if how < 3:
            tunnelled.append(i + 1)
    path = tmp_path / "tunnels.pcap"
    wrpcap(str(path), frames)
    report = analyze(str(path))
    assert report["capture"]["tunnelled_frames"] == len(tunnelled)
    [warning] = [f for f in report["verdict"]["findings"] if f["rule"] == "tunnels"]
    assert warning["count"] == len(tunnelled) and warning["message"].endswith(TUNNEL_FILTER)
    assert analyze(str(path), engine="tshark")["capture"]["eglink_packets"] == 30
    with tshark.workspace(tmp_path / "ws") as ws:
        local = ws.dir / path.name
        local.write_bytes(path.read_bytes())
        shown = ws.run(["-r", str(local), "-Y", TUNNEL_FILTER, "-T", "fields", "-e", "frame.number"]).stdout.split()
    assert [int(n) for n in shown] == tunnelled
