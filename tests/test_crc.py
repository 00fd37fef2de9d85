"""CRC variants against their catalogue check values and the bit-by-bit reference."""
from __future__ import annotations

import pytest
from hypothesis import given, strategies as st

from reference_crc import MODELS, reference_crc
import zlib

from vm110.crc import BYTE_ORDERS, REVERSE_BITS, VARIANTS, crc32, crc_bytes, trailer_function, zlib_form

CHECK = {"mpeg2": 0x0376E6E7, "iso-hdlc": 0xCBF43926, "bzip2": 0xFC891918, "jamcrc": 0x340BC6D9}


def test_every_variant_is_offered():
    assert set(VARIANTS) == set(CHECK) == set(MODELS)
    assert VARIANTS[0] == "mpeg2" and BYTE_ORDERS == ("little", "big")


@pytest.mark.parametrize("variant", sorted(CHECK))
def test_check_value(variant):
    assert crc32(b"123456789", variant) == CHECK[variant]
    assert reference_crc(b"123456789", variant) == CHECK[variant]


@given(st.binary(max_size=600), st.sampled_from(sorted(CHECK)))
def test_matches_bitwise_reference(data, variant):
    assert crc32(data, variant) == reference_crc(data, variant)


def test_stored_byte_order():
    assert crc_bytes(b"123456789") == bytes.fromhex("e7e67603")
    assert crc_bytes(b"123456789", "mpeg2", "big") == bytes.fromhex("0376e6e7")


@pytest.mark.parametrize("call", [lambda: crc32(b"", "crc32c"), lambda: crc_bytes(b"", "mpeg2", "middle")])
def test_unknown_settings_are_refused_by_name(call):
    with pytest.raises(ValueError, match="choose from"):
        call()


@given(st.binary(max_size=300), st.sampled_from(sorted(CHECK)), st.sampled_from(BYTE_ORDERS))
def test_hot_path_forms_agree_with_crc_bytes(data, variant, order):
    assert trailer_function(variant, order)(data) == crc_bytes(data, variant, order)
    reversed_input, xor, written = zlib_form(variant, order)
    stored = crc_bytes(data, variant, order)
    if reversed_input:
        data, stored = data.translate(REVERSE_BITS), stored.translate(REVERSE_BITS)
    assert zlib.crc32(data) ^ xor == int.from_bytes(stored, written)
