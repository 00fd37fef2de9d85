"""Network impairments between a sender and its receivers, reproducible from a seed.

Random loss, duplication, reordering, delay with jitter and CRC corruption; mirror copies (a
switch mirror port showing the capture a packet twice, 0.05-3 ms apart: only the tap sees the
copy, the receivers get the packet once); scheduled outages
(nothing gets through), type-selective drops (e.g. every VRAO for two seconds: a failed command)
and scheduled manglings that turn the next packet illegal for a chosen reason of
interpretation.md. `Impairer.apply` says what arrives, when, why it is illegal and whether the
receivers get it: that is the event log the ground truth is made from.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Optional

from .. import constants as C
from .. import protocol as P
from ..crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, crc_bytes
from .clock import ms, seconds

# Order in which `vm110.decode` lists the reasons.
REASON_ORDER = tuple(p.value for p in C.Problem)
OVERSIZE = C.MAX_PAYLOAD + 8
MIRROR_DELAY_MS = (0.05, 3.0)
REORDER_SPREAD = (0.5, 1.5)    # a packet held back waits this many times `reorder_ms`
# What arrives: (arrival time µs, bytes, illegal reasons, delivered to the receivers (False: a
# mirror copy only the tap sees)).
Copy = tuple[int, bytes, tuple[str, ...], bool]


def _set_header(body: bytes, name: str, value: int) -> bytes:
    """`body` with one header field replaced."""
    fields = list(P.HEADER.unpack_from(body))
    fields[1 + [f.name for f in P.HEADER_FIELDS].index(name)] = value
    return P.HEADER.pack(*fields) + body[P.HEADER.size:]


@dataclass
class Impairment:
    loss: float = 0.0            # % of packets lost
    duplicate: float = 0.0       # % delivered twice
    mirror: float = 0.0          # % seen twice by the tap (a mirror port), delivered once
    reorder: float = 0.0         # % held back by about `reorder_ms`, so later packets overtake them
    reorder_ms: float = 150.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0       # extra delay, uniform in [0, jitter]
    corrupt: float = 0.0         # % with a corrupted CRC
    outages: tuple[tuple[float, float], ...] = ()                 # (start s, end s): all lost
    drops: tuple[tuple[float, float, tuple[str, ...]], ...] = ()  # (start, end, types): those lost
    mangles: tuple[tuple[float, str, Optional[str]], ...] = ()    # (at s, reason[+reason], type or None)
    only: tuple[str, ...] = ()   # random loss/duplication/reordering/delay/corruption hit only these types
    loss_from: float = 0.0       # s: random loss spares what is sent before (its draws are made all the same)
    seed: int = 0

    def active(self) -> bool:
        return any((self.loss, self.duplicate, self.mirror, self.reorder, self.delay_ms, self.jitter_ms, self.corrupt,
                    self.outages, self.drops, self.mangles))


def mangle(data: bytes, reasons: str, variant: str = DEFAULT_VARIANT,
           order: str = DEFAULT_BYTE_ORDER) -> tuple[bytes, tuple[str, ...]]:
    """Turn a legal packet illegal for exactly the given reasons ("revision", "revision+bad_crc")."""
    wanted = reasons.split("+")
    unknown = set(wanted) - set(REASON_ORDER)
    if unknown:
        raise ValueError(f"unknown illegal reason {', '.join(sorted(unknown))}; choose from {', '.join(REASON_ORDER)}")
    body, trailer = data[:-C.CRC_LEN], b""
    if C.Problem.UNKNOWN_ID.value in wanted:
        body = b"VRX" + body[3:]                        # keeps the direction letter, no known type
    if C.Problem.REVISION.value in wanted:
        body = _set_header(body, "revision", 1)
    if C.Problem.SIZE_TOO_LARGE.value in wanted:
        payload = body[C.PREFIX_LEN:].ljust(OVERSIZE, b"\0")
        body = _set_header(body, "size", len(payload))[:C.PREFIX_LEN] + payload
    if C.Problem.TRUNCATED.value in wanted:
        low = P.PAYLOAD_BOUNDS[C.PacketType(data[:C.ID_LEN].decode("latin-1"))][0]
        payload = body[C.PREFIX_LEN:C.PREFIX_LEN + max(1, low // 2)]      # shorter than the type's layout
        body = _set_header(body, "size", len(payload))[:C.PREFIX_LEN] + payload
    if C.Problem.SIZE_MISMATCH.value in wanted:
        trailer = b"\xde\xad\xbe\xef"                   # bytes beyond 20 + size: the CRC stays valid
    crc = crc_bytes(body, variant, order)
    if C.Problem.BAD_CRC.value in wanted:
        crc = crc[:-1] + bytes((crc[-1] ^ 0x5A,))
    return body + crc + trailer, tuple(r for r in REASON_ORDER if r in wanted)


class Impairer:
    """Applies one `Impairment` to one sender's packets. Times are µs; windows count from `t0`."""

    def __init__(self, imp: Impairment, name: str, variant: str = DEFAULT_VARIANT,
                 order: str = DEFAULT_BYTE_ORDER, t0: int = 0) -> None:
        self.imp = imp
        self._rng = random.Random(f"{name}:{imp.seed}")
        self._variant, self._order = variant, order
        self._delay = ms(imp.delay_ms)
        self._loss, self._duplicate, self._mirror, self._only = imp.loss, imp.duplicate, imp.mirror, imp.only
        self._rare = bool(imp.corrupt or imp.jitter_ms or imp.reorder)   # checked in that order, after loss
        self.set_origin(t0)

    def set_origin(self, t0: int) -> None:
        imp = self.imp
        self._outages = [(t0 + seconds(a), t0 + seconds(b)) for a, b in imp.outages]
        self._drops = [(t0 + seconds(a), t0 + seconds(b), frozenset(types)) for a, b, types in imp.drops]
        self._mangles = sorted((t0 + seconds(at), reason, ptype) for at, reason, ptype in imp.mangles)
        self._scheduled = bool(self._outages or self._drops or self._mangles)
        self._loss_from = t0 + seconds(imp.loss_from)

    def apply(self, data: bytes, now: int, ptype: str) -> list[Copy]:
        """Every copy that arrives (`Copy`); [] when lost."""
        problems: tuple[str, ...] = ()
        if self._scheduled:
            if self._outages and any(a <= now < b for a, b in self._outages):
                return []
            if self._drops and any(a <= now < b and ptype in types for a, b, types in self._drops):
                return []
            if self._mangles:
                data, problems = self._scheduled_mangle(data, now, ptype)
        copies = self._network(data, now, ptype, problems)
        if copies and self._mirror and self._rng.random() * 100 < self._mirror:     # the tap's, any type
            t, data, problems, _ = copies[0]
            copies.append((t + ms(self._rng.uniform(*MIRROR_DELAY_MS)), data, problems, False))
        return copies

    def _network(self, data: bytes, now: int, ptype: str, problems: tuple[str, ...]) -> list[Copy]:
        """The random impairments of the network (`only` selects the types they hit)."""
        if self._only and ptype not in self._only:
            return [(now, data, problems, True)]
        rng, loss, duplicate = self._rng, self._loss, self._duplicate
        if loss and rng.random() * 100 < loss and now >= self._loss_from:
            return []
        delay = self._delay
        if self._rare:
            imp = self.imp
            if not problems and imp.corrupt and rng.random() * 100 < imp.corrupt:
                data, problems = mangle(data, C.Problem.BAD_CRC.value, self._variant, self._order)
            if imp.jitter_ms:
                delay += ms(rng.uniform(0, imp.jitter_ms))
            if imp.reorder and rng.random() * 100 < imp.reorder:
                delay += ms(rng.uniform(*REORDER_SPREAD) * imp.reorder_ms)
        if duplicate and rng.random() * 100 < duplicate:
            return [(now + delay, data, problems, True),
                    (now + delay + ms(rng.uniform(0.05, 2.0)), data, problems, True)]
        return [(now + delay, data, problems, True)]

    def _scheduled_mangle(self, data: bytes, now: int, ptype: str) -> tuple[bytes, tuple[str, ...]]:
        for i, (at, reason, only) in enumerate(self._mangles):
            if at > now:
                break
            if only is None or only == ptype:
                del self._mangles[i]
                return mangle(data, reason, self._variant, self._order)
        return data, ()
