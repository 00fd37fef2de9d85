"""Shrink a triggering packet to the smallest difference from its valid twin that still triggers.

The difference is a set of edits: changed bytes, plus one tail (bytes beyond the twin's length)
or one cut (the packet is shorter). Delta debugging (ddmin) finds a minimal set of edits; a tail
is then shortened by bisection. When the packet's CRC is valid, edits are made on the packet
without its CRC and the CRC is recomputed for each candidate, so that "valid CRC" stays part of
the packet rather than becoming a difference of its own.
"""
from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from typing import Callable, Optional

from .. import constants as C
from ..crc import crc_bytes
from ..decode import crc_span, decode
from .mutate import SIZE_OFFSET

Predicate = Callable[[bytes], bool]


@dataclass
class Result:
    packet: bytes
    differences: int          # bytes that differ from the twin (length change counted in bytes)
    trials: int
    complete: bool            # False when the budget ran out first


def _strip_crc(data: bytes) -> Optional[bytes]:
    """The packet without its CRC when the CRC is valid there, else None."""
    if len(data) < C.OVERHEAD or C.Problem.BAD_CRC.value in decode(data)["problems"]:
        return None
    end = crc_span(data, struct.unpack_from("<H", data, SIZE_OFFSET)[0])
    return data[:end] + data[end + C.CRC_LEN:]


def _size_fits(content: bytes) -> bool:
    """`size` (of a packet without its CRC) counts exactly the bytes after the prefix."""
    return len(content) >= C.PREFIX_LEN and struct.unpack_from("<H", content, SIZE_OFFSET)[0] == \
        len(content) - C.PREFIX_LEN


def _with_crc(content: bytes) -> bytes:
    if len(content) < C.PREFIX_LEN:
        return content + crc_bytes(content)
    end = min(C.PREFIX_LEN + struct.unpack_from("<H", content, SIZE_OFFSET)[0], len(content))
    return content[:end] + crc_bytes(content[:end]) + content[end:]


def difference(a: bytes, b: bytes) -> int:
    return sum(x != y for x, y in zip(a, b)) + abs(len(a) - len(b))


def minimize(packet: bytes, twin: bytes, triggers: Predicate, max_trials: int = 40,
             budget_s: float = 30.0) -> Result:
    """Minimise `packet` (which triggers) towards `twin` (valid); `triggers` runs one trial."""
    deadline = time.time() + budget_s
    trials = 0
    content, base = _strip_crc(packet), _strip_crc(twin)
    fix = content is not None and base is not None
    if not fix:
        content, base = packet, twin
    assert content is not None and base is not None
    # A legal packet longer than its twin (`size` matching its payload): `size` follows the length
    # of each candidate, or every shorter tail would be a size mismatch, another defect.
    sized = fix and _size_fits(content) and _size_fits(base)
    size_bytes = range(SIZE_OFFSET, SIZE_OFFSET + 2) if sized else range(0)
    edits: list[object] = [i for i in range(min(len(content), len(base)))
                           if content[i] != base[i] and i not in size_bytes]
    if len(content) != len(base):
        edits.append("length")
    cache: dict[bytes, bool] = {packet: True, twin: False}

    def build(chosen: list[object], tail: Optional[int] = None) -> bytes:
        out = bytearray(base)
        if "length" in chosen:
            if len(content) < len(base):
                out = out[:len(content)]
            else:
                out += content[len(base):] if tail is None else content[len(base):len(base) + tail]
        for i in chosen:
            if isinstance(i, int):
                out[i] = content[i]
        if sized:
            struct.pack_into("<H", out, SIZE_OFFSET, len(out) - C.PREFIX_LEN)
        return _with_crc(bytes(out)) if fix else bytes(out)

    def test(candidate: bytes) -> bool:
        nonlocal trials
        if candidate not in cache:
            if trials >= max_trials or time.time() > deadline:
                raise _OutOfBudget
            trials += 1
            cache[candidate] = triggers(candidate)
        return cache[candidate]

    best = edits
    complete = True
    try:
        best = ddmin(edits, lambda chosen: test(build(chosen)))
        if "length" in best and len(content) > len(base):
            best_tail = _shrink_tail(len(content) - len(base), lambda n: test(build(best, n)))
            result = build(best, best_tail)
        else:
            result = build(best)
    except _OutOfBudget:
        complete = False
        result = build(best)
        if not cache.get(result, False):
            result = packet
    return Result(result, difference(result, twin), trials, complete)


class _OutOfBudget(Exception):
    pass


def ddmin(edits: list[object], test: Callable[[list[object]], bool]) -> list[object]:
    """Zeller's ddmin: a 1-minimal subset of `edits` for which `test` holds."""
    n = 2
    while len(edits) >= 2:
        size = max(1, len(edits) // n)
        chunks = [edits[i:i + size] for i in range(0, len(edits), size)]
        for chunk in chunks:
            if test(chunk):
                edits, n = chunk, 2
                break
        else:
            for chunk in chunks:
                rest = [e for e in edits if e not in chunk]
                if rest and test(rest):
                    edits, n = rest, max(n - 1, 2)
                    break
            else:
                if n >= len(edits):
                    break
                n = min(len(edits), 2 * n)
    return edits


def _shrink_tail(length: int, test: Callable[[int], bool]) -> int:
    """The shortest tail (prefix of the original tail) that still triggers, by bisection."""
    low, high = 0, length          # test(high) holds; test(low) is the twin plus nothing
    while high - low > 1:
        mid = (low + high) // 2
        if test(mid):
            high = mid
        else:
            low = mid
    return high
