"""Packets the capture itself dropped are said, and not passed off as packets the link lost.

pcapng records them: the Interface Statistics Blocks' isb_ifdrop and isb_osdrop (cumulative: per
interface the last block counts) and the packet blocks' epb_dropcount. The captures here are
written with struct.pack (not the reader's code), and what they say is read back by Wireshark's
own file-level pcapng dissector (tshark -X read_format:"MIME Files Format"), the figures the report
must give: both engines and the monitor alike.
"""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path
from typing import Optional

import pytest
from lxml import etree

import report_schema
import tshark_runner as T
from test_analysis_craft import vrpi
from test_monitor import _reports
from vm110.analysis import analyze, summary

SHB, IDB, ISB, EPB = 0x0A0D0D0A, 1, 5, 6
needs_tshark = pytest.mark.skipif(shutil.which("tshark") is None, reason="no tshark")


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + bytes(-len(value) % 4)


def _options(*pairs: tuple[int, bytes]) -> bytes:
    return b"".join(_option(c, v) for c, v in pairs) + (_option(0, b"") if pairs else b"")


def _block(btype: int, body: bytes) -> bytes:
    return struct.pack("<II", btype, 12 + len(body)) + body + struct.pack("<I", 12 + len(body))


def shb() -> bytes:
    return _block(SHB, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))


def idb(name: str) -> bytes:
    return _block(IDB, struct.pack("<HHI", 1, 0, 65535) + _options((2, name.encode())))


def isb(iface: int, ifdrop: Optional[int] = None, osdrop: Optional[int] = None, raw: bytes = b"") -> bytes:
    opts = [(4, struct.pack("<Q", 1000))] + [(c, struct.pack("<Q", v)) for c, v in ((5, ifdrop), (7, osdrop))
                                             if v is not None]
    return _block(ISB, struct.pack("<III", iface, 0, 0) + (raw or _options(*opts)))


class Packets:
    """VRPI of one base unit, serials in order, 10 ms apart, each an enhanced packet block."""

    def __init__(self) -> None:
        self.serial, self.t = 0, 1_700_000_000_000_000

    def epb(self, iface: int, dropcount: Optional[int] = None, skip: int = 0) -> bytes:
        self.serial += skip
        data = T.frame(T.Datagram(vrpi(self.serial)))
        self.serial += 1
        self.t += 10_000
        opts = _options((4, struct.pack("<Q", dropcount))) if dropcount is not None else b""
        return _block(EPB, struct.pack("<IIIII", iface, self.t >> 32, self.t & 0xFFFFFFFF, len(data), len(data))
                      + data + bytes(-len(data) % 4) + opts)


def dropping_capture(path: Path) -> int:
    """Two sections, the first with two interfaces, several statistics blocks per interface (the
    last counts), drop counts on packet blocks; serial gaps of 8 packets in all. Returns those."""
    p = Packets()
    blocks = [shb(), idb("eth0"), idb("eth1"), *(p.epb(0) for _ in range(5)), p.epb(0, dropcount=3, skip=3),
              isb(0, ifdrop=2, osdrop=1), p.epb(1, dropcount=0), *(p.epb(0) for _ in range(5)),
              isb(1, ifdrop=4), isb(0, ifdrop=5, osdrop=1), p.epb(0, skip=2),
              shb(), idb("lo"), p.epb(0), p.epb(0, dropcount=2, skip=3), *(p.epb(0) for _ in range(5)),
              isb(0, ifdrop=1), isb(0, ifdrop=6)]
    path.write_bytes(b"".join(blocks))
    return 8


def wireshark_drops(path: Path) -> Optional[dict]:
    """capture.dropped as Wireshark's file-level pcapng dissector reads the file: per interface (each
    section's its own) the last statistics block's dropped and dropped-by-OS counts, and the sum of
    the packet blocks' drop counts."""
    done = subprocess.run(["tshark", "-X", 'read_format:MIME Files Format', "-r", str(path), "-T", "pdml"],
                          capture_output=True, check=True)
    ifaces: list[dict] = []
    section, block, start = -1, {}, 0
    for field in etree.fromstring(done.stdout).iter("field"):
        name, show = field.get("name"), field.get("show")
        if name == "pcapng.block.type":
            block = {"type": int(show, 16)}
            if block["type"] == SHB:
                section, start = section + 1, len(ifaces)
            elif block["type"] == IDB:
                ifaces.append({"section": section, "interface": len(ifaces) - start, "name": None,
                               "ifdrop": None, "osdrop": None, "dropcount": None})
        elif name == "pcapng.options.option.data.interface.name" and block.get("type") == IDB:
            ifaces[-1]["name"] = show
        elif name == "pcapng.interface_id":
            block["iface"] = ifaces[start + int(show)]
        elif name in ("pcapng.options.option.data.interface.dropped", "pcapng.options.option.data.interface.dropped_by_os"):
            block["iface"]["osdrop" if name.endswith("_by_os") else "ifdrop"] = int(show)
        elif name == "pcapng.options.option.data.packet.drop_count":
            block["iface"]["dropcount"] = (block["iface"]["dropcount"] or 0) + int(show)
    said = [i for i in ifaces if any(i[k] is not None for k in ("ifdrop", "osdrop", "dropcount"))]
    if not said:
        return None
    for i in said:
        i["total"] = max((i["ifdrop"] or 0) + (i["osdrop"] or 0), i["dropcount"] or 0)
    sums = {k: sum(i[k] or 0 for i in said) if any(i[k] is not None for i in said) else None
            for k in ("ifdrop", "osdrop", "dropcount")}
    return {"total": sum(i["total"] for i in said), **sums, "interfaces": said}


def _warning(report: dict) -> Optional[dict]:
    return next((f for f in report["verdict"]["findings"] if f["rule"] == "capture_dropped"), None)


@needs_tshark
@pytest.mark.parametrize("engine", ["fast", "tshark"])
def test_the_capture_s_own_drops_are_said_beside_the_lost_packets(tmp_path, engine):
    """A flood past the capture host's buffer: the losses were reported as the link's (trial). The
    report now gives what the capture says it dropped, as Wireshark reads it, and warns that up
    to that many of the packets counted lost may be the capture's."""
    path = tmp_path / "drops.pcapng"
    lost = dropping_capture(path)
    expected = wireshark_drops(path)
    assert expected is not None and expected["total"] == 16 and expected["dropcount"] == 5
    report = report_schema.validating(analyze)(str(path), engine=engine)
    assert report["totals"]["lost"] == lost
    assert report["capture"]["dropped"] == expected
    assert report["totals"]["capture_dropped"] == 16
    warning = _warning(report)
    assert warning is not None and (warning["severity"], warning["count"], warning["items"]) == ("warning", 16, [])
    for said in ("dropped 16 packets", "isb_ifdrop 15, isb_osdrop 1, epb_dropcount 5",
                 f"up to 8 of the {lost} packets counted lost", "dumpcap -B", '-f "udp port 5825 or udp port 5827"',
                 "Capture File Properties", "frame.drop_count > 0"):
        assert said in warning["message"], said
    assert warning["message"] in summary.render(report)
    if engine == "fast":       # the filter it gives shows the packets after a drop (frames 6 and 15)
        shown = warning["message"].rsplit("the packets after a drop: ", 1)[1]
        done = subprocess.run(["tshark", "-r", str(path), "-Y", shown, "-T", "fields", "-e", "frame.number"],
                              capture_output=True, text=True, check=True)
        assert done.stdout.split() == ["6", "15"]


def test_the_monitor_ends_with_the_same_drops(tmp_path, capsys):
    path = tmp_path / "drops.pcapng"
    dropping_capture(path)
    a, m = _reports(str(path), tmp_path)
    assert a == m and json.loads(m)["capture"]["dropped"]["total"] == 16


@needs_tshark
def test_a_capture_that_says_nothing_of_drops_is_not_one_without(tmp_path):
    """No statistics and no drop counts (a pcapng so written, a classic pcap): dropped is null, no
    warning; statistics of 0 drops: dropped says 0, no warning either."""
    p = Packets()
    quiet = tmp_path / "quiet.pcapng"
    quiet.write_bytes(shb() + idb("eth0") + b"".join(p.epb(0) for _ in range(5)) + isb(0) + p.epb(0, skip=2))
    none = tmp_path / "none.pcapng"
    none.write_bytes(shb() + idb("eth0") + b"".join(p.epb(0) for _ in range(5)) + isb(0, ifdrop=0))
    classic = tmp_path / "classic.pcap"
    T.write_pcap(classic, [vrpi(s) for s in (0, 1, 4)])
    for path, dropped in ((quiet, None), (classic, None), (none, wireshark_drops(none))):
        report = analyze(str(path))
        assert report["capture"]["dropped"] == dropped, path.name
        assert _warning(report) is None and report["totals"]["capture_dropped"] == 0
    assert dropped == {"total": 0, "ifdrop": 0, "osdrop": None, "dropcount": None, "interfaces": [
        {"section": 0, "interface": 0, "name": "eth0", "ifdrop": 0, "osdrop": None, "dropcount": None, "total": 0}]}


@needs_tshark
def test_damaged_statistics_are_read_as_wireshark_reads_them(tmp_path):
    """A statistics block whose drop count is 4 bytes long, not 8: Wireshark ignores that option
    and reads on, and so does the reader. One whose option runs past the block: Wireshark stops
    there, so does the reader (damage, no traceback), keeping the counts before it."""
    p = Packets()
    head = shb() + idb("eth0") + b"".join(p.epb(0) for _ in range(3)) + isb(0, ifdrop=2)
    short = tmp_path / "short.pcapng"
    short.write_bytes(head + isb(0, raw=_options((5, struct.pack("<I", 9)))) + p.epb(0, dropcount=1))
    report = analyze(str(short))
    assert report["capture"]["problem"] is None and report["capture"]["packets"] == 4
    assert report["capture"]["dropped"] == wireshark_drops(short) and report["capture"]["dropped"]["ifdrop"] == 2
    past = tmp_path / "past.pcapng"
    bad = _block(ISB, struct.pack("<III", 0, 0, 0) + struct.pack("<HH", 5, 40) + struct.pack("<Q", 9))
    past.write_bytes(head + bad + p.epb(0, dropcount=1))
    done = subprocess.run(["tshark", "-r", str(past), "-T", "fields", "-e", "frame.number"], capture_output=True,
                          text=True)
    report = analyze(str(past))
    assert "corrupt pcapng block" in report["capture"]["problem"] and "damaged or corrupt" in done.stderr
    assert report["capture"]["packets"] == len(done.stdout.split()) == 3
    intact = tmp_path / "intact.pcapng"
    intact.write_bytes(head)
    assert report["capture"]["dropped"] == wireshark_drops(intact) and report["capture"]["dropped"]["total"] == 2


@needs_tshark
def test_a_real_dumpcap_capture_gives_its_statistics(tmp_path):
    """dumpcap writes a statistics block per interface at the end (ifrecv, ifdrop)."""
    if shutil.which("dumpcap") is None:
        pytest.skip("no dumpcap")
    path = tmp_path / "lo.pcapng"
    done = subprocess.run(["dumpcap", "-q", "-i", "lo", "-f", "udp port 9", "-a", "duration:1", "-w", str(path)],
                          capture_output=True, text=True, timeout=20)
    if done.returncode or not path.exists():
        pytest.skip(f"dumpcap cannot capture on lo here: {done.stderr.strip()[-200:]}")
    expected = wireshark_drops(path)
    assert expected is not None and expected["ifdrop"] is not None
    assert analyze(str(path))["capture"]["dropped"] == expected
