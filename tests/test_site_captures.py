"""`vm110 analyze` on captures as a site records them (tests/site_captures.py lays out their bytes
from the pcap, pcapng and TS-0006 texts, sharing no code with vm110): what TS-0006 and
interpretation.md say the analysis must report, whatever the capture's layout."""
from __future__ import annotations

import gzip
import pathlib

import pytest

import site_captures as S
import tshark_runner as T
from test_analysis_tshark import assert_same
from vm110.analysis import analyze
from vm110.analysis.findings import FRAGMENT_FILTER

SLL, SLL2, ETHERNET = 113, 276, 1


def _expected(report: dict, site: S.Site, duplicates: int = 0) -> None:
    """The site's traffic as TS-0006 reads it: every packet per sender and type, the VRPI lost,
    the one command resent once and acknowledged, every VRPO burst complete."""
    by_type = {}
    for sender in report["senders"]:
        by_type.update(sender["by_type"])
    want = site.expect()
    assert by_type == {k: v * (1 + bool(duplicates)) for k, v in want.items() if k.isupper()}
    tot = report["totals"]
    assert (tot["lost"], tot["duplicates"], tot["commands"], tot["retransmissions"], tot["unacked"]) == (
        want["lost"], duplicates, want["commands"], want["retransmissions"], 0)
    assert report["vrpo_bursts"]["complete"] == site.vrpo_count and report["vrpo_bursts"]["incomplete"] == 0
    assert [g["after"] + 1 for s in report["senders"] for g in s["serial"]["gaps"]] == list(site.lost_vrpi)


def _pcapng_of_two_links(site: S.Site, resolutions: tuple[int, int], link: int, big: bool) -> bytes:
    """The base unit seen on an Ethernet interface, the controller on a cooked one, each with its
    own if_tsresol."""
    records = []
    for rec, d in zip(S.frames(site, S.on_ethernet()), site.datagrams):
        if d.payload[3:4] == b"I":
            records.append(rec)
        else:
            cooked = S.on_sll if link == SLL else S.on_sll2
            records.append(S.Record(rec.ts_ns, cooked(d, rec.data[14:]), iface=1))
    return S.pcapng([S.Interface(ETHERNET, resolutions[0]), S.Interface(link, resolutions[1])], records, big=big)


LAYOUTS = {
    "sll": lambda s: S.pcap(S.frames(s, S.on_sll), SLL),
    "sll2": lambda s: S.pcap(S.frames(s, S.on_sll2), SLL2),
    "vlan": lambda s: S.pcap(S.frames(s, S.on_ethernet([(0x8100, 42)])), ETHERNET),
    "qinq": lambda s: S.pcap(S.frames(s, S.on_ethernet([(0x88A8, 100), (0x8100, 42)])), ETHERNET),
    "pcap-ns-big-endian": lambda s: S.pcap(S.frames(s, S.on_ethernet()), ETHERNET, nanos=True, big=True),
    "pcap-gzip": lambda s: gzip.compress(S.pcap(S.frames(s, S.on_ethernet()), ETHERNET)),
    "pcapng-ns-and-1e-4": lambda s: _pcapng_of_two_links(s, (9, 4), SLL, False),
    "pcapng-2^-20-and-ms-big-endian": lambda s: _pcapng_of_two_links(s, (0x80 | 20, 3), SLL2, True),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_layout_of_a_site_capture_gives_the_same_analysis(layout, tmp_path):
    site = S.Site(lost_vrpi=(10,))
    path = tmp_path / "site.cap"
    path.write_bytes(LAYOUTS[layout](site))
    report = analyze(str(path))
    assert report["capture"]["problem"] is None
    _expected(report, site)


def test_ipv6_multicast_on_other_ports_from_ephemeral_source_ports(tmp_path):
    site = S.Site(lost_vrpi=(10,), ipv6=True, port=6000)
    for d in site.datagrams:
        d.sport = 50000 if d.payload[3:4] == b"O" else 40000
    path = tmp_path / "site.pcap"
    path.write_bytes(S.pcap(S.frames(site, S.on_ethernet()), ETHERNET))
    report = analyze(str(path), port=6000)
    _expected(report, site)
    assert sorted(s["src"] for s in report["senders"]) == ["[fd00::10]:40000", "[fd00::20]:50000"]


def test_a_span_port_s_copy_of_every_frame_is_a_duplicate_and_nothing_else(tmp_path):
    site = S.Site(lost_vrpi=(10,))
    records = []
    for rec, d in zip(S.frames(site, S.on_ethernet()), site.datagrams):   # ingress tagged, egress not
        records += [S.Record(rec.ts_ns, S.on_ethernet([(0x8100, 42)])(d, rec.data[14:])),
                    S.Record(rec.ts_ns + 3000, rec.data)]
    path = tmp_path / "span.pcap"
    path.write_bytes(S.pcap(records, ETHERNET))
    report = analyze(str(path))
    _expected(report, site, duplicates=len(site.datagrams))
    assert report["totals"]["duplicate_acks"] == 0 and report["periodic"][0]["count"] == site.vrpi_count


def _fragmented(site: S.Site, mtu: int, broken: int, copied: int) -> tuple[list[S.Record], list[int]]:
    """The site's traffic over a link of `mtu` bytes: every VRPO in IP fragments; the `broken`-th
    fragmented datagram loses its middle fragment, and a mirror port repeats the fragments of the
    `copied`-th after it. Also the frame numbers of the fragments never reassembled."""
    records, never, n = [], [], 0
    for d in site.datagrams:
        body = S.udp(d.src, d.sport, d.dst, d.dport, d.payload)
        if len(body) + 48 <= mtu:
            packet = S.ipv6(d.src, d.dst, body) if site.ipv6 else S.ipv4(d.src, d.dst, body)
            records.append(S.Record(d.ts_ns, S.on_ethernet()(d, packet)))
            continue
        n += 1
        split = S.ipv6_fragments if site.ipv6 else S.ipv4_fragments
        parts = split(d.src, d.dst, body, mtu, 0x100 + n)
        assert len(parts) == 3
        if n == broken:
            parts = [parts[0], parts[2]]
        for copy in range(1 + (n == copied)):
            for i, part in enumerate(parts):
                records.append(S.Record(d.ts_ns + copy * 500_000 + i * 20_000, S.on_ethernet()(d, part)))
                if n == broken:
                    never.append(len(records))
    return records, never


@pytest.mark.parametrize("ipv6", [False, True], ids=["ipv4", "ipv6"])
def test_a_vrpo_fragmented_by_a_small_mtu_is_analysed_as_wireshark_reassembles_it(ipv6, tmp_path):
    """A VRPO of 488 data bytes is a 538-byte IP packet (558 over IPv6): over a link of a smaller
    MTU it arrives in fragments, and the base unit (and Wireshark, by default) receives it whole.
    Both engines left every fragment unanalysed (trial): the controller's VRPO stream vanished from
    the report, with no watchdog violation and no loss, and the verdict was OK."""
    site = S.Site(lost_vrpi=(10,), ipv6=ipv6, vrpo_data=488)
    records, never = _fragmented(site, 256, broken=5, copied=9)
    path = tmp_path / "small-mtu.pcap"
    path.write_bytes(S.pcap(records, ETHERNET))
    report = analyze(str(path))
    by_type = {t: n for s in report["senders"] for t, n in s["by_type"].items()}
    assert by_type == {"VRPI": site.vrpi_count, "VRCI": 2, "VRPO": site.vrpo_count - 1 + 1, "VRAO": 1}
    tot = report["totals"]
    assert (tot["lost"], tot["duplicates"], report["capture"]["fragments"]) == (2, 1, len(never))
    controller = next(s for s in report["senders"] if s["direction"] == "Output")
    assert [g["after"] + 1 for g in controller["serial"]["gaps"]] == [5]      # the 5th VRPO's serial
    assert report["vrpo_bursts"]["complete"] == site.vrpo_count - 1
    [warning] = [f for f in report["verdict"]["findings"] if f["rule"] == "ip_fragments"]
    assert warning["count"] == len(never) == 2 and warning["message"].endswith(FRAGMENT_FILTER)
    assert_same(str(path))


def test_a_mirror_port_s_copy_of_each_fragment_is_not_said_to_be_a_loss(tmp_path):
    """A SPAN port that repeats each frame right after it: a fragmented VRPO is whole at its last
    fragment, whose copy then starts a datagram never whole (Wireshark's count too). The warning
    gave one cause only, a fragment lost or cut, whose EG-Link packets count as lost (trial-fleet):
    here nothing was lost, every VRPO analysed once."""
    site = S.Site(vrpo_data=488, seconds=1.0)
    records, never = _fragmented(site, 256, broken=0, copied=0)
    path = tmp_path / "span-fragments.pcap"
    path.write_bytes(S.pcap([S.Record(r.ts_ns + copy * 1000, r.data) for r in records for copy in (0, 1)], ETHERNET))
    report = analyze(str(path))
    by_type = {t: n for s in report["senders"] for t, n in s["by_type"].items()}
    want = site.expect()
    assert by_type == {"VRPI": 2 * want["VRPI"], "VRCI": 4, "VRAO": 2, "VRPO": want["VRPO"]}
    assert (report["totals"]["lost"], report["totals"]["duplicates"]) == (0, len(site.datagrams) - site.vrpo_count)
    [warning] = [f for f in report["verdict"]["findings"] if f["rule"] == "ip_fragments"]
    assert never == [] and warning["count"] == site.vrpo_count
    assert "a mirror port's copy of a fragment that came after its datagram was whole" in warning["message"]


def test_a_flood_of_fragments_never_whole_gives_up_the_oldest_datagram_as_documented(tmp_path):
    """The fast engine bounds the datagrams waiting for their rest; Wireshark does not. A VRPO
    with more of them begun between its fragments was not analysed, and docs/report.md said
    fragments are reassembled as Wireshark reassembles them, no word of the bound (trial-fleet)."""
    from vm110.capture.reassembly import MAX_PENDING, MAX_PENDING_BYTES
    d = S.Site(vrpo_data=488).datagrams[0]
    first, last = S.ipv4_fragments(S.CTRL_IP, S.GROUP, S.udp(S.CTRL_IP, 5827, S.GROUP, 5827, S.vrpo(1, 0, bytes(488))),
                                   400, 9)
    flood = [S.ipv4("10.0.0.99", S.GROUP, bytes(8), ident=k, offset8=1, more=True) for k in range(MAX_PENDING)]
    for pending, name in ((MAX_PENDING - 1, "kept"), (MAX_PENDING, "given-up")):
        packets = [first, *flood[:pending], last]
        path = tmp_path / f"{name}.pcap"
        path.write_bytes(S.pcap([S.Record(S.T0_NS + n, S.on_ethernet()(d, p)) for n, p in enumerate(packets)], ETHERNET))
        cap = analyze(str(path))["capture"]
        assert (cap["eglink_packets"], cap["fragments"]) == ((1, pending) if name == "kept" else (0, pending + 2))
    doc = (pathlib.Path(__file__).parent.parent / "docs" / "report.md").read_text()
    assert f"at most {MAX_PENDING} datagrams ({MAX_PENDING_BYTES >> 20} MiB of fragments)" in " ".join(doc.split())


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_the_fragments_filter_shows_the_fragments_never_reassembled_in_wireshark(tshark, tmp_path):
    records, never = _fragmented(S.Site(vrpo_data=488, seconds=1.0), 256, broken=2, copied=3)
    site6 = S.Site(vrpo_data=488, seconds=1.0, ipv6=True)
    for d in site6.datagrams:
        d.t += 1.0
    more, never6 = _fragmented(site6, 256, broken=4, copied=1)
    never += [len(records) + n for n in never6]
    path = tmp_path / "fragments.pcap"
    path.write_bytes(S.pcap(records + more, ETHERNET))
    assert analyze(str(path))["capture"]["fragments"] == len(never) == 4
    with tshark.workspace(tmp_path / "ws") as ws:
        local = ws.dir / path.name
        local.write_bytes(path.read_bytes())
        # (two passes, as Wireshark's own: a fragment knows the frame it was reassembled in)
        shown = ws.run(["-2", "-r", str(local), "-Y", FRAGMENT_FILTER, "-T", "fields", "-e", "frame.number"],
                       plugin=False).stdout.split()
    assert [int(n) for n in shown] == never


def test_fragments_are_told_apart_and_overlaps_settled_as_in_wireshark(tmp_path):
    """Found by a fuzz of fragment sets against the tshark engine: a fragment past the datagram's
    end kept it from ever being whole, and IPv6 fragments were told apart by VLAN (Wireshark keys
    IPv4 reassembly by VLAN, IPv6 not)."""
    records, t = [], 0.0

    def datagram(ipv6: bool) -> tuple[S.Datagram, bytes]:
        nonlocal t
        t += 0.1
        src, dst = (S.CTRL_IP6, S.GROUP6) if ipv6 else (S.CTRL_IP, S.GROUP)
        d = S.Datagram(t, src, 5827, dst, 5827, S.vrpo(round(t * 10), 0, bytes(488)))
        return d, S.udp(d.src, d.sport, d.dst, d.dport, d.payload)

    def add(d: S.Datagram, *packets: bytes, tags: tuple = ()) -> None:
        for packet in packets:
            records.append(S.Record(d.ts_ns + len(records) * 1000, S.on_ethernet(tags)(d, packet)))

    d, body = datagram(False)           # a stray fragment past the end: whole at its tail all the same
    a, b, c = S.ipv4_fragments(d.src, d.dst, body, 256, 1)
    add(d, a, S.ipv4(d.src, d.dst, bytes(16), 1, offset8=100, more=True), b, c)
    d, body = datagram(True)            # IPv6 fragments on two VLANs: one datagram
    a, b, c = S.ipv6_fragments(d.src, d.dst, body, 256, 2)
    add(d, a, tags=((0x8100, 10),))
    add(d, b, c)
    d, body = datagram(False)           # IPv4 fragments on two VLANs: never whole
    a, b, c = S.ipv4_fragments(d.src, d.dst, body, 256, 3)
    add(d, a, tags=((0x8100, 10),))
    add(d, b, c)
    d, body = datagram(False)           # garbage at offset 0 after the real first fragment: the real one stands
    a, b, c = S.ipv4_fragments(d.src, d.dst, body, 256, 4)
    add(d, a, S.ipv4(d.src, d.dst, body[:20] + b"\xff" * 4, 4, more=True), b, c)
    d, body = datagram(False)           # ... before it: the garbage stands (a bad CRC)
    a, b, c = S.ipv4_fragments(d.src, d.dst, body, 256, 5)
    add(d, S.ipv4(d.src, d.dst, body[:20] + b"\xff" * 4, 5, more=True), a, b, c)   # (the spare field)
    path = tmp_path / "fragments.pcap"
    path.write_bytes(S.pcap(records, ETHERNET))
    report = analyze(str(path))
    assert (report["capture"]["eglink_packets"], report["capture"]["fragments"]) == (4, 3)
    assert (report["crc"]["valid"], report["illegal"]["by_reason"]) == (3, {"bad_crc": 1})
    assert_same(str(path))


def test_fragments_are_taken_or_left_as_wireshark_takes_them(tmp_path):
    """Found by the same fuzz: Wireshark tells fragments apart by VLAN only between private or
    link-local addresses (the same ones may be in use on several VLANs), takes a total length of 0
    as the frame's (segmentation offload), leaves a fragment the snaplen cut out of reassembly (and
    the tshark engine took such a first fragment, which Wireshark dissects as it is, for a datagram
    reassembled), and shows a fragment whose IP header the capture cut."""
    records, t = [], 0.0

    def datagram(src: str) -> tuple[S.Datagram, list[bytes]]:
        nonlocal t
        t += 0.1
        d = S.Datagram(t, src, 5827, S.GROUP, 5827, S.vrpo(round(t * 10), 0, bytes(488)))
        return d, S.ipv4_fragments(d.src, d.dst, S.udp(d.src, d.sport, d.dst, d.dport, d.payload), 256, round(t * 10))

    def add(d: S.Datagram, packet: bytes, tags: tuple = (), cut: int = 0) -> None:
        frame = S.on_ethernet(tags)(d, packet)
        records.append(S.Record(d.ts_ns + len(records) * 1000, frame[:len(frame) - cut], len(frame)))

    d, (a, b, c) = datagram("198.51.100.20")    # public addresses on two VLANs: one datagram
    add(d, a, tags=((0x8100, 10),))
    add(d, b)
    add(d, c)
    d, (a, b, c) = datagram(S.CTRL_IP)          # the first fragment cut by the snaplen: never whole
    add(d, a, cut=100)
    add(d, b)
    add(d, c)
    d, (a, b, c) = datagram(S.CTRL_IP)          # a total length of 0: the frame's
    add(d, a[:2] + b"\0\0" + a[4:])
    add(d, b)
    add(d, c)
    d, (a, _, _) = datagram(S.CTRL_IP)          # an IP header cut after 10 bytes: still a fragment
    add(d, a, cut=len(a) - 10)
    path = tmp_path / "fragments.pcap"
    path.write_bytes(S.pcap(records, ETHERNET))
    report = analyze(str(path))
    assert (report["capture"]["eglink_packets"], report["capture"]["fragments"]) == (2, 4)
    assert report["crc"]["valid"] == 2 and report["illegal"]["total"] == 0
    assert_same(str(path))



def test_a_datagram_of_thousands_of_fragments_is_judged_whole_once(monkeypatch):
    """A capture decides how many fragments a datagram has (up to 8,192 of 8 bytes) and how often
    each comes: whether it was whole was judged by sorting every fragment again at each one,
    quadratic (8,000 fragments, last first: 6.7 s). The bytes are assembled once, at the fragment
    that makes the datagram whole, and where a copy differs the first placed stand."""
    from vm110.capture import reassembly

    sorts = []
    monkeypatch.setattr(reassembly, "sorted", lambda parts, **kw: sorts.append(1) or sorted(parts, **kw),
                        raising=False)
    body = bytes(i * 7 % 251 for i in range(8 * 8000))
    table, done = reassembly.Reassembly(), []
    for i in range(7999, -1, -1):            # the last fragment first, each but the first twice
        for part in [body[i * 8:i * 8 + 8]] + ([b"\xff" * 8] if i else []):
            done.append(table.add(("key",), i * 8, i != 7999, part))
    assert done[-1] == (body, 8000 * 2 - 1)
    assert done[:-1] == [None] * (8000 * 2 - 2) and len(sorts) == 1


def test_fragments_never_whole_hold_at_most_the_table_s_bound():
    """A link flooded with fragments that never complete (another protocol's, a lossy link, a
    fuzzer) must not grow a monitor watching it for days: the table holds 4096 datagrams at most.
    A fragment reaching past 64 KiB, each of a datagram of its own, went round the bound (the
    monitor on 400,000 of them: 297 MB resident, 102 MB at 50,000)."""
    from vm110.capture import reassembly

    table = reassembly.Reassembly()
    for i in range(3 * reassembly.MAX_PENDING):
        assert table.add(("far", i), 8180 * 8, False, bytes(200)) is None       # past 64 KiB
    assert len(table._pending) <= reassembly.MAX_PENDING
    for i in range(3 * reassembly.MAX_PENDING):
        assert table.add(("near", i), 0, True, bytes(200)) is None
    assert len(table._pending) <= reassembly.MAX_PENDING


def test_copies_of_a_small_fragment_hold_the_table_to_its_bytes(monkeypatch):
    """The 16 MiB bound counted the fragments' bytes alone: copies of one 8-byte fragment (a fuzzer,
    a looping mirror) cost some 130 bytes each held, and 2.2 million took 350 MB before the bound
    (here a bound of 1 MiB, and 40,000 copies: 6.6 MB)."""
    import tracemalloc

    from vm110.capture import reassembly

    monkeypatch.setattr(reassembly, "MAX_PENDING_BYTES", 1 << 20)
    table = reassembly.Reassembly()
    tracemalloc.start()
    try:
        for i in range(40_000):
            table.add(("key",), i % 100 * 8, True, i.to_bytes(8, "little"))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 << 20
