"""Damaged and hostile input for `decode` and `analyze` (issue 17, parts 1 and 4): what comes
before the damage is analysed and reported, the damage is named with its byte offset, several
captures are each reported, pipes read as files, and output files are never lost."""
from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest

import report_schema
from test_analysis_craft import T0, Traffic, vrpi
from longrun import on_runner
from tshark_runner import RUNNERS, ip_checksum
from vm110 import constants as C
from vm110.analysis import analyze, report_json
from vm110.cli import main

CAPTURES = Path(__file__).resolve().parent.parent / "captures"

# Wiretap and IP reading, the same on 4.0, 4.4 and 4.6 (no Lua of ours): 4.4 in the long run.
READERS = [on_runner(r, id=r.version, short=[RUNNERS[0].version]) for r in RUNNERS]   # (wiretap: all alike)


def vm110(*args: str, stdin: bytes = b"") -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], input=stdin, capture_output=True, timeout=300)


def _traffic(path: Path, n: int = 12, fmt: str = "pcap") -> None:
    tr = Traffic()
    for k in range(n):
        tr.add(k * 0.125, vrpi(k))
    tr.write(path, fmt)


def _record_starts(data: bytes) -> list[int]:
    pos, out = 24, []
    while pos + 16 <= len(data):
        out.append(pos)
        pos += 16 + struct.unpack_from("<I", data, pos + 8)[0]
    return out


def test_several_captures_each_reported_and_the_unreadable_one_named(tmp_path):
    junk = tmp_path / "junk.pcap"
    junk.write_bytes(os.urandom(3000))
    out = tmp_path / "r.json"
    done = vm110("analyze", str(CAPTURES / "normal.pcap"), str(junk), "--json", str(out), "--quiet")
    assert done.returncode == 2 and b"junk.pcap: not a pcap or pcapng capture" in done.stderr
    assert b"Traceback" not in done.stderr
    doc = json.loads(out.read_text())
    assert [r["capture"]["file"] for r in doc["reports"]] == [str(CAPTURES / "normal.pcap")]
    assert doc["errors"] == [{"file": str(junk), "error": f"{junk}: not a pcap or pcapng capture (magic "
                              + doc["errors"][0]["error"].split("(magic ")[1]}]
    assert doc["reports"][0]["totals"]["eglink_packets"] == 382


def test_a_damaged_later_pcapng_section_keeps_what_came_before(tmp_path):
    first, second = tmp_path / "a.pcapng", tmp_path / "b.pcapng"
    _traffic(first, 10, "pcapng")
    _traffic(second, 10, "pcapng")
    bad = bytearray(second.read_bytes())
    struct.pack_into("<I", bad, 8, 0xDEADBEEF)          # the second section's byte-order magic
    joined = tmp_path / "joined.pcapng"
    joined.write_bytes(first.read_bytes() + bytes(bad))
    for engine in ("fast", "tshark"):
        report = analyze(str(joined), engine)
        assert report["capture"]["packets"] == 10, engine
        assert report["capture"]["damage"] == {"offset": first.stat().st_size, "message":
                                               f"bad pcapng byte-order magic in the section at byte {first.stat().st_size}"}
        assert report["totals"]["damaged"] == 1 and report["verdict"]["findings"][0]["rule"] == "damaged"


def _on(runner) -> dict:
    """The environment in which the package's commands find `runner`'s tshark."""
    import tshark_runner
    if runner.root is None:
        return dict(os.environ)
    return dict(os.environ, PATH=f"{tshark_runner.overlay_bin(runner)}{os.pathsep}{os.environ.get('PATH', '')}")


def _reports(path: Path, env: dict) -> list[dict]:
    """Both engines' JSON reports of `path`, `tool` left out."""
    out = []
    for engine in ("fast", "tshark"):
        done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(path), "--engine", engine, "--quiet",
                               "--json", "-"], capture_output=True, env=env, timeout=300)
        assert done.returncode in (0, 1, 2) and b"Traceback" not in done.stderr, (engine, done.stderr)
        report = json.loads(done.stdout)
        report_schema.check(report)
        report.pop("tool")
        out.append(report)
    return out


@pytest.mark.tshark
@pytest.mark.parametrize("runner", READERS)
def test_a_fraction_of_a_second_or_more_is_read_as_wireshark_reads_it(runner, tmp_path):
    """A pcap record's fraction of a million microseconds or more (damage): wiretap keeps it in
    signed 32-bit nanoseconds, which tshark prints out of range, "S.1250000000" (4.0) or
    "S.(1250000000 nanosec" (4.4 and later), wrapped ones negative. The tshark engine lost a second
    on the first (a trial: 8 times backwards, 3 watchdogs) and stopped at the last with a
    ValueError (self-fuzz); the fast engine put the last 2,890 s later than Wireshark shows it."""
    path = tmp_path / "usec.pcap"
    _traffic(path)                                       # 12 VRPI, T0 + k * 0.125 s
    data = bytearray(path.read_bytes())
    starts = _record_starts(bytes(data))
    struct.pack_into("<II", data, starts[0], int(T0) - 1, 1_000_000)         # T0, written oddly
    struct.pack_into("<II", data, starts[4], int(T0) - 1, 1_500_000)         # T0 + 0.5
    struct.pack_into("<II", data, starts[11], int(T0) + 2, 2_890_186_947)   # wraps: T0 + 2 - 0.326043208
    path.write_bytes(bytes(data))
    fast, slow = _reports(path, _on(runner))
    assert fast == slow
    assert fast["capture"]["first_time"] == T0
    assert fast["capture"]["last_time"] == pytest.approx(T0 + 2 - 0.326043208, abs=1e-6)
    assert fast["totals"]["lost"] == 0


def _pcapng_blocks(data: bytes) -> list[bytes]:
    pos, out = 0, []
    while pos < len(data):
        n = struct.unpack_from("<I", data, pos + 4)[0]
        out.append(data[pos:pos + n])
        pos += n
    return out


def _pcapng_block(btype: int, body: bytes) -> bytes:
    body += bytes(-len(body) % 4)
    return struct.pack("<II", btype, 12 + len(body)) + body + struct.pack("<I", 12 + len(body))


@pytest.mark.tshark
@pytest.mark.parametrize("runner", READERS)
def test_records_that_are_no_packets_and_packets_without_a_time_as_in_wireshark(runner, tmp_path):
    """Wireshark numbers custom blocks and systemd journal entries as frames: the fast engine
    skipped them, so its frame numbers (and the display filters on them) named other packets; a
    simple packet block has no time: the tshark engine put it at 0 (1970), the fast engine at the
    packet's before it (a trial). Both engines now agree, and with Wireshark's frame numbers."""
    path = tmp_path / "records.pcapng"
    tr = Traffic()
    for k in range(12):
        if k != 7:                                       # serial 7 lost
            tr.add(k * 0.125, vrpi(k))
    tr.write(path, "pcapng")
    head, idb, *packets = _pcapng_blocks(path.read_bytes())
    extra = {1: _pcapng_block(0xBAD, struct.pack("<I", 32473) + b"note"),
             3: _pcapng_block(0x40000BAD, struct.pack("<I", 32473) + b"note"),
             5: _pcapng_block(0x9, b"__REALTIME_TIMESTAMP=1700000000500000\nMESSAGE=plc\n")}
    out = head + idb
    for k, epb in enumerate(packets):
        if k == 4:                                       # as a simple packet block: no time
            incl = struct.unpack_from("<I", epb, 20)[0]
            out += _pcapng_block(3, struct.pack("<I", incl) + epb[28:28 + incl])
        else:
            out += epb + extra.get(k, b"")
    path.write_bytes(out)
    env = _on(runner)
    fast, slow = _reports(path, env)
    assert fast == slow
    frames = subprocess.run(["tshark", "-r", str(path), "-T", "fields", "-e", "frame.number"], env=env,
                            capture_output=True, text=True, timeout=120).stdout.split()
    assert fast["capture"]["packets"] == len(frames) == 14
    lost = next(f for f in fast["verdict"]["findings"] if f["rule"] == "lost")
    shown = subprocess.run(["tshark", "-r", str(path), "-Y", lost["items"][0]["filter"], "-T", "fields",
                            "-e", "frame.number"], env=env, capture_output=True, text=True, timeout=120).stdout.split()
    assert shown == [str(lost["items"][0]["frame"])] == ["11"]   # serial 8: its 8th packet, after three records
    assert fast["senders"][0]["serial"]["received"] == 11


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + bytes(-len(value) % 4)


def _with_options(block: bytes, options: bytes) -> bytes:
    return _pcapng_block(struct.unpack_from("<I", block)[0], block[8:-4] + options)


_SHB = struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1)
Blocks = Callable[[list[bytes]], list[bytes]]


def _options_of(at: int, options: bytes) -> Blocks:
    """Block `at` (0 the section header, 1 the interface, 2.. the packets) with `options` added."""
    def change(blocks: list[bytes]) -> list[bytes]:
        block = _pcapng_block(0x0A0D0D0A, _SHB) if at == 0 else blocks[at]
        return blocks[:at] + [_with_options(block, options)] + blocks[at + 1:]
    return change


def _after_first_packet(btype: int, body: bytes) -> Blocks:
    return lambda blocks: blocks[:3] + [_pcapng_block(btype, body)] + blocks[3:]


# pcapng blocks and options, and the frames Wireshark (4.0, 4.4, 4.6 alike) reads of three
# packets: what wiretap refuses ends the file there.
_PCAPNG: dict[str, tuple[Blocks, int]] = {
    "a packet comment": (_options_of(3, _option(1, b"crane stopped here") + _option(0, b"")), 3),
    "an option of another code": (_options_of(3, _option(0x7777, b"abcd")), 3),
    "bytes after the end of options": (_options_of(3, _option(0, b"") + struct.pack("<HH", 1, 200)), 3),
    "an option past its block": (_options_of(3, struct.pack("<HH", 1, 100) + b"abcd"), 1),
    "packet flags of 2 bytes": (_options_of(3, _option(2, b"\x01\x00")), 1),
    "a captured length one byte past the padded data": (
        lambda blocks: blocks[:3] + [blocks[3][:20] + struct.pack("<I", struct.unpack_from("<I", blocks[3], 20)[0] + 1)
                                     + blocks[3][24:]] + blocks[4:], 1),
    "an XDP verdict of 5 bytes": (_options_of(3, _option(7, b"\x02abcd")), 1),
    "a hardware verdict of 5 bytes": (_options_of(3, _option(7, b"\x00abcd")), 3),
    "an interface's time resolution of 2 bytes (ignored)": (_options_of(1, _option(9, b"\x09\x00")), 3),
    "an interface's time offset of 4 bytes (ignored)": (_options_of(1, _option(14, bytes(4))), 3),
    "an empty interface filter": (_options_of(1, _option(11, b"")), 0),
    "a section option past its block": (_options_of(0, struct.pack("<HH", 1, 100)), 0),
    "a name record past its block": (_after_first_packet(4, struct.pack("<HH", 1, 200) + bytes(8)), 1),
    "an IPv4 name record of 3 bytes": (_after_first_packet(4, _option(1, b"\x0a\x00\x00") + _option(0, b"")), 1),
    "decryption secrets past their block": (_after_first_packet(10, struct.pack("<II", 0x544C534B, 500) + bytes(8)), 1),
    "a simple packet block of more data than it holds": (_after_first_packet(3, struct.pack("<I", 5000) + bytes(8)), 1),
    "a simple packet block of less data than it holds": (_after_first_packet(3, struct.pack("<I", 4) + bytes(8)), 1),
    "a simple packet block of the data it holds": (_after_first_packet(3, struct.pack("<I", 8) + bytes(8)), 4),
    "interface statistics of 20 bytes": (_after_first_packet(5, bytes(8)), 1),
    "a custom block of 12 bytes": (_after_first_packet(0xBAD, b""), 1),
}


@pytest.mark.tshark
@pytest.mark.parametrize("runner", READERS)
def test_pcapng_blocks_and_options_are_read_as_wireshark_reads_them(runner, tmp_path, monkeypatch):
    """The readers skipped a block's options and the contents of blocks that are no packets:
    wiretap stops at an option past its block or of a length it refuses, at a name record or
    decryption secrets past their block, at a block below its kind's size, at a simple packet
    block whose data do not fill it, and the fast engine read on (503 packets where Wireshark
    shows 451; self-fuzz agreement check); it took an interface's time resolution or offset of
    another length, which wiretap ignores (times a thousand times too early; the monitor's reader
    alike). The tshark engine failed on every packet with a comment (pyshark took the comment for
    the frame: 'cannot analyse ...: AttributeError')."""
    env = _on(runner)
    monkeypatch.setenv("PATH", env["PATH"])             # (the engines run here: 19 captures)
    tr = Traffic()
    for k in range(3):
        tr.add(k * 0.125, vrpi(k))
    base = tmp_path / "base.pcapng"
    tr.write(base, "pcapng")
    for n, (name, (change, frames)) in enumerate(_PCAPNG.items()):
        path = tmp_path / f"blocks-{n}.pcapng"
        path.write_bytes(b"".join(change(_pcapng_blocks(base.read_bytes()))))
        fast, slow = (analyze(str(path), engine) for engine in ("fast", "tshark"))
        assert fast.pop("tool") != slow.pop("tool") and fast == slow, name
        shown = subprocess.run(["tshark", "-r", str(path), "-T", "fields", "-e", "frame.number", "-e",
                                "frame.time_epoch"], env=env, capture_output=True, text=True, timeout=120)
        rows = [line.split("\t") for line in shown.stdout.splitlines()]
        times = [float(row[1]) for row in rows if row[1]]     # (a simple packet block has none)
        cap = fast["capture"]
        assert cap["packets"] == len(rows) == frames, name
        assert (cap["problem"] is not None) == (frames < 3) == ("tshark: The file" in shown.stderr), name
        assert cap["first_time"] == (times[0] if times else None), name
        if runner is RUNNERS[0]:                         # (the monitor runs no tshark)
            out = tmp_path / f"monitor-{n}.json"
            assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json",
                         str(out)]) in (0, 1, 2), name
            live = json.loads(out.read_text())
            assert all(live[key] == fast[key] for key in ("illegal", "senders", "totals")), name


def _ipv4_frame(payload: bytes, ulen: int | None = None, tot: int | None = None, ihl: int = 5, version: int = 4,
                pad: bytes = b"") -> bytes:
    """Ethernet, IPv4 and UDP (5825 -> 5825) around `payload`, with the header fields given (damage)."""
    udp = struct.pack("!HHHH", C.INPUT_PORT, C.INPUT_PORT, 8 + len(payload) if ulen is None else ulen, 0) + payload
    ip = bytearray(struct.pack("!BBHHHBBH4s4s", (version << 4) | ihl, 0, 20 + len(udp) if tot is None else tot, 1, 0,
                               64, 17, 0, bytes([10, 0, 0, 10]), bytes([239, 1, 1, 1])))
    struct.pack_into("!H", ip, 10, ip_checksum(bytes(ip)))
    return b"\x01\x00\x5e\x01\x01\x01" + b"\x02" * 6 + b"\x08\x00" + bytes(ip) + udp + pad


# Damaged IPv4/UDP headers, and what Wireshark (4.0, 4.4, 4.6 alike) makes of the datagram: a
# legal packet, an illegal one, a UDP datagram whose payload nothing dissects, or no UDP at all.
# (n: the EG-Link packet's length.)
_DAMAGE = {
    "UDP length 10 past the IP payload": (lambda n: {"ulen": 18 + n}, "legal"),
    "IP total length 20 past the frame": (lambda n: {"tot": 48 + n}, "legal"),
    "IP total length 0 (segmentation offload)": (lambda n: {"tot": 0}, "legal"),
    "UDP length over 4 bytes of padding": (lambda n: {"ulen": 12 + n, "pad": bytes(8)}, "legal"),
    "IP total length over 4 bytes of padding": (lambda n: {"tot": 32 + n, "pad": bytes(8)}, "legal"),
    "UDP length 4 short": (lambda n: {"ulen": 4 + n}, "illegal"),
    "IP total length 4 short": (lambda n: {"tot": 24 + n}, "illegal"),
    "IP total length 3 bytes into the payload": (lambda n: {"tot": 31}, "illegal"),
    "IP and UDP lengths 32 past a whole frame": (lambda n: {"tot": 60 + n, "ulen": 40 + n}, "legal"),
    "UDP length 4": (lambda n: {"ulen": 4}, "other UDP"),
    "UDP length 0": (lambda n: {"ulen": 0}, "other UDP"),
    "IP total length 24 (half a UDP header)": (lambda n: {"tot": 24}, "other UDP"),
    "IP total length 27": (lambda n: {"tot": 27}, "other UDP"),
    "IP total length 28 (the UDP header alone)": (lambda n: {"tot": 28}, "other UDP"),
    "IP total length 10 (below the header)": (lambda n: {"tot": 10}, "no UDP"),
    "IP header length 16": (lambda n: {"ihl": 4}, "no UDP"),
    "IP version 6 in an IPv4 frame": (lambda n: {"version": 6}, "no UDP"),
    "IP total length 20 (no UDP)": (lambda n: {"tot": 20}, "no UDP"),
    "IP total length 22": (lambda n: {"tot": 22}, "no UDP"),
    "IP total length 23": (lambda n: {"tot": 23}, "no UDP"),
}


def _ipv6_frame(payload: bytes, ulen: int | None = None, plen: int | None = None, version: int = 6,
                ext: bytes = b"", pad: bytes = b"") -> bytes:
    """Ethernet, IPv6 (with extension headers `ext`, the first a hop-by-hop one) and UDP
    (5825 -> 5825) around `payload`, with the header fields given (damage)."""
    udp = struct.pack("!HHHH", C.INPUT_PORT, C.INPUT_PORT, 8 + len(payload) if ulen is None else ulen, 0) + payload
    ip = struct.pack("!IHBB16s16s", version << 28, len(ext) + len(udp) if plen is None else plen,
                     0 if ext else 17, 64, bytes.fromhex("fe80" + "0" * 26 + "10"), bytes.fromhex("ff02" + "0" * 26 + "01"))
    return b"\x33\x33\x00\x00\x00\x01" + b"\x02" * 6 + b"\x86\xdd" + ip + ext + udp + pad


_HOP_BY_HOP = bytes([17, 0, 1, 4, 0, 0, 0, 0])          # to UDP; a PadN option of 4 bytes

# Damaged IPv6/UDP headers, and what Wireshark (4.0, 4.4, 4.6 alike) makes of the datagram.
_DAMAGE_IPV6 = {
    "payload length 10 past the frame": (lambda n: {"plen": 18 + n}, "legal"),
    "payload length over 8 bytes of padding": (lambda n: {"plen": 8 + n, "pad": bytes(8)}, "legal"),
    "UDP length over 4 bytes of padding": (lambda n: {"ulen": 12 + n, "pad": bytes(8)}, "legal"),
    "UDP length 10 past the IP payload": (lambda n: {"ulen": 18 + n}, "legal"),
    "UDP length 0 (the IP payload's)": (lambda n: {"ulen": 0, "pad": bytes(8)}, "legal"),
    "payload and UDP lengths 32 past a whole frame": (lambda n: {"plen": 40 + n, "ulen": 40 + n}, "legal"),
    "a hop-by-hop header": (lambda n: {"ext": _HOP_BY_HOP}, "legal"),
    "payload length 4 short": (lambda n: {"plen": 4 + n}, "illegal"),
    "payload length 4 short, a hop-by-hop header": (lambda n: {"ext": _HOP_BY_HOP, "plen": 12 + n}, "illegal"),
    "payload length 3 bytes into the payload": (lambda n: {"plen": 11}, "illegal"),
    "UDP length 4 short": (lambda n: {"ulen": 4 + n}, "illegal"),
    "payload length 6 (part of a UDP header)": (lambda n: {"plen": 6}, "other UDP"),
    "payload length 8 (the UDP header alone)": (lambda n: {"plen": 8}, "other UDP"),
    "UDP length 4": (lambda n: {"ulen": 4}, "other UDP"),
    "payload length 0 (no jumbo option)": (lambda n: {"plen": 0}, "no UDP"),
    "payload length 0, a hop-by-hop header": (lambda n: {"plen": 0, "ext": _HOP_BY_HOP}, "no UDP"),
    "payload length 0, UDP length 0": (lambda n: {"plen": 0, "ulen": 0}, "no UDP"),
    "payload length 2": (lambda n: {"plen": 2}, "no UDP"),
    "payload length of the hop-by-hop header alone": (lambda n: {"plen": 8, "ext": _HOP_BY_HOP}, "no UDP"),
    "IP version 4 in an IPv6 frame": (lambda n: {"version": 4}, "no UDP"),
}


@pytest.mark.tshark
@pytest.mark.parametrize("ip", [4, 6])
@pytest.mark.parametrize("runner", READERS)
def test_damaged_ip_and_udp_headers_are_read_as_wireshark_reads_them(runner, ip, tmp_path):
    """The fast engine read a datagram by its UDP length alone: a UDP length past the IP payload was
    "cut short by the snaplen", padding under a UDP length an illegal size, a UDP length below 8 or
    a damaged IP header a legal packet; over IPv6 it ignored the payload length and the version
    (a payload length of 0 was a legal packet, padding under it an illegal size); the tshark engine
    saw what Wireshark sees (trials, and the self-fuzzer's soak). Both now read IP and UDP headers
    as Wireshark does, and agree."""
    damage, frame_of = (_DAMAGE, _ipv4_frame) if ip == 4 else (_DAMAGE_IPV6, _ipv6_frame)
    path = tmp_path / "damaged.pcap"
    out = bytearray(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1))
    kinds = {}
    for k in range(2 * len(damage) + 1):
        packet = vrpi(k)
        fields, kind = {}, "legal"
        if k % 2:                                        # every other packet damaged, one way each
            fields, kind = (lambda f, w: (f(len(packet)), w))(*list(damage.values())[k // 2])
        kinds[k] = kind
        frame = frame_of(packet, **fields)
        sec, usec = divmod(int(T0 * 1_000_000) + k * 125_000, 1_000_000)
        out += struct.pack("<IIII", sec, usec, len(frame), len(frame)) + frame
    path.write_bytes(bytes(out))
    fast, slow = _reports(path, _on(runner))
    assert fast == slow
    done = subprocess.run([sys.executable, "-m", "vm110", "monitor", "--read", str(path), "--idle", "0", "--json", "-"],
                          capture_output=True, timeout=300)
    live = json.loads(done.stdout)
    assert all(live[key] == fast[key] for key in ("illegal", "senders", "totals")), done.stderr
    count = {w: sum(v == w for v in kinds.values()) for w in ("legal", "illegal", "other UDP", "no UDP")}
    cap = fast["capture"]
    assert (cap["packets"], cap["udp_packets"], cap["eglink_packets"], fast["illegal"]["total"]) == (
        len(kinds), len(kinds) - count["no UDP"], count["legal"] + count["illegal"], count["illegal"])
    assert cap["snaplen_truncated"] == 0                 # (every frame is whole: its headers lie)
    assert sorted(fast["senders"][0]["serial"]["lost_serials"]) == sorted(k for k, w in kinds.items() if w != "legal")


@pytest.mark.tshark
def test_a_packet_the_capture_cut_has_no_crc_checked_in_either_engine(tmp_path):
    """A record one byte shorter than its frame (the snaplen): the dissector checks no CRC of it
    (the CRC is cut), while the fast engine counted it as checked (crc.unchecked 0 against 1;
    self-fuzz agreement check, seed 67). Such a packet is truncated and nothing else, also with an
    unknown packet ID, which the dissector still marked as unknown_id (agreement check, seed 107)."""
    path = tmp_path / "cut.pcap"
    _traffic(path)
    data = bytearray(path.read_bytes())
    for k, packet_id in ((7, b"VRP/"), (5, None)):     # (from the end: the offsets before stay)
        at = _record_starts(bytes(data))[k]
        if packet_id:
            data[at + 16 + 42:at + 16 + 46] = packet_id   # (after Ethernet, IPv4 and UDP headers)
        incl = struct.unpack_from("<I", data, at + 8)[0]
        struct.pack_into("<I", data, at + 8, incl - 1)
        data = data[:at + 16 + incl - 1] + data[at + 16 + incl:]
    path.write_bytes(bytes(data))
    fast, slow = _reports(path, dict(os.environ))
    assert fast == slow
    assert fast["capture"]["snaplen_truncated"] == 2 and fast["crc"]["unchecked"] == 2
    assert fast["illegal"]["by_reason"] == {"truncated": 2}
    assert [e["type"] for e in fast["illegal"]["examples"]] == ["VRPI", "VRP/"]


@pytest.mark.tshark
@pytest.mark.parametrize("runner", RUNNERS, ids=lambda r: r.version)
def test_an_unknown_packet_id_is_shown_alike_by_both_engines(runner, tmp_path):
    """The tshark engine took the ID from tshark's text, which drops or escapes bytes that are no
    UTF-8, differently by version ("VPO" for V 0x8d P O on 4.0): the reports differed (self-fuzz
    agreement check). Both engines now show the four bytes as the fast engine reads them."""
    tr = Traffic()
    ids = [b"V\x8dPO", b"VR\x12O", b"\xaa\xaa\xaa\xaa", b"eRPI"]
    for k in range(8):
        packet = vrpi(k)
        tr.add(k * 0.125, ids[k // 2] + packet[4:] if k % 2 else packet)
    path = tmp_path / "ids.pcap"
    tr.write(path)
    fast, slow = _reports(path, _on(runner))
    assert fast == slow
    assert [e["type"] for e in fast["illegal"]["examples"]] == [i.decode("latin-1") for i in ids]


@pytest.mark.tshark
def test_a_capture_after_2038_has_its_times_in_both_engines(tmp_path):
    """pyshark's sniff_timestamp (tshark's general information) wraps at 2^31 seconds: the tshark
    engine put a frame of 2039 in 1955 (self-fuzz agreement check). It reads frame.time_epoch."""
    path = tmp_path / "2039.pcap"
    _traffic(path)
    data = bytearray(path.read_bytes())
    for at in _record_starts(bytes(data)):
        struct.pack_into("<I", data, at, struct.unpack_from("<I", data, at)[0] + 500_000_000)
    path.write_bytes(bytes(data))
    fast, slow = _reports(path, dict(os.environ))
    assert fast == slow and fast["capture"]["first_time"] == T0 + 500_000_000


@pytest.mark.tshark
def test_an_empty_datagram_on_the_eglink_port_is_a_truncated_packet_everywhere(tmp_path):
    """Wireshark gives an empty UDP datagram no dissector ("UDP Len=0"): the tshark engine counted it
    as other UDP, while the fast engine had a truncated EG-Link packet. Both now report it, and the
    illegal finding's display filter shows it in Wireshark."""
    from scapy.layers.inet import IP, UDP, Ether
    from scapy.utils import wrpcap
    from tshark_runner import HOST
    frames = []
    for k in range(6):
        frame = Ether() / IP(src="10.0.0.10", dst=C.MULTICAST_GROUP) / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT)
        frame = frame / (b"" if k == 3 else vrpi(k))
        frame.time = T0 + k * 0.125
        frames.append(frame)
    path = tmp_path / "empty.pcap"
    wrpcap(str(path), frames)
    reports = [analyze(str(path), engine) for engine in ("fast", "tshark")]
    for report in reports:
        assert (report["capture"]["eglink_packets"], report["illegal"]["by_reason"]) == (6, {"truncated": 1})
        illegal = next(f for f in report["verdict"]["findings"] if f["rule"] == "illegal")
        assert [i["frame"] for i in illegal["items"]] == [4]
    with HOST.workspace(tmp_path / "ws") as ws:
        shown = ws.run(["-r", str(path), "-Y", illegal["filter"], "-T", "fields", "-e", "frame.number"]).stdout.split()
    assert shown == ["4"]


@pytest.mark.tshark
def test_a_udp_header_cut_short_is_no_crash_of_the_tshark_engine(tmp_path):
    """An IP total length of 24 leaves the UDP header 4 bytes (self-fuzz): tshark's udp layer then
    has its ports but no length, and the tshark engine's AttributeError stopped the analysis."""
    from scapy.layers.inet import IP, Ether
    from scapy.packet import Raw
    from scapy.utils import wrpcap
    cut = Ether() / IP(src="10.0.0.10", dst=C.MULTICAST_GROUP, proto=17, len=24) / Raw(
        struct.pack("!HH", C.INPUT_PORT, C.INPUT_PORT))
    cut.time = T0
    path = tmp_path / "cut-udp.pcap"
    wrpcap(str(path), [cut])
    done = vm110("analyze", str(path), "--engine", "tshark", "--quiet", "--json", "-")
    assert done.returncode in (0, 1) and b"Error" not in done.stderr, done.stderr
    assert json.loads(done.stdout)["capture"]["packets"] == 1


@pytest.mark.tshark
def test_the_tshark_engine_keeps_what_comes_before_a_cut(tmp_path):
    path = tmp_path / "cut.pcap"
    _traffic(path)
    data = path.read_bytes()
    path.write_bytes(data[:-20])
    fast, slow = analyze(str(path)), analyze(str(path), "tshark")
    assert slow["capture"]["packets"] == fast["capture"]["packets"] == 11
    assert slow["capture"]["damage"] == fast["capture"]["damage"] == {
        "offset": _record_starts(data)[-1], "message": fast["capture"]["problem"]}
    assert slow["senders"][0]["serial"]["received"] == 11
    done = vm110("analyze", str(path), "--engine", "tshark", "--quiet", "--fail-on", "damaged")
    # (exit 2: a verdict on part of the input is not the verdict on it; the rule still names it)
    assert done.returncode == 2 and b"damaged=1" in done.stderr and b"Traceback" not in done.stderr


@pytest.mark.tshark
def test_a_corrupt_record_header_leaves_both_engines_the_times_before_it(tmp_path):
    """The tshark engine takes the capture's times from the reader, which lost them at a corrupt
    record header (a trial): null first and last times, null item times, a report that failed its
    own schema."""
    path = tmp_path / "corrupt.pcap"
    _traffic(path)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, _record_starts(bytes(data))[6] + 8, 0x7FFFFFFF)
    path.write_bytes(bytes(data))
    fast, slow = _reports(path, dict(os.environ))
    assert fast == slow
    assert (fast["capture"]["packets"], fast["capture"]["first_time"], fast["capture"]["last_time"]) == (
        6, T0, T0 + 5 * 0.125)


@pytest.mark.tshark
@pytest.mark.parametrize("name,cut,message", [("normal.pcap", 10, "pcap file header cut short"),
                                              ("loss.pcapng", 30, "pcapng section header block cut short")])
def test_a_file_header_cut_short_is_no_capture_for_every_reader(tmp_path, name, cut, message):
    """No capture at all: one line, exit 2, no report, whichever command reads it. The monitor
    reported a pcap's cut header as a record cut at byte 0 and wrote a report; a pcapng's cut
    section header was that in analyze too (a trial)."""
    path = tmp_path / f"cut.{name.split('.')[1]}"
    path.write_bytes((CAPTURES / name).read_bytes()[:cut])
    for command in (["analyze", str(path), "--json", "-"], ["analyze", str(path), "--engine", "tshark", "--json", "-"],
                    ["monitor", "--read", str(path), "--idle", "0", "--json", "-"], ["decode", str(path)]):
        done = vm110(*command)
        assert (done.returncode, done.stdout, done.stderr.decode()) == (
            2, b"", f"vm110 {command[0]}: {path}: {message}\n"), command


def test_ctrl_c_stops_analyze_and_its_reading_process_quietly(tmp_path):
    """Ctrl-C goes to the whole process group: the reading child of a large capture printed a
    traceback of its own ("Process ForkProcess-1: ... KeyboardInterrupt") beside exit 130 (a
    trial). The parent now handles it and ends the child."""
    import signal
    from vm110.analysis.engine import PIPELINE_MIN_BYTES
    from vm110.synth import synthesize
    path = tmp_path / "day.pcap"
    synthesize("day", str(path), duration_s=3000)
    assert path.stat().st_size >= PIPELINE_MIN_BYTES                     # read by a child process
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # (a background run ignores it)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "vm110", "analyze", str(path), "--quiet"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    finally:
        signal.signal(signal.SIGINT, previous)
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline and not children.read_text().split():
        time.sleep(0.005)
    assert proc.poll() is None, "the analysis ended before its reading process was seen"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert (proc.returncode, err) == (130, b"")


def test_decode_and_analyze_read_a_pipe():
    data = (CAPTURES / "normal.pcap").read_bytes()
    done = vm110("decode", "-", stdin=data)
    assert done.returncode == 0 and done.stdout.decode().splitlines()[-1] == "382 EG-Link packets"
    done = vm110("analyze", "-", "--quiet", "--json", "-", stdin=data)
    report = json.loads(done.stdout)
    report_schema.check(report)
    assert done.returncode == 0 and report["capture"]["file"] == "-" and report["totals"]["eglink_packets"] == 382


@pytest.mark.parametrize("command", [["decode", "-"], ["analyze", "-"], ["analyze", "-", "--engine", "tshark"]])
def test_a_bad_pipe_is_named_standard_input(command):
    """Not the temporary file standard input was copied to: the user never named that."""
    for data in (b"", b"not a capture at all"):
        done = vm110(*command, stdin=data)
        err = done.stderr.decode()
        assert done.returncode == 2 and err.count("\n") == 1 and "standard input: " in err and "vm110-stdin" not in err


def test_a_record_claiming_gigabytes_is_damage_never_silence(tmp_path):
    path = tmp_path / "big.pcap"
    _traffic(path)
    data = bytearray(path.read_bytes())
    third = _record_starts(bytes(data))[2]
    struct.pack_into("<II", data, third + 8, 1 << 31, 1 << 31)
    path.write_bytes(bytes(data))
    done = vm110("decode", str(path))
    lines = done.stdout.decode().splitlines()
    assert done.returncode == 2 and lines[-1] == "2 EG-Link packets"
    assert f"damaged, read up to byte {third}".encode() in done.stderr


def test_one_record_over_the_limit_costs_no_more_than_its_bytes(tmp_path):
    """A 64 MiB record (real bytes, not a lying header) ends the read at once: damage, not a
    minute of rescanning, and nothing of it loaded."""
    path = tmp_path / "huge.pcap"
    _traffic(path, 10)
    data = path.read_bytes()
    huge = 64 << 20
    with open(path, "ab") as out:
        out.write(struct.pack("<IIII", 1_700_000_002, 0, huge, huge))
        out.write(bytes(huge))
    start = time.perf_counter()
    report = analyze(str(path))
    assert time.perf_counter() - start < 5.0
    assert report["capture"]["packets"] == 10 and report["capture"]["damage"]["offset"] == len(data)
    assert "over the 262144-byte limit" in report["capture"]["problem"]


def test_reports_are_written_whole_or_not_at_all(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    done = vm110("analyze", str(CAPTURES / "normal.pcap"), "--json", str(fifo), "--quiet")
    assert done.returncode == 2 and b"is not a regular file" in done.stderr and fifo.exists()
    folder = tmp_path / "dir.json"
    folder.mkdir()
    done = vm110("analyze", str(CAPTURES / "normal.pcap"), "--json", str(folder), "--quiet")
    assert done.returncode == 2 and b"is not a regular file" in done.stderr and folder.is_dir()
    done = vm110("analyze", str(CAPTURES / "normal.pcap"), "--json", "", "--quiet")   # ("refusing to write : ...")
    assert (done.returncode, done.stderr) == (2, b"vm110 analyze: refusing to write a file with an empty name\n")
    plain = tmp_path / "plain"
    plain.write_text("a file")
    done = vm110("monitor", "--read", str(CAPTURES / "normal.pcap"), "--idle", "0", "--evidence", str(plain))
    assert (done.returncode, done.stderr) == (2, f"vm110 monitor: --evidence {plain}: not a directory\n".encode())
    old = tmp_path / "r.json"
    old.write_text("the previous report")
    with pytest.raises(TypeError):         # a value that is not JSON
        report_json.write(str(old), {"a": list(range(100000)), "b": object()})
    assert old.read_text() == "the previous report"
    assert sorted(os.listdir(tmp_path)) == ["dir.json", "fifo", "plain", "r.json"]


def _block_starts(data: bytes) -> list[int]:
    """Where each block of a little-endian pcapng file starts."""
    pos, out = 0, []
    while pos < len(data):
        out.append(pos)
        pos += struct.unpack_from("<I", data, pos + 4)[0]
    return out


def test_pcapng_block_lengths_that_disagree_are_damage(tmp_path):
    path = tmp_path / "t.pcapng"
    _traffic(path, 6, "pcapng")
    data = bytearray(path.read_bytes())
    blocks = _block_starts(data)
    fifth = blocks[-2]                                   # the fifth packet's block
    end = fifth + struct.unpack_from("<I", data, fifth + 4)[0]
    struct.pack_into("<I", data, end - 4, 4236)          # its trailing length lies
    path.write_bytes(bytes(data))
    from vm110.capture.reader import CaptureReader
    reader = CaptureReader(str(path))
    assert len(list(reader)) == 4 and reader.damage == fifth
    assert reader.problem == f"corrupt pcapng block at byte {fifth} (leading length {end - fifth}, trailing 4236)"
    report = analyze(str(path))                          # the fast engine walks pcapng itself
    assert report["capture"]["packets"] == 4 and report["capture"]["damage"] == {
        "offset": fifth, "message": reader.problem}


@pytest.mark.tshark
def test_damage_only_tshark_sees_ends_the_tshark_engine_with_a_problem_not_a_traceback(tmp_path):
    """A system-call event block too short for its fields: the readers do not judge those (their
    sizes differ between Wireshark versions), tshark stops there (the self-fuzzer found pyshark's
    exception escaping as a traceback, on an option longer than its block, which the readers now
    judge as wiretap does)."""
    path = tmp_path / "event.pcapng"
    _traffic(path, 6, "pcapng")
    data = path.read_bytes()
    third = _block_starts(bytearray(data))[-3]
    path.write_bytes(data[:third] + _pcapng_block(0x204, bytes(12)) + data[third:])
    done = vm110("analyze", str(path), "--engine", "tshark", "--quiet", "--json", "-")
    assert done.returncode == 2 and b"tshark stopped reading" in done.stderr and b"Traceback" not in done.stderr and b"Exception" not in done.stderr
    report = json.loads(done.stdout)
    report_schema.check(report)
    assert report["capture"]["problem"].startswith("tshark stopped reading after frame ")
    assert report["totals"]["damaged"] == 1


@pytest.mark.parametrize("command, outputs", [
    (["analyze", "{cap}", "--quiet"], ["--json", "{cap}"]),
    (["analyze", "{cap}", "--quiet"], ["--html", "{link}"]),
    (["analyze", "{cap}", "--quiet"], ["--json", "{out}", "--html", "{out}"]),
    (["monitor", "--read", "{cap}", "--idle", "0", "--no-dashboard", "--quiet"], ["--json", "{cap}"]),
    (["monitor", "--read", "{cap}", "--idle", "0", "--no-dashboard", "--quiet"], ["--json-lines", "{link}"]),
    (["monitor", "--read", "{cap}", "--idle", "0", "--no-dashboard", "--quiet"], ["--json-lines", "{out}",
                                                                                  "--json", "{out}"]),
])
def test_no_output_over_the_capture_or_another_output(tmp_path, command, outputs):
    """Trial: `analyze in.pcap --json in.pcap` replaced the capture by its report (exit 0), also
    through a symbolic link, and `--json r.json --html r.json` kept the HTML alone."""
    cap, link, out = tmp_path / "in.pcap", tmp_path / "link.pcap", tmp_path / "r.out"
    cap.write_bytes((CAPTURES / "normal.pcap").read_bytes())
    link.symlink_to(cap)
    args = [a.format(cap=cap, link=link, out=out) for a in command + outputs]
    done = subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "refusing to write over it" in done.stderr or "one would be lost" in done.stderr
    assert cap.read_bytes() == (CAPTURES / "normal.pcap").read_bytes() and not out.exists()


def test_timestamps_beyond_any_calendar_are_reported_not_a_traceback(tmp_path):
    """Trial: a pcapng interface whose if_tsoffset is 2^63-1 s crashed the HTML report (a chart of
    no span: x0 + 1 == x0) and fleet build (microseconds beyond int64), which lost the whole build."""
    from vm110 import encode as E
    from vm110.capture.writer import UdpFlow, build_block, build_option
    shb = build_block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))
    idb = build_block(1, struct.pack("<HHI", 1, 0, 0) + build_option(14, struct.pack("<q", 2**63 - 1))
                      + struct.pack("<HH", 0, 0))
    flow = UdpFlow("10.0.0.10", 5825, "239.255.42.20", 5825)
    epbs = []
    for i in range(12):
        f = flow.frame(E.packet("VRPI", E.vrpi_payload({}), serial=i))
        ticks = 1_700_000_000_000_000 + i * 125_000
        epbs.append(build_block(6, struct.pack("<IIIII", 0, ticks >> 32, ticks & 0xFFFFFFFF, len(f), len(f))
                                + f + bytes(-len(f) % 4)))
    cap = tmp_path / "far.pcapng"
    cap.write_bytes(shb + idb + b"".join(epbs))
    for args in (["analyze", str(cap), "--quiet", "--html", str(tmp_path / "a.html")],
                 ["monitor", "--read", str(cap), "--idle", "0", "--no-dashboard", "--quiet", "--html",
                  str(tmp_path / "m.html")],
                 ["fleet", "build", str(cap), "--out", str(tmp_path / "ds"), "-j", "1"]):
        done = vm110(*args)
        assert done.returncode in (0, 1) and b"Traceback" not in done.stderr, (args, done.stderr[-2000:])
    assert (tmp_path / "a.html").stat().st_size > 0 and (tmp_path / "m.html").stat().st_size > 0


@pytest.mark.parametrize("defect", ["interface 7", "captured length", "no interface block"])
def test_a_corrupt_packet_block_is_damage_in_every_reader(tmp_path, defect):
    """Trial: packet blocks naming an interface the section lacks (or claiming more bytes than
    they hold) were skipped in silence by the fast engine (exit 0, '0 EG-Link'), while tshark stops
    there (exit 2). Now every reader stops there: decode, analyze (both engines), monitor."""
    from vm110 import encode as E
    from vm110.capture.writer import UdpFlow, build_block
    shb = build_block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))
    idb = build_block(1, struct.pack("<HHI", 1, 0, 0))
    flow = UdpFlow("10.0.0.10", 5825, "239.255.42.20", 5825)

    def epb(i: int, iface: int = 0, claim: int = 0) -> bytes:
        f = flow.frame(E.packet("VRPI", E.vrpi_payload({}), serial=i))
        ticks = 1_700_000_000_000_000 + i * 125_000
        return build_block(6, struct.pack("<IIIII", iface, ticks >> 32, ticks & 0xFFFFFFFF, claim or len(f), len(f))
                           + f + bytes(-len(f) % 4))
    good = [epb(i) for i in range(4)]
    bad = {"interface 7": epb(4, iface=7), "captured length": epb(4, claim=5000), "no interface block": epb(4)}[defect]
    cap = tmp_path / "bad.pcapng"
    cap.write_bytes(shb + bad if defect == "no interface block" else shb + idb + b"".join(good) + bad)
    for args in (["decode", str(cap)], ["analyze", str(cap), "--quiet"], ["analyze", str(cap), "--quiet", "--engine",
                                                                         "tshark"],
                 ["monitor", "--read", str(cap), "--idle", "0", "--no-dashboard", "--quiet"]):
        done = vm110(*args)
        assert done.returncode == 2 and b"Traceback" not in done.stderr, (args, done.stderr)
        if "tshark" not in args:
            assert b"corrupt pcapng packet block" in done.stderr, (args, done.stderr)


@pytest.mark.parametrize("command", ["analyze", "decode"])
def test_a_named_pipe_is_told_to_come_on_standard_input(tmp_path, command):
    """Trial: a FIFO was 'cannot read f: None' with a writer and a wait forever without one."""
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    done = vm110(command, str(fifo))
    assert done.returncode == 2 and b"is a named pipe: give it on standard input" in done.stderr, done.stderr


@pytest.mark.parametrize("args", [["decode", "NAME"], ["synth", "--out", "NAME/x.pcap", "day"],
                                  ["fleet", "query", "NAME", "--worst", "links"]], ids=lambda a: a[0])
def test_a_file_name_in_any_command_s_error_reaches_the_terminal_escaped(tmp_path, args):
    """Every command's one-line error names the file it could not use: the name's escape sequences
    and newlines reached the terminal raw (report trial: analyze's were fixed alone)."""
    name = str(tmp_path / os.fsdecode(b"no\x1b[2J\n\xff"))
    done = vm110(*(a.replace("NAME", name) for a in args))
    assert done.returncode == 2, done.stderr
    assert done.stderr.count(b"\n") == 1 and b"\x1b" not in done.stderr and b"\\x1b[2J\\n\\udcff" in done.stderr


def test_file_names_of_any_bytes_reach_the_reports_valid_and_the_terminal_escaped(tmp_path):
    """A file name is any bytes but / and NUL: one that is no UTF-8 made the JSON and HTML writers
    raise (a traceback, exit 1, no report) after the whole analysis; an escape sequence, a newline or
    an RTL override in it reached the terminal on the error, damage and --fail-on lines, and the
    HTML's heading, raw. Each is shown as its escape there, as the summary shows it."""
    cap = tmp_path / os.fsdecode(b'a<script>\xff\xe2\x80\xae\x1b[31m\n".pcap')
    _traffic(cap)
    junk = tmp_path / os.fsdecode(b"junk\x1b[2J\n\xfe.pcap")
    junk.write_bytes(b"no capture at all")
    out, page = tmp_path / "r.json", tmp_path / "r.html"
    done = vm110("analyze", str(cap), str(junk), "--json", str(out), "--html", str(page), "--quiet",
                 "--fail-on", "packets>0")
    assert done.returncode == 2 and b"Traceback" not in done.stderr, done.stderr
    unreadable, violated = done.stderr.decode().splitlines()
    assert unreadable.startswith(f"vm110 analyze: {tmp_path}/junk\\x1b[2J\\n\\udcfe.pcap: not a pcap or pcapng capture")
    assert violated == f'fail-on: {tmp_path}/a<script>\\udcff\\u202e\\x1b[31m\\n".pcap: packets=12 (rule packets>0)'
    doc = json.loads(out.read_text(encoding="utf-8"))
    assert doc["reports"][0]["capture"]["file"] == f'{tmp_path}/a<script>\\udcff\u202e\x1b[31m\n".pcap'
    assert doc["errors"][0]["file"] == f"{tmp_path}/junk\x1b[2J\n\\udcfe.pcap"
    text = page.read_text(encoding="utf-8")
    assert "<script>" not in text and not {"\u202e", "\x1b"} & set(text)
    assert f"<h2>{tmp_path}/a&lt;script&gt;\\udcff\\u202e\\x1b[31m\\n&quot;.pcap</h2>" in text
