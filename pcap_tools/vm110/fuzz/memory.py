"""The memory oracle: the resident memory (RSS) of the controller `--target-cmd` started, sampled
about once a second, as AFL++'s `-m` and boofuzz's process monitor watch their targets. A PLC
program runs for days: memory it leaks per packet ends it in the end, long after a short run.

The controller's process group counts whole (a controller run under gdb, one with workers). A
finding when the RSS exceeds `--target-memory` (a hard limit), or when it keeps rising well past
its warm-up level (`Rule`): one per controller life, the runner restarts it then. Linux only
(/proc); elsewhere the oracle is off and the summary says so.

A leak is seldom in every packet: one that only an unknown packet ID or an ack of no command makes
grows the RSS in the seconds such packets came. The finding names the kinds of case packet whose
count per sample interval goes with the growth (`suspects`), so that its user knows which to look at.
"""
from __future__ import annotations

import collections
import os
import re
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from .. import constants as C
from ..decode import decode

MAX_SERIES = 240          # samples kept for the evidence: thinned, older ones further apart
SUSPECT_CORRELATION = 0.5   # a kind named only when its count goes this well with the growth
_SUSPECTS = 3
_PROC = "/proc"
_PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024 if hasattr(os, "sysconf") else 4


def unavailable() -> Optional[str]:
    """Why the oracle cannot run here (None: it can)."""
    return None if os.path.exists(f"{_PROC}/self/stat") else "no /proc to read a process's memory from (Linux only)"


def group_rss_kib(pgid: int) -> Optional[int]:
    """The resident memory of the processes of group `pgid`, in KiB (None: none is left)."""
    total, found = 0, False
    try:
        names = os.listdir(_PROC)
    except OSError:
        return None
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"{_PROC}/{name}/stat", "rb") as f:
                stat = f.read()
        except OSError:          # gone meanwhile, or not ours to read
            continue
        # After the command name (which may hold spaces and parentheses): state, ppid, pgrp, ... rss (24th)
        rest = stat[stat.rfind(b")") + 2:].split()
        if len(rest) > 21 and int(rest[2]) == pgid:
            total += _exact_rss_kib(name, int(rest[21]) * _PAGE_KIB)
            found = True
    return total if found else None


def _exact_rss_kib(pid: str, approximate: int) -> int:
    """The RSS counted page by page (smaps_rollup): the kernel's counters in /proc/PID/stat move in
    steps of 32 pages per CPU (trial: 128 KiB, so a leak of 16 KiB a packet showed in one interval
    of eight, and which packets it went with was lost). `approximate` when it cannot be read."""
    try:
        with open(f"{_PROC}/{pid}/smaps_rollup", "rb") as f:
            for line in f:
                if line.startswith(b"Rss:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return approximate


def asan_allowance_kib(options: str) -> int:
    """What AddressSanitizer keeps resident of memory the controller freed: its quarantine
    (`quarantine_size_mb` of ASAN_OPTIONS, 256 MiB when unset on 64-bit Linux; one thread's 1 MiB
    `thread_local_quarantine_size_kb`) and its shadow (an eighth). It fills as a correct controller
    frees buffers: a rising RSS up to that much is no leak."""
    values = dict(p.split("=", 1) for p in re.split(r"[\s,:]+", options) if "=" in p)

    def value(name: str) -> int:
        try:
            return int(values.get(name, "-1"))
        except ValueError:
            return -1
    mb = value("quarantine_size_mb")
    if mb < 0 and value("quarantine_size") >= 0:      # (the older option, in bytes)
        mb = value("quarantine_size") >> 20
    thread_kb = value("thread_local_quarantine_size_kb")
    return ((256 if mb < 0 else mb) * 1024 + (1024 if thread_kb < 0 else thread_kb)) * 9 // 8


@dataclass(frozen=True)
class Rule:
    """When the RSS is a finding. Growth: after `warmup` samples (their highest RSS is the warm-up
    level, the working set the cases made), `sustain` samples in a row each at least the warm-up
    level plus max(`growth_kib`, `share` of that level), the newest the highest of them and `rise_kib`
    above the oldest (still rising: a cache that filled and stays full is not a leak, however large,
    nor are a page or two in and out after a buffer allocated at once). A controller's steady
    state and its allocator's noise (pages in and out, a trimmed heap) stay below. A false finding
    costs its user a hunt for a leak that is not there; a growth asked too large misses a leak on a
    rare packet kind (trial: 16 MiB missed 64 KiB per unknown packet ID, 7 % of the cases, in a
    90 s run; 1 MiB found it in 16 s). `allowance_kib` is added to the growth asked: what a
    sanitizer keeps of freed memory (`asan_allowance_kib`)."""

    limit_kib: Optional[float] = None       # --target-memory (None: no limit)
    growth_kib: Optional[float] = 1 * 1024    # --memory-growth (None: growth not judged)
    share: float = 0.5
    warmup: int = 5
    sustain: int = 5
    rise_kib: float = 16.0      # 4 pages: a leak of 4 KiB/s at least is seen rising
    period_s: float = 1.0
    allowance_kib: float = 0.0

    def text(self) -> str:
        parts = []
        if self.growth_kib is not None:
            parts.append(f"growth: {self.sustain} samples in a row at least max({self.growth_kib / 1024:g} MiB, "
                         f"{self.share:.0%}){self._allowed()} above the highest of the first {self.warmup}, "
                         f"the newest the highest, {self.rise_kib:g} KiB above the oldest")
        if self.limit_kib is not None:
            parts.append(f"limit: above {self.limit_kib / 1024:g} MiB")
        return "; ".join(parts) or "off"

    def _allowed(self) -> str:
        return f" + {self.allowance_kib / 1024:g} MiB of AddressSanitizer's quarantine" if self.allowance_kib else ""


@dataclass
class Sample:
    t: float
    rss_kib: int
    case: int             # the last case played (-1: none yet)
    packets: int          # case packets sent so far in the run


def packet_kind(data: bytes) -> str:
    """What a case packet is to the controller: its type and why it is illegal ("VRAI legal",
    "VRCI bad_crc", "unknown_id": any ID it does not know)."""
    fields = decode(data)
    problems = fields["problems"]
    if C.Problem.UNKNOWN_ID.value in problems:
        return " ".join(problems)
    return f"{fields.get('type', 'short')} {' '.join(problems) or 'legal'}"


class Watch:
    """One controller life's RSS series and the rule's verdict on it."""

    def __init__(self, rule: Rule) -> None:
        self.rule = rule
        self.life: Optional[tuple[int, int]] = None    # (pid, start number) of the controller
        self.started = 0.0
        self.next_at = 0.0
        self.series: list[Sample] = []                 # bounded: see _keep
        self.recent: collections.deque[Sample] = collections.deque(maxlen=rule.sustain)
        self.kinds: collections.Counter[str] = collections.Counter()   # case packets since the last sample
        self.intervals: collections.deque[tuple[int, collections.Counter[str]]] = collections.deque(maxlen=MAX_SERIES)
        self.count = 0
        self.warm: Optional[Sample] = None             # the last warm-up sample
        self.level = 0                                 # the warm-up level (KiB)
        self.reported = False
        self.last: Optional[int] = None                # of the run, across restarts
        self.peak = 0

    def sample(self, now: float, pid: int, start: int, case: int, packets: int) -> Optional[dict[str, Any]]:
        """Read the RSS of `pid`'s group (the controller's `start`th start) when a sample is due;
        the evidence when the rule fires."""
        if (pid, start) != self.life:
            self._restart((pid, start), now)
        if now < self.next_at:
            return None
        self.next_at = now + self.rule.period_s
        rss = group_rss_kib(pid)
        return None if rss is None else self.add(Sample(now, rss, case, packets))

    def _restart(self, life: tuple[int, int], now: float) -> None:
        self.life, self.started, self.next_at = life, now, now
        self.series, self.count, self.warm, self.level, self.reported = [], 0, None, 0, False
        self.recent.clear()
        self.kinds, self.intervals = collections.Counter(), collections.deque(maxlen=MAX_SERIES)

    def note(self, data: bytes) -> None:
        """A case packet went out (what `suspects` weighs)."""
        self.kinds[packet_kind(data)] += 1

    def add(self, s: Sample) -> Optional[dict[str, Any]]:
        """Take one sample; the evidence when the rule fires (once per controller life)."""
        rule = self.rule
        self.count += 1
        if self.series:
            self.intervals.append((s.rss_kib - self.series[-1].rss_kib, self.kinds))
        self.kinds = collections.Counter()
        self.last, self.peak = s.rss_kib, max(self.peak, s.rss_kib)
        self._keep(s)
        self.recent.append(s)
        if self.count <= rule.warmup:
            self.level = max(self.level, s.rss_kib)
            self.warm = s
        if self.reported:
            return None
        if rule.limit_kib is not None and s.rss_kib > rule.limit_kib:
            return self._fire("limit", f"RSS {_mib(s.rss_kib)} above --target-memory {rule.limit_kib / 1024:g} MiB")
        if rule.growth_kib is None or self.count < rule.warmup + rule.sustain:
            return None
        threshold = self.level + max(rule.growth_kib, rule.share * self.level) + rule.allowance_kib
        *before, newest = self.recent
        if (all(x.rss_kib >= threshold for x in self.recent) and newest.rss_kib > max(x.rss_kib for x in before)
                and newest.rss_kib >= before[0].rss_kib + rule.rise_kib):
            return self._fire("growth", f"RSS grew from {_mib(self.level)} (warm-up) to {_mib(s.rss_kib)}, "
                              "still rising")
        return None

    def _keep(self, s: Sample) -> None:
        """The series stays bounded on a run of days: every other sample dropped when full (the
        first and, MAX_SERIES being even, the newest kept)."""
        self.series.append(s)
        if len(self.series) > MAX_SERIES:
            self.series = self.series[:1] + self.series[2::2]

    def _fire(self, kind: str, what: str) -> dict[str, Any]:
        """The evidence: the series, and the growth since the warm-up ended per case and per packet
        sent meanwhile (a limit hit during the warm-up: since the first sample)."""
        self.reported = True
        s = self.series[-1]
        since = self.warm if self.warm is not None and self.warm is not s else self.series[0]
        per_case = _rate(s.rss_kib - since.rss_kib, s.case - since.case)
        rate = "" if per_case is None else (f"; {per_case:.1f} KiB per case over the {s.case - since.case} "
                                            f"cases of the last {s.t - since.t:.0f} s")
        suspects = self.suspects()
        if suspects:
            top = suspects[0]
            rate += (f"; it goes with {top['kind']} packets ({top['packets']} sent, "
                     f"{top['kib_per_packet']:.1f} KiB each, {top['share']:.0%} of the growth)")
        return {
            "kind": kind, "detail": what + rate, "rule": self.rule.text(), "period_s": self.rule.period_s,
            "warmup_kib": self.level, "rss_kib": s.rss_kib, "limit_kib": self.rule.limit_kib,
            "since_s": round(s.t - since.t, 3), "growth_kib": s.rss_kib - since.rss_kib,
            "cases": {"first": since.case + 1, "last": s.case, "count": max(0, s.case - since.case)},
            "packets": max(0, s.packets - since.packets),
            "kib_per_case": per_case,
            "kib_per_packet": _rate(s.rss_kib - since.rss_kib, s.packets - since.packets),
            "suspects": suspects,
            "series": [{"s": round(x.t - self.started, 3), "rss_kib": x.rss_kib, "case": x.case,
                        "packets": x.packets} for x in self.series],
        }

    def suspects(self) -> list[dict[str, Any]]:
        """The kinds of case packet whose count per sample interval goes with the RSS growth in it,
        most of the growth first. Chosen one by one, each the kind whose counts go best
        (`SUSPECT_CORRELATION`) with the growth the ones chosen do not yet explain, then fitted
        together (least squares, with a growth per interval of no kind): a kind that came once or
        twice beside the leaking one in a few intervals gets its growth back. A kind sent the same
        number of times in every interval, or no kind at all (a leak per second, or in the
        controller's own packets), gives none."""
        rows = list(self.intervals)
        kinds = sorted(set().union(*(k for _, k in rows)))
        if len(rows) < 3 or not kinds:
            return []
        growth = np.array([g for g, _ in rows], dtype=float)
        counts = np.array([[k[kind] for kind in kinds] for _, k in rows], dtype=float)
        chosen: list[int] = []
        per = np.zeros(0)
        left = growth - growth.mean()
        for _ in range(_SUSPECTS):
            r = [(_correlation(counts[:, j], left), j) for j in range(len(kinds)) if j not in chosen]
            best, j = max(r, default=(0.0, -1))
            if best < SUSPECT_CORRELATION:
                break
            chosen.append(j)
            design = np.column_stack([counts[:, chosen], np.ones(len(rows))])
            fit = np.linalg.lstsq(design, growth, rcond=None)[0]
            per, left = fit[:-1], growth - design @ fit
        total = max(float(growth.sum()), 1.0)
        out = [{"kind": kinds[j], "packets": int(counts[:, j].sum()), "kib_per_packet": round(float(b), 1),
                "share": round(float(b * counts[:, j].sum()) / total, 3)} for j, b in zip(chosen, per) if b > 0]
        return sorted(out, key=lambda x: -x["share"])

    def summary(self) -> dict[str, Any]:
        return {"oracle": "on", "rule": self.rule.text(), "rss_kib": self.last, "peak_kib": self.peak or None}


def _correlation(xs: np.ndarray, ys: np.ndarray) -> float:
    """Pearson's r (0 when either does not vary)."""
    dx, dy = xs - xs.mean(), ys - ys.mean()
    norm = float(np.sqrt((dx @ dx) * (dy @ dy)))
    return float(dx @ dy) / norm if norm > 0 else 0.0


def _rate(kib: int, count: int) -> Optional[float]:
    return round(kib / count, 3) if count > 0 else None


def _mib(kib: float) -> str:
    return f"{kib / 1024:.1f} MiB"
