"""The corpus of coverage-guided mode: whole cases (packets, their delays, the base unit's stream
during them), each kept because it reached new coverage; on disk one JSON per case in
`--corpus DIR` (read back to resume, every value checked: the folder is data).

Also the dictionary: AFL's format (`name="value"` lines, `\\xNN` escapes) and printable strings from
the target binary's read-only data.
"""
from __future__ import annotations

import functools
import glob
import json
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from .. import constants as C
from ..errors import CliError
from ..fileio import read_at_most, write_text
from ..layers import PAYLOAD_CLASSES
from . import mutate as M
from .findings import MAX_STEPS, make_folder
from ..jsonin import loads

_MAX_PACKET = 65_507
_MAX_MS = 5_000.0
_MAX_ENTRY_FILE = 4 << 20
_MAX_TOKENS = 512
_MAX_TOKEN = 64
_MAX_DICT_FILE = 1 << 20
_MAX_BINARY = 256 << 20
_STREAM_FIELDS = frozenset(f.name for f in PAYLOAD_CLASSES[C.PacketType.VRPI].fields_desc)


@dataclass
class Packet:
    data: bytes
    delay_ms: float = 0.0
    raw: bool = False            # the case means to break size or CRC: never recomputed
    expect_ack: bool = True


@dataclass
class Entry:
    packets: list[Packet]
    stream: Optional[dict[str, Any]] = None     # VRPI fields the base unit streams during the case
    pause_vrpi_ms: float = 0.0
    withhold_vrai_ms: float = 0.0
    settle_ms: float = 0.0
    origin: str = ""                            # how it was made
    new_edges: int = 0
    picked: int = 0
    run_edges: int = 0                          # the edges of the run that kept it, once it was kept

    def cost(self) -> float:
        """Seconds one run of the case waits at least (the scheduler prefers cheap cases)."""
        waits = sum(p.delay_ms for p in self.packets) + self.pause_vrpi_ms + self.withhold_vrai_ms + self.settle_ms
        return waits / 1000

    def to_json(self) -> dict[str, Any]:
        return {"vm110_corpus_entry": 1, "origin": self.origin, "new_edges": self.new_edges,
                "run_edges": self.run_edges,
                "stream": self.stream, "pause_vrpi_ms": self.pause_vrpi_ms,
                "withhold_vrai_ms": self.withhold_vrai_ms, "settle_ms": self.settle_ms,
                "packets": [{"hex": p.data.hex(), "delay_ms": p.delay_ms, "raw": p.raw, "expect_ack": p.expect_ack}
                            for p in self.packets]}


class _Bad(Exception):
    pass


def _ms(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= _MAX_MS:
        raise _Bad(f"{what} is not a number of milliseconds from 0 to {_MAX_MS:.0f}")
    return float(value)


def entry_from_json(raw: Any) -> Entry:
    if not isinstance(raw, dict) or raw.get("vm110_corpus_entry") != 1:
        raise _Bad("not a vm110 corpus entry")
    packets = raw.get("packets")
    # (no packets: a case of waiting alone, a VRPI gap or a VRAI withheld)
    if not isinstance(packets, list) or len(packets) > MAX_STEPS:
        raise _Bad(f"packets: a list of at most {MAX_STEPS}")
    out = []
    for n, p in enumerate(packets):
        if not isinstance(p, dict) or not isinstance(p.get("hex"), str) or len(p["hex"]) > 2 * _MAX_PACKET:
            raise _Bad(f"packets[{n}] has no hex")
        try:
            data = bytes.fromhex(p["hex"])
        except ValueError:
            raise _Bad(f"packets[{n}].hex is not hex") from None
        if not isinstance(p.get("raw"), bool) or not isinstance(p.get("expect_ack"), bool):
            raise _Bad(f"packets[{n}]: raw and expect_ack are true or false")
        out.append(Packet(data, _ms(p.get("delay_ms"), f"packets[{n}].delay_ms"), p["raw"], p["expect_ack"]))
    stream = raw.get("stream")
    if stream is not None:
        if not isinstance(stream, dict) or not all(
                key in _STREAM_FIELDS and isinstance(v, int) and not isinstance(v, bool) for key, v in stream.items()):
            raise _Bad("stream is not a set of VRPI fields with integer values")
        try:
            M.build(C.PacketType.VRPI, 0, stream)
        except (ValueError, struct.error, OverflowError):
            raise _Bad("stream: a value does not fit its VRPI field") from None
    run_edges = raw.get("run_edges", 0)         # (not in corpora written before it)
    if isinstance(run_edges, bool) or not isinstance(run_edges, int) or not 0 <= run_edges <= 1 << 28:
        raise _Bad("run_edges is not a number of edges")
    return Entry(out, stream, _ms(raw.get("pause_vrpi_ms", 0), "pause_vrpi_ms"),
                 _ms(raw.get("withhold_vrai_ms", 0), "withhold_vrai_ms"), _ms(raw.get("settle_ms", 0), "settle_ms"),
                 str(raw.get("origin", ""))[:200], 0, run_edges=run_edges)


def is_entry(raw: Any) -> bool:
    """Whether the JSON of a file is a corpus case (not a finding)."""
    return isinstance(raw, dict) and "vm110_corpus_entry" in raw


def checked_entry(raw: Any, path: str) -> Entry:
    """The corpus case of the JSON `raw` read from `path`, checked; CliError (one line) when it is
    not a valid corpus case."""
    try:
        return entry_from_json(raw)
    except _Bad as exc:
        raise CliError(f"{path} is not a valid vm110 corpus case: {exc}") from None


class CorpusDir:
    """`--corpus DIR`: one `id-NNNNNN.json` per entry; entries already there are resumed."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        make_folder(folder, "--corpus")
        self.next = 0
        self.skipped: list[str] = []

    def load(self) -> list[Entry]:
        entries = []
        for path in sorted(self.folder.glob("id-*.json")):
            m = re.fullmatch(r"id-(\d{6,9})\.json", path.name)
            if m is None:
                continue
            self.next = max(self.next, int(m.group(1)) + 1)
            try:
                entries.append(entry_from_json(loads(read_at_most(path, _MAX_ENTRY_FILE))))
            except OSError as exc:      # (the name is said once, not again in the full path that may not fit)
                self.skipped.append(f"{path.name}: {exc.strerror or exc}")
            except (ValueError, _Bad) as exc:
                self.skipped.append(f"{path.name}: {str(exc)[:100]}")
        return entries

    def save(self, entry: Entry) -> None:
        path = self.folder / f"id-{self.next:06d}.json"
        self.next += 1
        write_text(path, json.dumps(entry.to_json(), indent=1) + "\n")


# --- dictionary -----------------------------------------------------------------------------
_DICT_LINE = re.compile(r'^\s*(?:[A-Za-z0-9_]+(?:@\d+)?\s*=\s*)?"((?:[^"\\]|\\.)*)"\s*$')


def _unescape(text: str) -> bytes:
    out = bytearray()
    i = 0
    while i < len(text):
        c = text[i]
        if c == "\\" and i + 1 < len(text):
            nxt = text[i + 1]
            if nxt == "x" and re.fullmatch(r"[0-9A-Fa-f]{2}", text[i + 2:i + 4]):
                out.append(int(text[i + 2:i + 4], 16))
                i += 4
                continue
            if nxt in '\\"':
                out.append(ord(nxt))
                i += 2
                continue
            raise ValueError(f"unknown escape \\{nxt}")
        if not 32 <= ord(c) < 127:
            raise ValueError("non-printable character (write it as \\xNN)")
        out.append(ord(c))
        i += 1
    return bytes(out)


def load_dictionary(path: str) -> list[bytes]:
    """Tokens of an AFL dictionary; CliError (one line, with the line number) for a bad line."""
    try:
        lines = read_at_most(path, _MAX_DICT_FILE).decode("latin-1").splitlines()
    except OSError as exc:
        raise CliError(f"cannot read --dict {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise CliError(f"--dict {path}: {exc}") from None
    tokens = []
    for n, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _DICT_LINE.match(line)
        try:
            if m is None:
                raise ValueError('not name="value"')
            token = _unescape(m.group(1))
        except ValueError as exc:
            raise CliError(f"--dict {path} line {n}: {exc}") from None
        if token and len(token) <= _MAX_TOKEN and token not in tokens:
            tokens.append(token)
    return tokens[:_MAX_TOKENS]


def _words(data: bytes, minimum: int) -> list[bytes]:
    found = re.findall(rb"[!-~]{%d,%d}" % (minimum, _MAX_TOKEN), data)
    return [w for w in dict.fromkeys(found) if b"%" not in w and not w.startswith((b"_", b"."))]


@functools.lru_cache(maxsize=1)
def _runtime_words() -> frozenset[bytes]:
    """Words of AFL++'s instrumentation runtime, linked into every instrumented program: not the target's."""
    folders = [os.environ.get("AFL_PATH", ""), "/usr/lib/afl", "/usr/local/lib/afl"]
    words: set[bytes] = set()
    for folder in filter(None, folders):
        for name in glob.glob(os.path.join(glob.escape(folder), "afl-*rt*.o")):
            try:
                with open(name, "rb") as f:
                    words.update(_words(f.read(_MAX_BINARY), 3))
            except OSError:
                continue
    return frozenset(words)


def binary_strings(path: str, minimum: int = 3) -> list[bytes]:
    """Printable words (no spaces or format characters) in an ELF file's read-only data
    (`.rodata`), or in the whole file when it is not ELF: the target's own literals, without
    those of AFL++'s runtime."""
    try:
        with open(path, "rb") as f:
            blob = f.read(_MAX_BINARY)
    except OSError:
        return []
    runtime = _runtime_words()
    return [w for w in _words(_rodata(blob) or blob, minimum) if w not in runtime][:_MAX_TOKENS]


def _rodata(blob: bytes) -> bytes:
    """The bytes of the `.rodata` section of a 64-bit little-endian ELF file, else b""."""
    if blob[:4] != b"\x7fELF" or len(blob) < 64 or blob[4] != 2 or blob[5] != 1:
        return b""
    try:
        shoff, = struct.unpack_from("<Q", blob, 0x28)
        shentsize, shnum, shstrndx = struct.unpack_from("<HHH", blob, 0x3A)
        sections = [struct.unpack_from("<IIQQQQ", blob, shoff + i * shentsize) for i in range(shnum)]
        names_at = sections[shstrndx][4]
        for name, _type, _flags, _addr, offset, size in sections:
            end = blob.index(b"\0", names_at + name)
            if blob[names_at + name:end] == b".rodata":
                return blob[offset:offset + size]
    except (struct.error, IndexError, ValueError):
        return b""
    return b""
