"""The scapy layers against the shared vectors, round trips, port binding and answers()."""
from __future__ import annotations

import struct

import pytest
from scapy.config import conf
from scapy.layers.inet import IP, UDP
from scapy.layers.l2 import Ether
from scapy.packet import Raw
from scapy.plist import PacketList

from vectorlib import expected_fields, load_vectors, packet_bytes, vector_ids
from vm110 import constants as C
from vm110.layers import (
    PAYLOAD_CLASSES, VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO, bind_ports, crc_settings, unbind_ports,
)

VECTORS = load_vectors()
# Vectors whose whole layout is on the wire: scapy dissects them field for field.
WHOLE = [v for v in VECTORS if set(v["problems"]) <= {"bad_crc", "unknown_id", "revision"}]
# Vectors a user could have crafted with the layers from their field values.
CRAFTABLE = [v for v in VECTORS if not v["problems"] and "extra_payload" not in v["warnings"]]
HEADER = ("type", "revision", "origin", "serial", "size", "spare", "crc")


def _layer_fields(vector):
    fields = expected_fields(vector)
    header = {k: fields[k] for k in HEADER}
    header["type"] = header["type"].encode("latin-1")
    ptype = fields["type"]
    known = ptype in C.PacketType.__members__ and fields["revision"] == C.SUPPORTED_REVISION
    cls = PAYLOAD_CLASSES.get(C.PacketType(ptype)) if known else None  # else: header only (TS-0006 3.2)
    names = {f.name for f in cls.fields_desc} if cls else set()
    payload = {k: v for k, v in fields.items() if k in names}
    return header, cls, payload


@pytest.mark.parametrize("vector", WHOLE, ids=vector_ids(WHOLE))
def test_dissect_matches_vector(vector):
    header, cls, payload = _layer_fields(vector)
    with crc_settings(vector["crc_variant"], vector["crc_byte_order"]):
        pkt = VM110(packet_bytes(vector))
        assert pkt.crc_ok() == ("bad_crc" not in vector["problems"])
    # Written back after the block (wrpcap of what rdpcap read in it): the same bytes, the CRC in
    # the byte order it was read in (a big-endian one came back little-endian).
    assert bytes(pkt) == bytes(pkt.copy()) == packet_bytes(vector)
    assert {k: pkt.getfieldval(k) for k in HEADER} == header
    if cls is None:
        assert not isinstance(pkt.payload, tuple(PAYLOAD_CLASSES.values()))
        return
    layer = pkt[cls]
    assert {k: layer.getfieldval(k) for k in payload} == payload
    for name, shown in vector["names"].items():
        if name != "type" and not shown.startswith("Unknown"):
            assert layer.get_field(name).i2repr(layer, layer.getfieldval(name)) == shown


@pytest.mark.parametrize("vector", CRAFTABLE, ids=vector_ids(CRAFTABLE))
def test_build_from_fields_gives_vector_bytes(vector):
    header, cls, payload = _layer_fields(vector)
    del header["size"], header["crc"]  # computed
    with crc_settings(vector["crc_variant"], vector["crc_byte_order"]):
        assert bytes(VM110(**header) / cls(**payload)) == packet_bytes(vector)


def test_explicit_size_and_crc_are_kept():
    pkt = VM110(size=99, crc=0x12345678) / VRAO(command_id=1)
    raw = bytes(pkt)
    assert raw[10:12] == b"\x63\x00" and raw[-4:] == bytes.fromhex("78563412")
    assert not VM110(raw).crc_ok()


@pytest.mark.parametrize("crc", [2**32, -1, "7", 1.5])
def test_a_crc_beyond_32_bits_is_the_value_error_of_every_field(crc):
    # scapy raises ValueError for a value its field cannot carry (serial=65536, as below); the CRC
    # raised a bare struct.error, which a crafting loop catching ValueError let through
    with pytest.raises(ValueError, match="serial"):
        bytes(VM110(serial=65536) / VRAO())
    with pytest.raises(ValueError, match="Incorrect type of value for field crc"):
        bytes(VM110(crc=crc) / VRAO())


@pytest.mark.parametrize("cut", [None, 30, 12])
def test_a_memoryview_dissects_as_its_bytes(cut):
    # a buffer socket.recv_into filled, as vm110.decode takes it: VM110(memoryview(...)) raised a
    # TypeError (memoryview + memoryview) where a bytearray or bytes dissected
    data = bytes(VM110(serial=7) / VRPI(bu_state=0x11, armed_ru=0x0C07))[:cut]
    pkt = VM110(memoryview(data))
    assert bytes(pkt) == data and pkt.summary() == VM110(data).summary() and pkt.serial == 7


def test_crc_found_from_size_not_frame_end():
    raw = bytes(VM110() / VRAO(command_id=5))
    padded = VM110(raw + b"\x00" * 12)  # Ethernet padding after the CRC
    assert padded.crc_ok() and padded[VRAO].command_id == 5
    assert bytes(padded)[:len(raw)] == raw


def test_type_is_set_by_the_payload_layer():
    for ptype, cls in PAYLOAD_CLASSES.items():
        assert bytes(VM110() / cls())[:4] == ptype.value.encode()


def test_unknown_id_keeps_header_and_raw_payload():
    raw = bytes(VM110(type=b"VRXX") / Raw(b"\x01\x02\x03"))
    pkt = VM110(raw)
    assert pkt.type == b"VRXX" and pkt.size == 3 and pkt[Raw].load == b"\x01\x02\x03"
    assert pkt.crc_ok()


REVISED = [v for v in VECTORS if "revision" in v["problems"]]


@pytest.mark.parametrize("vector", REVISED, ids=vector_ids(REVISED))
def test_other_revision_keeps_header_and_raw_payload(vector):
    # TS-0006 3.2: only revision 0 has this document's layout; vm110.decode and the dissector
    # decode the header alone (the vector lists no payload field)
    pkt = VM110(packet_bytes(vector))
    assert pkt.revision != C.SUPPORTED_REVISION
    assert not isinstance(pkt.payload, tuple(PAYLOAD_CLASSES.values()))
    assert pkt[Raw].load == packet_bytes(vector)[C.PREFIX_LEN:C.PREFIX_LEN + pkt.size]
    # a revision set on purpose is built as given, with the payload layer's fields after it
    crafted = VM110(revision=1) / VRAO(command_id=3)
    assert bytes(crafted)[4:6] == b"\x01\x00" and bytes(crafted)[C.PREFIX_LEN:-C.CRC_LEN] == b"\x03\x00"


# Cut short, with the header and CRC whole: the payload is there in part.
CUT = [v for v in VECTORS if "truncated" in v["problems"] and "size" in v["fields"] and "crc" in v["fields"]]


@pytest.mark.parametrize("vector", CUT, ids=vector_ids(CUT))
def test_payload_cut_short_carries_the_fields_that_fit_whole(vector):
    # interpretation.md, tests/vectors/README: a payload shorter than its layout is illegal
    # (truncated) and the fields that fit whole are decoded, by vm110.decode and the dissector alike
    _, cls, payload = _layer_fields(vector)
    pkt = VM110(packet_bytes(vector))
    assert bytes(pkt) == packet_bytes(vector)
    layer = pkt.getlayer(cls)
    carried = {f.name: layer.getfieldval(f.name) for f in cls.fields_desc if layer and layer.getfieldval(f.name) is not None}
    assert carried == payload
    shown = layer.show(dump=True) if layer else ""
    assert all((f" {f.name} " in shown or f" {f.name}=" in shown) == (f.name in payload) for f in cls.fields_desc)
    if layer:   # changed, it is built as it was read: the fields it lacked stay out
        layer.setfieldval(cls.fields_desc[0].name, layer.getfieldval(cls.fields_desc[0].name))
        assert bytes(pkt) == packet_bytes(vector)


# Cut short before its CRC, with a whole packet ID: the header is there in part.
SHORT = [v for v in VECTORS if "crc" not in v["fields"] and "type" in v["fields"]]


@pytest.mark.parametrize("vector", SHORT, ids=vector_ids(SHORT))
def test_datagram_cut_before_its_crc_carries_the_header_fields_that_fit_whole(vector):
    # As vm110.decode and the dissector: truncated, the header fields that fit whole (vectors README).
    # VM110(data) raised struct.error, and in a capture such a datagram was Raw after UDP.
    header = {k: v for k, v in expected_fields(vector).items() if k in HEADER}
    header["type"] = header["type"].encode("latin-1")
    frame = Ether(bytes(Ether() / IP() / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / Raw(packet_bytes(vector))))
    pkt = frame[VM110]
    assert {k: pkt.getfieldval(k) for k in HEADER if pkt.getfieldval(k) is not None} == header
    assert bytes(pkt) == bytes(frame[UDP].payload) == packet_bytes(vector) and not pkt.crc_ok()
    assert not isinstance(pkt.payload, tuple(PAYLOAD_CLASSES.values()))


def test_a_field_set_to_none_moves_no_field_after_it():
    # scapy builds a field set to None as 0 (IP(ttl=None)); here it was left out and every field
    # after it moved: armed_ru=0x0C07 went out as 0x000C (show() still said 0xc07), and a VRPO's
    # data became its packet number. Layouts: TS-0006 4.1, 4.2, 4.3.
    vrpi = VM110() / VRPI(bu_state=0x11, vlaps=None, armed_ru=0x0C07)
    assert bytes(vrpi)[C.PREFIX_LEN:-C.CRC_LEN] == struct.pack("<6BH", 0x11, 0, 0, 0, 0, 0, 0x0C07).ljust(46, b"\0")
    assert bytes(VM110() / VRPO(packet_number=None, periodic_data=b"abc"))[C.PREFIX_LEN:-C.CRC_LEN] == b"\0\0abc"
    # None to the end is the cut end of a payload: crafted as a dissected one is built
    cut = VM110() / VRCI(command_id=5, command_spare=None, command_data=None)
    assert bytes(cut)[C.PREFIX_LEN:-C.CRC_LEN] == struct.pack("<H", 5)


def test_a_vrpo_crafted_without_data_has_a_summary():
    # sniff(prn=lambda p: p.summary()) on crafted traffic ended in a TypeError (len(None))
    cut = VM110(serial=4) / VRPO(packet_number=3, periodic_data=None)
    assert bytes(cut)[C.PREFIX_LEN:-C.CRC_LEN] == struct.pack("<H", 3)
    assert cut.summary() == "VM110 / VRPO serial=4 #3 0 bytes"


def test_show_prints_enum_names_and_numbers_for_unknown():
    text = (VM110() / VRPI(bu_state=0x11, eg_link=6, ru_state=0x42)).show(dump=True)
    assert "bu_state  = Armed" in text and "eg_link   = Passive" in text and "ru_state  = 66" in text


@pytest.mark.parametrize("sport,dport", [(C.INPUT_PORT, C.INPUT_PORT), (40000, C.OUTPUT_PORT)])
def test_bound_to_default_ports(sport, dport):
    frame = Ether(bytes(Ether() / IP() / UDP(sport=sport, dport=dport) / VM110() / VRAO(command_id=9)))
    assert frame[VRAO].command_id == 9


def test_bind_other_input_port():
    def dissected(port):
        return VM110 in Ether(bytes(Ether() / IP() / UDP(sport=40000, dport=port) / Raw(bytes(VM110() / VRAO()))))
    assert not dissected(7002)
    bind_ports(7000)
    try:
        assert dissected(7000) and dissected(7002)
    finally:
        unbind_ports(7000)
    assert not dissected(7002)
    for port in (0, -1, 65534, 5825.5, "x", True):       # (output port 65536; all were bound, "x" a TypeError)
        with pytest.raises(ValueError, match="an integer from 1 to 65533"):
            bind_ports(port)


def test_unbinding_an_input_port_keeps_the_ports_another_one_covers():
    # A second base unit on input port 5823 sends its output to 5825 (TS-0006 2.2: input + 2), the
    # first one's input port: unbind_ports(5823) unbound 5825 too, and the first one's traffic
    # dissected as Raw from then on (5827 likewise after bind_ports(5827), unbind_ports(5827)).
    def dissected(port):
        return VM110 in Ether(bytes(Ether() / IP() / UDP(sport=40000, dport=port) / Raw(bytes(VM110() / VRAO()))))
    for other in (C.INPUT_PORT - C.OUTPUT_PORT_OFFSET, C.OUTPUT_PORT):
        bind_ports(other)
        unbind_ports(other)
        ports = {other, other + C.OUTPUT_PORT_OFFSET}
        assert [dissected(p) for p in sorted(ports - {C.INPUT_PORT, C.OUTPUT_PORT})] == [False]
        assert dissected(C.INPUT_PORT) and dissected(C.OUTPUT_PORT)


def test_ack_answers_command_with_same_id():
    vrci, vrco = VM110() / VRCI(command_id=17), VM110() / VRCO(command_id=17)
    vrao, vrai = VM110() / VRAO(command_id=17), VM110() / VRAI(command_id=17)
    assert vrao.answers(vrci) and vrai.answers(vrco)
    assert not vrao.answers(vrco) and not vrai.answers(vrci)
    assert not (VM110() / VRAO(command_id=18)).answers(vrci)
    assert not vrci.answers(vrao)
    assert vrao.hashret() == vrci.hashret() != vrai.hashret()
    dissected = [VM110(bytes(p)) for p in (vrci, vrao)]
    assert dissected[1].answers(dissected[0])


def test_a_command_id_left_unset_pairs_with_nothing():
    # scapy calls hashret() on every packet sr() sees: a crafted VRCI(command_id=None) raised
    # struct.error there, and two packets with no ID answered each other.
    vrci, vrao = VM110() / VRCI(command_id=None), VM110() / VRAO(command_id=None)
    assert vrci.hashret() == vrao.hashret() == b"CI"
    assert not vrao.answers(vrci)
    assert not vrao.answers(VM110() / VRCI(command_id=0))
    assert not (VM110() / VRAO(command_id=0)).answers(vrci)


def test_only_the_acknowledgement_answers_its_command(monkeypatch):
    # TS-0006 5.1.3: the BU resends a VRCI (same command ID, new serial) until a VRAO comes, and
    # sends VRPI all along. PacketList.sr() pairs what answers what: it paired each VRCI with its
    # own retransmission and each VRPI with the next (scapy's default answers() for one class).
    # The acknowledgement goes to the group and the output port (2.2), not back to the command's
    # source: scapy pairs it once its address checks are off (README).
    monkeypatch.setattr(conf, "checkIPsrc", False)
    monkeypatch.setattr(conf, "checkIPaddr", False)
    base, controller = ("10.0.0.10", C.INPUT_PORT), ("10.0.0.20", C.OUTPUT_PORT)
    traffic = PacketList([
        Ether(bytes(Ether() / IP(src=addr, dst=C.MULTICAST_GROUP) / UDP(sport=port, dport=port) / VM110(serial=s) / p))
        for s, ((addr, port), p) in enumerate([
            (base, VRCI(command_id=17)), (base, VRPI()), (base, VRCI(command_id=17)), (base, VRPI()),
            (controller, VRAO(command_id=17)), (controller, VRPO()), (controller, VRPO()),
            (controller, VRCO(command_id=3)), (controller, VRCO(command_id=3)), (base, VRAI(command_id=3))])])
    answered, _ = traffic.sr()
    assert [(q[VM110].serial, a[VM110].serial) for q, a in answered] == [(0, 4), (7, 9)]


def test_vrpo_data_fills_the_rest_of_the_payload():
    pkt = VM110(bytes(VM110() / VRPO(packet_number=2, periodic_data=b"abc")))
    assert pkt.size == 5 and pkt[VRPO].periodic_data == b"abc"


# --- scapy's contrib conventions: a user's scapy session ---------------------------------------
SESSION = r"""
import io, contextlib, sys
from scapy.all import IP, UDP, Ether, ls, sniff, wrpcap
from vm110.layers import *
names = sorted(k for k in dir() if not k.startswith("_"))
print("names", " ".join(n for n in names if n not in ("IP", "UDP", "Ether", "ls", "sniff", "wrpcap", "io",
                                                      "contextlib", "sys")))
out = io.StringIO()
with contextlib.redirect_stdout(out):
    ls(VRPI)
print("ls", out.getvalue().count("\n"), "joystick1" in out.getvalue(), "bu_state" in out.getvalue())
frames = [Ether() / IP(src="10.0.0.10", dst="239.255.42.20") / UDP(sport=5825, dport=5825) /
          VM110(origin=0x0101, serial=7) / VRPI(bu_state="Armed", armed_ru=0x0C07, ru_state="Enabled"),
          Ether() / IP(src="10.0.0.20", dst="239.255.42.20") / UDP(sport=40000, dport=5827) /
          VM110(serial=1) / VRAO(command_id=17)]
wrpcap(sys.argv[1], frames)
seen = []
sniff(offline=sys.argv[1], prn=lambda p: seen.append(p[VM110].summary()), store=False)
print("sniffed", "|".join(seen))
"""


def test_a_scapy_session_imports_lists_and_sniffs(tmp_path):
    import subprocess
    import sys
    run = subprocess.run([sys.executable, "-c", SESSION, str(tmp_path / "s.pcap")], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    lines = dict(line.split(" ", 1) for line in run.stdout.splitlines())
    # `import *` gives the layers and helpers of __all__, nothing of the module's own imports
    assert lines["names"].split() == sorted(
        ["VM110", "VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO", "PAYLOAD_CLASSES", "bind_ports", "unbind_ports",
         "crc_settings"])
    count, joystick, state = lines["ls"].split()
    assert int(count) == len(VRPI.fields_desc) and joystick == state == "True"
    # sniff() on a capture dissects EG-Link by port (the binding the import made), with summaries
    # that carry each packet's serial (scapy shows the top layer's only; the serial was lost)
    assert lines["sniffed"] == ("VM110 / VRPI serial=7 Armed armed_ru=0xc07 Enabled|"
                                "VM110 / VRAO serial=1 command_id=17")


def test_vm110_fills_in_size_and_crc():
    from vm110.decode import decode
    for payload in (VRPI(bu_state=0x11), VRPO(periodic_data=b"x" * 30), VRCI(command_id=3), VRAI(command_id=3)):
        data = bytes(VM110(serial=5) / payload)
        fields = decode(data)
        assert fields["problems"] == [] and fields["size"] == len(data) - C.OVERHEAD
        assert VM110(data).crc_ok()
