"""A gzip-compressed capture, as Wireshark reads one (`tcpdump -z gzip`, `dumpcap --compress
gzip`, a `.pcap.gz` from the field): decompressed as it is read, one member or several back to
back. Nothing goes to disk (a temporary folder may be memory: /tmp is on Debian 13) and memory
stays flat however large the capture, or however far a hostile file inflates. A file cut short
or damaged gives what decompressed before the damage, and says why.
"""
from __future__ import annotations

import zlib
from typing import BinaryIO, Optional

GZIP_MAGIC = b"\x1f\x8b"
_GZIP_WBITS = 16 + zlib.MAX_WBITS       # a gzip header and trailer
_READ = 1 << 16                         # compressed bytes fed at a time
_OUT = 1 << 20                          # decompressed bytes made at a time
# Other compressions Wireshark 4.2 and later read: what to say of them.
OTHER_COMPRESSIONS = {b"\x28\xb5\x2f\xfd": "zstd", b"\x04\x22\x4d\x18": "lz4"}


def is_gzip(head: bytes) -> bool:
    return head[:2] == GZIP_MAGIC


class Gunzip:
    """The capture `src` holds, for a reader that reads forward: `read`, `tell`, and `seek` (back:
    decompressed again from the start; the capture reader goes back only to the file header).
    `problem`: why decompression stopped early, once the data have ended (None: they did not)."""

    def __init__(self, src: BinaryIO) -> None:
        self._src = src
        self._rewind()

    def _rewind(self) -> None:
        self._src.seek(0)
        self._inflate = zlib.decompressobj(_GZIP_WBITS)
        self._input = b""          # compressed bytes not fed yet
        self._buf = b""            # decompressed bytes not read yet
        self._pos = 0              # decompressed bytes read
        self._made = 0             # decompressed bytes made
        self.ended = False
        self.problem: Optional[str] = None

    def read(self, n: int = -1) -> bytes:
        while (n < 0 or len(self._buf) < n) and not self.ended:
            self._more()
        out, self._buf = (self._buf, b"") if n < 0 else (self._buf[:n], self._buf[n:])
        self._pos += len(out)
        return out

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int) -> int:
        if pos < self._pos:
            self._rewind()
        while self._pos < pos and self.read(min(pos - self._pos, _OUT)):
            pass
        return self._pos

    def drain(self) -> None:
        """Decompress the rest, unread: for its `problem`."""
        self._buf = b""
        while not self.ended:
            self._more()
            self._buf = b""

    def close(self) -> None:
        self._src.close()

    def _more(self) -> None:
        data = self._input or self._src.read(_READ)
        self._input = b""
        if self._inflate.eof and data:
            while len(data) < len(GZIP_MAGIC) and (more := self._src.read(_READ)):
                data += more
            if not is_gzip(data):
                data = b""          # trailing bytes after the last member, which gzip ignores too
            else:
                self._inflate = zlib.decompressobj(_GZIP_WBITS)
        if not data:
            if not self._inflate.eof:
                self.problem = f"gzip data cut short after {self._made} bytes of capture"
            self.ended = True
            return
        before = self._inflate.copy()
        try:
            piece = self._inflate.decompress(data, _OUT)
        except zlib.error as exc:
            self._give(_up_to_damage(before, data))
            why = str(exc).rsplit(": ", 1)[-1]     # ("Error -3 while decompressing data: ...")
            self.problem = f"gzip data corrupt after {self._made} bytes of capture: {why}"
            self.ended = True
            return
        self._give(piece)
        self._input = self._inflate.unused_data if self._inflate.eof else self._inflate.unconsumed_tail

    def _give(self, piece: bytes) -> None:
        self._buf += piece
        self._made += len(piece)


def _up_to_damage(inflate, data: bytes) -> bytes:
    """What `inflate` gives of `data` before the byte at which it fails (the call that failed
    returned nothing): fed a byte at a time, only ever after damage (at most _READ bytes)."""
    got = []
    for at in range(len(data)):
        try:
            got.append(inflate.decompress(data[at:at + 1]))
        except zlib.error:
            break
    return b"".join(got)
