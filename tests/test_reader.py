"""The streaming capture reader: formats, link types, and every way a file can be broken.

Frames are built with scapy and written with struct here, so the expectations do not come from
the reader's own code."""
from __future__ import annotations

import gzip
import itertools
import os
import struct
import tempfile
import zlib

import pytest
from scapy.layers.inet import IP, TCP, UDP, fragment
from scapy.layers.inet6 import IPv6, IPv6ExtHdrFragment
from scapy.layers.l2 import ARP, CookedLinux, CookedLinuxV2, Dot1AD, Dot1Q, Ether, Loopback
from scapy.packet import Padding

from vm110.capture.reader import CaptureError, CaptureReader

PAYLOAD = b"VRPI" + bytes(30)
SRC = "10.1.2.3"


def udp_ip(payload: bytes = PAYLOAD, sport: int = 5825, dport: int = 5825, src: str = SRC):
    return IP(src=SRC if src is None else src, dst="239.255.42.20") / UDP(sport=sport, dport=dport) / payload


def pcap(records, linktype: int = 1, endian: str = "<", nanos: bool = False, snaplen: int = 65535) -> bytes:
    """records: (seconds as int/float, frame bytes[, original length])."""
    magic = 0xA1B23C4D if nanos else 0xA1B2C3D4
    out = [struct.pack(endian + "IHHiIII", magic, 2, 4, 0, 0, snaplen, linktype)]
    for rec in records:
        t, frame = rec[0], bytes(rec[1])
        orig = rec[2] if len(rec) > 2 else len(frame)
        sec = int(t)
        frac = round((t - sec) * (1e9 if nanos else 1e6))
        out.append(struct.pack(endian + "IIII", sec, frac, len(frame), orig) + frame)
    return b"".join(out)


def block(btype: int, body: bytes, e: str = "<") -> bytes:
    body += bytes(-len(body) % 4)
    return struct.pack(e + "II", btype, 12 + len(body)) + body + struct.pack(e + "I", 12 + len(body))


def option(code: int, value: bytes, e: str = "<") -> bytes:
    return struct.pack(e + "HH", code, len(value)) + value + bytes(-len(value) % 4)


def read(tmp_path, data: bytes, name: str = "c.pcap", **kw):
    path = tmp_path / name
    path.write_bytes(data)
    reader = CaptureReader(str(path), **kw)
    return reader, list(reader)


def test_ethernet_pcap_gives_udp_payload_without_padding(tmp_path):
    short = Ether() / udp_ip(b"VRAO") / Padding(b"\xee" * 14)       # padded to the Ethernet minimum
    assert len(bytes(short)) == 60
    reader, got = read(tmp_path, pcap([(100.25, short), (101.5, Ether() / udp_ip(sport=5827, dport=6000))]))
    assert got == [(100.25, bytes([10, 1, 2, 3]), 5825, 5825, b"VRAO", 1),
                   (101.5, bytes([10, 1, 2, 3]), 5827, 6000, PAYLOAD, 2)]
    assert (reader.frames, reader.non_udp, reader.problem, reader.format) == (2, 0, None, "pcap")
    assert (reader.first_ts, reader.last_ts) == (100.25, 101.5)


@pytest.mark.parametrize("endian", ["<", ">"])
@pytest.mark.parametrize("nanos", [False, True])
def test_byte_orders_and_resolutions(tmp_path, endian, nanos):
    _, got = read(tmp_path, pcap([(1_700_000_000.123456, Ether() / udp_ip())], endian=endian, nanos=nanos))
    assert got[0][0] == pytest.approx(1_700_000_000.123456, abs=1e-7)
    assert got[0][4] == PAYLOAD


@pytest.mark.parametrize("frame,linktype", [
    (Ether() / Dot1Q(vlan=7) / udp_ip(), 1),
    (Ether() / Dot1AD(vlan=1) / Dot1Q(vlan=7) / udp_ip(), 1),
    (CookedLinux(proto=0x0800) / udp_ip(), 113),
    (CookedLinuxV2(proto=0x0800) / udp_ip(), 276),
    # a cooked capture of a tagged interface: the tag follows the cooked header
    (CookedLinux(proto=0x8100) / Dot1Q(vlan=7) / udp_ip(), 113),
    (CookedLinuxV2(proto=0x8100) / Dot1Q(vlan=7) / udp_ip(), 276),
    (udp_ip(), 101),
    (udp_ip(), 228),
    (Loopback(type=2) / udp_ip(), 0),
    (Ether() / IP(src=SRC, dst="239.255.42.20", options=b"\x01\x01\x01\x00") / UDP(sport=5825, dport=5825) / PAYLOAD, 1),
], ids=["vlan", "qinq", "sll", "sll2", "sll-vlan", "sll2-vlan", "raw", "ipv4", "null", "ip-options"])
def test_link_types(tmp_path, frame, linktype):
    reader, got = read(tmp_path, pcap([(5.0, frame)], linktype=linktype))
    assert [(g[1], g[2], g[4]) for g in got] == [(bytes([10, 1, 2, 3]), 5825, PAYLOAD)]
    assert reader.non_udp == 0


def _radiotap(flags: int | None = None, tsft: bool = False, extended: bool = False) -> bytes:
    """A radiotap header (built here, not by the reader): presence words (two with `extended`), a
    TSFT (8 bytes, aligned to 8) and a Flags byte when asked."""
    present = (1 if tsft else 0) | (2 if flags is not None else 0)
    words = struct.pack("<II", present | 0x80000000, 0) if extended else struct.pack("<I", present)
    fields = b""
    if tsft:
        fields += bytes(-(4 + len(words)) % 8) + bytes(8)
    if flags is not None:
        fields += bytes([flags])
    return struct.pack("<BBH", 0, 0, 4 + len(words) + len(fields)) + words + fields


def _wlan_frames() -> dict[str, bytes]:
    """802.11 data frames as a G-Link capture over the air holds them (TS-0006 5.3: G-Link is
    WiFi), each carrying udp_ip() in LLC/SNAP."""
    from scapy.layers.dot11 import Dot11, Dot11QoS
    from scapy.layers.l2 import LLC, SNAP
    snap = bytes(LLC(dsap=0xAA, ssap=0xAA, ctrl=3) / SNAP(OUI=0, code=0x0800)) + bytes(udp_ip())
    qos = bytes(Dot11(type=2, subtype=8, FCfield=0x02) / Dot11QoS())
    return {"data": bytes(Dot11(type=2, subtype=0, FCfield=0x02)) + snap,
            "qos": qos + snap,
            "qos-htc": bytes(Dot11(type=2, subtype=8, FCfield=0x82) / Dot11QoS()) + bytes(4) + snap,
            "wds-qos": bytes(Dot11(type=2, subtype=8, FCfield=0x03, addr4="00:01:02:03:04:05") / Dot11QoS()) + snap,
            "bridge-tunnel": bytes(Dot11(type=2, subtype=0, FCfield=0x02) / LLC(dsap=0xAA, ssap=0xAA, ctrl=3)
                                   / SNAP(OUI=0xF8, code=0x0800) / udp_ip()),
            "datapad": qos + bytes(2) + snap}


@pytest.mark.parametrize("name", ["data", "qos", "qos-htc", "wds-qos", "bridge-tunnel"])
@pytest.mark.parametrize("radiotap", [None, b"", "tsft+flags", "extended+flags", "fcs"])
def test_802_11_data_frames(tmp_path, name, radiotap):
    """A capture of the G-Link over the air (radiotap, 127) or without radiotap (105): the fast engine
    found no UDP in it ("no EG-Link packets in the capture") where tshark, and so `--engine tshark`,
    found every packet (trial). Each of these frames is UDP to tshark 4.0 (checked by hand)."""
    frame = _wlan_frames()[name]
    if radiotap is None:
        data = pcap([(5.0, frame)], linktype=105)
    else:
        head = {b"": _radiotap(), "tsft+flags": _radiotap(0, tsft=True),
                "extended+flags": _radiotap(0, extended=True), "fcs": _radiotap(0x10, tsft=True)}[radiotap]
        data = pcap([(5.0, head + frame + (bytes(4) if radiotap == "fcs" else b""))], linktype=127)
    reader, got = read(tmp_path, data)
    assert [(g[1], g[2], g[4]) for g in got] == [(bytes([10, 1, 2, 3]), 5825, PAYLOAD)]
    assert reader.non_udp == 0


def test_802_11_padding_protection_and_frames_without_data(tmp_path):
    """Radiotap's datapad flag pads the 802.11 header to 32 bits; a protected frame (not decrypted),
    a null-data frame and a management frame carry no UDP, as in tshark."""
    from scapy.layers.dot11 import Dot11, Dot11Beacon, Dot11Elt
    frames = _wlan_frames()
    protected = bytearray(frames["data"])
    protected[1] |= 0x40
    null = bytes(Dot11(type=2, subtype=4, FCfield=0x01))
    beacon = bytes(Dot11(type=0, subtype=8) / Dot11Beacon() / Dot11Elt(ID=0, info=b"site"))
    reader, got = read(tmp_path, pcap([(1.0, _radiotap(0x20, tsft=True) + frames["datapad"]),
                                       *((2.0, _radiotap() + f) for f in (bytes(protected), null, beacon))],
                                      linktype=127))
    assert [(g[4], g[5]) for g in got] == [(PAYLOAD, 1)]
    assert reader.non_udp == 3 and reader.link_types == {"radiotap"}


def test_ipv6_udp(tmp_path):
    frame = Ether() / IPv6(src="fe80::1", dst="ff02::1") / UDP(sport=5825, dport=5825) / PAYLOAD
    _, got = read(tmp_path, pcap([(1.0, frame)]))
    assert got[0][1] == bytes.fromhex("fe800000000000000000000000000001") and got[0][4] == PAYLOAD


def test_ipv6_atomic_fragment_is_a_whole_datagram(tmp_path):
    """RFC 6946: a fragment header with offset 0 and no more fragments holds the whole datagram
    (tshark decodes it too); a real first fragment is still a fragment, counted and not analysed."""
    atomic = Ether() / IPv6(src="fe80::1", dst="ff02::1") / IPv6ExtHdrFragment(offset=0, m=0, id=7) / \
        UDP(sport=5825, dport=5825) / PAYLOAD
    first = Ether() / IPv6(src="fe80::1", dst="ff02::1") / IPv6ExtHdrFragment(offset=0, m=1, id=8) / \
        UDP(sport=5825, dport=5825) / PAYLOAD
    reader, got = read(tmp_path, pcap([(1.0, atomic), (2.0, first)]))
    assert [(g[4], g[5]) for g in got] == [(PAYLOAD, 1)]
    assert (reader.fragments, reader.non_udp) == (1, 1)


def test_other_traffic_is_counted_not_yielded(tmp_path):
    # (the fragments of a datagram whose last fragment never came: never whole)
    frags = fragment(IP(src=SRC, dst="10.0.0.1") / UDP(sport=1, dport=2) / bytes(3000), fragsize=1000)[:-1]
    frames = [Ether() / ARP(), Ether() / IP() / TCP(), *(Ether() / f for f in frags), Ether() / udp_ip()]
    reader, got = read(tmp_path, pcap([(1.0, f) for f in frames]))
    assert len(got) == 1 and got[0][5] == len(frames)
    assert reader.frames == len(frames)
    assert reader.non_udp == len(frames) - 1 and reader.fragments == len(frags)


def test_pcapng_interfaces_resolutions_and_blocks(tmp_path):
    ether, raw = bytes(Ether() / udp_ip()), bytes(udp_ip(sport=5827))
    shb = block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))
    idb0 = block(1, struct.pack("<HHI", 1, 0, 65535))                                   # microseconds
    idb1 = block(1, struct.pack("<HHI", 101, 0, 65535) + option(9, b"\x09") + option(0, b""))   # nanoseconds
    idb2 = block(1, struct.pack("<HHI", 228, 0, 65535) + option(9, b"\x83") + option(14, struct.pack("<q", 10)))
    def epb(iface, ticks, frame):
        return block(6, struct.pack("<IIIII", iface, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), len(frame)) + frame)
    data = b"".join([shb, idb0, idb1, idb2,
                     epb(0, 1_700_000_000_250_000, ether),
                     block(0x1234, b"unknown block"),                                    # skipped
                     epb(1, 1_700_000_001_000_000_500, raw),
                     block(3, struct.pack("<I", len(ether)) + ether),                    # simple packet block
                     epb(2, 12, raw)])                                                   # 12/8 s + 10 s
    reader, got = read(tmp_path, data, "c.pcapng")
    assert [g[0] for g in got] == [1_700_000_000.25, pytest.approx(1_700_000_001.0000005, abs=1e-6),
                                   1_700_000_001.0000005, 11.5]
    assert [(g[2], g[5]) for g in got] == [(5825, 1), (5827, 2), (5825, 3), (5827, 4)]
    assert reader.format == "pcapng" and reader.frames == 4 and reader.link_types == {"ethernet", "raw", "ipv4"}


def test_big_endian_pcapng(tmp_path):
    frame = bytes(Ether() / udp_ip())
    shb = block(0x0A0D0D0A, struct.pack(">IHHq", 0x1A2B3C4D, 1, 0, -1), ">")
    idb = block(1, struct.pack(">HHI", 1, 0, 65535), ">")
    epb = block(6, struct.pack(">IIIII", 0, 0, 3_000_000, len(frame), len(frame)) + frame, ">")
    _, got = read(tmp_path, shb + idb + epb, "c.pcapng")
    assert [(g[0], g[4]) for g in got] == [(3.0, PAYLOAD)]


@pytest.mark.parametrize("cut", [3, 10, 20])
def test_file_cut_in_the_middle_of_a_record(tmp_path, cut):
    data = pcap([(1.0, Ether() / udp_ip()), (2.0, Ether() / udp_ip()), (3.0, Ether() / udp_ip())])
    reader, got = read(tmp_path, data[:-cut])
    assert [g[5] for g in got] == [1, 2]
    assert reader.frames == 2 and "cut in the middle of a record" in reader.problem


def test_pcapng_cut_and_corrupt_block(tmp_path):
    frame = bytes(Ether() / udp_ip())
    shb = block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))
    idb = block(1, struct.pack("<HHI", 1, 0, 65535))
    epb = block(6, struct.pack("<IIIII", 0, 0, 1, len(frame), len(frame)) + frame)
    reader, got = read(tmp_path, shb + idb + epb + epb[:-9], "cut.pcapng")
    assert len(got) == 1 and "cut" in reader.problem
    reader, got = read(tmp_path, shb + idb + epb + struct.pack("<II", 6, 7) + bytes(40), "bad.pcapng")
    assert len(got) == 1 and "corrupt pcapng block" in reader.problem


def test_snaplen_truncated_packet(tmp_path):
    frame = bytes(Ether() / udp_ip(b"VRPI" + bytes(62)))
    reader, got = read(tmp_path, pcap([(1.0, frame[:60], len(frame)), (2.0, frame)], snaplen=60))
    assert [len(g[4]) for g in got] == [60 - 42, 66]
    assert reader.snap_truncated == {1}


def test_empty_capture_and_backwards_time(tmp_path):
    reader, got = read(tmp_path, pcap([]))
    assert got == [] and reader.frames == 0 and reader.problem is None and reader.first_ts is None
    _, got = read(tmp_path, pcap([(5.0, Ether() / udp_ip()), (4.0, Ether() / udp_ip())]))
    assert [g[0] for g in got] == [5.0, 4.0]


def _gzip_members(data: bytes, *cuts: int) -> bytes:
    """`data` gzip-compressed, one member per part between the cuts (as `cat a.gz b.gz` makes)."""
    bounds = [0, *cuts, len(data)]
    return b"".join(gzip.compress(data[a:b]) for a, b in itertools.pairwise(bounds))


def test_gzip_compressed_captures_are_read_as_the_plain_file(tmp_path):
    """Wireshark opens a `.pcap.gz` (tcpdump -z gzip, dumpcap --compress gzip) as it is; the reader
    said "not a pcap or pcapng capture (magic 0x1f8b0800)" (trial)."""
    frames = [(1.0 + i / 8, Ether() / udp_ip(bytes([i]) * (i + 4))) for i in range(30)]
    shb = block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))
    idb = block(1, struct.pack("<HHI", 1, 0, 65535))
    epbs = b"".join(block(6, struct.pack("<IIIII", 0, 0, 1000 + i, len(bytes(f)), len(bytes(f))) + bytes(f))
                    for i, (_, f) in enumerate(frames))
    for name, data in (("c.pcap", pcap(frames)), ("c.pcapng", shb + idb + epbs)):
        plain, want = read(tmp_path, data, name)
        for gz in (gzip.compress(data), _gzip_members(data, 100, 333)):
            reader, got = read(tmp_path, gz, name + ".gz")
            assert got == want and len(got) == 30
            assert (reader.format, reader.frames, reader.problem) == (plain.format, 30, None)


def test_gzip_cut_short_or_corrupt_keeps_the_records_before_and_says_why(tmp_path):
    frames = [(1.0 + i, Ether() / udp_ip(bytes([i]) * 20)) for i in range(6)]
    data = pcap(frames)
    _, want = read(tmp_path, data)
    # Cut where three whole records end (flushed there): nothing is cut in a record, and yet the
    # file is incomplete.
    whole3 = 24 + 3 * (16 + len(bytes(frames[0][1])))
    pack = zlib.compressobj(wbits=31)
    head = pack.compress(data[:whole3]) + pack.flush(zlib.Z_FULL_FLUSH)
    reader, got = read(tmp_path, head, "cut.pcap.gz")
    assert got == want[:3]
    assert reader.problem == (f"gzip data cut short after {whole3} bytes of capture: records read up to "
                              f"byte {whole3} of it") and reader.damage == whole3
    reader, got = read(tmp_path, head + pack.compress(data[whole3:whole3 + 30]) + pack.flush(zlib.Z_FULL_FLUSH),
                       "cut.pcap.gz")
    assert got == want[:3] and reader.problem.endswith("of it, 30 bytes of a record after it ignored")
    whole = gzip.compress(data)
    bad_check = whole[:-8] + bytes(4) + whole[-4:]          # the CRC-32 of the trailer zeroed
    reader, got = read(tmp_path, bad_check, "bad.pcap.gz")
    assert got == want and reader.problem.startswith(f"gzip data corrupt after {len(data)} bytes of capture")
    with pytest.raises(CaptureError, match="gzip data cut short after 0 bytes of capture"):
        read(tmp_path, whole[:10], "early.pcap.gz")          # the gzip header alone


def test_gzip_is_decompressed_as_it_is_read_with_no_temporary_file(tmp_path, monkeypatch):
    """A .pcap.gz of several GiB decompressed into a temporary file filled /tmp, which is memory on
    Debian 13 (tmpfs), a second time in analyze's reading process: it is decompressed as
    it is read. A file inflating 200-fold and more (29 MB from 0.1 MB) reads record by record; a
    damaged member in the middle keeps what came before it."""
    frame = bytes(Ether() / udp_ip(bytes(1400)))
    data = pcap([]) + b"".join(struct.pack("<IIII", 1 + i // 8, i % 8 * 125_000, len(frame), len(frame)) + frame
                               for i in range(20_000))
    packed = gzip.compress(data, compresslevel=9)
    assert len(data) > 200 * len(packed)
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setenv("TMPDIR", str(temporary))
    monkeypatch.setattr(tempfile, "tempdir", None)
    path = tmp_path / "big.pcap.gz"
    path.write_bytes(packed)
    with CaptureReader(str(path)) as reader:
        held = [os.readlink(f"/proc/self/fd/{fd}") for fd in os.listdir("/proc/self/fd")
                if os.path.exists(f"/proc/self/fd/{fd}")]
        count = sum(1 for _ in reader)
    assert (count, reader.problem) == (20_000, None)
    assert not [name for name in held if name.startswith(str(temporary))], held     # (deleted ones too)
    middle = gzip.compress(data[:24 + 1000 * 1458])
    damaged = middle[:len(middle) // 2] + bytes(64) + middle[len(middle) // 2 + 64:] + gzip.compress(data[24:])
    reader, got = read(tmp_path, damaged, "damaged.pcap.gz")
    assert 0 < len(got) < 1000 and reader.problem and "gzip data corrupt after" in reader.problem


@pytest.mark.parametrize("content,message", [
    (gzip.compress(b"hello, this is text\n"), "not a pcap or pcapng"),
    (gzip.compress(gzip.compress(pcap([]))), "compressed with gzip, which is not read here"),  # one layer, as Wireshark
    (b"\x28\xb5\x2f\xfd" + bytes(20), "compressed with zstd, which is not read here: decompress it first"),
    (b"\x04\x22\x4d\x18" + bytes(20), "compressed with lz4"),
], ids=["gzip-text", "gzip-twice", "zstd", "lz4"])
def test_compressed_files_that_are_not_read(tmp_path, content, message):
    path = tmp_path / "x.pcap.gz"
    path.write_bytes(content)
    before = _open_fds()
    with pytest.raises(CaptureError, match=message):
        CaptureReader(str(path))
    assert _open_fds() == before


@pytest.mark.parametrize("content,message", [
    (b"", "empty file"), (b"ab", "too short"), (b"hello, this is text\n", "not a pcap or pcapng"),
    (struct.pack("<IHHiI", 0xA1B2C3D4, 2, 4, 0, 0), "file header cut short"),
])
def test_not_a_capture(tmp_path, content, message):
    path = tmp_path / "x.pcap"
    path.write_bytes(content)
    with pytest.raises(CaptureError, match=message):
        list(CaptureReader(str(path)))


def test_missing_file(tmp_path):
    with pytest.raises(CaptureError, match="No such file"):
        CaptureReader(str(tmp_path / "nope.pcap"))


def test_chunk_boundaries_do_not_matter(tmp_path):
    frames = [(1.0 + i, Ether() / udp_ip(bytes([i]) * (i + 1))) for i in range(40)]
    data = pcap(frames)
    _, whole = read(tmp_path, data)
    for size in (17, 64, 100):
        _, chunked = read(tmp_path, data, chunk_size=size)
        assert chunked == whole


def _open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


@pytest.mark.parametrize("content", [b"", b"hello, this is text\n"])
def test_a_file_that_is_not_a_capture_is_closed_at_once(tmp_path, content):
    path = tmp_path / "x.pcap"
    path.write_bytes(content)
    before = _open_fds()
    with pytest.raises(CaptureError):
        CaptureReader(str(path))
    assert _open_fds() == before


def test_a_walk_stopped_early_or_never_started_closes_the_file_on_leaving_the_with(tmp_path):
    path = tmp_path / "c.pcap"
    path.write_bytes(pcap([(1.0 + i, Ether() / udp_ip()) for i in range(5)]))
    before = _open_fds()
    with CaptureReader(str(path), chunk_size=64) as reader:
        assert len(_open_fds() - before) == 1
        walk = iter(reader)
        assert next(walk)[5] == 1                  # stopped after the first datagram, walk still held
    assert _open_fds() == before
    with CaptureReader(str(path)):
        pass
    assert _open_fds() == before


def test_crc_sniffing_that_stops_at_its_limit_leaves_no_file_open(tmp_path):
    from vm110.analysis.engine import crc_candidates
    path = tmp_path / "c.pcap"
    path.write_bytes(pcap([(1.0 + i, Ether() / udp_ip()) for i in range(5)]))
    before = _open_fds()
    crc_candidates(str(path), (5825,), limit=1, chunk_size=64)
    assert _open_fds() == before
