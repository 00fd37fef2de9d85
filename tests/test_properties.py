"""Property tests: random field values round trip through the layers and decode(); random bytes
never make decode() raise."""
from __future__ import annotations

import struct

from hypothesis import given, settings, strategies as st
from scapy.fields import ConditionalField, StrFixedLenField

from vm110 import constants as C
from vm110 import protocol as P
from vm110 import decode
from vm110.crc import BYTE_ORDERS, VARIANTS
from vm110.layers import PAYLOAD_CLASSES, VM110, VRPO, crc_settings

u16 = st.integers(0, 0xFFFF)


def _strategy(field):
    if isinstance(field, ConditionalField):   # payload fields: absent only from a payload cut short
        field = field.fld
    if isinstance(field, StrFixedLenField):
        return st.binary(min_size=field.length_from(None), max_size=field.length_from(None))
    code = field.fmt[-1]
    bits = struct.calcsize(code) * 8
    if code.islower():
        return st.integers(-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
    return st.integers(0, (1 << bits) - 1)


@st.composite
def packets(draw):
    ptype = draw(st.sampled_from(list(PAYLOAD_CLASSES)))
    cls = PAYLOAD_CLASSES[ptype]
    if cls is VRPO:
        values = {"packet_number": draw(u16), "periodic_data": draw(st.binary(max_size=C.VRPO_MAX_DATA))}
    else:
        values = {f.name: draw(_strategy(f)) for f in cls.fields_desc}
    header = {"origin": draw(u16), "serial": draw(u16), "spare": draw(st.integers(0, 0xFFFFFFFF))}
    return ptype, cls, header, values


@settings(max_examples=300)
@given(packets(), st.sampled_from(VARIANTS), st.sampled_from(BYTE_ORDERS))
def test_random_fields_round_trip(packet, variant, order):
    ptype, cls, header, values = packet
    with crc_settings(variant, order):
        raw = bytes(VM110(**header) / cls(**values))
        again = VM110(raw)
    got = decode(raw, variant, order)
    assert got["problems"] == []
    assert got["type"] == ptype.value and got["direction"] == ptype.direction.value
    assert {k: got[k] for k in header} == header
    assert {k: got[k] for k in values} == values
    assert {k: again[cls].getfieldval(k) for k in values} == values
    assert again.crc == got["crc"] == got["crc.calculated"]


@settings(max_examples=500)
@given(st.binary(max_size=600))
def test_random_bytes_never_raise(data):
    got = decode(data)
    assert isinstance(got["problems"], list) and isinstance(got["warnings"], list)
    if len(data) < C.OVERHEAD:
        assert C.Problem.TRUNCATED.value in got["problems"]


@settings(max_examples=500)
@given(st.sampled_from([t.value.encode() for t in C.PacketType]), st.binary(max_size=520))
def test_random_bytes_after_a_valid_id_never_raise(packet_id, rest):
    got = decode(packet_id + rest)
    assert got["type"] == packet_id.decode()
    legal = not got["problems"]
    assert legal == (len(rest) >= C.OVERHEAD - C.ID_LEN and got.get("crc.status") == C.CRC_GOOD
                     and got["revision"] == 0 and got["size"] + C.OVERHEAD == len(rest) + C.ID_LEN
                     and got["size"] >= P.PAYLOAD_BOUNDS[C.PacketType(packet_id.decode())][0]
                     and got["size"] <= C.MAX_PAYLOAD)
