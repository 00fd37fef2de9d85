"""Every shared vector through the fast path `vm110.decode`."""
from __future__ import annotations

import pytest

from vectorlib import expected_fields, load_vectors, packet_bytes, vector_ids
from vm110 import decode

VECTORS = load_vectors()
GENERATED = {"problems", "warnings"}


def test_vectors_cover_every_reason_and_type():
    problems = {p for v in VECTORS for p in v["problems"]}
    assert problems == {"unknown_id", "bad_crc", "revision", "size_mismatch", "size_too_large", "truncated"}
    types = {v["fields"].get("type") for v in VECTORS if not v["problems"]}
    assert types == {"VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO"}
    codes = {w.split(":")[0] for v in VECTORS for w in v["warnings"]}
    assert codes == {"spare_nonzero", "origin_nonzero", "out_of_range", "unknown_enum",
                     "disarmed_ru_data", "extra_payload"}


@pytest.mark.parametrize("vector", VECTORS, ids=vector_ids(VECTORS))
def test_decode_matches_vector(vector):
    got = decode(packet_bytes(vector), vector["crc_variant"], vector["crc_byte_order"])
    assert sorted(got["problems"]) == vector["problems"]
    assert sorted(got["warnings"]) == vector["warnings"]
    assert {k: v for k, v in got.items() if k not in GENERATED} == expected_fields(vector)


@pytest.mark.parametrize("kind", [bytearray, memoryview])
def test_decode_takes_any_bytes_like_object(kind):
    # (README: "it never raises"; a bytearray was a TypeError, a memoryview an AttributeError)
    for vector in VECTORS:
        data = packet_bytes(vector)
        assert decode(kind(data), vector["crc_variant"], vector["crc_byte_order"]) == decode(
            data, vector["crc_variant"], vector["crc_byte_order"])
