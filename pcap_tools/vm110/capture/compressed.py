"""A gzip-compressed capture, as Wireshark reads one (`tcpdump -z gzip`, `dumpcap --compress
gzip`, a `.pcap.gz` from the field): decompressed into a temporary file of our own, which the
reader then reads as it reads any capture (it seeks: CRC sniffing, a second pass). A compressed
file cut short or damaged keeps what decompressed before the damage, and says why.
"""
from __future__ import annotations

import tempfile
import zlib
from typing import BinaryIO, Optional

GZIP_MAGIC = b"\x1f\x8b"
_GZIP_WBITS = 16 + zlib.MAX_WBITS       # a gzip header and trailer
_READ = 1 << 20
# Other compressions Wireshark 4.2 and later read: what to say of them.
OTHER_COMPRESSIONS = {b"\x28\xb5\x2f\xfd": "zstd", b"\x04\x22\x4d\x18": "lz4"}


def is_gzip(head: bytes) -> bool:
    return head[:2] == GZIP_MAGIC


def decompress(src: BinaryIO) -> tuple[BinaryIO, Optional[str]]:
    """The capture in `src` (gzip, one member or several back to back) in a temporary file, at its
    start, and why decompression stopped early (None: it did not). OSError when the temporary
    file cannot be written."""
    out = tempfile.TemporaryFile(prefix="vm110-gunzip-")   # noqa: SIM115 -- the caller owns it
    try:
        problem = _copy(src, out)
        out.seek(0)
    except BaseException:
        out.close()
        raise
    return out, problem


def _copy(src: BinaryIO, out: BinaryIO) -> Optional[str]:
    inflate = zlib.decompressobj(_GZIP_WBITS)
    done = 0
    while data := src.read(_READ):
        while data:
            if inflate.eof:                # a member ended: another follows, or trailing bytes
                if not is_gzip(data):
                    return None            # (which gzip ignores too)
                inflate = zlib.decompressobj(_GZIP_WBITS)
            before = inflate.copy()
            try:
                piece = inflate.decompress(data)
            except zlib.error as exc:
                done += out.write(_up_to_damage(before, data))
                why = str(exc).rsplit(": ", 1)[-1]     # ("Error -3 while decompressing data: ...")
                return f"gzip data corrupt after {done} bytes of capture: {why}"
            done += out.write(piece)
            data = inflate.unused_data
    if not inflate.eof:
        return f"gzip data cut short after {done} bytes of capture"
    return None


def _up_to_damage(inflate, data: bytes) -> bytes:
    """What `inflate` gives of `data` before the byte at which it fails (the call that failed
    returned nothing): fed a byte at a time, only ever after damage."""
    got = []
    for at in range(len(data)):
        try:
            got.append(inflate.decompress(data[at:at + 1]))
        except zlib.error:
            break
    return b"".join(got)
