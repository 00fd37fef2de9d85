"""Read a pcap or pcapng capture as it arrives: from a pipe (dumpcap -w -, tcpdump -w -), standard
input, or a file still being written.

`StreamReader.feed(data)` takes the next bytes, whatever their size, and returns the packets that
are now complete: `(ts, frame, link, frame_bytes, datagram)` with `datagram` the
`(src, sport, dport, payload)` of the frame's UDP datagram or None. An incomplete record waits for
the next bytes; `close()` at the end of the input says whether some were left over. Frames are
numbered, timed and decoded exactly as `CaptureReader` does for a file (the methods are its own),
so that what a stream shows is what the same bytes read as a file show.
"""
from __future__ import annotations

import struct
from typing import Optional

from . import linktypes as L
from .reader import (_FAST, _FAST_HEAD, _FAST_VI, MAX_RECORD, PCAP_HEADER_LEN, PCAPNG_SHB, CaptureError, CaptureReader,
                     format_of)

Packet = tuple   # (ts, frame, link, frame bytes, (src, sport, dport, payload) or None)
_MAX_BUFFER = 1 << 21          # more waiting than any legal record or block: the stream is not a capture


class StreamReader(CaptureReader):
    """One capture stream named `name` (for messages); feed it bytes in order."""

    def __init__(self, name: str) -> None:     # pylint: disable=super-init-not-called
        # No file: the counters and per-section state of the reader, which its methods use
        # (bytes_read: the stream offset of the start of `buf`).
        self.path = name
        self.format = ""
        self.reset_counters()
        self._record: Optional[tuple] = None   # pcap: (record struct, layout, link)
        self.buf = b""
        self.stopped = False                   # damage seen: the rest is not read

    # -- public --------------------------------------------------------------------------------
    def feed(self, data: bytes) -> list[Packet]:
        """The packets completed by `data`; CaptureError when the stream is not a capture."""
        if self.stopped:
            return []
        self.buf = self.buf + data if self.buf else data
        if not self.format:
            if len(self.buf) < 4:
                return []
            self.format = format_of(self.buf, self.path)
        out: list[Packet] = []
        used = self._walk_pcap(out) if self.format == "pcap" else self._walk_pcapng(out)
        self.buf = self.buf[used:]
        self.bytes_read += used
        if not self.stopped and len(self.buf) > _MAX_BUFFER:
            self.damaged(self.bytes_read, f"corrupt record at byte {self.bytes_read} (no record ends within "
                                          f"{_MAX_BUFFER} bytes)")
            self.stopped = True
        return out

    def close(self) -> None:
        """The input ended: bytes left over are a record cut short."""
        if not self.format:
            if not self.buf and not self.bytes_read:
                raise CaptureError(f"{self.path}: empty file, not a pcap or pcapng capture")
            raise CaptureError(f"{self.path}: not a pcap or pcapng capture (too short)")
        # No capture at all, as `vm110 analyze` has it: one line, no report.
        if self.format == "pcap" and self._record is None:
            raise CaptureError(f"{self.path}: pcap file header cut short")
        if self.format == "pcapng" and self.buf and not self.bytes_read:
            raise CaptureError(f"{self.path}: pcapng section header block cut short")
        if self.buf and not self.stopped:
            self.damaged(self.bytes_read, f"file cut in the middle of a record at byte {self.bytes_read} "
                                          f"({len(self.buf)} bytes ignored)")
        self.buf = b""

    # -- formats -------------------------------------------------------------------------------
    def _walk_pcap(self, out: list[Packet]) -> int:
        data, pos = self.buf, 0
        if self._record is None:
            if len(data) < PCAP_HEADER_LEN:
                return 0
            layout = self.pcap_header(data)
            self._record = (struct.Struct(layout.endian + "IIII"), layout, layout.link)
            pos = PCAP_HEADER_LEN
        rec, layout, link = self._record
        end = len(data)
        while pos + 16 <= end:
            sec, frac, incl, orig = rec.unpack_from(data, pos)
            if incl > MAX_RECORD:
                self.corrupt(pos, incl)
                self.stopped = True
                break
            if pos + 16 + incl > end:
                break
            ts = layout.time(sec, frac)
            self._packet(out, ts, link, data, pos + 16, incl, orig)
            pos += 16 + incl
        return pos

    def _walk_pcapng(self, out: list[Packet]) -> int:
        data, pos, end = self.buf, 0, len(self.buf)
        while pos + 12 <= end:
            if struct.unpack_from("<I", data, pos)[0] == PCAPNG_SHB:
                if pos + 12 > end:
                    break
                self.pcapng_section(data, pos)
            btype, blen = struct.unpack_from(self.endian + "II", data, pos)
            if self.bad_block(pos, blen, btype):
                self.stopped = True
                break
            if pos + blen > end:
                break
            if self.bad_trailer(data, pos, blen) or self.corrupt_block(data, pos, btype, blen):
                self.stopped = True
                break
            block = self.pcapng_block(data, pos, btype, blen)
            pos += blen
            if block is None:
                continue
            ts, link, start, incl, orig = block
            if link is None:
                self.frames += 1
                self.non_udp += 1
                continue
            self._packet(out, ts, link, data, start, incl, orig)
        return pos

    def _packet(self, out: list[Packet], ts: float, link: int, data: bytes, start: int, incl: int, orig: int) -> None:
        self.frames += 1
        frame = self.frames
        self.last_ts = ts
        if self.first_ts is None:
            self.first_ts = ts
        self.spanned(ts, ts)
        if link == L.LINKTYPE_ETHERNET and incl >= _FAST_HEAD:
            # The common frame (Ethernet, IPv4 without options, UDP) in one call, as the reader does.
            et, vi, tot, frag, proto, src, sport, dport, ulen = _FAST.unpack_from(data, start)
            if (et == L.ETHERTYPE_IPV4 and vi == _FAST_VI and proto == L.IPPROTO_UDP and not frag & L.IPV4_FRAGMENT_MASK
                    and tot == 20 + ulen and 34 + ulen <= incl and ulen >= 8):
                out.append((ts, frame, link, data[start:start + incl],
                            (src, sport, dport, data[start + 42:start + 34 + ulen])))
                return
        out.append((ts, frame, link, data[start:start + incl], self.udp_of(link, data, start, incl, orig, frame)))
