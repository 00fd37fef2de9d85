"""The fast engine: one streaming pass over the file into compact arrays (`Collected`).

Per datagram the hot path does a handful of C-level operations: a port test, one `struct`
call for the header, a dict lookup for the sender, a structural test, the CRC (zlib, see
`_hot_crc`) and a few `array.append`s. Anything unusual (illegal, unknown sender, other port)
takes `_slow`, which decodes with `vm110.decode` and so applies exactly its rules.
"""
from __future__ import annotations

import struct
import zlib
from typing import Callable, Optional

from .. import constants as C
from ..capture.reader import CaptureReader
from ..crc import BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, MASK, VARIANTS, _REVERSE, crc32
from ..decode import decode
from .collect import CODE_OF_ID, STATE_LEN, VRPI_CODE, Collected, Sender, address

_HDR = struct.Struct("<4sHHHHIH")           # packet ID, header, first payload u16
_LOW = {CODE_OF_ID[t.value.encode()]: C.PAYLOAD_BOUNDS[t][0] for t in C.PacketType}
_SNIFF = 256                                # EG-Link packets looked at to guess the CRC variant
TRUNCATED = C.Problem.TRUNCATED.value
Progress = Callable[[int, int], None]


def crc_matches(data: bytes, end: int) -> set[tuple[str, str]]:
    """Every (variant, byte order) under which the CRC at `end` validates `data[:end]`."""
    stored = data[end:end + C.CRC_LEN]
    got = set()
    for variant in VARIANTS:
        value = crc32(data[:end], variant)
        for order in BYTE_ORDERS:
            if value == int.from_bytes(stored, order):
                got.add((variant, order))
    return got


def _hot_crc(variant: str, order: str) -> tuple[bool, int, str]:
    """(work on bit-reversed bytes, XOR, byte order to read the stored CRC) for the hot path.

    iso-hdlc is zlib's CRC; jamcrc is it XOR 0xFFFFFFFF. mpeg2 is bitrev(zlib(rev(bytes)) ^ MASK),
    so on the bit-reversed packet (`bytes.translate`) it compares zlib(...) ^ MASK with the
    stored CRC bit-reversed, which is the reversed stored bytes read in the other byte order;
    bzip2 is mpeg2 XOR 0xFFFFFFFF.
    """
    other = BYTE_ORDERS[1 - BYTE_ORDERS.index(order)]
    return {
        "iso-hdlc": (False, 0, order), "jamcrc": (False, MASK, order),
        "mpeg2": (True, MASK, other), "bzip2": (True, 0, other),
    }[variant]


class FastEngine:
    """Analyse one capture file with the streaming reader."""

    def __init__(self, port: int = C.INPUT_PORT, crc: str = "auto", crc_order: str = "auto",
                 progress: Optional[Progress] = None) -> None:
        self.ports = frozenset((port, port + C.OUTPUT_PORT_OFFSET))
        self.crc, self.crc_order = crc, crc_order
        self.progress = progress

    def collect(self, path: str) -> Collected:
        variant = DEFAULT_VARIANT if self.crc == "auto" else self.crc
        order = DEFAULT_BYTE_ORDER if self.crc_order == "auto" else self.crc_order
        sniffed = self._sniff(path) if "auto" in (self.crc, self.crc_order) else None
        if sniffed:
            variant, order = sniffed
        got = self._pass(path, variant, order)
        best = self._best(got)
        if best != (variant, order) and got.crc_counts[best] > got.crc_counts[(variant, order)]:
            got = self._pass(path, *best)     # the sniffed guess was wrong: judge again with the best
        return got

    def _candidates(self) -> list[tuple[str, str]]:
        variants = VARIANTS if self.crc == "auto" else (self.crc,)
        orders = BYTE_ORDERS if self.crc_order == "auto" else (self.crc_order,)
        return [(v, o) for v in variants for o in orders]

    def _best(self, got: Collected) -> tuple[str, str]:
        # Ties go to the earliest candidate: the documented default comes first.
        candidates = self._candidates()
        return max(candidates, key=lambda c: (got.crc_counts[c], -candidates.index(c)))

    def _sniff(self, path: str) -> Optional[tuple[str, str]]:
        counts: dict[tuple[str, str], int] = {}
        seen = 0
        for ts, src, sport, dport, payload, frame in CaptureReader(path):
            if (sport in self.ports or dport in self.ports) and len(payload) >= C.OVERHEAD:
                size = struct.unpack_from("<H", payload, 10)[0]
                end = min(C.PREFIX_LEN + size, len(payload) - C.CRC_LEN)
                for combo in crc_matches(payload, end):
                    counts[combo] = counts.get(combo, 0) + 1
                seen += 1
                if seen >= _SNIFF:
                    break
        candidates = self._candidates()
        if not counts:
            return None
        return max(candidates, key=lambda c: (counts.get(c, 0), -candidates.index(c)))

    def _pass(self, path: str, variant: str, order: str) -> Collected:
        reader = CaptureReader(path)
        got = Collected(path=path, engine="fast", format=reader.format, ports=tuple(sorted(self.ports)),
                        crc_variant=variant, crc_order=order,
                        crc_auto=self.crc == "auto" or self.crc_order == "auto")
        streams: dict = {}
        state_ids: dict = {}
        states = got.states
        ports = self.ports
        reversed_bytes, xor, stored_order = _hot_crc(variant, order)
        rev_table = _REVERSE
        crc = zlib.crc32
        from_bytes = int.from_bytes
        unpack = _HDR.unpack_from
        vrpi_code = VRPI_CODE
        max_payload = C.MAX_PAYLOAD
        hot_valid = udp = 0
        slow = self._slow
        total = reader.size
        for batch in reader.batches():
            udp += len(batch)
            for ts, src, sport, dport, payload, frame in batch:
                if sport not in ports and dport not in ports:
                    slow(got, reader, streams, state_ids, variant, order, ts, src, sport, payload, frame, False)
                    continue
                n = len(payload)
                if n < 22:
                    slow(got, reader, streams, state_ids, variant, order, ts, src, sport, payload, frame, True)
                    continue
                pid, rev, origin, serial, size, spare, aux = unpack(payload)
                entry = streams.get((pid, src, sport, origin))
                if entry is None or rev or n != size + 20:
                    slow(got, reader, streams, state_ids, variant, order, ts, src, sport, payload, frame, True)
                    continue
                add_ts, add_serial, code, low, add_code, add_frame, add_aux, add_size, add_state = entry
                if not low <= size <= max_payload:
                    slow(got, reader, streams, state_ids, variant, order, ts, src, sport, payload, frame, True)
                    continue
                if reversed_bytes:
                    t = payload.translate(rev_table)
                    ok = crc(t[:-4]) ^ xor == from_bytes(t[-4:], stored_order)
                else:
                    ok = crc(payload[:-4]) ^ xor == from_bytes(payload[-4:], stored_order)
                if not ok:
                    slow(got, reader, streams, state_ids, variant, order, ts, src, sport, payload, frame, True)
                    continue
                hot_valid += 1
                if code == vrpi_code:
                    key = payload[16:30]
                    sid = state_ids.get(key)
                    if sid is None:
                        sid = state_ids[key] = len(states)
                        states.append(key)
                    add_state(sid)
                add_ts(ts)
                add_serial(serial)
                add_code(code)
                add_frame(frame)
                add_aux(aux)
                add_size(size)
            if self.progress is not None:
                self.progress(reader.bytes_read, total)
        got.eglink += hot_valid
        got.crc_checked += hot_valid
        got.crc_counts[(variant, order)] += hot_valid
        got.udp = udp
        got.frames, got.non_udp, got.fragments = reader.frames, reader.non_udp, reader.fragments
        got.snap_truncated, got.problem = len(reader.snap_truncated), reader.problem
        got.first_ts, got.last_ts = reader.first_ts, reader.last_ts
        got.link_types = sorted(reader.link_types)
        return got

    def _slow(self, got: Collected, reader: CaptureReader, streams: dict, state_ids: dict, variant: str,
              order: str, ts: float, src: bytes, sport: int, payload: bytes, frame: int, on_port: bool) -> None:
        n = len(payload)
        if not on_port:
            # Heuristic for other ports: a known packet ID and a size consistent with the length.
            if not C.OVERHEAD <= n <= C.MAX_PACKET or payload[:C.ID_LEN] not in CODE_OF_ID \
                    or n != C.OVERHEAD + struct.unpack_from("<H", payload, 10)[0]:
                got.other_udp += 1
                return
        got.eglink += 1
        fields = decode(payload, variant, order)
        problems = list(fields["problems"])
        if n >= C.OVERHEAD:
            got.crc_checked += 1
            end = min(C.PREFIX_LEN + fields["size"], n - C.CRC_LEN)
            got.crc_counts.update(crc_matches(payload, end))
        if frame in reader.snap_truncated:
            problems = [TRUNCATED]       # the capture cut it: nothing else can be judged
        where = address(src, sport)
        if problems:
            got.add_illegal(frame, ts, where, fields.get("type", ""), problems)
            return
        add_legal(got, streams, state_ids, ts, src, sport, payload, frame, fields)


def add_legal(got: Collected, streams: dict, state_ids: dict, ts: float, src: bytes, sport: int,
              payload: bytes, frame: int, fields: dict) -> None:
    """Record one legal packet from its bytes and its decoded header."""
    aux = struct.unpack_from("<H", payload, C.PREFIX_LEN)[0]
    state = payload[C.PREFIX_LEN:C.PREFIX_LEN + STATE_LEN]
    record(got, streams, state_ids, ts, src, sport, payload[:C.ID_LEN], fields["origin"], fields["direction"],
           fields["serial"], fields["size"], aux, state, frame)


def record(got: Collected, streams: dict, state_ids: dict, ts: float, src: bytes, sport: int, pid: bytes,
           origin: int, direction: str, serial: int, size: int, aux: int, state: bytes, frame: int) -> None:
    """Record one legal packet (creating its sender and hot-path entry when new). `aux` is the
    command ID or VRPO packet number, `state` the VRPI state bytes (see collect.STATE)."""
    code = CODE_OF_ID[pid]
    key = (pid, src, sport, origin)
    entry = streams.get(key)
    if entry is None:
        skey = (direction, origin, src, sport)
        sender = got.senders.get(skey)
        if sender is None:
            sender = got.senders[skey] = Sender(direction, origin, address(src, sport))
        entry = streams[key] = (sender.ts.append, sender.serial.append, code, _LOW[code], sender.code.append,
                                sender.frame.append, sender.aux.append, sender.size.append, sender.state.append)
    add_ts, add_serial, code, _, add_code, add_frame, add_aux, add_size, add_state = entry
    if code == VRPI_CODE:
        sid = state_ids.get(state)
        if sid is None:
            sid = state_ids[state] = len(got.states)
            got.states.append(state)
        add_state(sid)
    add_ts(ts)
    add_serial(serial)
    add_code(code)
    add_frame(frame)
    add_aux(aux)
    add_size(size)
