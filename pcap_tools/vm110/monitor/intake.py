"""Datagrams into the analysis, judged exactly as the fast engine judges those of a file.

A datagram on the EG-Link ports that passes the quick checks (known ID, revision 0, size, CRC)
is a legal packet; anything else is decoded by the engine's own slow path (`FastEngine._slow`),
which applies `vm110.decode`'s rules. The records gathered go to the `Analysis` (and to the
live view, `tap`) when `flush` is called.

With `--crc auto` (or `--crc-order auto`) the variant is chosen as `analyze` chooses it: by the
first SNIFF EG-Link datagrams on the ports. A file is read twice for that; a stream cannot be, so
the datagrams are held until SNIFF have come, or `decide()` is called (a live link does not wait
longer than a moment), or the input ends. When, at the end, another variant validates more
packets than the one chosen, `analyze` would have judged the file again with it: `regret()`
says so (a stream cannot be judged again).
"""
from __future__ import annotations

import zlib
from collections import Counter
from typing import Callable, Optional

from .. import constants as C
from ..analysis.collect import Collected
from .. import protocol as P
from ..analysis.engine import _HDR, _LOW, _SNIFF, _U32, FastEngine, best_candidate
from ..crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, REVERSE_BITS, crc_matches, zlib_form

HOLD_MAX = 1 << 16                                 # datagrams held at most while choosing the CRC
Illegal = Callable[[int, float, str, str, list], None]


class Watched(Collected):
    """A Collected that tells `on_illegal` of each illegal packet as it is found, and keeps its
    legal packets for the live view too (`live`: (ts, frame, src, sport, packet), taken away
    by the caller)."""

    on_illegal: Optional[Illegal] = None
    live: Optional[list] = None

    def add_legal(self, ts: float, frame: int, src: bytes, sport: int, packet: bytes) -> None:
        super().add_legal(ts, frame, src, sport, packet)
        if self.live is not None:
            self.live.append((ts, frame, src, sport, packet))

    def add_illegal(self, frame: int, ts: float, src: str, ptype: str, reasons: list) -> None:
        super().add_illegal(frame, ts, src, ptype, reasons)
        if self.on_illegal is not None:
            self.on_illegal(frame, ts, src, ptype, reasons)


class Intake:
    """The judged datagrams of one stream named `name`, fed to `analysis` (and `tap`)."""

    def __init__(self, name: str, port: int, crc: str, crc_order: str, analysis, fmt: str = "") -> None:
        self.engine = FastEngine(port, crc, crc_order)
        self.ports = self.engine.ports
        self.auto = crc == "auto" or crc_order == "auto"
        self.got = Watched(path=name, engine="fast", analysis=analysis, format=fmt, ports=tuple(sorted(self.ports)),
                           crc_auto=self.auto)
        self.got.live = []
        self.variant: Optional[str] = None if self.auto else crc
        self.order: Optional[str] = None if self.auto else crc_order
        self.candidates = self.engine.candidates()
        self.sniffed: Counter = Counter()
        self.sniff_seen = 0
        self.held: list[tuple] = []
        if not self.auto:
            self._set(crc, crc_order)

    @property
    def deciding(self) -> bool:
        """Datagrams are held while the CRC variant is chosen."""
        return self.variant is None

    def _set(self, variant: str, order: str) -> None:
        self.variant, self.order = variant, order
        self.got.crc_variant, self.got.crc_order = variant, order
        self.reversed_bytes, self.xor, stored_order = zlib_form(variant, order)
        self.stored = _U32[stored_order].unpack_from

    def datagram(self, reader, ts: float, src: bytes, sport: int, dport: int, payload: Optional[bytes],
                 frame: int) -> None:
        """One UDP datagram of the stream (reader: the StreamReader that read it; payload None: one
        whose payload nothing dissects)."""
        if self.variant is None:
            self.held.append((reader, ts, src, sport, dport, payload, frame))
            if (sport in self.ports or dport in self.ports) and payload is not None and len(payload) >= C.OVERHEAD:
                size = P.SIZE.unpack_from(payload, P.SIZE_OFFSET)[0]
                self.sniffed.update(crc_matches(payload, min(C.PREFIX_LEN + size, len(payload) - C.CRC_LEN)))
                self.sniff_seen += 1
            if self.sniff_seen >= _SNIFF or len(self.held) >= HOLD_MAX:
                self.decide()
            return
        self._judge(reader, ts, src, sport, dport, payload, frame)

    def decide(self) -> None:
        """Choose the CRC variant now (from what was sniffed) and judge the held datagrams."""
        if self.variant is not None:
            return
        cands = self.candidates
        if self.sniffed:
            best = best_candidate(cands, self.sniffed)
        else:                                   # as analyze: the documented default, or the one asked for
            best = (DEFAULT_VARIANT if len({v for v, _ in cands}) > 1 else cands[0][0],
                    DEFAULT_BYTE_ORDER if len({o for _, o in cands}) > 1 else cands[0][1])
        self._set(*best)
        held, self.held = self.held, []
        for item in held:
            self._judge(*item)

    def regret(self) -> Optional[tuple[str, str]]:
        """The variant `analyze` would have judged the packets with in the end, when not the
        chosen one (it validates more of them)."""
        counts, cands = self.got.crc_counts, self.candidates
        if not self.auto or self.variant is None:
            return None
        best = best_candidate(cands, counts)
        chosen = (self.variant, self.order)
        return best if best != chosen and counts[best] > counts[chosen] else None

    def _judge(self, reader, ts: float, src: bytes, sport: int, dport: int, payload: Optional[bytes],
               frame: int) -> None:
        got, ports = self.got, self.ports
        # A datagram the snaplen cut short is judged by the slow path (truncated), as the engine's
        # do; one whose payload nothing dissects (None) is other UDP there.
        if (payload is not None and (sport in ports or dport in ports) and len(payload) >= C.OVERHEAD
                and frame not in reader.snap_truncated):
            n = len(payload)
            pid, rev, size = _HDR.unpack_from(payload)
            low = _LOW.get(pid)
            if low is not None and not rev and n == size + C.OVERHEAD and low <= size <= C.MAX_PAYLOAD:
                data = payload.translate(REVERSE_BITS) if self.reversed_bytes else payload
                if zlib.crc32(data[:-4]) ^ self.xor == self.stored(data, n - C.CRC_LEN)[0]:
                    got.eglink += 1
                    got.crc_checked += 1
                    got.crc_counts[(self.variant, self.order)] += 1
                    got.add_legal(ts, frame, src, sport, payload)
                    return
        assert self.variant is not None and self.order is not None
        self.engine._slow(got, reader, self.variant, self.order, ts, src, sport, dport, payload, frame)
        # Judged: counted and let go (the reader keeps the number of each frame the snaplen cut,
        # millions on a link watched for days through `tcpdump -s 64`).
        reader.snap_truncated.discard(frame)

    def sync(self, reader) -> None:
        """The file-level facts of the reader so far, as the engine sets them at the end."""
        got = self.got
        got.format = reader.format
        got.frames, got.non_udp, got.fragments = reader.frames, reader.non_udp, reader.fragments
        got.unread, got.tunnelled = reader.unknown_link, reader.tunnelled
        got.udp = reader.frames - reader.non_udp
        got.problem, got.damage = reader.problem, reader.damage
        got.dropped = reader.drops.report()
        got.first_ts, got.last_ts = reader.first_ts, reader.last_ts
        got.earliest_ts, got.latest_ts = reader.earliest, reader.latest
        got.link_types = sorted(reader.link_types)
