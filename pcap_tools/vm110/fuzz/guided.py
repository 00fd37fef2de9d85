"""Coverage-guided mode (`vm110 fuzz --coverage`) for a controller built with AFL++.

The controller keeps running between cases (no fork server, no restart per input): the map is
cleared before each case and read once the case has settled (the map stops changing). A case
that reaches a new edge or a new hit-count class joins the corpus, as a whole case: packets,
delays and the base unit's stream (state-aware, as AFLNet). The fixed sweep seeds an empty corpus;
then each case is a mutation of a corpus case, cheap cases (no waits) and recent finds first.

What the map gathers between cases (the controller's start, its timers, the base unit's stream and
acks, replays of suspects) counts as coverage too, but makes no corpus case: no stored case would
reach it again. Counted only when it fell inside a case, it made a resumed corpus reach fewer
edges than the run that wrote it (57 of 69).
"""
from __future__ import annotations

import os
import random
import shlex
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from .. import constants as C
from ..errors import CliError
from . import cases as K
from .corpus import CorpusDir, Entry, Packet, binary_strings, load_dictionary
from .coverage import ShmMap, Virgin
from .fields import COMMAND_ID_AT, SERIAL_AT
from .havoc import Mutator, fix
from .session import Sent, Session

_SETTLE_STEP_S = 0.0001       # the map is read until it has hits and two reads this far apart agree
_SETTLE_MAX_S = 0.03
_EMPTY_AFTER = 30             # cases: a map still empty then is not instrumented
_SERIES_POINTS = 2000
_RECENT = 8
_BETWEEN_KEPT = 4096


@dataclass
class GuidedConfig:
    map_size: int
    corpus_dir: Optional[Path] = None
    dictionary: Optional[str] = None
    binary: Optional[str] = None        # where to take strings from (default: the target command's program)


def _builder(p: Packet, ids: dict[int, int]) -> K.Builder:
    """The packet on the session's next serial, its VRCI command ID made fresh for this run of the case."""
    def build(serial: int) -> tuple[bytes, bytes]:
        data = p.data
        if p.raw or len(data) < C.OVERHEAD:
            return data, fix(data)
        body = bytearray(data)
        body[SERIAL_AT:SERIAL_AT + 2] = serial.to_bytes(2, "little")
        if body[:C.ID_LEN] == b"VRCI" and len(body) >= COMMAND_ID_AT + 2:
            old = int.from_bytes(body[COMMAND_ID_AT:COMMAND_ID_AT + 2], "little")
            if old in ids:
                body[COMMAND_ID_AT:COMMAND_ID_AT + 2] = ids[old].to_bytes(2, "little")
        data = fix(bytes(body))
        return data, data
    return build


def case_of(entry: Entry, index: int, family: str, description: str) -> K.Case:
    fresh = K.command_ids(index)
    ids: dict[int, int] = {}
    for p in entry.packets:
        if p.data[:C.ID_LEN] == b"VRCI" and len(p.data) >= COMMAND_ID_AT + 2 and len(ids) < len(fresh):
            ids.setdefault(int.from_bytes(p.data[COMMAND_ID_AT:COMMAND_ID_AT + 2], "little"), fresh[len(ids)])
    steps = [K.Step(_builder(p, ids), p.delay_ms, p.expect_ack) for p in entry.packets]
    return K.Case(index, family, description, steps, entry.pause_vrpi_ms, entry.withhold_vrai_ms,
                  dict(entry.stream) if entry.stream else None, entry.settle_ms)


def entry_of(case: K.Case, sent: list[Sent], origin: str) -> Entry:
    packets = [Packet(s.data, s.delay_ms, s.data != fix(s.data), s.expect_ack) for s in sent]
    return Entry(packets, dict(case.stream) if case.stream else None, case.pause_vrpi_ms, case.withhold_vrai_ms,
                 case.settle_ms, origin)


def packet_id(data: bytes) -> str:
    """A packet's ID as text: bytes outside printable ASCII as \\xNN (a havoc'd ID's ESC or NUL
    went raw to the terminal in the finding's line)."""
    return "".join(chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}" for b in data[:C.ID_LEN])


class Guided:
    def __init__(self, cfg: GuidedConfig, seed: int) -> None:
        self.cfg = cfg
        self.rng = random.Random(f"vm110-coverage/{seed}")
        self.tokens: list[bytes] = load_dictionary(cfg.dictionary) if cfg.dictionary else []   # refused first
        self.store = CorpusDir(cfg.corpus_dir) if cfg.corpus_dir else None
        self.map = ShmMap(cfg.map_size)
        self.virgin = Virgin(cfg.map_size)
        self.empty = bytes(cfg.map_size)
        self.corpus: list[Entry] = []
        self.resume: list[Entry] = []
        self.mutator = Mutator(self.rng, self.tokens, list(self.tokens))
        self.seed = seed
        self.sweep = 0
        self.cases = 0
        self.started = time.time()
        self.series: list[tuple[float, int, int]] = []     # (seconds, edges, cases)
        self.pending: Optional[tuple[str, Optional[Entry]]] = None
        self.found_by: dict[str, int] = {}
        self.recent: list[Entry] = []
        self.resumed = 0                         # corpus cases played again so far
        self.resume_edges: Optional[int] = None  # the edges once the whole stored corpus was played
        self.stored_edges = 0                    # the most the runs that kept them had (0: not said)
        self.between: set[int] = set()           # hashes of the maps between cases already judged

    def environment(self) -> dict[str, str]:
        return {"__AFL_SHM_ID": str(self.map.id), "AFL_MAP_SIZE": str(self.cfg.map_size)}

    def open(self, target_cmd: Optional[str]) -> None:
        binary = self.cfg.binary or (shlex.split(target_cmd)[0] if target_cmd else None)
        if binary:
            where = shutil.which(binary) or binary
            self.tokens += [t for t in binary_strings(where) if t not in self.tokens]
        if self.store is not None:
            self.resume = self.store.load()
            self.stored_edges = max((e.run_edges for e in self.resume), default=0)
        self.sweep = 0 if self.resume else len(K.sweep(self.seed))
        self.started = time.time()

    def close(self) -> None:
        self.map.close()

    def edges(self) -> int:
        return self.virgin.edges

    # --- the loop ------------------------------------------------------------------------------
    def next_case(self, index: int) -> K.Case:
        if self.resume:                       # the stored corpus first: it restores the coverage
            entry = self.resume.pop(0)
            self.resumed += 1
            self.pending = ("resumed", entry)
            return case_of(entry, index, "corpus", f"resumed corpus case ({entry.origin or 'stored'})")
        if index < self.sweep:
            self.pending = ("sweep", None)
            return K.generate(self.seed, index)
        if not self.corpus:
            self.pending = ("sweep", None)
            return K.generate(self.seed, index)
        parent = self._pick()
        other = self.rng.choice(self.corpus)
        child = self.mutator.mutate(parent, other)
        self.pending = ("mutation", None)
        kinds = "+".join(sorted({packet_id(p.data) for p in child.packets}))
        return case_of(child, index, "coverage", f"mutation of a corpus case: {len(child.packets)} packet(s) {kinds}")

    def _pick(self) -> Entry:
        """Half the time one of the latest cases that reached new edges (what they opened is
        explored at once); else cheap cases and those picked less often first (a small tournament)."""
        if self.recent and self.rng.random() < 0.5:
            return self.rng.choice(self.recent)
        best = None
        for _ in range(4):
            e = self.rng.choice(self.corpus)
            score = e.cost() * 100 + e.picked * 0.01 - 0.5 * (e.new_edges > 0)
            if best is None or score < best[0]:
                best = (score, e)
        assert best is not None
        best[1].picked += 1
        return best[1]

    def before_case(self) -> None:
        raw = self.map.read()                 # what came between cases: coverage, not a corpus case
        # (the same few maps again and again, the timers' and the stream's: judged once each)
        if raw != self.empty and hash(raw) not in self.between:
            if len(self.between) < _BETWEEN_KEPT:
                self.between.add(hash(raw))
            if self.virgin.novel(raw):
                self._point()
        if self.resume_edges == -1:
            self.resume_edges = self.virgin.edges
        self.map.clear()

    def settle(self, session: Session) -> bytes:
        """The map once the case has settled: it has hits (every datagram the controller reads
        makes some) and two reads `_SETTLE_STEP_S` apart agree. Between reads the fuzzer yields
        the processor (the controller may need it) and keeps the base unit's side going."""
        deadline = time.time() + _SETTLE_MAX_S
        last, last_at = self.map.read(), time.time()
        while True:
            now = time.time()
            if now >= deadline:
                return last
            session.pump(now)
            os.sched_yield()
            if time.time() - last_at < _SETTLE_STEP_S:
                continue
            raw, last_at = self.map.read(), time.time()
            if raw == last and raw != self.empty:
                return raw
            last = raw

    def after_case(self, session: Session, case: K.Case, sent: list[Sent]) -> None:
        raw = self.settle(session)
        self.cases += 1
        new = self.virgin.novel(raw)
        kind, resumed = self.pending or ("mutation", None)
        if new:
            entry = resumed or entry_of(case, sent, f"{kind} case {case.index}: {case.description}"[:200])
            entry.new_edges = max(new, 0)
            entry.run_edges = max(entry.run_edges, self.virgin.edges)
            self.corpus.append(entry)
            if new > 0 and entry.cost() == 0:
                self.recent = (self.recent + [entry])[-_RECENT:]
            self.found_by[kind] = self.found_by.get(kind, 0) + 1
            if self.store is not None and kind != "resumed":
                self.store.save(entry)
            self._point()
        elif kind == "resumed" and resumed is not None:
            self.corpus.append(resumed)       # kept: it was new once, its state may matter
        if kind == "resumed" and not self.resume:
            self.resume_edges = -1                # set once what came after the last one is read
        if self.cases == _EMPTY_AFTER and not self.virgin.ever_nonzero:
            raise CliError("--coverage: the coverage map stayed empty: is the controller built with afl-clang-fast "
                           "or afl-cc, and does __AFL_SHM_ID reach it (not through a wrapper that drops it)?")

    def _point(self) -> None:
        self.series.append((round(time.time() - self.started, 3), self.virgin.edges, self.cases))
        if len(self.series) > _SERIES_POINTS:
            self.series = self.series[::2]

    def summary(self) -> dict[str, Any]:
        self._point()
        return {"map_size": self.cfg.map_size, "edges": self.virgin.edges, "corpus": len(self.corpus),
                "cases": self.cases, "corpus_found_by": self.found_by, "dictionary_tokens": len(self.tokens),
                "corpus_dir": str(self.cfg.corpus_dir) if self.cfg.corpus_dir else None,
                "corpus_skipped": self.store.skipped if self.store else [],
                "resumed": {"cases": self.resumed, "of": self.resumed + len(self.resume),
                            "edges": self.virgin.edges if self.resume_edges == -1 else self.resume_edges,
                            "stored_edges": self.stored_edges or None}
                if self.resumed or self.resume else None,
                "edges_over_time": [{"s": s, "edges": e, "cases": c} for s, e, c in self.series]}
