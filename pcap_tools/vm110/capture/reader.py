"""Stream UDP datagrams out of pcap and pcapng files, fast and without scapy.

`CaptureReader(path)` yields `(ts, src, sport, dport, payload, frame)` per UDP datagram: time in
seconds, source address as packed bytes (4 or 16), ports, the UDP payload cut to the UDP length
(Ethernet padding excluded) and the 1-based frame number. Everything else is counted, not yielded.

The file is read in large chunks; the common frame (Ethernet + IPv4 without options + UDP) is
decoded by one `struct` call, every other layout by `udp_of`. A file that ends in the middle of a
record keeps what was read and says so in `problem`; a file that is not a capture raises
`CaptureError` (exit code 2 in the CLI). A gzip-compressed capture is decompressed as it is read
(`compressed`).
"""
from __future__ import annotations

import ipaddress
import math
import os
import stat
import struct
import sys
from typing import BinaryIO, Generator, Iterator, NamedTuple, Optional

from ..errors import CliError
from . import linktypes as L
from .compressed import OTHER_COMPRESSIONS, Gunzip, is_gzip
from .drops import Drops, options
from .reassembly import Reassembly

Datagram = tuple  # (ts: float, src: bytes, sport: int, dport: int, payload: bytes or None (see udp_of), frame: int)

PCAP_MAGIC_US = 0xA1B2C3D4
PCAP_MAGIC_NS = 0xA1B23C4D
PCAPNG_SHB = 0x0A0D0D0A
PCAPNG_BOM = 0x1A2B3C4D
PCAPNG_IDB, PCAPNG_PB, PCAPNG_SPB, PCAPNG_EPB = 1, 2, 3, 6
PCAPNG_NRB, PCAPNG_ISB, PCAPNG_DSB = 4, 5, 10
# Blocks that are records (frames) in Wireshark, not packets: systemd journal entries, custom
# blocks, system-call events (Sysdig/Falco). Frame numbers count them, as Wireshark's do.
PCAPNG_OTHER_RECORDS = frozenset((0x9, 0xBAD, 0x40000BAD, 0x204, 0x208, 0x216, 0x217, 0x221, 0x222))
OPT_END, OPT_TSRESOL, OPT_TSOFFSET = 0, 9, 14
# The least length of a block of each kind (its fixed fields), below which wiretap stops reading.
# (Not a system-call event's: that depends on the Wireshark version.)
_LEAST_BLOCK = {PCAPNG_SHB: 28, PCAPNG_IDB: 20, PCAPNG_PB: 32, PCAPNG_SPB: 16, PCAPNG_NRB: 16, PCAPNG_ISB: 24,
                PCAPNG_EPB: 32, 0x9: 35, PCAPNG_DSB: 20, 0xBAD: 16, 0x40000BAD: 16}   # (9: journal; custom)
_NRB_ADDRESS = {1: 4, 2: 16}                    # an IPv4 or IPv6 record: its address at least
# Where a block's options start, after its fixed fields (a packet block's: after its padded data
# too, a name resolution block's after its records; both worked out), for the blocks whose options
# wiretap reads.
_OPTIONS_AT = {PCAPNG_SHB: 24, PCAPNG_IDB: 16, PCAPNG_ISB: 20}
# Options that wiretap refuses (and stops reading the file) at another length: (least, most).
_PACKET_OPTION_LENGTHS = {2: (4, 4), 4: (8, 8), 5: (8, 8), 6: (4, 4), 7: (1, 0xFFFF)}   # flags .. verdict
_VERDICT_LENGTHS = {1: 9, 2: 9}                 # a verdict of Linux eBPF TC or XDP: its type and 8 bytes
_IDB_FILTER = 11                                # at least its type byte
PCAP_HEADER_LEN = 24
PCAP_RECORD_LEN = 16
MAX_RECORD = 1 << 18           # Wireshark's largest standard packet; a longer record is damage
MAX_PACKET_BLOCK = MAX_RECORD + (1 << 12)   # a pcapng packet block: the record, its header and options
MAX_BLOCK = 1 << 20            # any other pcapng block
CHUNK = 1 << 22

# The common frame (Ethernet, IPv4 without options, UDP): EtherType, version/IHL, total length,
# fragment field, protocol, source, ports, UDP length. It is taken at once when the IP total length
# and the UDP length agree; anything else goes through udp_of, which reads headers as Wireshark does.
_FAST = struct.Struct("!12xHBxH2xHxB2x4s4xHHH")
_FAST_HEAD = L.ETH_HEADER_LEN + L.IPV4_MIN_HEADER + L.UDP_HEADER_LEN
_FAST_VI = 0x45


def format_of(head: bytes, path: str) -> str:
    """"pcap" or "pcapng" from a capture's first 4 bytes, or CaptureError."""
    magic_le, magic_be = struct.unpack_from("<I", head)[0], struct.unpack_from(">I", head)[0]
    if magic_le == PCAPNG_SHB:
        return "pcapng"
    if PCAP_MAGIC_US in (magic_le, magic_be) or PCAP_MAGIC_NS in (magic_le, magic_be):
        return "pcap"
    if is_gzip(head):       # (a stream, which is not decompressed, or a file's second layer)
        raise CaptureError(f"{path}: compressed with gzip, which is not read here: decompress it first (gzip -d)")
    if head[:4] in OTHER_COMPRESSIONS:
        kind = OTHER_COMPRESSIONS[head[:4]]
        raise CaptureError(f"{path}: compressed with {kind}, which is not read here: decompress it first "
                           f"({kind} -d), or give it to --engine tshark (Wireshark 4.2 or later)")
    raise CaptureError(f"{path}: not a pcap or pcapng capture (magic 0x{magic_be:08x})")


def _cut_fragment(data: bytes, pos: int, end: int) -> bool:
    """Whether an IPv4 header the capture cut short still shows a fragment (Wireshark shows its
    fields up to the cut)."""
    if pos + 8 > end or data[pos] >> 4 != 4 or (data[pos] & 0x0F) * 4 < L.IPV4_MIN_HEADER:
        return False
    tot, frag = struct.unpack_from("!H2xH", data, pos + 2)
    return not 0 < tot < (data[pos] & 0x0F) * 4 and bool(frag & L.IPV4_FRAGMENT_MASK)


def _private(address: bytes) -> bool:
    """An IPv4 address of a private network (RFC 1918) or link-local, whose fragments Wireshark
    tells apart by VLAN (the same addresses may be in use on several)."""
    a, b = address[0], address[1]
    return a == 10 or (a == 172 and 16 <= b < 32) or (a, b) in ((192, 168), (169, 254))


def _vlan_id(link: int, data: bytes, pos: int, end: int) -> int:
    """The VLAN a frame's IP packet came on, as Wireshark's reassembly tells copies of a fragment
    apart: the ID of its last tag other than 802.1ad (0 untagged)."""
    if link == L.LINKTYPE_ETHERNET:
        et_at = pos + 12
    elif link == L.LINKTYPE_LINUX_SLL:
        et_at = pos + 14
    elif link == L.LINKTYPE_LINUX_SLL2:
        et_at = pos
    else:
        return 0
    tag = pos + (L.ETH_HEADER_LEN if link == L.LINKTYPE_ETHERNET else
                 L.SLL_HEADER_LEN if link == L.LINKTYPE_LINUX_SLL else L.SLL2_HEADER_LEN)
    vid = 0
    et = struct.unpack_from("!H", data, et_at)[0]
    while et in L.ETHERTYPE_VLANS and tag + L.VLAN_TAG_LEN <= end:
        if et != 0x88A8:
            vid = struct.unpack_from("!H", data, tag)[0] & 0x0FFF
        et = struct.unpack_from("!H", data, tag + 2)[0]
        tag += L.VLAN_TAG_LEN
    return vid


class PcapLayout(NamedTuple):
    endian: str          # struct byte order of the record headers
    scale: float         # seconds per unit of the fraction field (us or ns)
    link: int
    limit: int           # largest plausible record
    units: int           # fraction units in a second: a fraction this large or more is damage

    def time(self, sec: int, frac: int) -> float:
        """A record's time as Wireshark reads it, so that a frame's time is the one the user sees
        there and the two engines agree. wiretap keeps the fraction in signed 32-bit nanoseconds:
        one of a second or more (damage; no writer means it) wraps there."""
        if frac < self.units:
            return sec + frac * self.scale
        nsec = (frac * (1_000_000_000 // self.units)) & 0xFFFFFFFF
        return sec + (nsec - (1 << 32) if nsec >= 1 << 31 else nsec) * 1e-9


def address(src: bytes, port: int) -> str:
    """"ip:port" of a packed source address as the reader yields it (IPv6 in brackets)."""
    if len(src) == 4:
        return f"{src[0]}.{src[1]}.{src[2]}.{src[3]}:{port}"
    return f"[{ipaddress.IPv6Address(src)}]:{port}"


class CaptureError(CliError):
    """The file cannot be read as a capture."""


def padded(n: int) -> int:
    """`n` bytes of a pcapng block's field, padded to its 4-byte unit."""
    return (n + 3) & ~3


class CaptureReader:
    """One capture file; iterate it (or its `batches()`) once. A walk closes the file when it
    ends; use the reader as a context manager (`with CaptureReader(path) as reader:`) so that the
    file is closed also when a walk stops early or never starts."""

    _gunzip: Optional[Gunzip] = None      # a gzip file's decompression

    def __init__(self, path: str, chunk_size: int = CHUNK) -> None:
        self.path = path
        self.chunk_size = chunk_size
        try:
            if stat.S_ISFIFO(os.stat(path).st_mode):   # (opening one waits for a writer)
                raise CaptureError(f"{path} is a named pipe: give it on standard input (- < {path}), "
                                   "which is read as it comes")
            raw = open(path, "rb")   # noqa: SIM115 -- the reader owns it; close()/with
        except OSError as exc:
            raise CaptureError(f"cannot read {path}: {exc.strerror or exc}") from None
        self._file: BinaryIO | Gunzip = raw
        try:
            self.size, self.format = self._identify(path, raw)
        except BaseException:
            self._file.close()
            raise
        self._layout: Optional[PcapLayout] = None
        self.reset_counters()

    def reset_counters(self) -> None:
        """The counts and per-section state that reading fills in (a stream's too)."""
        self.frames = 0            # every packet record
        self.non_udp = 0           # frames that carry no (whole) UDP datagram
        self.fragments = 0         # IP fragments of datagrams not (yet) reassembled (in non_udp)
        self.unknown_link = 0      # frames of a link type the reader does not know (in non_udp)
        self.tunnelled = 0         # frames of a tunnel it does not unwrap (in non_udp, or other UDP)
        self.snap_truncated: set[int] = set()   # frames whose UDP payload the snaplen cut short
        self.problem: Optional[str] = None      # why reading stopped early, if it did
        self.damage: Optional[int] = None       # and the file offset where it did
        self.link_types: set[str] = set()
        self.bytes_read = 0
        self.first_ts: Optional[float] = None   # of the first and last packet record
        self.last_ts: Optional[float] = None
        # The earliest and latest time of any packet record (capinfos' span: records need not be in
        # time order); inf and -inf until one is read.
        self.earliest, self.latest = math.inf, -math.inf
        self.endian = "<"                       # pcapng: of the current section
        self.interfaces: list[tuple] = []       # pcapng: (link, ticks/s or 0, s/tick, offset, Ethernet?)
        self.spb_snaplen = 0                    # pcapng: the section's first interface's snaplen (0: none)
        self.drops = Drops()                    # pcapng: what the capture says it dropped
        self._reassembly = Reassembly()         # IP fragments waiting for the rest of their datagram
        self.ts_digits = 6                      # decimal digits of the finest timestamps (9: ns)

    def _identify(self, path: str, raw: BinaryIO) -> tuple[int, str]:
        """The file's size and format ("pcap" or "pcapng") from its magic, or CaptureError."""
        try:
            size = os.fstat(raw.fileno()).st_size
            head = raw.read(4)
            raw.seek(0)
        except OSError as exc:
            raise CaptureError(f"cannot read {path}: {exc.strerror or exc}") from None
        if not head:
            raise CaptureError(f"{path}: empty file, not a pcap or pcapng capture")
        if is_gzip(head):       # (one layer, as Wireshark reads; its size is not known before the end)
            self._file = self._gunzip = stream = Gunzip(raw)
            try:
                size, head = sys.maxsize, stream.read(PCAP_HEADER_LEN)
                stream.seek(0)
            except OSError as exc:
                raise CaptureError(f"cannot read {path}: {exc.strerror or exc}") from None
            if stream.problem and len(head) < PCAP_HEADER_LEN:
                raise CaptureError(f"{path}: {stream.problem}")
            if not head:
                raise CaptureError(f"{path}: gzip-compressed empty file, not a pcap or pcapng capture")
        if len(head) < 4:
            raise CaptureError(f"{path}: not a pcap or pcapng capture (too short)")
        return size, format_of(head, path)

    def close(self) -> None:
        """Close the file; safe to repeat."""
        self._file.close()

    def __enter__(self) -> CaptureReader:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- public --------------------------------------------------------------------------------
    def batches(self) -> Iterator[list[Datagram]]:
        """Lists of datagrams, one per chunk of the file (cheaper to loop over than a generator)."""
        try:
            yield from (self._pcap() if self.format == "pcap" else self._pcapng())
        finally:
            self._file.close()

    def __iter__(self) -> Iterator[Datagram]:
        for batch in self.batches():
            yield from batch

    # -- pcap ----------------------------------------------------------------------------------
    def pcap_layout(self) -> PcapLayout:
        """The pcap file header: byte order, seconds per fraction unit, link type, record limit."""
        if self._layout is not None:
            return self._layout
        self._file.seek(0)
        head = self._file.read(PCAP_HEADER_LEN)
        if len(head) < PCAP_HEADER_LEN:
            raise CaptureError(f"{self.path}: pcap file header cut short")
        self._layout = self.pcap_header(head)
        return self._layout

    def pcap_header(self, head: bytes) -> PcapLayout:
        """The layout a pcap file header (PCAP_HEADER_LEN bytes) gives; its link type noted."""
        e = "<" if struct.unpack_from("<I", head)[0] in (PCAP_MAGIC_US, PCAP_MAGIC_NS) else ">"
        magic, _, _, _, _, _snaplen, network = struct.unpack_from(e + "IHHiIII", head)
        link = network & 0x0FFFFFFF      # the top bits may carry FCS information
        self.link_types.add(L.NAMES.get(link, str(link)))
        # Never the snaplen: a file's own header must not let a record claim gigabytes.
        self.ts_digits = 9 if magic == PCAP_MAGIC_NS else 6
        ns = magic == PCAP_MAGIC_NS
        return PcapLayout(e, 1e-9 if ns else 1e-6, link, MAX_RECORD, 1_000_000_000 if ns else 1_000_000)

    def raw_chunks(self, start: int = PCAP_HEADER_LEN, stop: Optional[int] = None) -> Generator[bytes, int, None]:
        """Chunks of records (pcap) or blocks (pcapng) for a consumer that walks them itself: each
        chunk starts at a record; the consumer sends back how many bytes (whole records) it used.
        For pcap call `pcap_layout()` first; a consumer that stops at a corrupt record calls
        `corrupt()`. `start` and `stop` (file offsets of record boundaries) select a part."""
        leftover = b""
        offset = self.bytes_read = start
        self._file.seek(start)
        remaining = (self.size if stop is None else stop) - start
        read = self._file.read
        try:
            while remaining > 0:
                chunk = read(min(self.chunk_size, remaining))
                if not chunk:
                    break
                remaining -= len(chunk)
                data = leftover + chunk if leftover else chunk
                used = yield data
                leftover = data[used:]
                offset += used
                self.bytes_read = offset
        finally:
            self._file.close()
        self.bytes_read = offset + len(leftover)
        stream = self._gunzip
        if stream is not None and stream.problem and stop is None:   # (the cause of a cut record below)
            cut = f", {len(leftover)} bytes of a record after it ignored" if leftover else ""
            self.damaged(offset, f"{stream.problem}: records read up to byte {offset} of it{cut}")
        if leftover and not offset:      # (a pcap's records start after its header)
            raise CaptureError(f"{self.path}: pcapng section header block cut short")
        if leftover:
            self.damaged(offset, f"file cut in the middle of a record at byte {offset} ({len(leftover)} bytes ignored)")

    def damaged(self, offset: int, message: str) -> None:
        """Reading stops at `offset` for this reason (the first one counts); in a gzip file whose
        decompression stopped early, that is said too (corrupt data decompress into garbage first:
        the rest is decompressed, unread, to know)."""
        if self.damage is None:
            stream = self._gunzip
            if stream is not None:
                stream.drain()
                if stream.problem and not message.startswith(stream.problem):
                    message = f"{message} ({stream.problem})"
            self.damage, self.problem = offset, message

    def corrupt(self, pos: int, length: int) -> None:
        """Record that the record header at `pos` of the current chunk is corrupt."""
        at = self.bytes_read + pos
        over = f": over the {MAX_RECORD}-byte limit" if length > MAX_RECORD else ""
        self.damaged(at, f"corrupt record header at byte {at} (length {length}{over})")

    def _pcap(self) -> Iterator[list[Datagram]]:
        layout = self.pcap_layout()
        e, scale, link, limit, units = layout
        when = layout.time
        rec = struct.Struct(e + "IIII").unpack_from
        fast = _FAST.unpack_from if link == L.LINKTYPE_ETHERNET else None
        parse = self.udp_of
        vi45, head_len, frag_mask = _FAST_VI, _FAST_HEAD, L.IPV4_FRAGMENT_MASK
        ipv4, udp = L.ETHERTYPE_IPV4, L.IPPROTO_UDP
        frame, ts = 0, 0.0
        lo, hi = math.inf, -math.inf
        chunks = self.raw_chunks()
        data = next(chunks, None)
        while data is not None:
            end = len(data)
            pos = 0
            out: list[Datagram] = []
            append = out.append
            while pos + 16 <= end:
                sec, frac, incl, orig = rec(data, pos)
                p = pos + 16
                if incl > limit:
                    self.corrupt(pos, incl)
                    chunks.close()
                    self.spanned(lo, hi)
                    self._times(data, frame, ts, rec, when)
                    self.frames = frame
                    yield out
                    return
                if p + incl > end:
                    break
                pos = p + incl
                frame += 1
                ts = sec + frac * scale if frac < units else when(sec, frac)
                lo, hi = min(lo, ts), max(hi, ts)
                if fast is not None and incl >= head_len:
                    et, vi, tot, frag, proto, src, sport, dport, ulen = fast(data, p)
                    if (et == ipv4 and vi == vi45 and proto == udp and not frag & frag_mask
                            and tot == 20 + ulen and 34 + ulen <= incl and ulen >= 8):
                        append((ts, src, sport, dport, data[p + 42:p + 34 + ulen], frame))
                        continue
                got = parse(link, data, p, incl, orig, frame)
                if got is not None:
                    append((ts, *got, frame))
            self.spanned(lo, hi)
            self._times(data, frame, ts, rec, when)
            self.frames = frame
            yield out
            data = self.next_chunk(chunks, pos)

    def spanned(self, lo: float, hi: float) -> None:
        """Widen the span of record times (earliest, latest) to [lo, hi]."""
        self.earliest, self.latest = min(self.earliest, lo), max(self.latest, hi)

    def _times(self, data: bytes, frame: int, ts: float, rec, when) -> None:
        """first_ts and last_ts, `ts` the time of the last of `frame` records so far (the first
        one's read from the chunk `data` that began with it)."""
        if frame:
            self.last_ts = ts
            if self.first_ts is None:
                self.first_ts = when(*rec(data, 0)[:2])

    @staticmethod
    def next_chunk(chunks: Generator[bytes, int, None], pos: int) -> Optional[bytes]:
        """The next chunk of `raw_chunks`, resuming at `pos` of the current one; None at the end."""
        try:
            return chunks.send(pos)
        except StopIteration:
            return None

    # -- pcapng --------------------------------------------------------------------------------
    def pcapng_block(self, data: bytes, pos: int, btype: int, blen: int) -> Optional[tuple]:
        """Take in one pcapng block (its header checked by the caller). Section and interface
        blocks update the reader; a packet block returns (ts, link, start of frame, captured
        length, original length), another record link None; anything else None. A bad byte-order
        magic raises CaptureError."""
        e = self.endian
        if btype in (PCAPNG_EPB, PCAPNG_PB):
            if btype == PCAPNG_EPB:
                iface, tsh, tsl, incl, orig = struct.unpack_from(e + "IIIII", data, pos + 8)
            else:
                iface, _, tsh, tsl, incl, orig = struct.unpack_from(e + "HHIIII", data, pos + 8)
            if iface >= len(self.interfaces) or incl > blen - 28:
                return (self.last_ts or 0.0, None, pos + 28, 0, 0)
            if blen > 32 + ((incl + 3) & ~3) and btype == PCAPNG_EPB:       # (options: rare)
                self.drops.packet(data, iface, pos + 28 + padded(incl), pos + blen - 4, e)
            link, div, scale, tsoff, _ = self.interfaces[iface]
            ticks = (tsh << 32) | tsl
            if div:
                q, r = divmod(ticks, div)
                ts = q + r * scale + tsoff
            else:
                ts = ticks * scale + tsoff
            return ts, link, pos + 28, incl, orig
        if btype == PCAPNG_SPB:
            if not self.interfaces:
                return (self.last_ts or 0.0, None, pos + 12, 0, 0)
            orig = struct.unpack_from(e + "I", data, pos + 8)[0]
            # A simple packet block has no time: it gets the time of the packet before it.
            return self.last_ts or 0.0, self.interfaces[0][0], pos + 12, min(orig, self.spb_snaplen or orig), orig
        if btype in PCAPNG_OTHER_RECORDS:
            return (self.last_ts or 0.0, None, pos, 0, 0)
        if btype == PCAPNG_IDB:
            link, snaplen = struct.unpack_from(e + "H2xI", data, pos + 8)
            if not self.interfaces:
                self.spb_snaplen = snaplen              # (a simple packet block's: of the first interface)
            div, scale, tsoff = self._idb_options(data, pos + 16, pos + blen - 4, e)
            self.link_types.add(L.NAMES.get(link, str(link)))
            self.interfaces.append((link, div, scale, tsoff, link == L.LINKTYPE_ETHERNET))
            self.drops.interface(data, pos, blen, e)
            digits = len(str(div)) - 1 if div else 9       # (binary fractions: in nanoseconds)
            self.ts_digits = max(self.ts_digits, min(digits, 9))
        elif btype == PCAPNG_ISB:
            self.drops.statistics(data, pos, blen, e)
        return None

    def pcapng_section(self, data: bytes, pos: int) -> None:
        """A section header block at `pos`: its byte order; the interfaces start afresh."""
        if struct.unpack_from("<I", data, pos + 8)[0] == PCAPNG_BOM:
            self.endian = "<"
        elif struct.unpack_from(">I", data, pos + 8)[0] == PCAPNG_BOM:
            self.endian = ">"
        else:
            at = self.bytes_read + pos
            if not at:
                raise CaptureError(f"{self.path}: bad pcapng byte-order magic at byte 0")
            # A later section: what came before it is kept (bad_block stops the walk here).
            self.damaged(at, f"bad pcapng byte-order magic in the section at byte {at}")
        self.interfaces = []
        self.drops.section()

    def bad_trailer(self, data: bytes, pos: int, blen: int) -> bool:
        """Whether a whole block's trailing length differs from its leading one (damage)."""
        last = struct.unpack_from(self.endian + "I", data, pos + blen - 4)[0]
        if last == blen:
            return False
        at = self.bytes_read + pos
        self.damaged(at, f"corrupt pcapng block at byte {at} (leading length {blen}, trailing {last})")
        return True

    def corrupt_block(self, data: bytes, pos: int, btype: int, blen: int) -> bool:
        """Whether a whole block is corrupt (damage, where tshark stops too): shorter than its
        kind's fixed fields; a packet block that names an interface its section does not have, or
        whose packet data do not fit it; a name resolution record or decryption secrets past the
        block; an option past its block, or of a length wiretap refuses."""
        problem = self._packet_problem(data, pos, btype, blen)
        if problem is None:
            problem = self._block_problem(data, pos, btype, blen)
        if problem is None:
            return False
        at = self.bytes_read + pos
        self.damaged(at, f"corrupt pcapng {problem.format(at=at)}")
        return True

    def _block_problem(self, data: bytes, pos: int, btype: int, blen: int) -> Optional[str]:
        e, end = self.endian, pos + blen - 4
        least = _LEAST_BLOCK.get(btype, 12)
        if blen < least:
            return f"block at byte {{at}} (type {btype}, {blen} bytes, below its {least})"
        fixed = _OPTIONS_AT.get(btype)
        options = None if fixed is None else pos + fixed
        if btype in (PCAPNG_EPB, PCAPNG_PB):
            options = pos + 28 + padded(struct.unpack_from(e + "I", data, pos + 20)[0])
        elif btype == PCAPNG_NRB:
            options, problem = self._nrb_records(data, pos + 8, end)
            if problem is not None:
                return f"block at byte {{at}} ({problem})"
        elif btype == PCAPNG_DSB:
            secrets = struct.unpack_from(e + "I", data, pos + 12)[0]
            if padded(secrets) > blen - 20:
                return f"block at byte {{at}} (decryption secrets of {secrets} bytes in a {blen}-byte block)"
        if options is None:
            return None
        problem = self._option_problem(data, options, end, btype)
        return None if problem is None else f"block at byte {{at}} ({problem})"

    def _nrb_records(self, data: bytes, pos: int, end: int) -> tuple[int, Optional[str]]:
        """Where a name resolution block's options start, and what wiretap refuses in its records."""
        e = self.endian
        while pos + 4 <= end:
            kind, length = struct.unpack_from(e + "HH", data, pos)
            pos += 4
            if padded(length) > end - pos:
                return pos, f"name resolution record of {length} bytes past the block's end"
            if kind == 0:
                return pos, None
            if length < _NRB_ADDRESS.get(kind, 0):
                return pos, f"name resolution record of type {kind} of {length} bytes"
            pos += padded(length)
        return end, None

    def _option_problem(self, data: bytes, pos: int, end: int, btype: int) -> Optional[str]:
        """What wiretap refuses in the options from `pos` to `end` of a block, else None."""
        e = self.endian
        while pos + 4 <= end:                   # (blocks and options come in 4-byte units)
            code, length = struct.unpack_from(e + "HH", data, pos)
            pos += 4
            if length > end - pos:
                return f"option {code} of {length} bytes past the block's end"
            if code == OPT_END:
                return None
            if btype in (PCAPNG_EPB, PCAPNG_PB) and code in _PACKET_OPTION_LENGTHS:
                least, most = _PACKET_OPTION_LENGTHS[code]
                if code == 7 and length and data[pos] in _VERDICT_LENGTHS:
                    least = most = _VERDICT_LENGTHS[data[pos]]
                if not least <= length <= most:
                    return f"packet block option {code} of {length} bytes"
            elif btype == PCAPNG_IDB and code == _IDB_FILTER and not length:
                return "an empty interface filter option"
            pos += padded(length)
        return None

    def _packet_problem(self, data: bytes, pos: int, btype: int, blen: int) -> Optional[str]:
        e = self.endian
        if btype in (PCAPNG_EPB, PCAPNG_PB) and blen >= _LEAST_BLOCK[btype]:
            iface = struct.unpack_from(e + ("I" if btype == PCAPNG_EPB else "H"), data, pos + 8)[0]
            incl = struct.unpack_from(e + "I", data, pos + 20)[0]
            if iface >= len(self.interfaces):
                return f"packet block at byte {{at}} (interface {iface}; its section has {len(self.interfaces)})"
            if padded(incl) > blen - 32:      # (the data, padded, and the trailing length)
                return f"packet block at byte {{at}} (captured length {incl} in a {blen}-byte block)"
        elif btype == PCAPNG_SPB and blen >= _LEAST_BLOCK[btype]:
            if not self.interfaces:
                return "packet block at byte {at} (no interface block before it)"
            # wiretap reads min(length, snaplen) bytes of data, padded, then the trailing length.
            orig = struct.unpack_from(e + "I", data, pos + 8)[0]
            incl = min(orig, self.spb_snaplen or orig)
            if padded(incl) != blen - 16:
                return f"packet block at byte {{at}} ({incl} bytes of packet data in a {blen}-byte simple packet block)"
        return None

    def bad_block(self, pos: int, blen: int, btype: int) -> bool:
        """Whether the walk must stop at this block: damage found before, or a corrupt or
        oversized block length (and if so, say where)."""
        if self.damage is not None:
            return True
        limit = MAX_PACKET_BLOCK if btype in (PCAPNG_EPB, PCAPNG_PB, PCAPNG_SPB) else MAX_BLOCK
        if blen < 12 or blen % 4 or blen > limit:
            at = self.bytes_read + pos
            self.damaged(at, f"corrupt pcapng block at byte {at} (type {btype}, length {blen})")
            return True
        return False

    def _pcapng(self) -> Iterator[list[Datagram]]:
        parse = self.udp_of
        vi45, head_len, frag_mask = _FAST_VI, _FAST_HEAD, L.IPV4_FRAGMENT_MASK
        ipv4, udp = L.ETHERTYPE_IPV4, L.IPPROTO_UDP
        fast = _FAST.unpack_from
        frame = 0
        chunks = self.raw_chunks(0)
        data = next(chunks, None)
        while data is not None:
            end = len(data)
            pos = 0
            out: list[Datagram] = []
            append = out.append
            while pos + 12 <= end:
                if struct.unpack_from("<I", data, pos)[0] == PCAPNG_SHB:
                    self.pcapng_section(data, pos)
                btype, blen = struct.unpack_from(self.endian + "II", data, pos)
                if self.bad_block(pos, blen, btype):
                    chunks.close()
                    self.frames = frame
                    yield out
                    return
                if pos + blen > end:
                    break
                if self.bad_trailer(data, pos, blen):
                    chunks.close()
                    self.frames = frame
                    yield out
                    return
                if self.corrupt_block(data, pos, btype, blen):
                    chunks.close()
                    self.frames = frame
                    yield out
                    return
                p = pos
                pos += blen
                found = self.pcapng_block(data, p, btype, blen)
                if found is None:
                    continue
                frame += 1
                ts, link, d, incl, orig = found
                if link is None:
                    self.non_udp += 1
                    continue
                self.last_ts = ts
                if self.first_ts is None:
                    self.first_ts = ts
                self.spanned(ts, ts)
                if link == L.LINKTYPE_ETHERNET and incl >= head_len:
                    et, vi, tot, frag, proto, src, sport, dport, ulen = fast(data, d)
                    if (et == ipv4 and vi == vi45 and proto == udp and not frag & frag_mask
                            and tot == 20 + ulen and 34 + ulen <= incl and ulen >= 8):
                        append((ts, src, sport, dport, data[d + 42:d + 34 + ulen], frame))
                        continue
                got = parse(link, data, d, incl, orig, frame)
                if got is not None:
                    append((ts, *got, frame))
            self.frames = frame
            yield out
            data = self.next_chunk(chunks, pos)

    @staticmethod
    def _idb_options(data: bytes, pos: int, end: int, e: str) -> tuple[int, float, int]:
        """(ticks per second when a power of ten else 0, seconds per tick, offset) of an interface."""
        div, scale, tsoff = 1_000_000, 1e-6, 0
        for code, value in options(data, pos, end, e):
            if code == OPT_TSRESOL and len(value) == 1:     # (wiretap ignores one of another length)
                v = value[0]
                if v & 0x80:
                    div, scale = 0, 2.0 ** -(v & 0x7F)
                else:
                    div, scale = 10 ** v, 10.0 ** -v
            elif code == OPT_TSOFFSET and len(value) == 8:
                tsoff = struct.unpack(e + "q", value)[0]
        return div, scale, tsoff

    # -- every layout but the fast one ---------------------------------------------------------
    def udp_of(self, link: int, data: bytes, start: int, incl: int, orig: int,
               frame: int) -> Optional[tuple[bytes, int, int, Optional[bytes]]]:
        """(src, sport, dport, payload) of the UDP datagram in a frame, or None (counted as no
        UDP). The headers are read as Wireshark reads them, so that the two engines agree on
        damaged ones: an IP header that is no IP header is no UDP; the IPv4 total length, or the
        IPv6 payload length, bounds the datagram (an IPv4 total length of 0: the frame's, as for
        TCP segmentation offload; an IPv6 payload length of 0: nothing, Wireshark finds no jumbo
        option there); a UDP length past the IP payload gives way to it, and so does an IPv6 UDP
        length of 0; a UDP header cut short, or a UDP length below 8, is a datagram whose payload
        nothing dissects (None)."""
        end = start + incl
        net = self._network(link, data, start, end)
        if net is None:
            self.non_udp += 1
            return None
        version, pos = net
        if version == 4:
            if pos + L.IPV4_MIN_HEADER > end:
                self.non_udp += 1
                self.fragments += _cut_fragment(data, pos, end)
                return None
            ihl = (data[pos] & 0x0F) * 4
            tot, frag = struct.unpack_from("!H2xH", data, pos + 2)
            if data[pos] >> 4 != 4 or ihl < L.IPV4_MIN_HEADER or 0 < tot < ihl:
                self.non_udp += 1
                return None
            proto = data[pos + 9]
            src = data[pos + 12:pos + 16]
            ip_end = pos + tot if tot else end
            if frag & L.IPV4_FRAGMENT_MASK:
                # (Wireshark: a total length of 0 is the frame's as sent; a fragment cut short, or
                # empty, takes no part)
                sent = pos + tot if tot else start + orig
                dst = data[pos + 16:pos + 20]
                vlan = _vlan_id(link, data, start, end) if _private(src) or _private(dst) else 0
                key: tuple = (4, vlan, src, dst, proto, data[pos + 4:pos + 6])
                whole = sent > pos + ihl and sent <= end
                return self._fragment(key, (frag & 0x1FFF) * 8, bool(frag & 0x2000),
                                      data[pos + ihl:sent] if whole else None, src, proto, frame)
            pos += ihl
        else:
            if pos + L.IPV6_HEADER_LEN > end or data[pos] >> 4 != 6:
                self.non_udp += 1
                return None
            proto = data[pos + 6]
            src, dst = data[pos + 8:pos + 24], data[pos + 24:pos + 40]
            ip_end = pos + L.IPV6_HEADER_LEN + struct.unpack_from("!H", data, pos + 4)[0]
            pos += L.IPV6_HEADER_LEN
            while pos + 8 <= min(end, ip_end):
                if proto in L.IPV6_EXTENSIONS:
                    proto, pos = data[pos], pos + (data[pos + 1] + 1) * 8
                elif proto == L.IPV6_FRAGMENT and not struct.unpack_from("!H", data, pos + 2)[0] & 0xFFF9:
                    proto, pos = data[pos], pos + 8   # an atomic fragment (RFC 6946): the whole datagram
                else:
                    break
            if proto == L.IPV6_FRAGMENT:
                if pos + 8 > min(end, ip_end):
                    return self._fragment(None, 0, False, None, src, proto, frame)
                field = struct.unpack_from("!H", data, pos + 2)[0]
                key = (6, src, dst, data[pos + 4:pos + 8])     # (Wireshark: IPv6 keys no VLAN)
                whole = ip_end <= end and ip_end > pos + 8
                return self._fragment(key, field & 0xFFF8, bool(field & 1),
                                      data[pos + 8:ip_end] if whole else None, src, data[pos], frame)
        return self._udp(version, proto, src, data, pos, ip_end, end, incl, orig, frame)

    def _fragment(self, key: Optional[tuple], offset: int, more: bool, part: Optional[bytes], src: bytes,
                  proto: int, frame: int) -> Optional[tuple[bytes, int, int, Optional[bytes]]]:
        """An IP fragment (`part`: its bytes, None when the capture did not record it whole): the
        datagram it completes, taken at this frame as Wireshark does, else None (counted as no UDP
        and as a fragment not reassembled; `fragments` gives back the frames of a datagram once it
        is whole)."""
        self.non_udp += 1
        self.fragments += 1
        if key is None or part is None:
            return None
        done = self._reassembly.add(key, offset, more, part)
        if done is None:
            return None
        datagram, frames = done
        self.fragments -= frames
        self.non_udp -= 1
        return self._udp(key[0], proto, src, datagram, 0, len(datagram), len(datagram), 1, 1, frame)

    def _udp(self, version: int, proto: int, src: bytes, data: bytes, pos: int, ip_end: int, end: int,
             incl: int, orig: int, frame: int) -> Optional[tuple[bytes, int, int, Optional[bytes]]]:
        """The UDP datagram of an IP payload from `pos` to `ip_end` (the frame's bytes end at `end`)."""
        have = min(end, ip_end)
        if proto != L.IPPROTO_UDP or pos + 4 > have:     # (Wireshark shows UDP from its ports on)
            self.non_udp += 1
            self.tunnelled += proto in L.TUNNEL_PROTOCOLS
            return None
        sport, dport = struct.unpack_from("!HH", data, pos)
        body = pos + L.UDP_HEADER_LEN
        if body > have:
            return src, sport, dport, None
        ulen = struct.unpack_from("!H", data, pos + 4)[0]
        if ulen == 0 and version == 6:
            stop = ip_end
        elif ulen < L.UDP_HEADER_LEN:
            return src, sport, dport, None
        else:
            stop = pos + ulen
        if stop > ip_end:
            if ip_end == body:              # an IP payload of the UDP header alone
                return src, sport, dport, None
            stop = ip_end
        if stop > end:
            # The capture cut the frame (its snaplen): the datagram is truncated, nothing else can
            # be judged. A whole frame whose headers claim more is damage: its bytes are judged.
            if incl < orig:
                self.snap_truncated.add(frame)
            stop = end
        return src, sport, dport, data[body:stop]

    def _network(self, link: int, data: bytes, pos: int, end: int) -> Optional[tuple[int, int]]:
        """(IP version, offset of the IP header) for a frame, or None."""
        if link == L.LINKTYPE_ETHERNET:
            if pos + L.ETH_HEADER_LEN > end:
                return None
            return self._ethertype(struct.unpack_from("!H", data, pos + 12)[0], data, pos + L.ETH_HEADER_LEN, end)
        if link == L.LINKTYPE_LINUX_SLL:
            if pos + L.SLL_HEADER_LEN > end:
                return None
            return self._ethertype(struct.unpack_from("!H", data, pos + 14)[0], data, pos + L.SLL_HEADER_LEN, end)
        if link == L.LINKTYPE_LINUX_SLL2:
            if pos + L.SLL2_HEADER_LEN > end:
                return None
            return self._ethertype(struct.unpack_from("!H", data, pos)[0], data, pos + L.SLL2_HEADER_LEN, end)
        if link in (L.LINKTYPE_RAW, *L.DLT_RAW_ALIASES):
            if pos >= end:
                return None
            version = data[pos] >> 4
            return (version, pos) if version in (4, 6) else None
        if link == L.LINKTYPE_IPV4:
            return 4, pos
        if link == L.LINKTYPE_IPV6:
            return 6, pos
        if link == L.LINKTYPE_IEEE802_11_RADIOTAP:
            if pos + L.RADIOTAP_MIN_LEN > end:
                return None
            length = struct.unpack_from("<H", data, pos + 2)[0]
            return self._wlan(data, pos + length, end, self._radiotap_datapad(data, pos, min(end, pos + length)))
        if link == L.LINKTYPE_IEEE802_11:
            return self._wlan(data, pos, end, False)
        if link in (L.LINKTYPE_NULL, L.LINKTYPE_LOOP):
            if pos + L.NULL_HEADER_LEN > end:
                return None
            families = ({struct.unpack_from(">I", data, pos)[0]} if link == L.LINKTYPE_LOOP else
                        set(struct.unpack_from("<I", data, pos) + struct.unpack_from(">I", data, pos)))
            pos += L.NULL_HEADER_LEN
            if L.AF_INET in families:
                return 4, pos
            if families & set(L.AF_INET6):
                return 6, pos
            return None
        self.unknown_link += 1
        return None

    @staticmethod
    def _radiotap_datapad(data: bytes, pos: int, end: int) -> bool:
        """Whether a radiotap header's Flags say the 802.11 header after it is padded to 32 bits."""
        word = pos + 4
        present = struct.unpack_from("<I", data, word)[0]
        while struct.unpack_from("<I", data, word)[0] & L.RADIOTAP_EXT and word + 8 <= end:
            word += 4
        if not present & L.RADIOTAP_FLAGS:
            return False
        field = word + 4                                  # the fields follow the presence words
        if present & L.RADIOTAP_TSFT:
            field = pos + ((field - pos + 7) & ~7) + 8    # aligned to 8 from the header's start
        return field < end and bool(data[field] & L.RADIOTAP_DATAPAD)

    @classmethod
    def _wlan(cls, data: bytes, pos: int, end: int, datapad: bool) -> Optional[tuple[int, int]]:
        """(IP version, offset) in an 802.11 data frame carrying LLC/SNAP (a G-Link capture over the
        air), as Wireshark reads it without keys: a protected frame, a data frame without a body
        (null data) and any other frame carry none."""
        if pos + L.WLAN_HEADER_LEN > end:
            return None
        control, flags = data[pos], data[pos + 1]
        if control & 0x0F != 0x08 or control & 0x40 or flags & 0x40:  # version 0 data; null data; protected
            return None
        length = L.WLAN_HEADER_LEN + (6 if flags & 0x03 == 0x03 else 0)   # to and from DS: a fourth address
        if control & 0x80:                                   # QoS data: QoS control, HT control with Order
            length += 2 + (4 if flags & 0x80 else 0)
        if datapad:
            length = (length + 3) & ~3
        pos += length
        if pos + L.LLC_SNAP_LEN > end or data[pos:pos + 3] != L.LLC_SNAP or data[pos + 3:pos + 6] not in L.SNAP_OUIS:
            return None
        return cls._ethertype(struct.unpack_from("!H", data, pos + 6)[0], data, pos + L.LLC_SNAP_LEN, end)

    @staticmethod
    def _ethertype(et: int, data: bytes, pos: int, end: int) -> Optional[tuple[int, int]]:
        """(IP version, offset) after an EtherType at data[pos], past any VLAN tags (Ethernet, and the
        cooked captures of a tagged interface)."""
        while et in L.ETHERTYPE_VLANS and pos + L.VLAN_TAG_LEN <= end:
            et = struct.unpack_from("!H", data, pos + 2)[0]
            pos += L.VLAN_TAG_LEN
        if et == L.ETHERTYPE_IPV4:
            return 4, pos
        if et == L.ETHERTYPE_IPV6:
            return 6, pos
        return None
