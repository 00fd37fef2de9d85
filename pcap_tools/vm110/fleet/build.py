"""`vm110 fleet build`: decide what to analyse, run the engine, keep the manifest.

Incremental and idempotent: a capture whose path, size, content hash and metadata are already in
the dataset is skipped; a changed one is analysed again and its old parts removed once the
manifest no longer lists them; complete captures of a build that was stopped are adopted.
"""
from __future__ import annotations

import fnmatch
import glob
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from typing import Iterator, Optional, Sequence

from ..errors import CliError
from .dataset import Dataset
from .engines import run_dask, run_local
from .sources import MetadataError, MetaPattern, Source, content_hash, find, metadata, path_fields
from .tables import SCHEMA_ID, SCHEMAS, check_meta_keys
from .work import Done, Settings

HASH_THREADS = 8             # files hashed at once (reading is the limit, not the CPU)
CHECKPOINT_S = 2.0           # the journal gets a batch at most this often while a build runs


@dataclass
class Outcome:
    analysed: int = 0
    skipped: int = 0
    replaced: int = 0
    damaged: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    unmatched: list[str] = field(default_factory=list)     # captures whose path --meta does not match
    given: int = 0           # captures the SRCs name (copies among them too)
    copies: list[str] = field(default_factory=list)        # "copy: the capture it copies", not analysed
    cleared: int = 0         # unreadable entries of a folder walked (or globbed) that are there no longer


def fingerprint(settings: Settings) -> dict:
    """The options every capture of one dataset must share (so that its rows compare)."""
    return {"analysis": asdict(settings.options), "port": settings.port, "crc": settings.crc,
            "crc_order": settings.crc_order, "packets": settings.packets}


def _hash(source: Source) -> Source:
    """`source` with its size and content hash (none for a source that is not read, or cannot be)."""
    if source.problem is not None:
        return source
    try:
        size, digest = content_hash(source.path)
    except OSError:
        return source
    return replace(source, size=size, sha256=digest)


def sources(srcs: Sequence[str], pattern: Optional[MetaPattern], threads: int = 1,
            read: Optional[set[str]] = None) -> list[Source]:
    """The captures SRC names, each hashed (`threads` at a time: hashlib lets go of the GIL), with
    its metadata. A capture that cannot be hashed, or is not to be read (a FIFO, a broken link, a
    bad sidecar, a folder a glob cannot look into), still becomes a Source: it gives an unreadable
    row and a line, one each. `read` gets the folders the globs looked into."""
    if pattern is not None:
        check_meta_keys(set(pattern.keys))          # the command line's mistake: before any work
    found = [_source(path, pattern, problem) for path, problem in find(srcs, read).items()]
    with ThreadPoolExecutor(max(1, min(threads, HASH_THREADS))) as pool:
        return list(pool.map(_hash, found))


def _source(path: str, pattern: Optional[MetaPattern], problem: Optional[str]) -> Source:
    try:
        meta = metadata(path, pattern)
    except MetadataError as exc:     # the capture's own fault, as a damaged file: a row, not the end
        meta, problem = path_fields(path, pattern), problem or str(exc)
    return Source(path, None, None, tuple(sorted(meta.items())), problem)


def build(srcs: Sequence[str], settings: Settings, pattern: Optional[MetaPattern] = None,
          engine: str = "local", jobs: int = 1, scheduler: Optional[str] = None,
          progress: bool = False) -> Outcome:
    dataset = Dataset(settings.dataset)
    # A wrong --out (someone else's folder, other options) is said before the captures are hashed
    # (hours of reading, for hundreds of them); _build checks again under the lock.
    if dataset.exists():
        _check_options(dataset, dataset.read_manifest(), fingerprint(settings))
    else:
        dataset.check_new()
    globbed: set[str] = set()
    wanted = sources(srcs, pattern, jobs, globbed)
    if not dataset.exists():
        dataset.check_new()
    walked = [os.path.abspath(s) for s in srcs if os.path.isdir(s)]
    patterns = [os.path.abspath(s) for s in srcs if glob.has_magic(s) and not os.path.exists(s)]
    with dataset.lock():
        outcome = _build(dataset, wanted, Walked(walked, globbed, patterns), settings, engine, jobs, scheduler,
                         progress)
    if pattern is not None:
        outcome.unmatched = [s.path for s in wanted if pattern.fields(s.path) is None]
    outcome.given = len(wanted)
    return outcome


def _build(dataset: Dataset, wanted: list[Source], walked: "Walked", settings: Settings, engine: str, jobs: int,
           scheduler: Optional[str], progress: bool) -> Outcome:
    options = fingerprint(settings)
    if dataset.exists():
        manifest = dataset.read_manifest()
        _check_options(dataset, manifest, options)
        if dataset.journal_batches():           # a stopped build's: in the manifest, the journal afresh
            dataset.write_manifest(manifest)
    else:
        manifest = Dataset.new_manifest(options)
        dataset.write_manifest(manifest)        # first: a build stopped at once is still ours to resume
    dataset.remove_temporaries()
    listed = manifest["captures"]
    journal = Journal(dataset, listed)
    for cid, row in dataset.complete_captures(skip=set(listed)).items():     # a stopped build's finished work
        journal.add(cid, _entry(row["file"], row["size"], row["sha256"], row["status"], dataset.parts_on_disk(cid),
                                None, {k: v for k, v in row.items() if k not in _CAPTURE_COLUMNS},
                                SCHEMA_ID if _CAPTURE_COLUMNS <= set(row) else ""))
    outcome = Outcome()
    # An unreadable capture is tried again every time: what failed may have been passing (a file
    # still being copied, a worker that could not see the share).
    copies = _copies(listed, wanted)
    outcome.copies = [f"{copy}: the same capture as {of}" for copy, of in sorted(copies.items())]
    kept = [s for s in wanted if s.path not in copies]
    todo = [s for s in kept if s.capture_id not in listed or listed[s.capture_id]["status"] == "unreadable"]
    outcome.skipped = len(kept) - len(todo)
    versions = Versions(listed, {s.path: s.capture_id for s in wanted}, _moved(listed, wanted), copies)
    cleared = _gone_unreadable(listed, wanted, walked)
    outcome.cleared = len(cleared)
    stale = versions.stale() | cleared
    bar = Progress(len(todo), outcome.skipped) if progress else None
    last = time.monotonic()
    try:
        for done in _engine(engine, todo, settings, jobs, scheduler):
            journal.add(done.capture_id, _entry(done.path, done.size, done.sha256, done.status, list(done.parts),
                                                done.message, dict(done.meta)))
            outcome.analysed += 1
            if done.status == "unreadable":
                outcome.unreadable.append(f"{done.path}: {done.message}")
            elif done.status == "damaged":
                outcome.damaged.append(f"{done.path}: {done.message}")
            stale |= versions.add(done.path, done.capture_id)
            if bar:
                bar.step(outcome)
            if time.monotonic() - last > CHECKPOINT_S:
                journal.commit(stale)
                last = time.monotonic()
        outcome.replaced = len(stale) - len(cleared)
    finally:
        if bar:
            bar.close()
        journal.commit(stale, whole=manifest)
    return outcome


def _check_options(dataset: Dataset, manifest: dict, options: dict) -> None:
    if manifest.get("options") != options:
        differ = _difference(manifest.get("options"), options)
        raise CliError(f"{dataset.url}: built with other analysis options ({differ}); "
                       "build into a new folder, or give the same options")


_CAPTURE_COLUMNS = frozenset(SCHEMAS["captures"].names)


def _engine(engine: str, todo: list[Source], settings: Settings, jobs: int, scheduler: Optional[str]) -> Iterator[Done]:
    if engine == "dask":
        return run_dask(todo, settings, jobs, scheduler)
    return run_local(todo, settings, jobs)


def _entry(path: str, size: Optional[int], sha256: Optional[str], status: str, parts: list[str],
           message: Optional[str], meta: dict, schema: str = SCHEMA_ID) -> dict:
    """A capture of the manifest; `schema` the columns of its parts ("": an older vm110's, not known)."""
    return {"file": path, "size": size, "sha256": sha256, "status": status, "parts": sorted(parts),
            "message": message, "meta": meta, "schema": schema}


def _copies(listed: dict, wanted: list[Source]) -> dict[str, str]:
    """Copy -> the original it copies, among the captures of this build and those of the dataset
    still there: the same content under several paths (an archive folder, a file copied into two
    machines' folders, its `.pcap.gz`). Analysed, a copy is counted again in every sum of the
    fleet. The original is the one whose metadata gives the most fields (the copy in a machine's
    folder, not the archive's that --meta does not match), then the one in the fewest folders (a
    file beside its copy in a sub-folder), then the first in path order: a choice of the paths
    alone, the same whichever build saw which first."""
    current = {s.path for s in wanted}
    holders: dict[str, dict[str, int]] = {}         # content -> path -> metadata fields it gives
    for entry in listed.values():
        sha, path = entry.get("sha256"), entry["file"]
        if sha and entry["status"] != "unreadable" and path not in current and os.path.lexists(path):
            holders.setdefault(sha, {})[path] = _given(entry.get("meta") or {})
    for s in wanted:
        if s.sha256 and s.problem is None:
            holders.setdefault(s.sha256, {})[s.path] = _given(dict(s.meta))
    copies: dict[str, str] = {}
    for paths in holders.values():
        original = min(paths, key=lambda p: (-paths[p], p.count(os.sep), p))
        copies.update((p, original) for p in paths if p != original)
    return copies


def _given(meta: dict) -> int:
    return sum(value is not None for value in meta.values())


@dataclass(frozen=True)
class Walked:
    """Where this build looked: the SRC folders walked (all below them seen), the folders its
    glob patterns looked into and could, and the patterns (absolute)."""

    roots: list[str]
    globbed: set[str]
    patterns: list[str]


def _gone_unreadable(listed: dict, wanted: list[Source], walked: Walked) -> set[str]:
    """The unreadable entries inside a folder this build walked that the walk no longer finds (a
    file removed or renamed, a folder that can be read now), the folders a glob could not look
    into that it now can, and the files a pattern of this build names that are gone: there is
    nothing left to try again, and kept, each would count as a failing capture for ever. (fnmatch
    is looser than glob, `*` crossing folders: only for a path that is not there.)"""
    current = {s.path for s in wanted}
    return {cid for cid, entry in listed.items()
            if entry["status"] == "unreadable" and entry["file"] not in current
            and (entry["file"] in walked.globbed
                 or any(os.path.commonpath([entry["file"], root]) == root for root in walked.roots)
                 or (not os.path.lexists(entry["file"])
                     and any(fnmatch.fnmatchcase(entry["file"], p) for p in walked.patterns)))}


def _moved(listed: dict, wanted: list[Source]) -> dict[str, set[str]]:
    """Path -> the entries a capture moved or renamed to it leaves behind: listed with its content
    under a path that is no longer there (kept, it would be counted twice in every sum)."""
    gone: dict[str, set[str]] = {}
    for cid, entry in listed.items():
        if entry.get("sha256") and not os.path.lexists(entry["file"]):
            gone.setdefault(entry["sha256"], set()).add(cid)
    return {s.path: gone[s.sha256] for s in wanted if s.sha256 in gone}


class Versions:
    """The captures listed per path, to find those a changed file's new capture replaces: an
    entry for a path of this build whose capture id is no longer the file's, the entry of its
    content's old path if the file was moved there, and the entries of the paths that are copies of
    it now (what they held is gone, overwritten, or is counted under this path), once the file's
    current capture is complete (never before: a stop in between keeps the old rows)."""

    def __init__(self, listed: dict, current: dict[str, str], moved: Optional[dict[str, set[str]]] = None,
                 copies: Optional[dict[str, str]] = None) -> None:
        self.current = current
        self.moved = {path: set(cids) for path, cids in (moved or {}).items()}
        self.by_path: dict[str, set[str]] = {}
        for cid, entry in listed.items():
            self.by_path.setdefault(entry["file"], set()).add(cid)
        for copy, original in (copies or {}).items():
            self.moved.setdefault(original, set()).update(self.by_path.get(copy, set()))

    def stale(self) -> set[str]:
        """The entries stale now: of the paths of this build whose capture is complete, and the
        copies of an original that is not of this build (the dataset's, complete)."""
        return ({cid for path in self.current for cid in self._stale(path)}
                | {cid for path, cids in self.moved.items() if path not in self.current for cid in cids})

    def add(self, path: str, cid: str) -> set[str]:
        """Record a completed capture; the entries it makes stale."""
        self.by_path.setdefault(path, set()).add(cid)
        return self._stale(path)

    def _stale(self, path: str) -> set[str]:
        cids = self.by_path.get(path, set())
        now = self.current.get(path)
        return {c for c in cids | self.moved.get(path, set()) if c != now} if now in cids else set()


class Journal:
    """The build's updates to the manifest's captures (`listed`, changed in place): written as a
    journal batch of what changed since the last one (a cost that does not grow with the dataset),
    or as the whole manifest at the end."""

    def __init__(self, dataset: Dataset, listed: dict) -> None:
        self.dataset, self.listed = dataset, listed
        self.added: dict[str, dict] = {}

    def add(self, cid: str, entry: dict) -> None:
        self.listed[cid] = self.added[cid] = entry

    def commit(self, stale: set[str], whole: Optional[dict] = None) -> None:
        """Record the captures added and the stale entries gone (the whole manifest `whole`, if
        given), then remove the stale entries' parts (after: a stop in between leaves unlisted
        parts, never listed parts missing)."""
        gone = {cid: self.listed.pop(cid) for cid in sorted(stale) if cid in self.listed}
        if whole is not None:
            self.dataset.write_manifest(whole)
        else:
            self.dataset.journal({c: e for c, e in self.added.items() if c in self.listed}, gone)
        self.added = {}
        for entry in gone.values():
            self.dataset.remove_parts(entry["parts"])


def _difference(old: Optional[dict], new: dict) -> str:
    old = old or {}
    flat_old = {**(old.get("analysis") or {}), **{k: v for k, v in old.items() if k != "analysis"}}
    flat_new = {**new["analysis"], **{k: v for k, v in new.items() if k != "analysis"}}
    diff = [f"{k} {flat_old.get(k)!r}, now {flat_new.get(k)!r}" for k in sorted(set(flat_old) | set(flat_new))
            if flat_old.get(k) != flat_new.get(k)]
    return "; ".join(diff[:3]) or "unknown"


class Progress:
    """A one-line bar on standard error (only on a terminal)."""

    def __init__(self, total: int, skipped: int) -> None:
        self.total, self.skipped, self.start = total, skipped, time.monotonic()
        self.width = 30
        self.show(0, Outcome(skipped=skipped))

    def step(self, outcome: Outcome) -> None:
        self.show(outcome.analysed, outcome)

    def show(self, done: int, outcome: Outcome) -> None:
        frac = done / self.total if self.total else 1.0
        rate = done / max(time.monotonic() - self.start, 1e-9)
        bad = len(outcome.unreadable) + len(outcome.damaged)
        sys.stderr.write(f"\r[{'#' * int(frac * self.width):<{self.width}}] {done}/{self.total} captures"
                         f" ({outcome.skipped} already in, {bad} with errors, {rate:.1f}/s)\033[K")
        sys.stderr.flush()

    def close(self) -> None:
        sys.stderr.write("\r\033[K")
        sys.stderr.flush()


def absolute(url: str) -> str:
    """A local dataset path made absolute, so that worker processes find it wherever they run."""
    return url if "://" in url else os.path.abspath(url)
