"""The `vm110` command line: crafting, decoding, and clean errors with documented exit codes."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
from vm110.errors import EXIT_OK, EXIT_USAGE


def vm110(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True)


@pytest.mark.parametrize("name, magic", [("crafted.pcap", b"\xd4\xc3\xb2\xa1"), ("crafted.pcapng", b"\n\r\r\n"),
                                         ("CRAFTED.PCAPNG", b"\n\r\r\n")])
def test_craft_then_decode_gives_every_type(tmp_path, name, magic):
    capture = tmp_path / name            # (a .pcapng was written as pcap; a .PCAPNG too)
    assert vm110("craft", "--out", str(capture)).returncode == EXIT_OK
    assert capture.read_bytes()[:4] == magic
    result = vm110("decode", str(capture), "--json")
    assert result.returncode == EXIT_OK, result.stderr
    packets = [json.loads(line) for line in result.stdout.splitlines()]
    assert sorted(p["type"] for p in packets) == ["VRAI", "VRAO", "VRCI", "VRCO", "VRPI", "VRPO"]
    assert all(p["problems"] == [] and p["crc.status"] == "Good" for p in packets)


def test_craft_to_standard_output(tmp_path):
    """`--out -` wrote a file named "-" into the current folder (and nothing to the pipe), where
    `-` means standard output everywhere else: now the pcap goes down the pipe, the line to
    standard error; standard output that cannot be written is one line, exit 2."""
    done = subprocess.run([sys.executable, "-m", "vm110", "craft", "--out", "-"], capture_output=True, cwd=tmp_path)
    assert done.returncode == EXIT_OK and list(tmp_path.iterdir()) == []
    assert done.stdout[:4] == b"\xd4\xc3\xb2\xa1" and done.stderr == b"wrote 6 packets to standard output\n"
    decoded = subprocess.run([sys.executable, "-m", "vm110", "decode", "-", "--json"], input=done.stdout,
                             capture_output=True)
    packets = [json.loads(line) for line in decoded.stdout.splitlines()]
    assert sorted(p["type"] for p in packets) == ["VRAI", "VRAO", "VRCI", "VRCO", "VRPI", "VRPO"]
    with open("/dev/full", "wb") as full:
        failed = subprocess.run([sys.executable, "-m", "vm110", "craft", "--out", "-"], stdout=full,
                                stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    assert failed.returncode == EXIT_USAGE
    assert failed.stderr == "vm110 craft: cannot write standard output: No space left on device\n"


def test_decode_with_the_wrong_crc_variant_flags_every_packet(tmp_path):
    capture = tmp_path / "crafted.pcap"
    vm110("craft", "--out", str(capture))
    result = vm110("decode", str(capture), "--crc", "bzip2")
    assert result.stdout.count("ILLEGAL(bad_crc)") == 6


def test_decode_says_which_frames_it_could_not_read(tmp_path):
    """A capture in PPI (192): decode printed "0 EG-Link packets" and nothing else, where tshark
    decodes every packet (trial). Standard error now names the frames it did not read."""
    import struct
    from test_reader import pcap, udp_ip
    from scapy.layers.l2 import Ether
    capture = tmp_path / "ppi.pcap"
    capture.write_bytes(pcap([(1.0 + k, struct.pack("<BBHI", 0, 0, 8, 1) + bytes(Ether() / udp_ip())) for k in range(3)],
                             linktype=192))
    result = vm110("decode", str(capture))
    assert result.returncode == EXIT_OK and result.stdout == "0 EG-Link packets\n"
    assert result.stderr == ("vm110 decode: 3 frames of link type 192 not read (this reader reads Ethernet, Linux "
                             "cooked, raw IP, loopback and 802.11; `vm110 dissect` reads what Wireshark reads)\n")


def test_decode_says_which_frames_may_carry_packets_it_did_not_decode(tmp_path, capsys):
    """An EG-Link packet in IP fragments of a datagram never whole, in IP in IP or in VXLAN: decode
    printed "0 EG-Link packets" and nothing else, where `vm110 dissect` shows each (Wireshark
    unwraps; `analyze` warns ip_fragments and tunnels). A datagram whose fragments all came is
    reassembled and decoded, as Wireshark does."""
    from scapy.layers.inet import IP, UDP, fragment
    from scapy.layers.l2 import Ether
    from scapy.layers.vxlan import VXLAN
    from scapy.utils import wrpcap
    from vm110.cli import main
    from vm110.layers import VM110, VRAO, VRPO
    inner = IP(src="10.0.0.20", dst="239.255.42.20") / UDP(sport=5827, dport=5827) / VM110() / VRAO(command_id=4)
    whole, cut = (fragment(Ether() / IP(src="10.0.0.20", dst="239.255.42.20", id=n) / UDP(sport=5827, dport=5827)
                           / VM110(serial=n) / VRPO(periodic_data=bytes(400)), fragsize=200) for n in (1, 2))
    frames = [*whole, *cut[:-1],
              Ether() / IP(src="10.0.0.1", dst="10.0.0.2") / inner,
              Ether() / IP(src="10.0.0.1", dst="10.0.0.2") / UDP(sport=40000, dport=4789) / VXLAN() / Ether() / inner]
    capture = tmp_path / "wrapped.pcap"
    wrpcap(str(capture), frames)
    assert main(["decode", str(capture)]) == EXIT_OK
    out, err = capsys.readouterr()
    assert out.endswith(" 10.0.0.20:5827        VRPO serial=1 packet_number=0\n1 EG-Link packet\n")
    assert out.startswith("     3 ") and out.count("\n") == 2
    assert err == ("vm110 decode: 2 IP fragments of datagrams never whole: EG-Link packets in them are not decoded "
                   "(`vm110 dissect` reads what Wireshark reads)\n"
                   "vm110 decode: 2 frames of tunnels not unwrapped (IP in IP, GRE with ERSPAN, VXLAN, GENEVE): "
                   "EG-Link packets in them are not decoded (`vm110 dissect` reads what Wireshark reads)\n")


def test_dissect_tells_an_empty_input_without_reading_it(tmp_path):
    """What `vm110 dissect` looks at before tshark reads the same input (tshark passes over an empty
    one with exit 0): a pipe whose writer is gone with nothing in it and /dev/null are empty; a pipe
    with data keeps every byte for tshark; a terminal is tshark's to read."""
    import os
    from vm110.commands.dissect import _empty
    read, write = os.pipe()
    os.write(write, b"\xd4\xc3\xb2\xa1")
    assert not _empty(read) and os.read(read, 8) == b"\xd4\xc3\xb2\xa1"
    os.close(write)
    assert _empty(read)
    os.close(read)
    with open(os.devnull, "rb") as null, open(tmp_path / "empty", "wb+") as empty, open(tmp_path / "one", "wb+") as one:
        one.write(b"x")
        one.flush()
        one.seek(0)
        assert _empty(null.fileno()) and _empty(empty.fileno()) and not _empty(one.fileno())


def _decode_hex(argv, stdin=b""):
    """`vm110 decode --hex ...` in this process: (exit code, standard output, standard error)."""
    import io
    from unittest import mock
    from vm110.cli import main
    out, err = io.StringIO(), io.StringIO()
    with mock.patch("sys.stdin", io.TextIOWrapper(io.BytesIO(stdin))), mock.patch("sys.stdout", out), \
            mock.patch("sys.stderr", err):
        code = main(["decode", "--hex", *argv])
    return code, out.getvalue(), err.getvalue()


def test_decode_hex_gives_the_fields_of_the_shared_vectors():
    """A datagram in hex (Wireshark's Copy as Hex Stream, a fuzzer finding's `hex`) decodes as a
    capture's do: every vector's fields, problems and warnings, the CRC setting it names."""
    from vectorlib import load_vectors
    settings = {}
    for vector in load_vectors():
        if vector["hex"]:
            settings.setdefault((vector["crc_variant"], vector["crc_byte_order"]), []).append(vector)
    for (variant, order), vectors in settings.items():
        lines = "".join(v["hex"] + "\n" for v in vectors).encode()
        code, out, err = _decode_hex(["-", "--json", "--crc", variant, "--crc-order", order], lines)
        assert (code, err) == (EXIT_OK, "")
        for number, (vector, got) in enumerate(zip(vectors, map(json.loads, out.splitlines()), strict=True), 1):
            assert got["datagram"] == number
            assert {k: got[k] for k in vector["fields"]} == vector["fields"], vector["name"]
            assert (sorted(got["problems"]), sorted(got["warnings"])) == (vector["problems"], vector["warnings"])
    spaced = "56:52:41:4f 00 00 00 00 03 00 02 00 00 00 00 00 04 00 bf 66 3c fc"    # VRAO 4, serial 3
    assert _decode_hex([spaced]) == (EXIT_OK, "     1 VRAO serial=3 command_id=4\n1 EG-Link packet\n", "")
    lines = f"{spaced.replace(':', '')}\n\n{spaced[:20]}\n".encode()      # a blank line is none; one cut short
    assert _decode_hex(["-"], lines) == (EXIT_OK, ("     1 VRAO serial=3 command_id=4\n"
                                                   "     2 VRAO serial=? ILLEGAL(truncated)\n2 EG-Link packets\n"), "")


def test_decode_shows_enumerated_values_as_the_vectors_name_them():
    """The line's states in the dissector's form, the vectors' `names` (vectors README): a value
    beyond the enumeration was "Unknown (0xFF)", where the dissector, the vectors and the analysis
    report say "Unknown (0xff)"."""
    from vectorlib import load_vectors
    named = [v for v in load_vectors() if v["fields"].get("type") == "VRPI" and "ru_state" in v["names"]
             and v["crc_variant"] == "mpeg2" and v["crc_byte_order"] == "little"]
    assert any("Unknown (0xff)" in v["names"].values() for v in named)
    code, out, _ = _decode_hex(["-"], "".join(v["hex"] + "\n" for v in named).encode())
    assert code == EXIT_OK
    for vector, line in zip(named, out.splitlines()[:-1], strict=True):
        for name in ("bu_state", "ru_state"):
            assert f"{name}={vector['names'][name]} " in line + " ", vector["name"]


@pytest.mark.parametrize("argv, stdin, said", [
    (["5652414"], b"", "--hex: '5652414' is not hex (an odd number of digits, 7: half a byte)"),
    (["0x5652"], b"", "--hex: '0x5652' is not hex ('x' is no hex digit)"),
    (["56\x1b[2J"], b"", "--hex: '56\\x1b[2J' is not hex ('\\x1b' is no hex digit)"),
    ([""], b"", "--hex: no bytes given"),
    (["-"], b"", "standard input: empty, no datagram in hex"),
    (["-"], b"5652\n\xff\xfe\x00garbage\n", "standard input, line 2: '\u00ff\u00fe\\x00garbage' is not hex ('\u00ff' is no hex digit)"),
])
def test_decode_hex_refuses_what_is_not_hex_in_one_line(argv, stdin, said):
    code, _, err = _decode_hex(argv, stdin)
    assert (code, err) == (EXIT_USAGE, f"vm110 decode: {said}\n")


def test_not_a_capture_is_one_line_and_exit_2(tmp_path):
    bogus = tmp_path / "notes.txt"
    bogus.write_text("hello\n")
    for path in (str(bogus), str(tmp_path / "missing.pcap")):
        result = vm110("decode", path)
        assert result.returncode == EXIT_USAGE
        assert result.stderr.startswith("vm110 decode: ") and path in result.stderr
        assert "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1


def test_unwritable_output_is_exit_2(tmp_path):
    result = vm110("craft", "--out", str(tmp_path / "no" / "such" / "dir.pcap"))
    assert result.returncode == EXIT_USAGE and "cannot write" in result.stderr


def test_usage_errors_exit_2():
    assert vm110("decode").returncode == EXIT_USAGE
    assert vm110("no-such-command").returncode == EXIT_USAGE
    assert vm110("--version").stdout.startswith("vm110 ")



def test_decode_shows_packet_ids_off_the_network_escaped(tmp_path, capsys):
    """Trial: a datagram on port 5825 with the packet ID ESC [ 2 J cleared the terminal, and one
    with "VR\\r\\n" broke its line in two; the JSON keeps the characters (json escapes them)."""
    import struct
    from test_reader import pcap, udp_ip
    from scapy.layers.l2 import Ether
    from vm110.cli import main
    ids = [b"\x1b[2J", b"VR\r\n"]
    frames = [(1.0 + k, Ether() / udp_ip(struct.pack("<4sHHHHI", raw, 0, 0, 5, 0, 0) + bytes(4)))
              for k, raw in enumerate(ids)]
    capture = tmp_path / "ids.pcap"
    capture.write_bytes(pcap(frames))
    assert main(["decode", str(capture)]) == EXIT_OK
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert len(lines) == 3 and lines[-1] == "2 EG-Link packets"
    assert " \\x1b[2J serial=5 ILLEGAL(unknown_id" in lines[0] and " VR\\r\\n serial=5 ILLEGAL(unknown_id" in lines[1]
    assert not any(c in out for c in "\x1b\r")
    assert main(["decode", str(capture), "--json"]) == EXIT_OK
    decoded = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [d["type"].encode("latin-1") for d in decoded] == ids


def test_dissect_without_a_capture_asks_for_the_capture_only(capsys):
    """`vm110 dissect` said "the following arguments are required: capture, TSHARK_ARGS", though
    the tshark arguments are optional (`vm110 dissect cap.pcap` runs tshark on it)."""
    from vm110.cli import main
    with pytest.raises(SystemExit) as done:
        main(["dissect"])
    assert done.value.code == EXIT_USAGE
    assert capsys.readouterr().err.splitlines()[-1] == "vm110 dissect: the following arguments are required: capture"


_LOADED = ("import sys; from vm110 import cli; cli.build_parser(sys.argv[1:]); "
           "print(' '.join(sorted(m for m in cli.COMMANDS.values() if 'vm110.commands.' + m in sys.modules)))")


@pytest.mark.parametrize("argv, loaded", [([], ""), (["--help"], ""), (["bogus"], ""),
                                          (["decode", "x.pcap"], "decode"), (["--", "analyze"], ""),
                                          (["fuzz", "--help"], "fuzz")])
def test_only_the_command_named_is_loaded(argv, loaded):
    """Every command loaded every command's module and their libraries (scapy, numpy, the fuzzer):
    `vm110 --help` took 1.2 s and each command started 0.7 s later than its own needed."""
    done = subprocess.run([sys.executable, "-c", _LOADED, *argv], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == loaded.split()


def test_the_top_help_summarises_every_command_as_its_module_does():
    from vm110 import cli
    full = {name: p.description.strip().splitlines()[0] for name, p in cli.build_parser().commands.items()}
    assert set(full) == set(cli.COMMANDS)
    top = vm110("--help")
    assert top.returncode == EXIT_OK
    text = " ".join(top.stdout.split())
    assert all(" ".join(summary.split()) in text for summary in full.values()), text
