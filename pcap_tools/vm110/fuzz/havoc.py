"""Mutation of corpus cases in coverage-guided mode: at the field level (fields from the protocol
declaration, values at and beyond their boundaries, enums, dictionary tokens in text fields), at
the byte level (AFL-style havoc: bit flips, interesting values, arithmetic, block changes),
splicing two cases' packet sequences, and changes of the sequence itself. Size and CRC are
recomputed afterwards unless the packet means to break them (`raw`)."""
from __future__ import annotations

import random
from typing import Callable

from .. import constants as C
from ..crc import crc_bytes
from . import mutate as M
from .corpus import Entry, Packet
from .fields import COMMAND_ID_AT, SIZE_AT, FieldSpot, spots

INTERESTING_8 = (-128, -1, 0, 1, 16, 32, 64, 100, 127)
INTERESTING_16 = (-32768, -129, 128, 255, 256, 512, 1000, 1024, 4096, 32767)
INTERESTING_32 = (-2147483648, -100663046, -32769, 32768, 65535, 65536, 100663045, 2147483647)
_ARITH_MAX = 35
_MAX_PACKETS = 8
_MAX_LEN = C.MAX_PACKET + 64
_MAX_DELAY_MS = 20.0
_DELAY_SHARE = 0.05
_BREAK = 0.08                  # share of byte mutations that keep a broken size or CRC on purpose


_VRCI_TEMPLATE = M.build(C.PacketType.VRCI, 0, M.default_fields(C.PacketType.VRCI))
_COMMAND_DATA = next(s.offset for s in spots(b"VRCI") if s.name == "command_data")


def fix(data: bytes) -> bytes:
    """Size and CRC recomputed for the payload the packet carries."""
    if len(data) < C.OVERHEAD:
        return data
    size = len(data) - C.OVERHEAD
    body = bytearray(data[:-C.CRC_LEN])
    body[SIZE_AT:SIZE_AT + 2] = size.to_bytes(2, "little")
    return bytes(body) + crc_bytes(bytes(body))


class Mutator:
    def __init__(self, rng: random.Random, tokens: list[bytes], preferred: list[bytes] = ()) -> None:  # type: ignore[assignment]
        self.rng = rng
        self.tokens = tokens              # every token: the dictionary's, then the program's strings
        self.preferred = list(preferred)  # the user's dictionary: half the picks
        self.ops: list[Callable[[Entry, Entry], None]] = [
            self.field, self.field, self.field, self.token, self.token, self.command, self.havoc, self.havoc,
            self.splice, self.sequence]

    def _token(self) -> bytes:
        if self.preferred and self.rng.random() < 0.5:
            return self.rng.choice(self.preferred)
        return self.rng.choice(self.tokens)

    def mutate(self, entry: Entry, other: Entry) -> Entry:
        """A new case from `entry` (`other`: a second corpus case, for splicing): 1 to 4 stacked changes."""
        # Waits stay with the cases that are about time (the sweep's): a mutant keeps no delay, stream
        # pause or withholding (only the sequence change adds a short delay, rarely), so that it
        # needs no waiting.
        new = Entry([Packet(p.data, 0.0, p.raw, p.expect_ack) for p in entry.packets],
                    dict(entry.stream) if entry.stream else None)
        for _ in range(1 << self.rng.randrange(3)):
            self.rng.choice(self.ops)(new, other)
        del new.packets[_MAX_PACKETS:]
        return new

    def _packet(self, entry: Entry) -> Packet:
        if not entry.packets:
            entry.packets.append(Packet(M.build(C.PacketType.VRCI, 0, M.default_fields(C.PacketType.VRCI))))
        return self.rng.choice(entry.packets)

    def _spot(self, p: Packet) -> FieldSpot | None:
        choices = [s for s in spots(p.data[:C.ID_LEN]) if s.offset + s.width <= len(p.data) - C.CRC_LEN
                   and s.name not in ("serial", "size")]
        return self.rng.choice(choices) if choices else None

    def field(self, entry: Entry, other: Entry) -> None:
        """One field of one packet to a boundary value, an enum neighbour or a random value."""
        p = self._packet(entry)
        spot = self._spot(p)
        if spot is None:
            self.havoc(entry, other)
            return
        if spot.text:
            value = self.rng.choice(M.bytes_values(spot.width, self.rng))
        else:
            boundary = self.rng.random() < 0.8
            number = self.rng.choice(spot.interesting()) if boundary else self.rng.randrange(1 << 8 * spot.width)
            value = spot.pack(number)
        self._put(p, spot.offset, value[:spot.width])

    def token(self, entry: Entry, other: Entry) -> None:
        """A dictionary token at the start of a text field (where commands are), or anywhere."""
        if not self.tokens:
            self.field(entry, other)
            return
        p = self._packet(entry)
        token = self._token()
        spot = self._spot(p)
        texts = [s for s in spots(p.data[:C.ID_LEN]) if s.text]
        if texts and self.rng.random() < 0.75:
            spot = self.rng.choice(texts)
            at = spot.offset if self.rng.random() < 0.7 else spot.offset + self.rng.randrange(spot.width)
            self._put(p, at, token[:spot.offset + spot.width - at])
        elif spot is not None:
            self._put(p, spot.offset, token[:spot.width])
        else:
            self._put(p, self.rng.randrange(max(1, len(p.data))), token)

    def command(self, entry: Entry, other: Entry) -> None:
        """A new VRCI whose command data starts with a dictionary token, anywhere in the sequence:
        commands are where a controller compares strings, and some take a state earlier ones made."""
        data = self._token()[:C.COMMAND_DATA_LEN] if self.tokens else b""
        body = bytearray(_VRCI_TEMPLATE)
        body[COMMAND_ID_AT:COMMAND_ID_AT + 2] = self.rng.randrange(1 << 16).to_bytes(2, "little")
        body[_COMMAND_DATA:_COMMAND_DATA + C.COMMAND_DATA_LEN] = data.ljust(C.COMMAND_DATA_LEN, b"\0")
        entry.packets.insert(self.rng.randrange(len(entry.packets) + 1), Packet(fix(bytes(body))))

    def _put(self, p: Packet, at: int, value: bytes) -> None:
        data = bytearray(p.data)
        data[at:at + len(value)] = value
        p.data = bytes(data) if p.raw else fix(bytes(data))

    def havoc(self, entry: Entry, other: Entry) -> None:
        """AFL-style byte changes on one packet, 1 to 8 of them."""
        p = self._packet(entry)
        data = bytearray(p.data)
        r = self.rng
        for _ in range(1 << r.randrange(4)):
            if not data:
                data.append(0)
            kind = r.randrange(9)
            at = r.randrange(len(data))
            if kind == 0:
                data[at] ^= 1 << r.randrange(8)
            elif kind == 1:
                data[at] = r.choice(INTERESTING_8) & 0xFF
            elif kind == 2 and at + 2 <= len(data):
                data[at:at + 2] = (r.choice(INTERESTING_16) & 0xFFFF).to_bytes(2, r.choice(("little", "big")))
            elif kind == 3 and at + 4 <= len(data):
                data[at:at + 4] = (r.choice(INTERESTING_32) & 0xFFFFFFFF).to_bytes(4, r.choice(("little", "big")))
            elif kind == 4:
                data[at] = (data[at] + r.choice((-1, 1)) * r.randint(1, _ARITH_MAX)) & 0xFF
            elif kind == 5:
                data[at] = r.randrange(256)
            elif kind == 6 and len(data) > C.OVERHEAD:
                del data[at:at + r.randint(1, 8)]
            elif kind == 7 and len(data) < _MAX_LEN:
                data[at:at] = bytes(data[at:at + r.randint(1, 8)]) or b"\0"
            elif kind == 8:
                n = r.randint(1, 8)
                data[at:at + n] = bytes([r.randrange(256)]) * min(n, len(data) - at)
        p.raw = p.raw or r.random() < _BREAK
        p.data = bytes(data) if p.raw else fix(bytes(data))

    def splice(self, entry: Entry, other: Entry) -> None:
        """Packets of a second case after (or instead of the tail of) this one's: state reached by
        one case, explored by another's packets."""
        if not other.packets:
            self.sequence(entry, other)
            return
        cut = self.rng.randrange(len(entry.packets) + 1)
        start = self.rng.randrange(len(other.packets))
        entry.packets[cut:] = [Packet(p.data, p.delay_ms, p.raw, p.expect_ack) for p in other.packets[start:]]

    def sequence(self, entry: Entry, other: Entry) -> None:
        """A packet repeated, dropped or moved; rarely a delay before one (waits cost cases per second)."""
        r, packets = self.rng, entry.packets
        kind = r.randrange(4)
        if kind == 0 and packets:
            p = r.choice(packets)
            packets.insert(r.randrange(len(packets) + 1), Packet(p.data, 0.0, p.raw, p.expect_ack))
        elif kind == 1 and len(packets) > 1:
            del packets[r.randrange(len(packets))]
        elif kind == 2 and len(packets) > 1:
            packets.insert(r.randrange(len(packets)), packets.pop())
        elif packets and r.random() < _DELAY_SHARE:
            r.choice(packets).delay_ms = r.choice((1.0, 5.0, _MAX_DELAY_MS))
