"""CRC validation and decode() throughput on 66-byte VRPI packets (issue 2 target: >= 500,000
packets/s validated), as ratios against zlib.crc32 over the same bytes, measured in the same run."""
from __future__ import annotations

import random
import struct
import time
import zlib

from vm110 import constants as C
from vm110.crc import VARIANTS, crc_bytes, crc_function
from vm110.decode import decode

N = 500_000
TARGET_PPS = 500_000


def make_packets(n: int) -> list[bytes]:
    """Armed-remote VRPI packets with moving joysticks, as a base unit sends them."""
    rng = random.Random(1)
    out = []
    for serial in range(n):
        payload = struct.pack("<BBBBBBHBBBBBB4h8hBB6s", 0x11, 1, 0, 1, 1, 1, 0x0C07, 3, 88, 76, 0, 0, 0,
                              *(rng.randint(-1000, 1000) for _ in range(4)), 1, 0, -1, 500, 0, 0, 0, 0,
                              serial & 0xFF, 0, bytes(6))
        body = b"VRPI" + struct.pack("<HHHHI", 0, 0x0101, serial & 0xFFFF, len(payload), 0) + payload
        out.append(body + crc_bytes(body))
    return out


def best_of(runs: int, fn) -> float:
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    packets = make_packets(N)
    end = C.PREFIX_LEN + C.VRPI_SIZE
    baseline = best_of(3, lambda: [zlib.crc32(p[:end]) for p in packets])
    print(f"baseline zlib.crc32 (iso-hdlc, no compare): {N / baseline:,.0f} packets/s")
    for variant in VARIANTS:
        fn = crc_function(variant)
        order = "little"
        t = best_of(3, lambda fn=fn, order=order: [fn(p[:end]) == int.from_bytes(p[end:], order) for p in packets])
        verdict = "ok" if N / t >= TARGET_PPS else "BELOW TARGET"
        print(f"validate {variant:<8}: {N / t:>12,.0f} packets/s  ratio to baseline {t / baseline:.2f}x  "
              f"(target >= {TARGET_PPS:,}: {verdict})")
    t = best_of(3, lambda: [decode(p) for p in packets])
    print(f"decode() full      : {N / t:>12,.0f} packets/s  ratio to baseline {t / baseline:.2f}x")


if __name__ == "__main__":
    main()
