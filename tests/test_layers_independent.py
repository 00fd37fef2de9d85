"""The scapy layers against an encoder and a reader written here from TS-0006 alone (the layouts of
sections 3 and 4 typed out again, struct and the textbook CRC of reference_crc; nothing of vm110),
with random field values and random datagrams under every CRC variant and byte order: bytes from
here dissect to the values they were made of, and the layers build the same bytes from them."""
from __future__ import annotations

import struct

from hypothesis import given, settings, strategies as st
from reference_crc import MODELS, reference_crc
from scapy.packet import Packet

from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO, crc_settings

# TS-0006 3.2: revision, origin, serial, size, spare; 4.1 to 4.6: the payloads. VRPO's periodic
# data (0 to 488 bytes) follows its packet number.
HEADER = (("revision", "H"), ("origin", "H"), ("serial", "H"), ("size", "H"), ("spare", "I"))
_COMMAND = (("command_id", "H"), ("command_spare", "I"), ("command_data", "16s"))
LAYOUTS: dict[str, tuple[tuple[str, str], ...]] = {
    "VRPI": (("bu_state", "B"), ("vlaps", "B"), ("unarmed_rus", "B"), ("eg_link", "B"), ("ec_link", "B"),
             ("c_link", "B"), ("armed_ru", "H"), ("ru_state", "B"), ("ru_battery", "B"), ("ru_rssi", "B"),
             ("ru_cable", "B"), ("ru_docked", "B"), ("ru_disabled", "B"),
             *((f"joystick{i}", "h") for i in range(1, 5)), *((f"switch{i}", "h") for i in range(1, 9)),
             ("encoder", "B"), ("encoder_switch", "B"), ("vrpi_spare", "6s")),
    "VRPO": (("packet_number", "H"),),
    "VRCI": _COMMAND, "VRCO": _COMMAND, "VRAO": (("command_id", "H"),), "VRAI": (("command_id", "H"),),
}
LAYERS = {"VRPI": VRPI, "VRPO": VRPO, "VRCI": VRCI, "VRCO": VRCO, "VRAO": VRAO, "VRAI": VRAI}
CRC = st.sampled_from(sorted(MODELS))
ORDER = st.sampled_from(["little", "big"])


def _value(code: str) -> st.SearchStrategy:
    if code.endswith("s"):
        return st.binary(min_size=int(code[:-1]), max_size=int(code[:-1]))
    bits = 8 * struct.calcsize(code)
    return st.integers(-(1 << bits - 1), (1 << bits - 1) - 1) if code.islower() else st.integers(0, (1 << bits) - 1)


@st.composite
def packets(draw) -> tuple[str, dict, dict]:
    """(packet ID, header values but size, payload values) of a packet of a known type."""
    ptype = draw(st.sampled_from(sorted(LAYOUTS)))
    header = {name: draw(_value(code)) for name, code in HEADER if name not in ("revision", "size")}
    payload = {name: draw(_value(code)) for name, code in LAYOUTS[ptype]}
    if ptype == "VRPO":
        payload["periodic_data"] = draw(st.binary(max_size=488))
    return ptype, header, payload


def encode(ptype: str, header: dict, payload: dict, crc: str, order: str) -> bytes:
    body = struct.pack("<" + "".join(code for _, code in LAYOUTS[ptype]), *(payload[n] for n, _ in LAYOUTS[ptype]))
    body += payload.get("periodic_data", b"")
    packet = ptype.encode() + struct.pack("<HHHHI", 0, header["origin"], header["serial"], len(body),
                                          header["spare"]) + body
    return packet + reference_crc(packet, crc).to_bytes(4, order)


def read(data: bytes, order: str) -> dict:
    """The fields a datagram carries whole: the header fields that fit, the CRC (after `size`
    payload bytes, or in the last 4 bytes of a datagram shorter than that), and for revision 0 of
    a known ID the payload fields that fit in the bytes before the CRC."""
    fields: dict = {"type": data[:4]}
    offset = 4
    for name, code in HEADER:
        if offset + struct.calcsize(code) > len(data):
            return fields
        fields[name] = struct.unpack_from("<" + code, data, offset)[0]
        offset += struct.calcsize(code)
    if len(data) < 20:
        return fields
    end = min(16 + fields["size"], len(data) - 4)
    fields["crc"] = int.from_bytes(data[end:end + 4], order)
    if fields["revision"] != 0 or data[:4].decode("latin-1") not in LAYOUTS:
        return fields
    offset = 16
    for name, code in LAYOUTS[data[:4].decode()]:
        if offset + struct.calcsize(code) > end:
            return fields
        fields[name] = struct.unpack_from("<" + code, data, offset)[0]
        offset += struct.calcsize(code)
    if data[:4] == b"VRPO":
        fields["periodic_data"] = data[offset:min(end, offset + 488)]
    return fields


def carried(pkt: Packet) -> dict:
    """Every field the dissected layers hold that is not None (a field cut short is None)."""
    out = {}
    layer = pkt
    while layer:
        out.update((f.name, layer.getfieldval(f.name)) for f in layer.fields_desc
                   if f.name not in out and layer.getfieldval(f.name) is not None)
        layer = layer.payload
    return {k: v for k, v in out.items() if k != "load"}


@settings(max_examples=150, deadline=None)
@given(packets(), CRC, ORDER)
def test_independent_bytes_dissect_and_build_alike(packet, crc, order):
    ptype, header, payload = packet
    data = encode(ptype, header, payload, crc, order)
    with crc_settings(crc, order):
        pkt = VM110(data)
        assert pkt.crc_ok() and bytes(pkt) == data
        assert carried(pkt) == read(data, order) == {"type": ptype.encode(), "revision": 0, "size": len(data) - 20,
                                                      "crc": pkt.crc, **header, **payload}
        assert bytes(VM110(**header) / LAYERS[ptype](**payload)) == data


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([*(t.encode() for t in LAYOUTS), b"VRXO"]), st.integers(0, 600), st.binary(max_size=540),
       st.booleans(), ORDER)
def test_random_datagrams_dissect_as_read_here(packet_id, size, rest, sized, order):
    # `sized`: a header of revision 0 with `size` in it, so that the payload and CRC are where the
    # header says more often than random bytes would put them
    data = packet_id + (struct.pack("<HHHHI", 0, 1, 2, size, 0) + rest if sized else rest)
    with crc_settings("mpeg2", order):
        pkt = VM110(data)
        assert carried(pkt) == read(data, order)
        assert bytes(pkt) == data[:len(bytes(pkt))]
