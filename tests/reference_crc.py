"""Bit-by-bit CRC-32 (Rocksoft model), straight from the textbook: the independent reference that
the shared vectors are encoded with and that vm110.crc is checked against. Slow on purpose."""
from __future__ import annotations

POLY = 0x04C11DB7
INIT = 0xFFFFFFFF

# variant -> (reflect input, reflect output, final XOR)
MODELS = {
    "mpeg2": (False, False, 0x00000000),
    "bzip2": (False, False, 0xFFFFFFFF),
    "iso-hdlc": (True, True, 0xFFFFFFFF),
    "jamcrc": (True, True, 0x00000000),
}


def _reflect(value: int, width: int) -> int:
    out = 0
    for _ in range(width):
        out = (out << 1) | (value & 1)
        value >>= 1
    return out


def reference_crc(data: bytes, variant: str = "mpeg2") -> int:
    refin, refout, xorout = MODELS[variant]
    crc = INIT
    for byte in data:
        crc ^= (_reflect(byte, 8) if refin else byte) << 24
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) if crc & 0x80000000 else (crc << 1)
            crc &= 0xFFFFFFFF
    if refout:
        crc = _reflect(crc, 32)
    return crc ^ xorout
