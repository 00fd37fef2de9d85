"""vm110.encode (the fast builder) against the shared vectors and the scapy layers; the simulators'
legality check and the impairments' manglings against vm110.decode."""
from __future__ import annotations

import pytest
from vm110 import constants as C
from vm110 import encode
from vm110.crc import crc_function
from vm110.decode import decode
from vm110.layers import PAYLOAD_CLASSES, VM110, crc_settings
from vm110.sim.impair import REASON_ORDER, mangle
from vm110.sim.node import inspect
from vectorlib import expected_fields, load_vectors, packet_bytes, vector_ids

VECTORS = load_vectors()
# Vectors whose bytes are exactly the canonical encoding of their fields.
ENCODABLE = [v for v in VECTORS if not v["problems"] and "extra_payload" not in v["warnings"]]


@pytest.mark.parametrize("vector", ENCODABLE, ids=vector_ids(ENCODABLE))
def test_encode_inverts_the_vectors(vector):
    fields = expected_fields(vector)
    data = encode.encode({k: v for k, v in fields.items() if k not in ("crc", "size")},
                         vector["crc_variant"], vector["crc_byte_order"])
    assert data == packet_bytes(vector)


@pytest.mark.parametrize("vector", ENCODABLE, ids=vector_ids(ENCODABLE))
def test_encode_matches_the_scapy_layers(vector):
    fields = expected_fields(vector)
    ptype = C.PacketType(fields["type"])
    layer = PAYLOAD_CLASSES[ptype]
    payload_fields = {f.name: fields[f.name] for f in layer.fields_desc if f.name in fields}
    header = {k: fields[k] for k in ("revision", "origin", "serial", "spare")}
    with crc_settings(vector["crc_variant"], vector["crc_byte_order"]):
        crafted = bytes(VM110(type=fields["type"].encode(), **header) / layer(**payload_fields))
    assert encode.encode({k: v for k, v in fields.items() if k not in ("crc", "size")},
                         vector["crc_variant"], vector["crc_byte_order"]) == crafted


def test_hot_path_helpers_equal_the_generic_encoder():
    assert encode.command_payload(513, b"GO") == encode.payload("VRCI", {"command_id": 513, "command_data": b"GO".ljust(16, b"\0")})
    assert encode.ack_payload(65535) == encode.payload("VRAO", {"command_id": 65535})
    assert encode.vrpo_payload(2, b"xyz") == encode.payload("VRPO", {"packet_number": 2, "periodic_data": b"xyz"})
    assert encode.command_payload(65536 + 7)[:2] == b"\x07\x00"      # command IDs wrap


def test_wrong_size_and_crc_can_be_crafted():
    data = encode.packet(C.PacketType.VRAO, encode.ack_payload(1), size=7, crc=0x12345678)
    out = decode(data)
    assert out["size"] == 7 and out["crc"] == 0x12345678
    assert set(out["problems"]) == {"bad_crc", "size_mismatch"}


@pytest.mark.parametrize("vector", VECTORS, ids=vector_ids(VECTORS))
def test_inspect_finds_the_same_problems_as_decode(vector):
    data = packet_bytes(vector)
    fn = crc_function(vector["crc_variant"])
    problems, ptype = inspect(data, fn, vector["crc_byte_order"])
    assert sorted(problems) == vector["problems"]
    if not problems:
        assert ptype.value == vector["fields"]["type"]


SAMPLES = {
    "VRPI": encode.packet("VRPI", encode.vrpi_payload({"bu_state": 0x11, "armed_ru": 7}), origin=0x101, serial=9),
    "VRPO": encode.packet("VRPO", encode.vrpo_payload(0, bytes(100)), serial=3),
    "VRPO0": encode.packet("VRPO", encode.vrpo_payload(0, b"")),
    "VRCI": encode.packet("VRCI", encode.command_payload(5, b"X"), origin=0x101),
    "VRAO": encode.packet("VRAO", encode.ack_payload(5)),
}
REASONS = list(REASON_ORDER) + ["revision+bad_crc", "unknown_id+bad_crc"]


@pytest.mark.parametrize("reasons", REASONS)
@pytest.mark.parametrize("sample", sorted(SAMPLES))
def test_mangle_gives_exactly_the_declared_reasons(sample, reasons):
    data, declared = mangle(SAMPLES[sample], reasons)
    assert sorted(declared) == sorted(reasons.split("+"))
    assert sorted(decode(data)["problems"]) == sorted(declared)
    assert sorted(inspect(data, crc_function("mpeg2"), "little")[0]) == sorted(declared)
    assert len(data) >= C.OVERHEAD     # every illegal packet still carries a CRC to check


def test_mangle_rejects_unknown_reasons():
    with pytest.raises(ValueError, match="unknown illegal reason"):
        mangle(SAMPLES["VRAO"], "bogus")
