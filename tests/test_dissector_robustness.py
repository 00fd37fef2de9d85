"""Robustness: over 20,000 random and mutated packets (random bytes behind a valid packet ID, scapy
fuzz(), truncations and extensions, wrong sizes, bit flips, other revisions and IDs) in one capture,
one tshark run per tshark version. No "Lua Error", no exception in dissection, tshark exits 0,
every packet gets a vm110 tree (the empty datagrams excepted: UDP hands them to no dissector); and each packet still decodes like Python's `vm110.decode()`:
every field, the set of problems, and the number of warnings of each code."""
from __future__ import annotations

from collections import Counter

import pytest

import dissector_packets as P
import tshark_runner as T
from vm110 import constants as C
from vm110 import decode
from vm110.decode import VRPI_LAYOUT

pytestmark = pytest.mark.tshark

SEED = 3_110
FIELDS = ["type", "direction", "revision", "origin", "serial", "size", "spare", "crc", "crc.calculated",
          "crc.status", *(name for name, _ in VRPI_LAYOUT),
          "es_relays_open", "packet_number", "periodic_data", "command_id", "command_spare", "command_data"]
EXPERTS = sorted({*T.PROBLEM_CODES, *(w.value for w in C.WarningCode), "es_relays_open"})
CRC_STATUS = {"0": "Bad", "1": "Good", "2": "Unverified"}


@pytest.fixture(scope="module")
def packets() -> list[bytes]:
    out = P.malformed_packets(SEED)
    assert len(out) >= 20_000
    return out


def _value(name: str, text: str):
    if name in T.BYTE_FIELDS:
        return "" if text == "<MISSING>" else text      # zero bytes, as tshark 4.0 prints them
    if name in T.STRING_FIELDS:
        return text
    if name in T.BOOL_FIELDS:
        return text in ("1", "True")
    if name == "crc.status":
        return CRC_STATUS[text]
    return int(text, 0)


def _printable(text: str) -> bool:
    return all(" " <= ch <= "~" for ch in text) and "\\" not in text


def _differences(columns: list[str], data: bytes) -> list[str]:
    expected = decode(data)
    want = T.python_expectation(expected)
    if "type" in want and not _printable(want["type"]):
        want.pop("type")        # tshark escapes what it cannot print; compared where printable
        columns[0] = ""
    got = {name: _value(name, text) for name, text in zip(FIELDS, columns) if text != ""}
    if want.get("periodic_data") == "":
        got.setdefault("periodic_data", "")   # zero bytes of data print as nothing
    errors = [f"{k}: tshark {got.get(k)!r} python {want.get(k)!r}"
              for k in sorted(set(got) | set(want)) if got.get(k) != want.get(k)]
    counts = {code: len(text.split(",")) if text else 0 for code, text in zip(EXPERTS, columns[len(FIELDS):])}
    warned = Counter(w.split(":")[0] for w in expected["warnings"])
    for code in EXPERTS:
        if code in T.PROBLEM_CODES:
            want_count = int(code in expected["problems"])
        elif code == "es_relays_open":
            want_count = int(bool(expected.get("es_relays_open")))
        else:
            want_count = warned[code]
        if counts[code] != want_count:
            errors.append(f"expert {code}: tshark {counts[code]} python {want_count}")
    return errors


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_malformed_packets(tshark, packets, tmp_path):
    # An exception in dissection would add a _ws.malformed layer after vm110 in frame.protocols.
    args = ["-T", "fields", "-E", "occurrence=a", "-e", "frame.protocols", "-e", "_ws.lua.error",
            *(a for name in FIELDS for a in ("-e", f"vm110.{name}")),
            *(a for code in EXPERTS for a in ("-e", f"vm110.expert.{code}"))]
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "malformed.pcap"
            T.write_pcap(pcap, packets)
            proc = ws.run(["-r", str(pcap), *args])
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in proc.stdout + proc.stderr
    lines = proc.stdout.split("\n")[:-1]
    assert len(lines) == len(packets)
    failures = {}
    for number, (line, data) in enumerate(zip(lines, packets), start=1):
        columns = line.split("\t")
        if len(columns) != 2 + len(FIELDS) + len(EXPERTS):
            failures[number] = [f"unparsable line {line!r}"]
            continue
        protocols, lua_error = columns[:2]
        if not data:
            continue            # an empty datagram reaches no dissector: nothing to compare
        errors = [] if protocols.endswith(":vm110") else [f"protocols {protocols}"]
        if lua_error:
            errors.append(f"lua error {lua_error!r}")
        errors += _differences(columns[2:], data)
        if errors:
            failures[number] = errors
    assert not failures, f"{len(failures)} of {len(packets)} frames fail, e.g. {list(failures.items())[:3]}"


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_first_ip_fragment_is_truncated_not_a_bad_crc(tshark, tmp_path):
    """With ip.defragment off (as `analyze --engine tshark` runs it), UDP hands the dissector the
    first IP fragment of a 420-byte VRPO: the dissector judged it as a whole datagram, "bad CRC,
    size mismatch", though its CRC and the rest of its payload are in later fragments. It is
    `truncated` alone, as a datagram the snaplen cut; reassembled, a bad CRC is still one."""
    from scapy.layers.inet import IP, UDP, fragment
    from scapy.layers.l2 import Ether
    from scapy.packet import Raw
    from scapy.utils import wrpcap
    from vm110 import encode
    frames = []
    for serial, crc in ((3, 0), (4, None)):
        datagram = IP(src="10.0.0.20", dst=C.MULTICAST_GROUP, id=serial) / UDP(sport=C.OUTPUT_PORT, dport=C.OUTPUT_PORT) \
            / Raw(encode.packet("VRPO", bytes(400), serial=serial, crc=crc))
        frames += [Ether() / f for f in fragment(datagram, fragsize=200)]
    codes = sorted(T.PROBLEM_CODES)
    fields = ["-T", "fields", "-e", "vm110.serial", "-e", "vm110.crc.status",
              *(a for code in codes for a in ("-e", f"vm110.expert.{code}")), "-e", "_ws.expert.message"]
    with tshark.workspace(tmp_path) as ws:
        pcap = ws.dir / "fragments.pcap"
        wrpcap(str(pcap), frames)
        for defragment, want in (("FALSE", [("3", [C.Problem.TRUNCATED.value]), ("4", [C.Problem.TRUNCATED.value])]),
                                 ("TRUE", [("3", [C.Problem.BAD_CRC.value]), ("4", [])])):
            for passes in ([], ["-2"]):
                proc = ws.run(["-r", str(pcap), *passes, "-o", f"ip.defragment:{defragment}", *T.pref_args(None),
                               "-Y", "vm110", *fields])
                assert T.LUA_ERROR not in proc.stdout + proc.stderr
                rows = [line.split("\t") for line in proc.stdout.splitlines()]
                got = [(r[0], sorted(c for c, v in zip(codes, r[2:]) if v)) for r in rows]
                assert got == want, (defragment, passes, rows)
                if defragment == "FALSE":
                    assert all("IP fragment" in r[-1] and r[1] == "" for r in rows), rows


def _problems_per_frame(ws: T.Workspace, pcap, *extra: str) -> list[tuple[str, list[str], str]]:
    """Per frame with EG-Link, in both pass modes alike: (serial, problem codes, the truncated expert's message)."""
    codes = sorted(T.PROBLEM_CODES)
    fields = ["-T", "fields", "-E", "aggregator=|", "-e", "vm110.serial",
              *(a for code in codes for a in ("-e", f"vm110.expert.{code}")), "-e", "_ws.expert.message"]
    runs = []
    for passes in ([], ["-2"]):
        proc = ws.run(["-r", str(pcap), *passes, *extra, *T.pref_args(None), "-Y", "vm110", *fields])
        assert T.LUA_ERROR not in proc.stdout + proc.stderr
        rows = [line.split("\t") for line in proc.stdout.splitlines()]
        runs.append([(r[0], [c for c, v in zip(codes, r[1:]) if v],
                      "".join(m for m in r[-1].split("|") if m.startswith("Truncated"))) for r in rows])
    assert runs[0] == runs[1]
    return runs[0]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_datagram_cut_short_on_another_port_is_truncated(tshark, tmp_path):
    """On a port only the heuristic finds EG-Link on, a datagram the snaplen cut, or the first IP
    fragment of one not reassembled, is EG-Link and `truncated`, as on the EG-Link ports: the
    heuristic compared `size` with the bytes captured, not with the UDP length, and left it plain
    UDP (trial: BU on port 6000 captured with snaplen 100: no VRPI and no VRPO at all, and the commands
    between them with serial gaps and no cause in sight)."""
    from scapy.layers.inet import IP, UDP, fragment
    from scapy.layers.l2 import Ether
    from scapy.packet import Raw
    from scapy.utils import wrpcap
    from test_analysis_tshark import snapped
    from vm110 import encode
    whole = tmp_path / "whole.pcap"
    T.write_pcap(whole, [T.Datagram(encode.packet("VRPI", bytes(46), origin=1, serial=7), 6000, 6000),
                         T.Datagram(encode.packet("VRAO", bytes(2), serial=8), 6002, 6002)])
    vrpo = IP(src=T.CONTROLLER_ADDR, dst=C.MULTICAST_GROUP, id=9) / UDP(sport=6002, dport=6002) \
        / Raw(encode.packet("VRPO", bytes(400), serial=9))
    with tshark.workspace(tmp_path / "ws") as ws:
        cut, fragments = ws.dir / "snap70.pcap", ws.dir / "fragments.pcap"
        snapped(whole, cut, 70)                            # the VRPI's 66-byte datagram keeps 28 bytes, the VRAO all
        wrpcap(str(fragments), [Ether() / f for f in fragment(vrpo, fragsize=200)])
        assert _problems_per_frame(ws, cut) == [("7", [C.Problem.TRUNCATED.value], "Truncated: cut short by the capture (snaplen)"),
                                                ("8", [], "")]
        assert _problems_per_frame(ws, fragments, "-o", "ip.defragment:FALSE") == [
            ("9", [C.Problem.TRUNCATED.value], "Truncated: the first IP fragment of a datagram not reassembled")]
        assert _problems_per_frame(ws, fragments) == [("9", [], "")]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_a_datagram_an_icmp_error_quotes_in_part_is_truncated_not_a_bad_crc(tshark, tmp_path):
    """An ICMP error quotes the datagram it answers, often only its beginning (RFC 792: 8 bytes;
    many stacks a few dozen). The dissector judged such a quote as a whole datagram, "bad CRC, size
    mismatch" (with "truncated" where it ended in the payload), though the CRC was never quoted:
    it is `truncated` alone, on the EG-Link ports and elsewhere; a quote of all of it decodes whole."""
    from scapy.layers.inet import ICMP, IP, UDP
    from scapy.layers.l2 import Ether
    from scapy.utils import wrpcap
    from vm110 import encode
    frames = []
    for port in (C.OUTPUT_PORT, 6002):
        datagram = bytes(IP(src=T.CONTROLLER_ADDR, dst=T.BU_ADDR) / UDP(sport=port, dport=port)
                         / encode.packet("VRPO", bytes(100), serial=port))
        for quoted in (28 + 20, 28 + 60, len(datagram) - 2, len(datagram)):   # (IP and UDP headers: 28 bytes)
            frames.append(Ether() / IP(src=T.BU_ADDR, dst=T.CONTROLLER_ADDR) / ICMP(type=3, code=3) / datagram[:quoted])
    cut = [C.Problem.TRUNCATED.value], "Truncated: cut short by an ICMP error's quote"
    with tshark.workspace(tmp_path) as ws:
        pcap = ws.dir / "quotes.pcap"
        wrpcap(str(pcap), frames)
        got = _problems_per_frame(ws, pcap)
    assert got == [(str(port), *want) for port in (C.OUTPUT_PORT, 6002) for want in (cut, cut, cut, ([], ""))]
