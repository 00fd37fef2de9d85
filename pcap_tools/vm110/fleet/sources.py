"""Which files a build takes, and the metadata each one carries (from its path or a sidecar JSON).

SRC arguments are files (taken whatever their name), folders (every capture below them, by
extension) or glob patterns. Metadata becomes string columns on every table of the dataset.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional

from ..errors import CliError

CAPTURE_SUFFIXES = (".pcap", ".pcapng", ".cap")
SIDECAR_SUFFIX = ".meta.json"
MAX_SIDECAR_BYTES = 64 << 10
KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,62}\Z")
HASH_CHUNK = 1 << 20


@dataclass(frozen=True)
class Source:
    """One capture to build: its path (absolute), size, content hash and metadata."""

    path: str
    size: Optional[int]                 # None: the file could not be read
    sha256: Optional[str]
    meta: tuple[tuple[str, Optional[str]], ...] = field(default=())

    @property
    def capture_id(self) -> str:
        """Names the capture's parts: the same file, content and metadata give the same id."""
        text = json.dumps([self.path, self.sha256, list(self.meta)])
        return hashlib.sha256(text.encode()).hexdigest()[:24]


def find(sources: Iterable[str]) -> list[str]:
    """The capture files named by SRC arguments, absolute, sorted, each once. CliError for a SRC
    that names nothing."""
    found: set[str] = set()
    for src in sources:
        if os.path.isdir(src):
            hits = [str(p) for p in Path(src).rglob("*") if p.suffix.lower() in CAPTURE_SUFFIXES and p.is_file()]
            if not hits:
                raise CliError(f"{src}: no captures in this folder (*{', *'.join(CAPTURE_SUFFIXES)})")
        elif os.path.exists(src):
            if not os.path.isfile(src):
                raise CliError(f"{src}: not a file or folder")
            hits = [src]
        elif glob.has_magic(src):
            hits = [p for p in glob.glob(src, recursive=True) if os.path.isfile(p)]
            if not hits:
                raise CliError(f"{src}: no file matches")
        else:
            raise CliError(f"{src}: no such file or folder")
        found.update(os.path.abspath(p) for p in hits)
    return sorted(found)


class MetaPattern:
    """`sites/{site}/{machine}/*.pcapng`: the end of a capture's path that the pattern matches
    gives the named fields. `*` and `?` match within one folder name, `**` across folders."""

    def __init__(self, pattern: str) -> None:
        self.pattern = pattern
        self.keys: list[str] = []
        out = []
        for piece in re.split(r"(\{[^{}]*\}|\*\*|\*|\?)", pattern.replace(os.sep, "/")):
            if piece.startswith("{") and piece.endswith("}"):
                key = piece[1:-1]
                if not KEY.match(key) or key in self.keys:
                    raise CliError(f"--meta: {piece!r} must name a new field (letters, digits, _)")
                self.keys.append(key)
                out.append(f"(?P<{key}>[^/]+)")
            elif piece == "**":
                out.append(".*")
            elif piece == "*":
                out.append("[^/]*")
            elif piece == "?":
                out.append("[^/]")
            else:
                out.append(re.escape(piece))
        if not self.keys:
            raise CliError(f"--meta {pattern!r}: names no field; e.g. 'sites/{{site}}/{{machine}}/*.pcapng'")
        self.regex = re.compile("(?:^|/)" + "".join(out) + r"\Z")

    def fields(self, path: str) -> Optional[dict[str, str]]:
        """The fields of `path`, or None when the pattern does not match it."""
        m = self.regex.search(path.replace(os.sep, "/"))
        return None if m is None else dict(m.groupdict())


def sidecar(path: str) -> dict[str, Optional[str]]:
    """The metadata in `CAPTURE.meta.json` (a flat object; values are kept as text), if there is
    one. CliError when it is not such an object."""
    side = path + SIDECAR_SUFFIX
    if not os.path.isfile(side):
        return {}
    try:
        with open(side, "rb") as f:
            raw = f.read(MAX_SIDECAR_BYTES + 1)
        if len(raw) > MAX_SIDECAR_BYTES:
            raise ValueError(f"larger than {MAX_SIDECAR_BYTES} bytes")
        data = json.loads(raw, parse_constant=_refuse_constant)
    except (OSError, ValueError) as exc:
        raise CliError(f"{side}: not a metadata file: {exc}") from None
    if not isinstance(data, dict):
        raise CliError(f"{side}: not a metadata file: a JSON object is expected")
    out: dict[str, Optional[str]] = {}
    for key, value in data.items():
        if not KEY.match(key):
            raise CliError(f"{side}: {key[:40]!r} is not a column name (letters, digits, _)")
        if isinstance(value, (dict, list)):
            raise CliError(f"{side}: {key}: only text, numbers, true/false or null")
        out[key] = None if value is None else (json.dumps(value) if isinstance(value, bool) else str(value))
    return out


def _refuse_constant(name: str) -> None:
    raise ValueError(f"{name} is not a value")


def metadata(path: str, pattern: Optional[MetaPattern]) -> dict[str, Optional[str]]:
    """Fields from the pattern (None each when it does not match), then the sidecar's; a field in
    both must agree."""
    meta: dict[str, Optional[str]] = {}
    if pattern is not None:
        meta = dict(pattern.fields(path) or dict.fromkeys(pattern.keys))
    for key, value in sidecar(path).items():
        if meta.get(key) is not None and meta[key] != value:
            raise CliError(f"{path}: {key} is {meta[key]!r} by --meta and {value!r} in its sidecar")
        meta[key] = value
    return meta


def content_hash(path: str) -> tuple[int, str]:
    """(size, sha256 hex) of the file as read now."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while True:
            block = f.read(HASH_CHUNK)
            if not block:
                return size, h.hexdigest()
            size += len(block)
            h.update(block)
