"""CRC-32 variants that TS-0006 section 3.3 can be read as, computed in C via zlib.

zlib implements the reflected CRC-32 (iso-hdlc). The non-reflected variants (mpeg2, bzip2) equal
the reflected algorithm run over bit-reversed bytes, with the 32-bit result bit-reversed, so all
four variants run at zlib speed with no per-byte Python loop.
"""
from __future__ import annotations

import zlib
from typing import Callable, Literal

from . import constants as C

Variant = Literal["mpeg2", "iso-hdlc", "bzip2", "jamcrc"]
ByteOrder = Literal["little", "big"]

VARIANTS: tuple[Variant, ...] = ("mpeg2", "iso-hdlc", "bzip2", "jamcrc")
BYTE_ORDERS: tuple[ByteOrder, ...] = ("little", "big")
DEFAULT_VARIANT: Variant = "mpeg2"
DEFAULT_BYTE_ORDER: ByteOrder = "little"
MASK = 0xFFFFFFFF

REVERSE_BITS = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))  # for bytes.translate


def _bitrev32(value: int) -> int:
    return int.from_bytes(value.to_bytes(4, "little").translate(REVERSE_BITS), "big")


def _mpeg2(data: bytes) -> int:
    return _bitrev32(zlib.crc32(data.translate(REVERSE_BITS)) ^ MASK)


def _bzip2(data: bytes) -> int:
    return _mpeg2(data) ^ MASK


def _jamcrc(data: bytes) -> int:
    return zlib.crc32(data) ^ MASK


_FUNCTIONS: dict[str, Callable[[bytes], int]] = {
    "mpeg2": _mpeg2,
    "iso-hdlc": zlib.crc32,
    "bzip2": _bzip2,
    "jamcrc": _jamcrc,
}


def crc_function(variant: str = DEFAULT_VARIANT) -> Callable[[bytes], int]:
    """The CRC function for a variant name; ValueError names the valid ones."""
    try:
        return _FUNCTIONS[variant]
    except KeyError:
        raise ValueError(f"unknown CRC variant {variant!r}; choose from {', '.join(VARIANTS)}") from None


def check_byte_order(order: str) -> ByteOrder:
    if order not in BYTE_ORDERS:
        raise ValueError(f"unknown CRC byte order {order!r}; choose from {', '.join(BYTE_ORDERS)}")
    return order


def crc32(data: bytes, variant: str = DEFAULT_VARIANT) -> int:
    """CRC of `data` in the given variant."""
    return crc_function(variant)(data)


def crc_matches(data: bytes, end: int) -> set[tuple[str, str]]:
    """Every (variant, byte order) under which the CRC stored at `end` validates `data[:end]`."""
    stored = data[end:end + C.CRC_LEN]
    got: set[tuple[str, str]] = set()
    for variant in VARIANTS:
        value = crc32(data[:end], variant)
        for order in BYTE_ORDERS:
            if value == int.from_bytes(stored, order):
                got.add((variant, order))
    return got


def crc_bytes(data: bytes, variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> bytes:
    """The 4-byte trailer for `data` as it is stored on the wire."""
    return crc32(data, variant).to_bytes(4, check_byte_order(order))


def zlib_form(variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> tuple[bool, int, ByteOrder]:
    """How one `zlib.crc32` call checks or makes a trailer, for loops that cannot afford a call
    per packet into this module: (run over the bit-reversed bytes, XOR to apply, byte order of the
    trailer as the 32-bit result is written; with reversed bytes, that trailer is bit-reversed
    with `bytes.translate(REVERSE_BITS)`).

    iso-hdlc is zlib's CRC and jamcrc its complement. mpeg2 is bitrev32(zlib(rev(data)) ^ MASK):
    writing that in the other byte order and bit-reversing each byte gives the trailer, so the
    stored trailer, bit-reversed and read in the other byte order, equals zlib(rev(data)) ^ MASK.
    bzip2 is the complement of mpeg2.
    """
    crc_function(variant)
    order = check_byte_order(order)
    other: ByteOrder = BYTE_ORDERS[1 - BYTE_ORDERS.index(order)]
    return {
        "iso-hdlc": (False, 0, order), "jamcrc": (False, MASK, order),
        "mpeg2": (True, MASK, other), "bzip2": (True, 0, other),
    }[variant]


def trailer_function(variant: str = DEFAULT_VARIANT, order: str = DEFAULT_BYTE_ORDER) -> Callable[[bytes], bytes]:
    """A `data -> 4-byte trailer` function for one setting, with the fewest calls (hot paths)."""
    reflected_input, xor, written = zlib_form(variant, order)
    if reflected_input:
        return lambda data: ((zlib.crc32(data.translate(REVERSE_BITS)) ^ xor).to_bytes(4, written)
                             .translate(REVERSE_BITS))
    return lambda data: (zlib.crc32(data) ^ xor).to_bytes(4, written)
