"""The fast engine: one streaming pass over the file, feeding the analysis a chunk at a time.

The budget is a few C-level operations per packet. In a little-endian Ethernet pcap one Python
step per record finds where the records of a chunk are; numpy then reads their record, Ethernet,
IPv4, UDP and EG-Link headers at once (`_HEADS`), picks the EG-Link candidates of the common frame
(IPv4 without options, UDP, a plausible header on the EG-Link ports), and zlib checks their CRC
(one call each, iterated in C; see `vm110.crc.zlib_form`); their records are gathered from the
chunk with numpy (`Collected.located_rows`). In a little-endian pcapng one `struct` call per
enhanced packet block reads the same headers (`_FUSED_NG`) and a legal packet packs one record.
Other frames go through the reader's general decoder, other files through its datagrams. At the
end of each chunk the records go to the analysis (`Collected.flush`), so memory does not grow
with the file. Anything unusual (illegal, other ports, odd frames) takes `_slow`, which decodes
with `vm110.decode` and so applies exactly its rules, in frame order.

Large pcaps were once read in parts by several processes; the parts' records then had to be
kept until the parts before them were analysed, which bounded memory forbids, and the
whole-chunk numpy reads made one process faster than that.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import struct
from array import array
import zlib
from collections import Counter
from typing import Callable, Collection, Optional

import numpy as np

from .. import constants as C
from .. import protocol as P
from ..capture import linktypes as L
from ..capture.reader import CHUNK, PCAP_HEADER_LEN, PCAPNG_EPB, PCAPNG_SHB, CaptureReader, address
from ..crc import BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, REVERSE_BITS, VARIANTS, crc_matches, zlib_form
from ..decode import decode
from ..errors import CliError
from .collect import CODE_OF_ID, RECORD, RECORD_DTYPE, Collected
from .incremental import Analysis

# The fused reads below are the header of vm110.protocol and the legality rules of vm110.decode
# written out by hand for speed: tests/test_protocol.py checks them against the declaration and
# holds each walk's legal/illegal verdicts to decode()'s, packet by packet.
_HDR = struct.Struct("<4sH4xH")                    # packet ID, revision, size (it once read the spare as size)
# One little-endian read of a record of the common frame: pcap record header (sec, frac, incl,
# orig); Ethernet type (raw bytes); IPv4 version/IHL, total length, fragment field, protocol,
# source; UDP ports and length (big-endian fields read little-endian: compared through _SWAP);
# EG-Link packet ID, revision and size. A frame whose IP total length is not its UDP length's
# (damage, padding it covers) goes through the reader's udp_of, as Wireshark reads it.
_FUSED = struct.Struct("<IIII12x2sBxH2xHxB2x4s4xHHH2x4sH4xH")
_FUSED_MIN_FRAME = _FUSED.size - 16
# The same fields for numpy, read from every record of a chunk at once (`_fused_pcap`): the bytes
# at these offsets of a record, packed.
_HEAD_FIELDS = (("sec", "<u4", 0), ("frac", "<u4", 4), ("incl", "<u4", 8), ("orig", "<u4", 12), ("et", "<u2", 28),
                ("vi", "u1", 30), ("tot", "<u2", 32), ("frag", "<u2", 36), ("proto", "u1", 39), ("sp", "<u2", 50),
                ("dp", "<u2", 52), ("ulen", "<u2", 54), ("pid", "<u4", 58), ("rev", "<u2", 62), ("size", "<u2", 68))
_HEADS = np.dtype([(name, kind) for name, kind, _ in _HEAD_FIELDS])
_HEAD_PICK = np.concatenate([np.arange(at, at + np.dtype(kind).itemsize) for _, kind, at in _HEAD_FIELDS])
_HEAD_ROWS = 4096              # records gathered at a time: the index array stays small
# The same for a pcapng enhanced packet block: block type and length, interface, time high and
# low, captured and original length, then the frame as above.
_EPB_HEAD = 28
_FUSED_NG = struct.Struct("<IIIIIII" + _FUSED.format[len("<IIII"):])
_ETH_IPV4 = L.ETHERTYPE_IPV4.to_bytes(2, "big")
_IPV4_PLAIN = 0x45                                 # version 4, 20-byte header
_IP_END = L.ETH_HEADER_LEN + L.IPV4_MIN_HEADER     # where UDP starts in the common frame
_FRAME_OVER = _IP_END + L.UDP_HEADER_LEN + C.OVERHEAD   # frame length = this + EG-Link size
_FRAG_LE = 0xFF3F                                  # MF + fragment offset, read little-endian
_U32 = {"little": struct.Struct("<I"), "big": struct.Struct(">I")}
_SWAP = [((x & 0xFF) << 8) | (x >> 8) for x in range(1 << 16)]   # big-endian u16 read little-endian
_LOW = {raw: P.PAYLOAD_BOUNDS[C.PacketType(raw.decode())][0] for raw in CODE_OF_ID}
_PID_LE = np.array(sorted(int.from_bytes(raw, "little") for raw in _LOW), dtype=np.uint32)
_LOW_LE = np.array([_LOW[int(p).to_bytes(4, "little")] for p in _PID_LE], dtype=np.int64)
_ETH_IPV4_LE = int.from_bytes(L.ETHERTYPE_IPV4.to_bytes(2, "big"), "little")
PIPELINE_MIN_BYTES = 4 << 20                       # smaller files: one process is quicker
WORKERS_ENV = "VM110_ANALYZE_WORKERS"              # 1: read and analyse in one process
_SNIFF = 256                                       # EG-Link packets looked at to guess the CRC variant
_SNIFF_CHUNK = 1 << 16
TRUNCATED = C.Problem.TRUNCATED.value
Progress = Callable[[int, int], None]


def looks_like_eglink(payload: bytes) -> bool:
    """The heuristic for a datagram on another port: a known packet ID and a size consistent with
    the length."""
    n = len(payload)
    return (C.OVERHEAD <= n <= C.MAX_PACKET and payload[:C.ID_LEN] in CODE_OF_ID
            and n == C.OVERHEAD + P.SIZE.unpack_from(payload, P.SIZE_OFFSET)[0])


def best_candidate(candidates: list[tuple[str, str]], counts: Counter) -> tuple[str, str]:
    """The (variant, byte order) that validates the most packets; ties go to the earliest
    candidate (the documented default comes first)."""
    return max(candidates, key=lambda c: (counts[c], -candidates.index(c)))


def crc_candidates(path: str, ports: Collection[int], limit: Optional[int] = None,
                   chunk_size: int = CHUNK) -> Counter:
    """How many EG-Link datagrams (the first `limit` of them) each (variant, byte order) validates:
    those the analysis checks, on `ports` or found by the heuristic, each with its whole CRC."""
    counts: Counter = Counter()
    seen = 0
    with CaptureReader(path, chunk_size=chunk_size) as reader:
        for _, _, sport, dport, payload, frame in reader:
            if payload is None or len(payload) < C.OVERHEAD or frame in reader.snap_truncated:
                continue
            if sport in ports or dport in ports or looks_like_eglink(payload):
                size = P.SIZE.unpack_from(payload, P.SIZE_OFFSET)[0]
                counts.update(crc_matches(payload, min(C.PREFIX_LEN + size, len(payload) - C.CRC_LEN)))
                seen += 1
                if seen == limit:
                    break
    return counts


def pipelined(path: str) -> bool:
    """Whether to read in a second process: on a machine with a second core, for files large
    enough to repay the fork, not inside a worker of `--jobs`, unless VM110_ANALYZE_WORKERS=1."""
    if os.environ.get(WORKERS_ENV) == "1" or (os.cpu_count() or 1) < 2:
        return False
    if multiprocessing.current_process().daemon:
        return False
    try:
        return os.path.getsize(path) >= PIPELINE_MIN_BYTES
    except OSError:
        return False


class _Forward:
    """Stands in for the Analysis in the reading child: sends each batch (and the sources new
    since the last one) to the analysing parent."""

    def __init__(self, conn) -> None:
        self.conn, self.sent = conn, 0

    def feed(self, rec: np.ndarray, sources: dict[bytes, int]) -> None:
        new = dict(list(sources.items())[self.sent:]) if len(sources) > self.sent else {}
        self.sent = len(sources)
        self.conn.send(("batch", rec.tobytes(), new))


class FastEngine:
    """Analyse one capture file with the streaming reader."""

    def __init__(self, port: int = C.INPUT_PORT, crc: str = "auto", crc_order: str = "auto",
                 progress: Optional[Progress] = None) -> None:
        self.port = port
        self.ports = frozenset((port, port + C.OUTPUT_PORT_OFFSET))
        self.crc, self.crc_order = crc, crc_order
        self.progress = progress

    def collect(self, path: str, opt) -> Collected:
        """Read the capture, feeding its legal packets to an `Analysis` with options `opt`."""
        variant = DEFAULT_VARIANT if self.crc == "auto" else self.crc
        order = DEFAULT_BYTE_ORDER if self.crc_order == "auto" else self.crc_order
        sniffed = self._sniff(path) if "auto" in (self.crc, self.crc_order) else None
        if sniffed:
            variant, order = sniffed
        got = self._pass(path, variant, order, opt)
        best = best_candidate(self.candidates(), got.crc_counts)
        if best != (variant, order) and got.crc_counts[best] > got.crc_counts[(variant, order)]:
            got = self._pass(path, *best, opt)     # the sniffed guess was wrong: judge again with the best
        return got

    def candidates(self) -> list[tuple[str, str]]:
        """The (variant, byte order) pairs the options allow, the documented default first."""
        variants = VARIANTS if self.crc == "auto" else (self.crc,)
        orders = BYTE_ORDERS if self.crc_order == "auto" else (self.crc_order,)
        return [(v, o) for v in variants for o in orders]

    def _sniff(self, path: str) -> Optional[tuple[str, str]]:
        counts = crc_candidates(path, self.ports, _SNIFF, _SNIFF_CHUNK)
        return best_candidate(self.candidates(), counts) if counts else None

    def _pass(self, path: str, variant: str, order: str, opt) -> Collected:
        if pipelined(path):
            return self._pipelined(path, variant, order, opt)
        return self._read(path, variant, order, Analysis(opt))

    def _pipelined(self, path: str, variant: str, order: str, opt) -> Collected:
        """Read in a child process while this one analyses: the child's batches come through a
        pipe as they are read, so memory stays bounded and both cores work."""
        ctx = multiprocessing.get_context("fork")
        recv, send = ctx.Pipe(duplex=False)
        child = ctx.Process(target=self._produce, args=(path, variant, order, send), daemon=True)
        # A Ctrl-C goes to the whole process group; it is this process's to handle (it ends the
        # child): the child starts with SIGINT blocked, and one that comes meanwhile waits here.
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            child.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        send.close()
        analysis = Analysis(opt)
        sources: dict[bytes, int] = {}
        done = False
        try:
            while True:
                try:
                    kind, body, more = recv.recv()
                except EOFError:
                    raise CliError(f"cannot analyse {path}: the reading process ended unexpectedly") from None
                if kind == "error":
                    raise body
                if kind == "done":
                    done = True
                    body.analysis, body.sources = analysis, sources
                    return body
                sources.update(more)
                analysis.feed(np.frombuffer(bytearray(body), dtype=RECORD_DTYPE), sources)
        finally:
            recv.close()
            if not done:            # an error or an interrupt here: the reader is not waited for
                child.terminate()
            child.join()

    def _produce(self, path: str, variant: str, order: str, conn) -> None:
        """The child of `_pipelined` (SIGINT blocked): read, send the batches, then the file's facts."""
        try:
            got = self._read(path, variant, order, _Forward(conn))
            got.analysis, got.sources = None, {}
            conn.send(("done", got, None))
        except CliError as exc:
            conn.send(("error", exc, None))
        except Exception as exc:           # one line in the parent, never a traceback
            conn.send(("error", CliError(f"cannot analyse {path}: {type(exc).__name__}: {exc}"), None))
        finally:
            conn.close()

    def _read(self, path: str, variant: str, order: str, analysis) -> Collected:
        with CaptureReader(path) as reader:
            return self._read_from(reader, variant, order, analysis)

    def _read_from(self, reader: CaptureReader, variant: str, order: str, analysis) -> Collected:
        path = reader.path
        got = Collected(path=path, engine="fast", analysis=analysis, format=reader.format,
                        ports=tuple(sorted(self.ports)), crc_variant=variant, crc_order=order,
                        crc_auto=self.crc == "auto" or self.crc_order == "auto")
        layout = reader.pcap_layout() if reader.format == "pcap" else None
        if layout is not None and layout.endian == "<" and layout.link == L.LINKTYPE_ETHERNET:
            valid = self._fused_pcap(got, reader, layout, variant, order)
        elif layout is None:
            valid = self._fused_pcapng(got, reader, variant, order)
        else:
            valid = self._datagrams(got, reader, variant, order)
        got.eglink += valid
        got.crc_checked += valid
        got.crc_counts[(variant, order)] += valid
        got.frames, got.non_udp, got.fragments = reader.frames, reader.non_udp, reader.fragments
        got.unread, got.tunnelled = reader.unknown_link, reader.tunnelled
        got.problem, got.damage = reader.problem, reader.damage
        got.dropped = reader.drops.report()
        got.first_ts, got.last_ts = reader.first_ts, reader.last_ts
        got.earliest_ts, got.latest_ts = reader.earliest, reader.latest
        got.link_types = sorted(reader.link_types)
        return got

    def _advance(self, reader: CaptureReader, chunks, pos: int) -> Optional[bytes]:
        """Report progress and move the fused loops on to the next chunk (None at the end)."""
        if self.progress is not None:
            self.progress(reader.bytes_read + pos, reader.size)
        return reader.next_chunk(chunks, pos)

    def _fused_pcap(self, got: Collected, reader: CaptureReader, layout, variant: str, order: str) -> int:
        """Walk the records of a little-endian Ethernet pcap; returns the legal packets recorded.
        A chunk at a time: one Python step per record finds where the records are, numpy reads
        their headers (`_HEADS`) and picks the EG-Link candidates of the common frame, a zlib call
        each checks their CRC; everything else goes the general way, in frame order."""
        link, limit, when = layout.link, layout.limit, layout.time
        length = struct.Struct("<I").unpack_from
        slack = bytes(_FUSED.size)
        ports_le = np.array(sorted(_SWAP[p] for p in self.ports), dtype=np.uint16)
        reversed_bytes, xor, stored_order = zlib_form(variant, order)
        rev_table, crc = REVERSE_BITS, zlib.crc32
        stored_dtype = np.dtype("<u4" if stored_order == "little" else ">u4")
        slow, udp_of, swap = self._slow, reader.udp_of, _SWAP
        udp_head, ip_head, ip_end, udp_data = L.UDP_HEADER_LEN, L.IPV4_MIN_HEADER, _IP_END, _IP_END + L.UDP_HEADER_LEN
        valid = frame = 0
        chunks = reader.raw_chunks(PCAP_HEADER_LEN)
        data = next(chunks, None)
        while data is not None:
            end = len(data)
            pos = 0
            damaged = False
            starts = array("q")
            mark = starts.append
            last = end - 16
            while pos <= last:
                incl = length(data, pos + 8)[0]
                nxt = pos + 16 + incl
                if nxt > end or incl > limit:       # one test on the hot path: the record's end
                    if incl > limit:
                        reader.corrupt(pos, incl)
                        chunks.close()
                        damaged = True
                    break
                mark(pos)
                pos = nxt
            data += slack               # so that the header reads never run off the end of a chunk
            # The CRC runs on the bytes as they are, or bit-reversed: reverse the chunk in one go.
            cdata = data.translate(rev_table) if reversed_bytes else data
            at = np.frombuffer(starts, dtype=np.int64)
            raw = np.frombuffer(data, dtype=np.uint8)
            head = np.concatenate([raw[at[k:k + _HEAD_ROWS, None] + _HEAD_PICK].view(_HEADS).ravel()
                                   for k in range(0, max(len(at), 1), _HEAD_ROWS)])
            size = head["size"].astype(np.int64)
            plain = ((head["et"] == _ETH_IPV4_LE) & (head["vi"] == _IPV4_PLAIN) & (head["proto"] == L.IPPROTO_UDP)
                     & (head["frag"] & _FRAG_LE == 0) & (head["incl"] >= _FUSED_MIN_FRAME))
            known = np.isin(head["pid"], _PID_LE)
            low = _LOW_LE[np.searchsorted(_PID_LE, head["pid"]).clip(0, len(_PID_LE) - 1)]
            over = size + L.UDP_HEADER_LEN + C.OVERHEAD
            total = over + L.IPV4_MIN_HEADER
            candidate = np.flatnonzero(
                plain & known & (head["rev"] == 0) & (low <= size) & (size <= C.MAX_PAYLOAD)
                & (head["ulen"] == (((over & 0xFF) << 8) | (over >> 8)))
                & (head["tot"] == (((total & 0xFF) << 8) | (total >> 8))) & (size + _FRAME_OVER <= head["incl"])
                & (np.isin(head["sp"], ports_le) | np.isin(head["dp"], ports_le)))
            q = at[candidate] + 16 + udp_data              # the EG-Link packet: q .. e, then the CRC
            e = q + C.PREFIX_LEN + size[candidate]
            # One zlib call per candidate, iterated in C (map) rather than in Python.
            got_crc = np.fromiter(map(crc, map(cdata.__getitem__, map(slice, q.tolist(), e.tolist()))),
                                  dtype=np.uint32, count=len(q))
            stored = np.frombuffer(cdata, dtype=np.uint8)[e[:, None] + np.arange(4)].view(stored_dtype).ravel()
            good = (got_crc ^ xor) == stored
            legal = candidate[good]
            offsets = array("q", q[good].tobytes())
            frames = array("I", (legal + frame + 1).astype(np.uint32).tobytes())
            valid += len(legal)
            rest = np.ones(len(at), dtype=bool)
            rest[legal] = False
            for i in np.flatnonzero(rest).tolist():
                h = head[i]
                p, incl = int(at[i]) + 16, int(h["incl"])
                ts = when(int(h["sec"]), int(h["frac"]))
                if plain[i]:
                    n = swap[int(h["ulen"])]
                    if udp_head <= n <= incl - ip_end and swap[int(h["tot"])] == n + ip_head:
                        slow(got, reader, variant, order, ts, data[p + 26:p + 30], swap[int(h["sp"])],
                             swap[int(h["dp"])], data[p + udp_data:p + ip_end + n], frame + i + 1)
                        continue
                found = udp_of(link, data, p, incl, int(h["orig"]), frame + i + 1)
                if found is not None:
                    slow(got, reader, variant, order, ts, *found, frame + i + 1)
            if len(at):
                if not frame:
                    reader.first_ts = when(int(head["sec"][0]), int(head["frac"][0]))
                reader.last_ts = when(int(head["sec"][-1]), int(head["frac"][-1]))
                times = head["sec"] + head["frac"] * layout.scale
                for i in np.flatnonzero(head["frac"] >= layout.units).tolist():   # damage: as Wireshark reads it
                    times[i] = when(int(head["sec"][i]), int(head["frac"][i]))
                reader.spanned(float(times.min()), float(times.max()))
            frame += len(at)
            reader.frames = frame
            got.flush(got.located_rows(data, offsets, frames, layout))
            if damaged:
                break
            data = self._advance(reader, chunks, pos)
        got.udp = frame - reader.non_udp        # every frame the reader did not count as other
        return valid

    def _fused_pcapng(self, got: Collected, reader: CaptureReader, variant: str, order: str) -> int:
        """Walk the blocks of a pcapng file: enhanced packet blocks of little-endian sections go
        the way of `_fused_pcap` (`_FUSED_NG`), every other block through the reader."""
        fused, slack = _FUSED_NG.unpack_from, bytes(_FUSED_NG.size)
        u32_at = _U32["little"].unpack_from
        ports_le = frozenset(_SWAP[p] for p in self.ports)
        swap, low_of, eth_ipv4 = _SWAP, _LOW, _ETH_IPV4
        reversed_bytes, xor, stored_order = zlib_form(variant, order)
        rev_table, crc = REVERSE_BITS, zlib.crc32
        stored = _U32[stored_order].unpack_from
        pack, sources, records = RECORD.pack, got.sources, got.records
        slow, udp_of = self._slow, reader.udp_of
        min_frame, max_payload = _FUSED_MIN_FRAME, C.MAX_PAYLOAD
        ipv4_plain, udp, frag_le = _IPV4_PLAIN, L.IPPROTO_UDP, _FRAG_LE
        prefix, udp_data = C.PREFIX_LEN, _IP_END + L.UDP_HEADER_LEN
        udp_over, frame_over, epb_head = L.UDP_HEADER_LEN + C.OVERHEAD, _FRAME_OVER, _EPB_HEAD
        ip_over = udp_over + L.IPV4_MIN_HEADER
        shb, epb = PCAPNG_SHB, PCAPNG_EPB
        ifaces, little = reader.interfaces, True
        valid = frame = 0
        ts = 0.0
        first = None
        lo, hi = np.inf, -np.inf            # the span of record times (reader.spanned)
        chunks = reader.raw_chunks(0)
        data = next(chunks, None)
        while data is not None:
            end = len(data)
            pos = 0
            damaged = False
            data += slack               # so that the fused read never runs off the end of a chunk
            cdata = data.translate(rev_table) if reversed_bytes else data
            while pos + 12 <= end:
                (btype, blen, iface, tsh, tsl, incl, orig, et, vi, tot, frag, proto, src, sp, dp, ulen,
                 pid, rev, size) = fused(data, pos)
                if btype == shb:
                    reader.pcapng_section(data, pos)
                    ifaces, little = reader.interfaces, reader.endian == "<"
                if not little:
                    btype, blen = struct.unpack_from(">II", data, pos)
                    et = None
                if reader.bad_block(pos, blen, btype):
                    chunks.close()
                    damaged = True
                    break
                p = pos
                if p + blen > end:
                    break
                if u32_at(data, p + blen - 4)[0] != blen and reader.bad_trailer(data, p, blen):
                    chunks.close()                  # (the quick test reads little-endian: the
                    damaged = True                  # reader judges big-endian sections itself)
                    break
                pos = p + blen
                # (an EPB with options, which wiretap checks, takes the general path)
                if btype == epb and et is not None and iface < len(ifaces) and blen == epb_head + 4 + ((incl + 3) & -4):
                    link, div, scale, tsoff, eth = ifaces[iface]
                    frame += 1
                    ticks = (tsh << 32) | tsl
                    if div:
                        q, r = divmod(ticks, div)
                        ts = q + r * scale + tsoff
                    else:
                        ts = ticks * scale + tsoff
                    if first is None:
                        first = ts
                    if ts > hi:         # (a new latest is no new earliest but for the first: `first`)
                        hi = ts
                    elif ts < lo:
                        lo = ts
                    d = p + epb_head
                    if (eth and et == eth_ipv4 and vi == ipv4_plain and proto == udp and not frag & frag_le
                            and incl >= min_frame):
                        low = low_of.get(pid)
                        if (low is not None and not rev and low <= size <= max_payload
                                and ulen == swap[size + udp_over] and tot == swap[size + ip_over]
                                and size + frame_over <= incl
                                and (sp in ports_le or dp in ports_le)):
                            q = d + udp_data            # the EG-Link packet: q .. e, then the CRC
                            e = q + prefix + size
                            if crc(cdata[q:e]) ^ xor == stored(cdata, e)[0]:
                                index = sources.get(src)
                                if index is None:
                                    index = got.source(src)
                                records += pack(ts, frame, index, swap[sp], data[q:e + 4])
                                valid += 1
                                continue
                    found = udp_of(link, data, d, incl, orig, frame)
                    if found is not None:
                        slow(got, reader, variant, order, ts, *found, frame)
                    continue
                if reader.corrupt_block(data, p, btype, blen):  # (off the fast path: it takes only good ones)
                    chunks.close()
                    damaged = True
                    break
                reader.last_ts = ts if frame else None      # a simple packet block takes this time
                block = reader.pcapng_block(data, p, btype, blen)
                if block is None:
                    continue
                frame += 1
                block_ts, link, d, incl, orig = block
                if link is None:
                    reader.non_udp += 1
                    continue
                ts = block_ts
                if first is None:
                    first = ts
                lo, hi = min(lo, ts), max(hi, ts)
                found = udp_of(link, data, d, incl, orig, frame)
                if found is not None:
                    slow(got, reader, variant, order, ts, *found, frame)
            reader.frames = frame
            reader.first_ts, reader.last_ts = first, (ts if frame else None)
            reader.spanned(lo if first is None else min(lo, first), hi)
            got.flush()
            if damaged:
                break
            data = self._advance(reader, chunks, pos)
        got.udp = frame - reader.non_udp
        return valid

    def _datagrams(self, got: Collected, reader: CaptureReader, variant: str, order: str) -> int:
        """Any other file, through the reader's datagrams; returns the legal packets recorded."""
        ports = self.ports
        reversed_bytes, xor, stored_order = zlib_form(variant, order)
        rev_table, crc = REVERSE_BITS, zlib.crc32
        stored = _U32[stored_order].unpack_from
        unpack, low_of, max_payload = _HDR.unpack_from, _LOW, C.MAX_PAYLOAD
        pack, sources, records = RECORD.pack, got.sources, got.records
        slow = self._slow
        valid = udp = 0
        for batch in reader.batches():
            udp += len(batch)
            for ts, src, sport, dport, payload, frame in batch:
                if payload is None or (sport not in ports and dport not in ports) or len(payload) < C.OVERHEAD:
                    slow(got, reader, variant, order, ts, src, sport, dport, payload, frame)
                    continue
                n = len(payload)
                pid, rev, size = unpack(payload)
                low = low_of.get(pid)
                if low is None or rev or n != size + C.OVERHEAD or not low <= size <= max_payload:
                    slow(got, reader, variant, order, ts, src, sport, dport, payload, frame)
                    continue
                if reversed_bytes:
                    t = payload.translate(rev_table)
                    ok = crc(t[:-4]) ^ xor == stored(t, n - C.CRC_LEN)[0]
                else:
                    ok = crc(payload[:-4]) ^ xor == stored(payload, n - C.CRC_LEN)[0]
                if not ok:
                    slow(got, reader, variant, order, ts, src, sport, dport, payload, frame)
                    continue
                index = sources.get(src)
                if index is None:
                    index = got.source(src)
                records += pack(ts, frame, index, sport, payload)
                valid += 1
            got.flush()
            if self.progress is not None:
                self.progress(reader.bytes_read, reader.size)
        got.udp = udp
        return valid

    def _slow(self, got: Collected, reader: CaptureReader, variant: str, order: str, ts: float, src: bytes,
              sport: int, dport: int, payload: Optional[bytes], frame: int) -> None:
        if payload is None or (sport not in self.ports and dport not in self.ports and not looks_like_eglink(payload)):
            got.other_udp += 1
            reader.tunnelled += dport in L.TUNNEL_PORTS
            return
        got.eglink += 1
        n = len(payload)
        fields = decode(payload, variant, order)
        problems = list(fields["problems"])
        cut = frame in reader.snap_truncated
        got.snap_truncated += cut               # (EG-Link only: the reader marks any datagram it cut)
        if n >= C.OVERHEAD and not cut:          # (a packet the capture cut has no whole CRC to check)
            got.crc_checked += 1
            end = min(C.PREFIX_LEN + fields["size"], n - C.CRC_LEN)
            # (valid under the chosen one: counted for it only, as on the hot path)
            matches = crc_matches(payload, end)
            got.crc_counts.update({(variant, order)} if (variant, order) in matches else matches)
        if cut:
            problems = [TRUNCATED]       # the capture cut it: nothing else can be judged
        if problems:
            got.add_illegal(frame, ts, address(src, sport), fields.get("type", ""), problems)
            return
        got.add_legal(ts, frame, src, sport, payload)
