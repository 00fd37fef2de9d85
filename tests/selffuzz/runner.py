"""Cases (a seed and an index give a base capture and its mutations), their runs through every
tool, the failures kept under out/fuzz-self/ (input + one-line description; never overwriting or
deleting anything), and the summary of a run. `python -m selffuzz` (tests/ on sys.path) or
scripts/fuzz-self runs a soak for FUZZ_SELF_SECONDS."""
from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import hashlib
import os
import random
import re
import shutil
import tempfile
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Sequence

from . import containers, mutators, oracles, tools

REPO = Path(__file__).resolve().parents[2]
BUNDLED = tuple(sorted(p for p in (REPO / "captures").iterdir() if p.suffix in (".pcap", ".pcapng")))
SMALL = tuple(p for p in BUNDLED if p.stat().st_size < 100_000)     # the bounded run's bases
OUT = REPO / "out" / "fuzz-self"


def budget(base: Path) -> float:
    """Seconds one tool may take on a mutation of `base`: 10 s, plus 5 s per 1000 records."""
    layout = containers.parse(base.read_bytes())
    return 10 + 5 * len(layout.packets if layout else ()) / 1000


@dataclass(frozen=True)
class Case:
    seed: int
    index: int
    base: Path
    steps: tuple[str, ...]
    data: bytes
    small: bool = False          # drawn from the bounded run's bases (SMALL), not all (BUNDLED)

    @property
    def name(self) -> str:
        return f"{self.base.stem}-s{self.seed}-c{self.index}{self.base.suffix}"


def make_case(seed: int, index: int, small: bool = False) -> Case:
    """The same seed, index and choice of bases give the same bytes."""
    rng = random.Random(f"{seed}/{index}")
    base = rng.choice(SMALL if small else BUNDLED)
    data, steps = mutators.mutate(base.read_bytes(), rng)
    return Case(seed, index, base, tuple(steps), data, small)


@dataclass
class Outcome:
    case: Case
    runs: list[tools.Run] = field(default_factory=list)
    failures: list[tuple[tools.Run, list[str]]] = field(default_factory=list)
    crc_auto: bool = True

    @property
    def recreate(self) -> str:
        c = self.case
        return f"scripts/fuzz-self --seed {c.seed} --case {c.index}" + (" --small" if c.small else "") + \
            ("" if self.crc_auto else " --fixed-crc")

    def describe(self) -> str:
        """One line: what failed, how the input was made, how to make it again."""
        failed = " / ".join(f"{r.tool.label}: {'; '.join(p)}" for r, p in self.failures)
        return f"{failed} | {self.case.base.name}: {', '.join(self.case.steps)} | recreate: {self.recreate}"


class Session:
    """The sites and tools of one run; cases are run in scratch directories of their own."""

    def __init__(self, all_sites: Sequence[tools.Site], crc_auto: bool = True) -> None:
        self.tools, self.crc_auto = tools.tools(all_sites, crc_auto), crc_auto

    def run(self, case: Case) -> Outcome:
        outcome, limit = Outcome(case, crc_auto=self.crc_auto), budget(case.base)
        placed: dict[int, Path] = {}
        try:
            for tool in self.tools:
                site = tool.site
                if id(site) not in placed:
                    (site.ws.dir / f"case-{case.seed}-{case.index}").mkdir(parents=True, exist_ok=True)
                    placed[id(site)] = site.place(f"case-{case.seed}-{case.index}/{case.name}", case.data)
                scratch = placed[id(site)].parent / tool.name.replace(" ", "_")
                run = tools.run(tool, placed[id(site)], scratch, timeout=2 * limit)
                outcome.runs.append(run)
                problems = oracles.judge(run, limit)
                if problems:
                    outcome.failures.append((run, problems))
            outcome.failures += oracles.disagreements(outcome.runs)
        finally:
            for path in placed.values():
                shutil.rmtree(path.parent, ignore_errors=True)
        return outcome


@contextlib.contextmanager
def session(base: Optional[Path] = None, crc_auto: bool = True) -> Iterator[Session]:
    with contextlib.ExitStack() as stack:
        root = base or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="selffuzz-")))
        yield Session(stack.enter_context(tools.sites(root)), crc_auto)


def keep(outcome: Outcome, out_dir: Path = OUT) -> Path:
    """The failing input and its one-line description under `out_dir`; an existing file is left."""
    out_dir.mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256(outcome.case.data).hexdigest()[:10]
    path = out_dir / f"{Path(outcome.case.name).stem}-{digest}{outcome.case.base.suffix}"
    for target, content in ((path, outcome.case.data), (path.with_name(path.name + ".txt"),
                                                         (outcome.describe() + "\n").encode())):
        with contextlib.suppress(FileExistsError), open(target, "xb") as f:
            f.write(content)
    return path


def summary(outcomes: Sequence[Outcome], seconds: float, kept: Sequence[Path] = ()) -> str:
    """Files tried, failures by tool, the slowest run of each tool, where the failing inputs are."""
    runs, failed, slowest = Counter(), Counter(), {}
    for o in outcomes:
        for r in o.runs:
            runs[r.tool.label] += 1
            if r.tool.label not in slowest or r.seconds > slowest[r.tool.label][0]:
                slowest[r.tool.label] = (r.seconds, o.case.name)
        for r, _ in o.failures:
            failed[r.tool.label] += 1
    lines = [(f"fuzz-self: {len(outcomes)} mutated files in {seconds:.0f} s, "
              f"{sum(1 for o in outcomes if o.failures)} with failures")]
    for label in runs:
        lines.append(f"  {label:<48} runs {runs[label]:>5}  failures {failed[label]:>4}  "
                     f"slowest {slowest[label][0]:5.1f} s ({slowest[label][1]})")
    kinds = defaultdict(list)
    for o in outcomes:
        for r, problems in o.failures:
            kinds[(r.tool.label, _kind(problems[0]))].append(o)
    for (label, kind), hit in sorted(kinds.items()):
        lines.append(f"  failure: {label}: {kind} ({len(hit)}x), e.g. {hit[0].recreate}")
    if kept:
        lines.append(f"  failing inputs: {len(kept)} under {kept[0].parent} (each with a .txt description)")
    return "\n".join(lines)


def _kind(problem: str) -> str:
    """A problem without its numbers: failures of one kind are counted together."""
    return "".join("#" if ch.isdigit() else ch for ch in re.sub(r"\S*/\S*", "FILE", problem))[:120]


def control(sess: Session, base: Path) -> list[tuple[tools.Run, list[str]]]:
    """Failures of the tools on an unmutated capture, where each must also exit 0 or 1: a tool that
    cannot even read a good capture would pass every fuzz oracle without testing anything."""
    outcome = sess.run(Case(0, 0, base, ("unmutated",), base.read_bytes()))
    bad = [(r, ["exit 2 on an unmutated capture: " + r.stderr.strip()[-300:]])
           for r in outcome.runs if r.returncode == 2 and r.tool.kind == "python"]
    return outcome.failures + bad


def soak(sess: Session, seed: int, seconds: float, jobs: int, small: bool = False,
         cases: Optional[Sequence[int]] = None) -> list[Outcome]:
    """Cases `seed`/0, 1, ... until `seconds` have passed (or exactly `cases`), `jobs` at a time."""
    deadline, outcomes = time.monotonic() + seconds, []
    indices = iter(cases) if cases is not None else iter(range(1 << 62))
    with concurrent.futures.ThreadPoolExecutor(jobs) as pool:
        pending = set()
        while True:
            while len(pending) < jobs and (cases is not None or time.monotonic() < deadline):
                index = next(indices, None)
                if index is None:
                    break
                pending.add(pool.submit(lambda i: sess.run(make_case(seed, i, small)), index))
            if not pending:
                return outcomes
            done, pending = concurrent.futures.wait(pending, return_when=concurrent.futures.FIRST_COMPLETED)
            outcomes += [f.result() for f in done]


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="fuzz-self", description=__doc__)
    parser.add_argument("--seconds", type=float, default=float(os.environ.get("FUZZ_SELF_SECONDS", "600")),
                        help="how long to start new cases (default: $FUZZ_SELF_SECONDS or 600)")
    parser.add_argument("--seed", type=int, default=int(os.environ.get("FUZZ_SELF_SEED", "0")) or None,
                        help="default: $FUZZ_SELF_SEED, else one from the clock (printed)")
    parser.add_argument("--case", type=int, action="append", help="run only these case indices (repeatable)")
    parser.add_argument("--small", action="store_true", help="mutate only the small captures (as make test does)")
    parser.add_argument("--fixed-crc", action="store_true",
                        help="tshark engine with --crc mpeg2 --crc-order little (as make test does)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=OUT, help="where failing inputs are kept")
    args = parser.parse_args(argv)
    seed = args.seed or int(time.time())
    print(f"fuzz-self: seed {seed}, {args.jobs} jobs, " +
          (f"cases {args.case}" if args.case else f"{args.seconds:.0f} s"), flush=True)
    start = time.monotonic()
    with session(crc_auto=not args.fixed_crc) as sess:
        broken = control(sess, SMALL[0])
        for run, problems in broken:
            print(f"  BROKEN on the unmutated {SMALL[0].name}: {run.tool.label}: {'; '.join(problems)}")
        outcomes = soak(sess, seed, args.seconds, args.jobs, args.small, args.case)
    kept = [keep(o, args.out) for o in outcomes if o.failures]
    print(summary(outcomes, time.monotonic() - start, kept))
    for o in [o for o in outcomes if o.failures][:5]:
        run, problems = o.failures[0]
        print(f"\n{o.case.name}: {run.tool.label}: {' '.join(run.command)}\n  {'; '.join(problems)}\n"
              f"  stderr: {run.stderr.strip()[-600:]}")
    return 1 if kept or broken else 0
