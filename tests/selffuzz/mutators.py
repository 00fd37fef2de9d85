"""File-level mutations, as Wireshark's tools/fuzz-test.sh does them (`editcap -E`) and beyond:
bit flips anywhere (headers too), cuts, lying length fields in pcap record headers and pcapng
block headers, duplicated, reordered and dropped records, timestamps thrown back or far ahead;
plus the EG-Link-aware ones of `eglink`. Everything is drawn from one `random.Random`, so a case
is the same bytes for the same seed."""
from __future__ import annotations

import itertools
import random
import struct
import subprocess
import tempfile
from pathlib import Path
from typing import Callable, Optional

from . import containers, eglink

Mutation = Callable[[bytes, Optional[containers.Layout], random.Random], tuple[bytes, str]]
LYING_LENGTHS = (0, 1, 11, 12, 0xFFFF, 262_144, 262_145, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF)


def editcap(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """`editcap -E <p> --seed <s>`: random bytes of the packet data changed (fuzz-test.sh's way)."""
    probability = rng.choice([0.001, 0.003, 0.01, 0.02, 0.05])
    seed = rng.randrange(1 << 31)
    if layout is None:
        return flip_bits(data, layout, rng)      # editcap cannot read it: flip bits ourselves
    with tempfile.TemporaryDirectory(prefix="selffuzz-") as tmp:
        src, dst = Path(tmp) / "in", Path(tmp) / "out"
        src.write_bytes(data)
        done = subprocess.run(["editcap", "-E", str(probability), "--seed", str(seed), "-F", layout.format,
                               str(src), str(dst)], capture_output=True, timeout=60)
        if done.returncode != 0 or not dst.exists():
            return flip_bits(data, layout, rng)
        return dst.read_bytes(), f"editcap -E {probability} --seed {seed} -F {layout.format}"


def flip_bits(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """A few bits anywhere in the file, headers included (editcap -E only touches packet data)."""
    out = bytearray(data)
    count = rng.choice([1, 2, 4, 16])
    for _ in range(count):
        pos = rng.randrange(len(out))
        out[pos] ^= 1 << rng.randrange(8)
    return bytes(out), f"{count} bit(s) flipped"


def cut(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """The file cut at a random offset: inside a header, a record or between two."""
    if layout and layout.blocks and rng.random() < 0.5:
        rec = rng.choice(layout.blocks)
        at = rng.randint(rec.start, rec.end)       # around record boundaries, where readers split
    else:
        at = rng.randrange(len(data))
    return data[:at], f"cut at {at} of {len(data)}"


def lie_length(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """A record or block header states a wrong length (captured, original or block total)."""
    if not layout or not layout.blocks:
        return flip_bits(data, layout, rng)
    rec = rng.choice(layout.blocks)
    at = rng.choice(rec.length_fields)
    old = struct.unpack_from(rec.endian + "I", data, at)[0]
    new = rng.choice([*LYING_LENGTHS, old + 1, old - 1 & 0xFFFFFFFF, old + 4, old * 2 & 0xFFFFFFFF,
                      rng.randrange(1 << 32)])
    out = bytearray(data)
    struct.pack_into(rec.endian + "I", out, at, new)
    return bytes(out), f"length field at {at}: {old} -> {new}"


def _records(layout: Optional[containers.Layout]) -> tuple[containers.Record, ...]:
    return layout.packets if layout else ()


def duplicate(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """Copies of a record inserted right after it or elsewhere (a mirror port, a double tap)."""
    recs = _records(layout)
    if not recs:
        return flip_bits(data, layout, rng)
    rec, where = rng.choice(recs), rng.choice(recs)
    copies = rng.choice([1, 1, 3, 50])
    at = rec.end if rng.random() < 0.5 else where.start
    return data[:at] + data[rec.start:rec.end] * copies + data[at:], \
        f"record at {rec.start} copied {copies}x to {at}"


def reorder(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """Two records swapped, or a run of records reversed."""
    recs = _records(layout)
    if len(recs) < 2:
        return flip_bits(data, layout, rng)
    i = rng.randrange(len(recs) - 1)
    j = min(len(recs) - 1, i + rng.choice([1, 2, 10, 100]))
    if recs[j].start != recs[i].end and rng.random() < 0.5:     # not adjacent: swap the two
        a, b = recs[i], recs[j]
        out = data[:a.start] + data[b.start:b.end] + data[a.end:b.start] + data[a.start:a.end] + data[b.end:]
        return out, f"records at {a.start} and {b.start} swapped"
    run = recs[i:j + 1]
    if any(x.end != y.start for x, y in itertools.pairwise(run)):
        return data, "records not contiguous: left in order"
    body = b"".join(data[r.start:r.end] for r in reversed(run))
    return data[:run[0].start] + body + data[run[-1].end:], f"{len(run)} records from {run[0].start} reversed"


def drop(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """A run of records removed: loss, or a silence long enough for the watchdogs."""
    recs = _records(layout)
    if not recs:
        return cut(data, layout, rng)
    i = rng.randrange(len(recs))
    j = min(len(recs) - 1, i + rng.choice([0, 5, 40, 400]))
    if any(x.end != y.start for x, y in zip(recs[i:j], recs[i + 1:j + 1])):
        return data, "records not contiguous: none dropped"
    return data[:recs[i].start] + data[recs[j].end:], f"{j - i + 1} records from {recs[i].start} dropped"


def time_warp(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
    """A record's timestamp thrown back, far ahead, or to the ends of its range."""
    recs = [r for r in _records(layout) if r.time_fields]
    if not recs:
        return flip_bits(data, layout, rng)
    rec = rng.choice(recs)
    at = rng.choice(rec.time_fields)
    new = rng.choice([0, 1, 0xFFFFFFFF, 0x7FFFFFFF, rng.randrange(1 << 32)])
    out = bytearray(data)
    struct.pack_into(rec.endian + "I", out, at, new)
    return bytes(out), f"timestamp word at {at} set to {new}"


def _eglink(mutation: Callable) -> Mutation:
    def run(data: bytes, layout: Optional[containers.Layout], rng: random.Random) -> tuple[bytes, str]:
        return mutation(data, layout, rng) if layout else flip_bits(data, layout, rng)
    run.__name__ = mutation.__name__
    return run


# (mutation, weight): editcap and the EG-Link mutations most often, as they reach the deepest code.
MUTATIONS: tuple[tuple[Mutation, int], ...] = (
    (editcap, 4), (flip_bits, 2), (cut, 2), (lie_length, 3), (duplicate, 2), (reorder, 2), (drop, 1),
    (time_warp, 1), *((_eglink(m), 4) for m in eglink.MUTATIONS))


def mutate(data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    """One to three mutations in a row; the description of each."""
    steps = []
    for _ in range(rng.choice([1, 1, 2, 3])):
        mutation = rng.choices([m for m, _ in MUTATIONS], [w for _, w in MUTATIONS])[0]
        data, what = mutation(data, containers.parse(data), rng)
        steps.append(what)
        if not data:
            break
    return data, steps
