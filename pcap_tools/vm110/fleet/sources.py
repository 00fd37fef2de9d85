"""Which files a build takes, and the metadata each one carries (from its path or a sidecar JSON).

SRC arguments are files (taken whatever their name), folders (every capture below them, by
extension) or glob patterns. Metadata becomes string columns on every table of the dataset.
An entry a build cannot take (a broken link, a FIFO, a link out of the folder walked, a bad
sidecar, a folder the walk or a glob cannot look into) is still a capture: it carries the reason,
and becomes an `unreadable` row.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass, field
from typing import Any, Iterable, Optional

from ..capture.compressed import GZIP_MAGIC, Gunzip, is_gzip
from ..errors import CliError
from ..fileio import read_at_most
from .tables import COLUMNS
from ..jsonin import loads

CAPTURE_SUFFIXES = (".pcap", ".pcapng", ".cap", ".pcap.gz", ".pcapng.gz", ".cap.gz")   # (gzip: as Wireshark reads)
SIDECAR_SUFFIX = ".meta.json"
MAX_SIDECAR_BYTES = 64 << 10
KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,62}\Z")
HASH_CHUNK = 1 << 20
_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"))


@dataclass(frozen=True)
class Source:
    """One capture to build: its path (absolute), size, content hash and metadata."""

    path: str
    size: Optional[int]                 # None: the file could not be read
    sha256: Optional[str]
    meta: tuple[tuple[str, Optional[str]], ...] = field(default=())
    problem: Optional[str] = None       # why it is not read at all (it is never opened)

    @property
    def capture_id(self) -> str:
        """Names the capture's parts: the same file, content and metadata give the same id."""
        text = json.dumps([self.path, self.sha256, list(self.meta)])
        return hashlib.sha256(text.encode()).hexdigest()[:24]


def find(sources: Iterable[str], read: Optional[set[str]] = None) -> dict[str, Optional[str]]:
    """The capture files named by SRC arguments, absolute, sorted, each once: path -> None to read
    it, or why it is not read. CliError for a SRC that names nothing. `read` gets the folders the
    glob patterns looked into (absolute), when they could."""
    found: dict[str, Optional[str]] = {}
    for src in sources:
        if os.path.isdir(src):
            hits = _walk(src)
            if not hits:
                raise CliError(f"{src}: no captures in this folder (*{', *'.join(CAPTURE_SUFFIXES)})")
            if src in hits:                  # the folder itself cannot be listed
                raise CliError(f"{src}: {hits[src]}")
        elif os.path.exists(src):
            if not os.path.isfile(src):
                raise CliError(f"{src}: not a file or folder")
            hits = {src: None}
        elif glob.has_magic(src):
            # The pattern names each path it matches: links are followed wherever they lead (`**`
            # goes round a link to a folder above it until the path is too long to resolve).
            hits = {p: not_a_capture(p) for p in glob.glob(src, recursive=True)
                    if not os.path.isdir(os.path.realpath(p))}
            looked = _looked_into(src)
            hits.update((folder, problem) for folder, problem in looked.items() if problem is not None)
            if read is not None:
                read.update(os.path.abspath(folder) for folder, problem in looked.items() if problem is None)
            if not hits:
                raise CliError(f"{src}: no file matches")
        else:
            raise CliError(f"{src}: no such file or folder")
        for path, problem in hits.items():
            found.setdefault(os.path.abspath(path), problem)
    return dict(sorted(_once(found).items()))


def _once(found: dict[str, Optional[str]]) -> dict[str, Optional[str]]:
    """Each file once: links (a loop, a `latest.pcap`) and several SRCs may name one file many
    times, and each name would count it again in every sum. The name kept: a readable one, the
    file's own rather than a link's, then the shortest."""
    def first(item: tuple[str, Optional[str]]) -> tuple:
        return item[1] is not None, os.path.islink(item[0]), item[0].count(os.sep), item[0]
    kept: dict[str, tuple[str, Optional[str]]] = {}
    for path, problem in sorted(found.items(), key=first):
        kept.setdefault(os.path.realpath(path), (path, problem))
    return dict(kept.values())


def _walk(folder: str) -> dict[str, Optional[str]]:
    """Every entry below `folder` named as a capture that is not a folder (links to folders are
    not walked), with why it is not read, if so; and every folder below it that cannot be listed,
    with why (rglob passed over it in silence, and with it every capture inside)."""
    inside = os.path.realpath(folder)
    found: dict[str, Optional[str]] = {}

    def unlisted(exc: OSError) -> None:
        if not isinstance(exc, (FileNotFoundError, NotADirectoryError)):     # (gone while walked: nothing missed)
            found[exc.filename] = f"a folder that cannot be read: {exc.strerror}; the captures in it are not seen"
    for top, _, files in os.walk(folder, onerror=unlisted):
        for name in files:
            if name.lower().endswith(CAPTURE_SUFFIXES):
                path = os.path.join(top, name)
                found[path] = not_a_capture(path, inside)
    return found


def _looked_into(pattern: str) -> dict[str, Optional[str]]:
    """The folders glob looks into for `pattern`, each with why it cannot (None: it can). glob
    passes over a folder it may not list (a `*` or `**` below it) or search (a name below it) in
    silence, and with it every capture inside: such a folder is an unreadable entry, as the walk's.
    Only what glob needs is asked (a folder named on the way need not be listed)."""
    parts = pattern.split(os.sep)
    out: dict[str, Optional[str]] = {}
    for k in range(1, len(parts)):
        prefix, below = os.sep.join(parts[:k]) or os.sep, parts[k]
        if not below:
            continue
        matches = glob.glob(prefix, recursive=True) if glob.has_magic(prefix) else [prefix]
        for folder in map(os.path.normpath, matches):
            if out.get(folder) is not None or not os.path.isdir(folder):
                continue
            try:
                if glob.has_magic(below):
                    with os.scandir(folder):
                        pass
                else:
                    os.lstat(os.path.join(folder, below))
                out[folder] = None
            except (FileNotFoundError, NotADirectoryError):     # (nothing there to miss)
                out[folder] = None
            except OSError as exc:
                out[folder] = f"a folder that cannot be read: {exc.strerror}; the captures in it are not seen"
    return out


def not_a_capture(path: str, inside: Optional[str] = None) -> Optional[str]:
    """Why `path` is not read as a capture, found without opening it (a FIFO would wait for a
    writer): a broken link, not a regular file, or a link that leads out of the folder `inside`
    (the user gave the folder, not what its links point to). None: read it."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if os.path.islink(path):
            return f"a broken symbolic link (to {_target(path)}): {exc.strerror}"
        return f"cannot read: {exc.strerror}"
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        return f"{kind}, not a capture file: not opened"
    if inside is not None and os.path.islink(path):
        target = os.path.realpath(path)
        if os.path.commonpath([target, inside]) != inside:
            return (f"a symbolic link to {target}, outside the folder given: not followed "
                    "(give it, or its folder, as a SRC to take it)")
    return None


def _target(path: str) -> str:
    try:
        return os.readlink(path)
    except OSError:
        return "?"


class MetaPattern:
    """`sites/{site}/{machine}/*.pcapng`: the end of a capture's path that the pattern matches
    gives the named fields. `*` and `?` match within one folder name, `**` across folders."""

    def __init__(self, pattern: str) -> None:
        self.pattern = pattern
        self.keys: list[str] = []
        out = []
        previous = ""
        for piece in _pieces(pattern.replace(os.sep, "/")):
            if not piece:
                continue
            if piece.startswith("{") and piece.endswith("}"):
                key = piece[1:-1]
                if not KEY.match(key) or key in self.keys:
                    raise CliError(f"--meta: {piece!r} must name a new field (letters, digits, _)")
                if previous.startswith("{") or previous == "*":
                    # "{a}{b}" against "ab": which letters are whose? Say so, not guess.
                    raise CliError(f"--meta {pattern!r}: {previous}{piece} has nothing between them to tell "
                                   "where one ends; put a separator, e.g. {site}_{machine}")
                self.keys.append(key)
                out.append(f"(?P<{key}>[^/]+)")
            elif piece == "/**/":
                out.append("/(?:.*/)?")
            elif piece == "**":
                out.append(".*")
            elif piece == "*":
                out.append("[^/]*")
            elif piece == "?":
                out.append("[^/]")
            else:
                out.append(re.escape(piece))
            previous = piece
        if not self.keys:
            raise CliError(f"--meta {pattern!r}: names no field; e.g. 'sites/{{site}}/{{machine}}/*.pcapng'")
        self.regex = re.compile("(?:^|/)" + "".join(out) + r"\Z")

    def fields(self, path: str) -> Optional[dict[str, str]]:
        """The fields of `path`, or None when the pattern does not match it."""
        m = self.regex.search(path.replace(os.sep, "/"))
        return None if m is None else dict(m.groupdict())


def _pieces(pattern: str) -> list[str]:
    """`pattern` split into fields, wildcards and text; `/**/` one piece: no folder or any number
    of them, as glob has it (`.*` between the slashes wanted one folder at least)."""
    pieces = re.split(r"(\{[^{}]*\}|\*\*|\*|\?)", pattern)
    for n in range(1, len(pieces) - 1):
        if pieces[n] == "**" and pieces[n - 1].endswith("/") and pieces[n + 1].startswith("/"):
            pieces[n - 1], pieces[n], pieces[n + 1] = pieces[n - 1][:-1], "/**/", pieces[n + 1][1:]
    return pieces


class MetadataError(CliError):
    """A capture's metadata cannot be made: every problem of its sidecar, in one message."""


def sidecar(path: str) -> tuple[dict[str, Optional[str]], list[str]]:
    """The metadata in `CAPTURE.meta.json` (a flat object; values are kept as text), if there is
    one, and every problem found in it (a bad field is left out, the others kept)."""
    side = path + SIDECAR_SUFFIX
    if not os.path.lexists(side):
        return {}, []
    if not os.path.isfile(side):      # (a FIFO would be waited on; a folder cannot be read)
        return {}, ["not a metadata file: not a regular file"]
    try:
        data = loads(read_at_most(side, MAX_SIDECAR_BYTES), parse_constant=_refuse_constant)
    except (OSError, ValueError) as exc:
        return {}, [f"not a metadata file: {exc}"]
    if not isinstance(data, dict):
        return {}, ["not a metadata file: a JSON object is expected"]
    out: dict[str, Optional[str]] = {}
    problems = []
    for key, value in data.items():
        if not KEY.match(key):
            problems.append(f"{key[:40]!r} is not a column name (letters, digits, _)")
        elif key in COLUMNS:
            problems.append(f"{key!r} is a column of the dataset already")
        elif isinstance(value, (dict, list)):
            problems.append(f"{key}: only text, numbers, true/false or null")
        else:
            out[key] = None if value is None else (json.dumps(value) if isinstance(value, bool) else str(value))
    return out, problems


def _refuse_constant(name: str) -> None:
    raise ValueError(f"{name} is not a value")


def path_fields(path: str, pattern: Optional[MetaPattern]) -> dict[str, Optional[str]]:
    """The fields `pattern` gives `path` (None each when it does not match)."""
    if pattern is None:
        return {}
    return dict(pattern.fields(path) or dict.fromkeys(pattern.keys))


def metadata(path: str, pattern: Optional[MetaPattern]) -> dict[str, Optional[str]]:
    """Fields from the pattern, then the sidecar's; a field in both must agree. MetadataError with
    every problem of the sidecar (the path is the capture's: the message does not repeat it)."""
    meta = path_fields(path, pattern)
    fields, problems = sidecar(path)
    for key, value in fields.items():
        if meta.get(key) is not None and meta[key] != value:
            problems.append(f"{key} is {value!r} in its sidecar and {meta[key]!r} by --meta")
        meta[key] = value
    if problems:
        raise MetadataError(f"sidecar {os.path.basename(path)}{SIDECAR_SUFFIX}: {'; '.join(problems)}")
    return meta


def content_hash(path: str) -> tuple[int, str]:
    """(size of the file, sha256 hex of the capture in it) as read now. A gzip-compressed file's
    is the hash of the capture it holds: `gzip w1.pcap` (which removes w1.pcap) is the capture
    moved, and a .pcap.gz beside its .pcap a copy, not a second capture counted in every sum."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        head = f.read(len(GZIP_MAGIC))
        f.seek(0)
        stream: Any = Gunzip(f) if is_gzip(head) else f
        while block := stream.read(HASH_CHUNK):
            h.update(block)
        # (the bytes hashed, of a file still growing; gzip may leave trailing bytes unread)
        return f.tell() if stream is f else os.fstat(f.fileno()).st_size, h.hexdigest()
