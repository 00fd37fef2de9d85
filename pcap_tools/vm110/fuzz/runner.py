"""A fuzzing run: cases in schedule order, triggers confirmed by replay and minimised, findings saved.

A trigger is a finding only when replaying its case (against a freshly restarted controller when
`--target-cmd` is given) triggers the same oracle again; triggers that do not reproduce are listed
in `findings.json` as unreproduced, so that a hiccup of a loaded machine is visible but not
reported as a bug.

One finding per bug: each trigger has a signature (a crash's: signal, sanitizer error type, top
frames; other oracles': oracle, kind, packet type). A trigger whose signature has a bucket only
counts there (no replays, no minimising; a smaller case may replace the reproducer). A crash is
pinned on the cases sent since the controller last spoke by bisecting their prefixes. Cases come
from the schedule (blind) or from `guided.Guided` (`--coverage`).
"""
from __future__ import annotations

import collections
import dataclasses
import shlex
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Callable, Optional

from .. import constants as C
from ..errors import CliError
from ..fileio import check_target
from . import cases as K
from . import findings as F
from . import memory as MEM
from .guided import Guided, GuidedConfig
from .link import taken
from .minimize import ddmin, difference, minimize
from .oracles import CRASH, MALFORMED_OUTPUT, MEMORY, MISSING_ACK, STALL, VRCO_RETRANSMIT, Monitor, Trigger
from .session import Sent, Session, Settings, TargetLost
from .supervisor import Supervisor

TRIAL = -1               # the case index of replayed packets
_MAX_SUSPECTS = 12       # replayed one by one (a stall's replay takes over 2 s)
_MAX_BISECTED = 400      # a stall's suspects bisected when none of those replayed triggers it
_MAX_LISTED = 100         # suspects listed when none could be replayed (the controller is gone)
_STATUS_EVERY_S = 0.5
_RATE_WINDOW_S = 5.0      # the status line's current rate: cases over about the last 5 s
_DYING_WAIT_S = 10.0      # for a sanitizer's report to be written
_SMALLER_TRIES = 3        # replays per bug of smaller cases that hit it again
_MISSES_IN_A_ROW = 3      # triggers of one kind that did not replay, then only every ...
_SAMPLE_EVERY = 10        # ... 10th of its triggers is replayed (a crash's always are)


@dataclass
class Replay:
    """A case as it was sent: exact bytes, delays, and what the base unit did around them."""

    packets: list[Sent]
    pause_vrpi_ms: float = 0.0
    withhold_vrai_ms: float = 0.0
    stream: Optional[dict[str, Any]] = None
    settle_ms: float = 0.0
    parts: list["Replay"] = field(default_factory=list)    # cases played in turn, each as it was sent

    @classmethod
    def of(cls, case: K.Case, sent: list[Sent]) -> "Replay":
        return cls(sent, case.pause_vrpi_ms, case.withhold_vrai_ms, case.stream, case.settle_ms)

    @classmethod
    def sequence(cls, replays: list["Replay"]) -> "Replay":
        """Several cases one after the other, each with its own stream, pause and withholding (a
        crash that the disarmed stream of one case made was not confirmed: its packets alone went)."""
        return cls([p for r in replays for p in r.packets], parts=replays)


@dataclass
class RunConfig:
    settings: Settings
    seed: int = 0
    duration_s: Optional[float] = 60.0
    cases: Optional[int] = None
    out: Path = Path("fuzz-out")
    target_cmd: Optional[str] = None
    minimize_budget_s: float = 30.0
    max_findings: int = 20
    progress: Callable[[str], None] = field(default=lambda text: None)
    status: Optional[Callable[[dict[str, Any]], None]] = None    # the progress line on a terminal
    core: bool = True
    coverage: Optional[GuidedConfig] = None
    stop: Callable[[], bool] = field(default=lambda: False)   # Ctrl-C or SIGTERM came (KeyboardInterrupt may not)
    memory: MEM.Rule = field(default_factory=MEM.Rule)      # the memory oracle's (with --target-cmd)


def _const(data: bytes, twin: bytes) -> K.Builder:
    return lambda serial: (data, twin)


def trial(session: Session, replay: Replay, oracle: str, signature: Optional[str] = None,
          strict: bool = True) -> Optional[Trigger]:
    """Play `replay` once: the trigger of `oracle` it caused (with `signature`, the trigger's kind,
    for a crash or a malformed output, when given: a crash with another stack, a serial going back
    where an ack of a command never sent was seen, is another bug; not `strict`: one of that kind
    first, else another), else None."""
    main = session.monitor
    mon = session.monitor = main.fork()
    try:
        for part in replay.parts or [replay]:
            steps = [(_const(p.data, p.twin), p.delay_ms, p.expect_ack) for p in part.packets]
            session.run_steps(TRIAL, steps, part.pause_vrpi_ms, part.withhold_vrai_ms, part.stream, part.settle_ms)
        _observe(session, mon, oracle, time.time())
        if oracle != CRASH and any(t.oracle == CRASH for t in mon.triggers):
            return None      # it crashed: that is the crash oracle's finding, not this one's
        fired = [t for t in mon.triggers if _counts_as(t, oracle)]
        if signature is not None and oracle in _BY_KIND:
            same = [t for t in fired if t.kind == signature]
            fired = same if strict or same else fired
        return fired[0] if fired else None
    finally:
        session.monitor = main
        for t in mon.triggers:
            F.discard_core(session.evidence_dir, t.crash)
        main.adopt(mon)


_BY_KIND = (CRASH, MALFORMED_OUTPUT)    # oracles whose kinds are different bugs


def _counts_as(trig: Trigger, oracle: str) -> bool:
    """`trig` is a trigger of `oracle`: a stall that holds an unacknowledged command, or an ack with
    a wrong ID that answered one, is a missing ack as well (the monitor reports the one bug once, as
    the stall or the malformed output; which the run saw may depend on the IDs it had sent before)."""
    return trig.oracle == oracle or (oracle == MISSING_ACK and (
        (trig.oracle == STALL and trig.command_id is not None) or trig.answered is not None))


def _observe(session: Session, mon: Monitor, oracle: str, t_end: float) -> None:
    limits = mon.limits
    fired = lambda: any(_counts_as(t, oracle) for t in mon.triggers)   # noqa: E731
    if oracle == STALL:
        # A stall that starts within `grace` of the packets: VRPO after that clears the case.
        grace = max(0.3, 2 * mon.vrpo_interval)
        deadline = t_end + grace + limits.stall_ms / 1000
        while time.time() < deadline:
            if mon.last_vrpo is not None and mon.last_vrpo > t_end + grace:
                return
            session.pump(min(deadline, time.time() + 0.02))
        mon.fire(Trigger(STALL, time.time(), "no VRPO after the replayed packets"))
        return
    window = {CRASH: 0.5, VRCO_RETRANSMIT: session.settings.vrco_wait_s}.get(
        oracle, limits.ack_timeout_ms / 1000 + 0.3)
    deadline = t_end + window
    while time.time() < deadline and not fired():
        session.pump(min(deadline, time.time() + 0.02))
    hung_until = t_end + (limits.ack_timeout_ms + limits.stall_ms) / 1000 + 0.5
    while oracle == MISSING_ACK and mon.held and not fired() and time.time() < hung_until:
        session.pump(time.time() + 0.02)      # an ack held by a silent controller: a stall, or late
    # A crash may come a while after its packet (a loop that ends in an overflow, memory running
    # out), and a controller restarted by its own service manager comes back later still: one silent
    # since the packets may yet die or come back, up to the stall limit (past it, the run would have
    # seen a stall first).
    grace = max(0.3, 2 * mon.vrpo_interval)
    silent_until = t_end + grace + limits.stall_ms / 1000
    while oracle in (CRASH, MALFORMED_OUTPUT) and not fired() and time.time() < silent_until \
            and (mon.last_vrpo is None or mon.last_vrpo <= t_end + grace):
        session.pump(min(silent_until, time.time() + 0.02))
    dying_until = time.time() + _DYING_WAIT_S
    while oracle == CRASH and not fired() and session.supervisor is not None and session.supervisor.dying() \
            and time.time() < dying_until:
        session.pump(time.time() + 0.02)


def start_target(s: Session) -> None:
    """Start the controller (when supervised) and wait until it sends VRPO."""
    if s.supervisor is not None:
        if taken(s.settings.target):
            # (a controller left running by a run that was killed: ours could not bind the port,
            # and its VRPO would make a controller the fuzzer neither started nor watches look like ours)
            raise TargetLost(f"another process already receives on {s.settings.target[0]}:{s.settings.target[1]} "
                             "(a controller left running by an earlier run?): the one --target-cmd starts could "
                             "not; stop it first")
        s.supervisor.start()
    if not s.wait_for_vrpo(0.0, s.settings.startup_s):
        where = f"{s.link.local[0]}:{s.link.local[1]}"
        code = s.supervisor.poll() if s.supervisor else None
        if code is not None and s.supervisor is not None:
            raise TargetLost(f"the controller exited with code {code} before sending any VRPO to {where}"
                             + s.supervisor.last_words())
        raise TargetLost(f"no VRPO from the controller on {where} within {s.settings.startup_s:.0f} s")
    s.settle()
    _forget_triggers(s.monitor)     # whatever happened before the first VRPI is not a case's doing


def _forget_triggers(monitor: Monitor) -> None:
    """Drop the triggers judged or not the cases' doing; not the memory oracle's, which fires once
    per controller life, on no case (a controller over --target-memory from its start)."""
    monitor.triggers = [t for t in monitor.triggers if t.oracle == MEMORY]


_PACKET_TYPES = frozenset(t.value for t in C.PacketType)


def case_kind(case: Optional[K.Case], shown: Optional[Sent] = None) -> str:
    """The packet type a case mutates (its description begins with it), else the type of `shown`,
    the packet of the case a finding shows (a sequence's: the command ID wrap is VRCI, as a
    VRCI field case on the same ID is), else its family: how the fuzz mutated the packet (its
    fields, its structure, its bytes, a sequence) is no part of a bug's signature, the packet it
    reached is."""
    if case is None:
        return "none"
    first = case.description.split(" ", 1)[0]
    if first in _PACKET_TYPES:
        return first
    sent_as = shown.twin[:C.ID_LEN].decode("latin-1") if shown is not None else ""
    return sent_as if sent_as in _PACKET_TYPES else case.family


class RecentRate:
    """Cases per second over about the last `window_s` (AFL++'s exec speed): the average since the
    start hides a controller, or a fuzzer busy replaying, that has slowed down an hour into a run."""

    def __init__(self, window_s: float, now: float) -> None:
        self.window_s = window_s
        self.samples: collections.deque[tuple[float, int]] = collections.deque([(now, 0)])

    def update(self, now: float, count: int) -> float:
        """The rate from the newest sample at least `window_s` old (else the first) to `count` now."""
        self.samples.append((now, count))
        while len(self.samples) > 2 and self.samples[1][0] <= now - self.window_s:
            self.samples.popleft()
        then, before = self.samples[0]
        return (count - before) / max(1e-6, now - then)


class Runner:
    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = cfg
        # What can be refused (the command, the dictionary, the corpus folder, the map) before --out
        # is made and the socket opened: a bad option leaves no files.
        self.supervisor = Supervisor(cfg.target_cmd, core=cfg.core) if cfg.target_cmd else None
        # Only a controller the fuzzer started has a process to measure.
        self.memory_off = "no --target-cmd: only a controller the fuzzer starts is measured" \
            if self.supervisor is None else MEM.unavailable()
        rule = cfg.memory
        if self.supervisor is not None and self.supervisor.asan:
            options = self.supervisor.environment().get("ASAN_OPTIONS", "")
            rule = dataclasses.replace(rule, allowance_kib=MEM.asan_allowance_kib(options))
        memory = MEM.Watch(rule) if self.memory_off is None else None
        self._log: Optional[IO[bytes]] = None
        self.guided: Optional[Guided] = None
        try:
            self.guided = Guided(cfg.coverage, cfg.seed) if cfg.coverage else None
            if self.guided is not None and self.supervisor is not None:
                self.supervisor.extra_env.update(self.guided.environment())
            F.make_folder(cfg.out, "--out")
            if self.supervisor is not None:
                self._log = self.supervisor.log = _open_log(cfg.out, self.supervisor.command)
            self.session = Session(cfg.settings, self.supervisor, cfg.out, memory)
        except BaseException:
            if self._log is not None:
                self._log.close()
            if self.guided is not None:
                self.guided.close()
            raise
        self.records: collections.OrderedDict[int, tuple[K.Case, list[Sent]]] = collections.OrderedDict()
        self.findings: list[F.Finding] = []
        self.files: list[str] = []
        self.unreproduced: list[dict[str, Any]] = []
        self.repeats: collections.Counter[str] = collections.Counter()
        self.buckets: dict[str, F.Bucket] = {}
        self.cases_run = 0
        self.restarts = 0          # the fuzzed controller restarted: it crashed, hung or leaked
        self.replay_starts = 0     # controllers started for replays, and a clean one after them
        self.started = time.time()
        self.end: Optional[float] = None
        self._last_status = 0.0
        self.recent = RecentRate(_RATE_WINDOW_S, self.started)
        self.stopped_early: Optional[str] = None
        self.interrupted = False             # by Ctrl-C or SIGTERM (stopped_early says so too)
        self.controller_lost = False         # the controller stopped while being fuzzed, for good
        self.judged_again: set[int] = set()   # cases played again after a crash cut their verdict short
        self.misses: collections.Counter[str] = collections.Counter()   # kind -> triggers since one replayed

    # --- the run ----------------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg, s = self.cfg, self.session
        self.started = time.time()
        self.recent = RecentRate(_RATE_WINDOW_S, self.started)
        end = None if cfg.duration_s is None else self.started + cfg.duration_s
        index = 0
        self.end = end
        try:
            if self.guided is not None:
                self.guided.open(cfg.target_cmd)
            start_target(s)
            while (cfg.cases is None or index < cfg.cases) and (end is None or time.time() < end) \
                    and len(self.findings) < cfg.max_findings:
                self._check_stop()
                case = self.guided.next_case(index) if self.guided else K.generate(cfg.seed, index)
                if self.guided is not None:
                    self.guided.before_case()
                sent = self._play(index, case)
                if self.guided is not None:
                    self.guided.after_case(s, case, sent)
                while len(self.records) > F.MAX_CASES:
                    self.records.popitem(last=False)
                self.cases_run = index = index + 1
                if s.monitor.triggers:
                    self._investigate_all()
                    self._judge_again()
                self._status()
            # The last cases are judged too: wait out the ack timeout and the VRPO watchdog.
            limits = s.settings.limits
            s.pump(time.time() + max(limits.ack_timeout_ms, limits.stall_ms) / 1000 + 0.2)
            self._investigate_all()
            if len(self.findings) >= cfg.max_findings:
                self.stopped_early = f"--max-findings {cfg.max_findings} reached"
        except TargetLost as exc:
            self.stopped_early = str(exc)
            # Nothing restarts it, or --target-cmd could not (a lock file its dead self left): the
            # trigger is unreproduced, but no pass.
            self.controller_lost = self.cases_run > 0
        except KeyboardInterrupt:          # Ctrl-C, SIGTERM: what was found is still summarised
            self.stopped_early, self.interrupted = "interrupted", True
        finally:
            s.close()
            if self._log is not None:
                self._log.close()
            if self.guided is not None:
                self.guided.close()
        return self.summary()

    def _play(self, index: int, case: K.Case) -> list[Sent]:
        sent = self.session.run_steps(index, [(st.build, st.delay_ms, st.expect_ack) for st in case.steps],
                                      case.pause_vrpi_ms, case.withhold_vrai_ms, case.stream, case.settle_ms)
        self.records[index] = (case, sent)
        return sent

    def _judge_again(self) -> None:
        """The cases whose acks a crash cut short (sent before the controller last spoke: none of
        its suspects), played once more to the restarted controller: a missing ack among them is a
        bug of its own (one was dropped with a crash that came 0.5 s later)."""
        again, self.session.monitor.cut_short = self.session.monitor.cut_short, []
        for index in again:
            if index in self.records and index not in self.judged_again:
                self.judged_again.add(index)
                self._play(index, self.records[index][0])

    def _status(self, force: bool = False) -> None:
        now = time.time()
        if self.cfg.status is None or (not force and now - self._last_status < _STATUS_EVERY_S):
            return
        self._last_status = now
        elapsed = max(1e-6, now - self.started)
        left = None if self.end is None else max(0.0, self.end - now)
        line: dict[str, Any] = {"cases": self.cases_run, "rate": self.cases_run / elapsed,
                                "rate_now": self.recent.update(now, self.cases_run),
                                "findings": len(self.findings),
                                "triggers": sum(b.count for b in self.buckets.values()), "left_s": left}
        if self.guided is not None:
            line.update(edges=self.guided.edges(), corpus=len(self.guided.corpus))
        if self.session.memory is not None and self.session.memory.last is not None:
            line.update(rss_kib=self.session.memory.last)
        self.cfg.status(line)

    def summary(self) -> dict[str, Any]:
        cfg = self.cfg
        counts = collections.Counter(f.oracle for f in self.findings)
        return {
            "schema": F.SCHEMA, "seed": cfg.seed, "target": "%s:%d" % cfg.settings.target,
            "cases_run": self.cases_run, "duration_s": round(time.time() - self.started, 3),
            "restarts": self.restarts, "replay_starts": self.replay_starts,
            "started": round(self.started, 6),
            "findings": [{"oracle": f.oracle, "case_index": f.case_index, "mutation": f.mutation,
                          "detail": f.detail, "signature": f.signature, "file": name, "time": f.time,
                          "pcap": f.pcap, "frame": f.frame, "display_filter": f.display_filter,
                          **({"rerun": f.memory["rerun"]} if f.memory else {})}
                         for f, name in zip(self.findings, self.files)],
            "counts": dict(counts), "repeats": dict(self.repeats), "unreproduced": self.unreproduced,
            "buckets": [b.to_json() for b in self.buckets.values()],
            "controller_lost": self.controller_lost,
            "sanitizer_options": self.supervisor.sanitizer_options if self.supervisor else {},
            "core_files": self.supervisor.core_files() if self.supervisor else None,
            "stopped_early": self.stopped_early,
            "memory": self.session.memory.summary() if self.session.memory is not None else
            {"oracle": "off", "why": self.memory_off},
            **({"coverage": self.guided.summary()} if self.guided else {}),
        }

    # --- triggers -----------------------------------------------------------------------------------
    def _settle(self) -> None:
        """Let outstanding acknowledgements arrive (or time out) before replays borrow the link."""
        s = self.session
        deadline = time.time() + s.settings.limits.ack_timeout_ms / 1000 + 0.05
        while s.monitor.pending and time.time() < deadline:
            s.pump(min(deadline, time.time() + 0.02))

    def _investigate_all(self) -> None:
        s = self.session
        self._settle()
        queue, s.monitor.triggers = s.monitor.triggers, []
        # A controller that died or hung in the cases, or leaks, needs a restart whatever is replayed.
        needed = not s.healthy() or any(t.oracle == MEMORY for t in queue)
        investigated = False
        for n, trig in enumerate(queue):
            if len(self.findings) >= self.cfg.max_findings:
                F.discard_core(self.cfg.out, trig.crash)      # not investigated: not kept
                continue
            try:
                investigated = self._investigate(trig) or investigated
            except (TargetLost, KeyboardInterrupt) as exc:
                # The controller gone for good, or the user stopping us: the triggers not confirmed
                # yet are kept with their cases, not replayed.
                why = str(exc) if isinstance(exc, TargetLost) else "interrupted"
                for left in queue[n:]:
                    self._unreproduced(left, self._suspects(left), why)
                raise
        if investigated or not s.healthy():
            self._recover(needed)
        s.monitor.pending.clear()
        s.monitor.unacked.clear()
        _forget_triggers(s.monitor)    # what happened during replays was judged there

    def _recover(self, needed: bool) -> None:
        """Back to a clean controller: restart it (a restart of the run's when `needed`, else one
        for the replays), or wait for it to come back on its own."""
        s = self.session
        if self.supervisor is not None:
            if needed:
                self.restarts += 1
            else:
                self.replay_starts += 1
            s.restart_target()
        elif not s.healthy() and not s.wait_for_vrpo(time.time(), s.settings.startup_s):
            raise TargetLost("the controller stopped sending VRPO and there is no --target-cmd to restart it")

    def _signature(self, trig: Trigger, index: Optional[int]) -> str:
        """What makes two triggers the same bug: a crash's own signature; for the other oracles,
        the oracle, what it judged and the packet type of the case."""
        if trig.oracle == CRASH:
            return f"crash {trig.kind}"
        if index is None or index not in self.records:
            return f"{trig.oracle} {trig.kind} ({case_kind(None)})"
        case, sent = self.records[index]
        return f"{trig.oracle} {trig.kind} ({case_kind(case, _pick(sent, trig.command_id))})"

    def _investigate(self, trig: Trigger) -> bool:
        """Confirm `trig` by replaying its suspects; save a finding. True if replays were run."""
        if trig.oracle == MEMORY:
            self._memory(trig)
            return True        # restarted: a leaking controller is not left to grow
        suspects = self._suspects(trig)
        spontaneous = not trig.suspects and trig.case_index is None
        # A trigger whose signature has a bucket is that bug again: counted, not replayed.
        candidates: list[Optional[int]] = list(suspects) if trig.oracle != CRASH and suspects else [None]
        for i in candidates:
            bucket = self.buckets.get(self._signature(trig, i))
            if bucket is not None:
                bucket.hit(trig.time)
                self.repeats[trig.oracle] += 1
                F.discard_core(self.cfg.out, trig.crash)
                culprit = i if i is not None else (suspects[0] if len(suspects) == 1 else None)
                return self._smaller(trig, bucket, culprit)
        if self._sampled_out(trig, suspects):
            return False
        replayed = len(suspects) if trig.oracle == CRASH else min(len(suspects), _MAX_SUSPECTS)
        what = "observing the controller again" if spontaneous else f"replaying {replayed} suspect case(s)"
        self.cfg.progress(f"{_headline(trig)}; {what}")
        traffic = [p for p in self.session.traffic if p[0] >= trig.time - 4.0]
        if spontaneous:   # nothing the cases did: does the controller do it again on its own?
            if self._trial(Replay([]), trig):
                vrai = trig.packet or b""
                what = "none: the base unit's normal VRAI" if trig.packet else "none: no case in the window"
                self._write(trig, None, max(0, self.cases_run - 1), F.NO_CASE, what, [],
                            Sent(trig.time, vrai, vrai, 0.0, False), None, False, None, traffic)
            else:
                self._unreproduced(trig, [])
            return True
        if trig.oracle == CRASH and len(suspects) > 1:
            return self._bisect(trig, suspects, traffic)
        for index in suspects[:_MAX_SUSPECTS]:
            if self._trial(Replay.of(*self.records[index]), trig):
                case, sent = self.records[index]
                kept, shown, small, complete = self._minimize(trig, case, sent)
                self._write(trig, index, index, case.family, case.description, kept, shown, small, complete, case,
                            traffic)
                self.misses[f"{trig.oracle} {trig.kind}"] = 0
                return True
        if trig.oracle == STALL and len(suspects) > _MAX_SUSPECTS:
            # At 100 cases/s and more, the VRPO cycles around a silence hold more cases than are
            # replayed one by one: they are bisected in the order sent, as a crash's are.
            chosen = sorted(suspects[:_MAX_BISECTED])
            self.cfg.progress(f"{trig.oracle}: no single case of the {_MAX_SUSPECTS} nearest; "
                              f"bisecting {len(chosen)} case(s)")
            return self._bisect(trig, chosen, traffic)
        self.misses[f"{trig.oracle} {trig.kind}"] += 1
        self._unreproduced(trig, suspects[:_MAX_SUSPECTS])
        return True

    def _sampled_out(self, trig: Trigger, suspects: list[int]) -> bool:
        """A kind of trigger that keeps not replaying (a controller that drops acks when a case rate
        overloads it, and acks the same command alone) is replayed only every `_SAMPLE_EVERY`th
        time: each replay takes seconds and a restart, and a run spent on them fuzzed nothing. A
        bug of that kind triggers again and is still found; a crash is always replayed."""
        key = f"{trig.oracle} {trig.kind}"
        missed = self.misses[key]
        if trig.oracle == CRASH or missed < _MISSES_IN_A_ROW or (missed - _MISSES_IN_A_ROW + 1) % _SAMPLE_EVERY == 0:
            return False
        if missed == _MISSES_IN_A_ROW:
            self.cfg.progress(f"{trig.oracle}: {missed} triggers in a row did not replay: from now on every "
                              f"{_SAMPLE_EVERY}th is replayed, the others listed (unreproduced, not_replayed)")
        self.misses[key] += 1
        self._unreproduced(trig, suspects, f"{missed} {key} triggers in a row did not replay: only every "
                           f"{_SAMPLE_EVERY}th is replayed")
        return True

    def _memory(self, trig: Trigger) -> None:
        """A memory finding is its evidence, not a case: memory grows over many cases and no replay
        of one would show it. Its rerun is the run's own seed and cases."""
        bucket = self.buckets.get(self._signature(trig, None))
        if bucket is not None:
            bucket.hit(trig.time)
            self.repeats[trig.oracle] += 1
            return
        assert trig.memory is not None
        cases = trig.memory["cases"]
        trig.memory.update(seed=self.cfg.seed, cases_run=self.cases_run, rerun=self._rerun(max(1, cases["last"] + 1)))
        traffic = [p for p in self.session.traffic if p[0] >= trig.time - 4.0]
        description = f"the {cases['count']} cases sent meanwhile, {cases['first']} to {cases['last']}" \
            if cases["count"] else "none: no case was sent meanwhile"
        self._write(trig, None, max(0, cases["last"]), F.NO_CASE, description, [], None, None, False, None, traffic)

    def _rerun(self, cases: int) -> str:
        """The command line that sends the same cases again (blind: from the seed; --coverage's
        depend on its corpus too), with the memory oracle as it was."""
        st, rule = self.cfg.settings, self.cfg.memory
        words = ["vm110", "fuzz", "--target", "%s:%d" % st.target, "--listen", "%s:%d" % st.listen,
                 "--target-cmd", self.cfg.target_cmd or "", "--seed", str(self.cfg.seed), "--cases", str(cases),
                 "--rate", f"{st.rate:g}", "--memory-growth", f"{(rule.growth_kib or 0) / 1024:g}"]
        if rule.limit_kib is not None:
            words += ["--target-memory", f"{rule.limit_kib / 1024:g}"]
        if not st.resend_ms:
            words += ["--no-resend"]
        if self.guided is not None:
            words += ["--coverage"]
        return shlex.join(words + ["--out", "fuzz-rerun"])

    def _smaller(self, trig: Trigger, bucket: F.Bucket, index: Optional[int]) -> bool:
        """A known bug hit by a smaller case than its reproducer: when a replay confirms it, that
        case becomes the reproducer. True if a replay was run."""
        if index is None or index not in self.records or bucket.tries >= _SMALLER_TRIES:
            return False
        case, sent = self.records[index]
        if _size(sent) >= bucket.size:
            return False
        bucket.tries += 1
        if self._trial(Replay.of(case, sent), trig) is None:
            return True
        finding = self.findings[bucket.number - 1]
        shown = _pick(sent, trig.command_id)
        finding.case_index, finding.family, finding.mutation = index, case.family, case.description
        finding.packet_hex = finding.original_hex = shown.data.hex() if shown else ""
        finding.valid_hex = shown.twin.hex() if shown else ""
        finding.differences = difference(shown.data, shown.twin) if shown else 0
        finding.minimised = finding.valid_triggers = False
        finding.steps = [{"hex": p.data.hex(), "valid_hex": p.twin.hex(),
                          "delay_ms": p.delay_ms if len(sent) > 1 else 0.0, "expect_ack": p.expect_ack} for p in sent]
        finding.pause_vrpi_ms, finding.withhold_vrai_ms = case.pause_vrpi_ms, case.withhold_vrai_ms
        finding.stream, finding.settle_ms, finding.cases = _jsonable(case.stream), case.settle_ms, None
        traffic = [p for p in self.session.traffic if p[0] >= trig.time - 4.0]
        F.write_finding(self.cfg.out, bucket.number, finding, traffic, self.session.link.local)
        bucket.size, bucket.replaced = _size(sent), bucket.replaced + 1
        self.cfg.progress(f"{bucket.file}: smaller reproducer, case {index} ({case.description})")
        return True

    def _bisect(self, trig: Trigger, suspects: list[int], traffic: list[Any]) -> bool:
        """A crash (or a stall) and many cases since the controller last spoke: the fewest of them
        that, played in order, trigger it again (one case, or a sequence when the bug needs a state)."""
        deadline = time.time() + self.cfg.minimize_budget_s

        def replay_of(chosen: list[object]) -> Replay:
            return Replay.sequence([Replay.of(*self.records[int(i)]) for i in chosen])   # type: ignore[call-overload]

        cache: dict[tuple[object, ...], bool] = {}

        def test(chosen: list[object]) -> bool:
            if time.time() > deadline:
                raise _Budget
            key = tuple(chosen)
            if key not in cache:
                cache[key] = self._trial(replay_of(chosen), trig) is not None
            return cache[key]
        cut = False
        try:
            chosen = _culprits(list(suspects), test)
        except _Budget:
            # The budget ran out, not the crash: the fewest cases seen to crash it are the
            # reproducer, not minimised (it was said to be a crash no replay made again)
            crashed = [list(key) for key, hit in cache.items() if hit]
            chosen, cut = min(crashed, key=len) if crashed else None, True
        if not chosen:
            self._unreproduced(trig, suspects)
            return True
        if len(chosen) == 1 and not cut:
            index = int(chosen[0])  # type: ignore[call-overload]
            case, sent = self.records[index]
            kept, shown, small, complete = self._minimize(trig, case, sent)
            self._write(trig, index, index, case.family, case.description, kept, shown, small, complete, case, traffic)
            return True
        indexes = [int(i) for i in chosen]  # type: ignore[call-overload]
        per_case, complete = self._fewest_packets(trig, [Replay.of(*self.records[i]) for i in indexes])
        complete = complete and not cut
        sent = [p for packets in per_case for p in packets]
        description = " then ".join(f"[{self.records[i][0].description}]" for i in indexes)
        # Each case is kept with what the base unit did during it (its stream, a pause): the
        # replay plays them in turn, as the bisection did.
        cases = [_case_json(i, self.records[i][0], packets) for i, packets in zip(indexes, per_case)]
        self._write(trig, indexes[-1], indexes[-1], "sequence-of-cases", description, sent, _pick(sent, None), None,
                    complete, None, traffic, cases)
        return True

    def _fewest_packets(self, trig: Trigger, parts: list[Replay]) -> tuple[list[list[Sent]], bool]:
        """The fewest packets of cases played in turn that still trigger, each case with its own
        (none, it may be, when its stream or pause is what it adds); complete: within the budget."""
        deadline = time.time() + self.cfg.minimize_budget_s
        owner = [n for n, part in enumerate(parts) for _ in part.packets]
        flat = [p for part in parts for p in part.packets]

        def split(chosen: list[object]) -> list[list[Sent]]:
            return [[flat[int(j)] for j in chosen if owner[int(j)] == n]  # type: ignore[call-overload]
                    for n in range(len(parts))]

        def test(chosen: list[object]) -> bool:
            if time.time() > deadline:
                raise _Budget
            return self._trial(Replay.sequence([
                Replay(packets, part.pause_vrpi_ms, part.withhold_vrai_ms, part.stream, part.settle_ms)
                for part, packets in zip(parts, split(chosen))]), trig) is not None
        chosen: list[object] = list(range(len(flat)))
        try:
            chosen = ddmin(chosen, test)
        except _Budget:
            return split(chosen), False
        return split(chosen), True

    def _suspects(self, trig: Trigger) -> list[int]:
        """The cases that may have caused `trig` and are still kept."""
        return [i for i in ([trig.case_index] if trig.case_index is not None else trig.suspects) if i in self.records]

    def _unreproduced(self, trig: Trigger, suspects: list[int], not_replayed: Optional[str] = None) -> None:
        F.discard_core(self.cfg.out, trig.crash)
        kept = suspects[:_MAX_LISTED if not_replayed is not None else _MAX_SUSPECTS]
        entry: dict[str, Any] = {"oracle": trig.oracle, "detail": trig.detail, "time": trig.time, "suspects": kept}
        if not_replayed is not None:     # the controller is gone: the cases are all there is to go on
            entry["not_replayed"] = not_replayed
            entry["suspect_cases"] = [self.records[i][0].description for i in kept]
        self.unreproduced.append(entry)

    def _check_stop(self) -> None:
        if self.cfg.stop():
            raise KeyboardInterrupt

    def _trial(self, replay: Replay, trig: Trigger) -> Optional[Trigger]:
        """One replay against a clean controller: restarted first when supervised, so that no
        state left by earlier replays decides the result."""
        self._check_stop()
        s = self.session
        if self.supervisor is not None:
            self.replay_starts += 1
            s.restart_target()
        elif not s.healthy() and not s.wait_for_vrpo(time.time(), s.settings.startup_s):
            raise TargetLost("the controller stopped sending VRPO and there is no --target-cmd to restart it")
        return trial(s, replay, trig.oracle, trig.kind)

    def _minimize(self, trig: Trigger, case: K.Case,
                  sent: list[Sent]) -> tuple[list[Sent], Optional[Sent], Optional[Sent], bool]:
        """(the packets of the case kept, the packet the finding shows, its minimised version or
        None, complete): first the fewest steps of the case that still trigger, then, with one
        packet left, its fewest changes; that is none (the twin itself) when its valid twin
        triggers too (the case's fields are then not the cause). `trig` comes to name the command
        the packets kept trigger on."""
        deadline = time.time() + self.cfg.minimize_budget_s

        def hit(packets: list[Sent]) -> Optional[Trigger]:
            if time.time() > deadline:
                raise _Budget
            return self._trial(Replay(packets, case.pause_vrpi_ms, case.withhold_vrai_ms, case.stream,
                                      case.settle_ms), trig)

        def again(packets: list[Sent]) -> bool:
            return hit(packets) is not None
        chosen: list[object] = list(range(len(sent)))
        complete = True
        cache: dict[tuple[object, ...], Optional[Trigger]] = {tuple(chosen): trig}   # subset -> what it triggered
        if len(chosen) > 1:
            def test(subset: list[object]) -> bool:
                if tuple(subset) not in cache:
                    cache[tuple(subset)] = hit([sent[int(i)] for i in subset])  # type: ignore[call-overload]
                return cache[tuple(subset)] is not None
            try:
                chosen = ddmin(chosen, test)
            except _Budget:
                complete = False
        kept = [sent[int(i)] for i in chosen]  # type: ignore[call-overload]
        last = cache.get(tuple(chosen))
        if last is not None and last.oracle == trig.oracle and last.command_id not in (None, trig.command_id):
            # The packets kept leave another of the case's commands unacknowledged (the one named
            # may be gone): the finding names that one, and shows its VRCI.
            trig.detail, trig.command_id = last.detail, last.command_id
        if len(kept) != 1:
            return kept, _pick(kept, trig.command_id), None, complete
        one = kept[0]
        if one.data == one.twin:
            return kept, one, one, complete
        twin = Sent(0.0, one.twin, one.twin, 0.0, one.expect_ack)
        try:
            if again([twin]):       # the minimiser assumes the twin does not: ask once
                return kept, one, twin, complete
        except _Budget:
            return kept, one, None, False
        result = minimize(one.data, one.twin, lambda candidate: again(
            [Sent(0.0, candidate, one.twin, 0.0, one.expect_ack)]), budget_s=max(0.0, deadline - time.time()))
        return kept, one, Sent(0.0, result.packet, one.twin, 0.0, one.expect_ack), complete and result.complete

    def _write(self, trig: Trigger, culprit: Optional[int], index: int, family: str, description: str,
               sent: list[Sent], shown: Optional[Sent], small: Optional[Sent], complete: bool,
               case: Optional[K.Case], traffic: list[Any], cases: Optional[list[dict[str, Any]]] = None) -> None:
        st = self.cfg.settings
        packet = small or shown
        steps = [small] if small is not None else sent
        signature = self._signature(trig, culprit)
        finding = F.Finding(
            oracle=trig.oracle, seed=self.cfg.seed, case_index=index, family=family, mutation=description,
            detail=trig.detail, packet_hex=packet.data.hex() if packet else "",
            original_hex=shown.data.hex() if shown else "", valid_hex=shown.twin.hex() if shown else "",
            differences=difference(packet.data, packet.twin) if packet else 0,
            minimised=complete,
            valid_triggers=small is not None and small.data == small.twin and shown is not None
            and shown.data != shown.twin,
            steps=[{"hex": p.data.hex(), "valid_hex": p.twin.hex(), "delay_ms": p.delay_ms if len(steps) > 1 else 0.0,
                    "expect_ack": p.expect_ack} for p in steps],
            pause_vrpi_ms=case.pause_vrpi_ms if case else 0.0,
            withhold_vrai_ms=case.withhold_vrai_ms if case else 0.0,
            stream=_jsonable(case.stream if case else None), settle_ms=case.settle_ms if case else 0.0,
            output_hex=trig.output.hex() if trig.output else None,
            target="%s:%d" % st.target, listen="%s:%d" % st.listen, group=st.group, target_cmd=self.cfg.target_cmd,
            signature=signature, cases=cases, memory=trig.memory, resend_ms=st.resend_ms)
        self.findings.append(finding)
        number = len(self.findings)
        if trig.crash is not None:
            finding.crash = F.write_crash(self.cfg.out, finding.name(number), trig.crash)
        path = F.write_finding(self.cfg.out, number, finding, traffic, self.session.link.local)
        self.files.append(path.name)
        headline = _headline(trig)
        self.buckets[signature] = F.Bucket(signature, trig.oracle, path.name, trig.time, trig.time, headline=headline,
                                           number=number, size=_size([small] if small is not None else sent))
        # (paths as the summary's lines give them: the --out folder's files, where the run was started)
        self.cfg.progress(f"finding {self.cfg.out / path.name}: {trig.detail if trig.oracle == CRASH else trig.oracle} "
                          f"at case {index} ({description})"
                          + ("; its valid twin triggers too: not the fields it changed" if finding.valid_triggers
                             else "")
                          + (f"; in {self.cfg.out / finding.pcap}: {finding.display_filter}"
                             if finding.display_filter else ""))


class _Budget(Exception):
    pass


def _headline(trig: Trigger) -> str:
    """`missing_ack: no VRAO ...`; a crash's detail names it already (`crash SIGSEGV in ...`)."""
    return trig.detail if trig.oracle == CRASH else f"{trig.oracle}: {trig.detail}"


def _size(sent: list[Sent]) -> int:
    """A reproducer's size: packets and bytes (fewer packets first)."""
    return 100_000 * len(sent) + sum(len(p.data) for p in sent)


def _culprits(suspects: list[object], crashes: Callable[[list[object]], bool]) -> Optional[list[object]]:
    """The cases of `suspects` (in the order sent) that crash the controller when played in order:
    the shortest crashing prefix by bisection (the crash comes at its last case), then that case
    alone, else the fewest earlier cases it needs before it (a state). None: no prefix crashes."""
    if not crashes(suspects):
        return None
    lo, hi = 0, len(suspects)            # the prefix of length hi crashes; of length lo does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if crashes(suspects[:mid]):
            hi = mid
        else:
            lo = mid
    last = suspects[hi - 1]
    if hi == 1 or crashes([last]):
        return [last]
    return ddmin(suspects[:hi - 1], lambda before: crashes(before + [last])) + [last]


def _pick(sent: list[Sent], command_id: Optional[int]) -> Optional[Sent]:
    """The packet of a case a finding shows: the VRCI with the command concerned, else the last."""
    vrci = C.PacketType.VRCI.value.encode()
    for p in sent:
        if command_id is not None and p.data[:C.ID_LEN] == vrci and len(p.data) >= C.PREFIX_LEN + 2 \
                and int.from_bytes(p.data[C.PREFIX_LEN:C.PREFIX_LEN + 2], "little") == command_id:
            return p
    return sent[-1] if sent else None


def _open_log(folder: Path, command: str) -> IO[bytes]:
    """The controller's output, appended to `folder`/target.log (a regular file, never a FIFO or
    device) under a line that says which run's it is."""
    path = check_target(folder / "target.log")
    try:
        log = path.open("ab")
        log.write(f"== vm110 fuzz {time.strftime('%Y-%m-%d %H:%M:%S')}: {command} ==\n".encode(errors="replace"))
        return log
    except OSError as exc:
        raise CliError(f"cannot write {folder / 'target.log'}: {exc.strerror}") from None


def _jsonable(stream: Optional[dict[str, Any]]) -> Optional[dict[str, Any]]:
    return None if stream is None else {k: int(v) for k, v in stream.items()}


def _case_json(index: int, case: K.Case, sent: list[Sent]) -> dict[str, Any]:
    """One of the cases of a finding that needs several (`Finding.cases`)."""
    return {"case_index": index, "mutation": case.description, "packets": len(sent),
            "pause_vrpi_ms": case.pause_vrpi_ms, "withhold_vrai_ms": case.withhold_vrai_ms,
            "stream": _jsonable(case.stream), "settle_ms": case.settle_ms}


def finding_replay(finding: F.Finding) -> Replay:
    """What replaying `finding` sends (its minimised packet when there is one): each of its cases
    in turn, with what the base unit did during it."""
    steps = finding.steps
    if len(steps) == 1 and finding.packet_hex:
        steps = [dict(steps[0], hex=finding.packet_hex)]
    packets = [Sent(0.0, bytes.fromhex(st["hex"]), bytes.fromhex(st["valid_hex"]),
                    float(st["delay_ms"]), bool(st["expect_ack"])) for st in steps]
    parts, at = [], 0
    for case in F.played(finding):
        parts.append(Replay(packets[at:at + case["packets"]], case["pause_vrpi_ms"], case["withhold_vrai_ms"],
                            case["stream"], case["settle_ms"]))
        at += case["packets"]
    return parts[0] if len(parts) == 1 else Replay.sequence(parts)


def finding_kind(finding: F.Finding) -> Optional[str]:
    """The kind of trigger a crash or malformed-output finding was (from its signature), else None."""
    head = f"{finding.oracle} "
    if finding.oracle not in _BY_KIND or not finding.signature.startswith(head):
        return None
    kind = finding.signature[len(head):]
    return kind if finding.oracle == CRASH else kind.rpartition(" (")[0] or None


def same_bug(finding: F.Finding, trig: Trigger) -> bool:
    """Whether a replay's crash or malformed output is the finding's bug: a crash by its stored
    evidence too, whose signature may be of older rules (findings.json keeps them)."""
    if trig.kind == finding_kind(finding):
        return True
    return finding.oracle == CRASH and trig.crash is not None and trig.crash.same_bug(finding.crash)


def replay_finding(finding: F.Finding, settings: Settings, target_cmd: Optional[str],
                   log: Optional[IO[bytes]] = None, core: bool = True) -> Optional[Trigger]:
    """Send the finding again (minimised packet when there is one); the trigger when it still
    triggers (a crash's or malformed output's carries its kind: the finding's first, else another
    bug's), else None. The controller's output goes to `log` (the terminal), not into a file
    beside the finding."""
    supervisor = Supervisor(target_cmd, log, core=core) if target_cmd else None
    scratch = Path(tempfile.mkdtemp(prefix="vm110-replay-"))
    session = Session(settings, supervisor, scratch)
    try:
        start_target(session)
        replay = finding_replay(finding)
        # It had VRCO to withhold: wait for one.
        session.monitor.vrco_seen = any(part.withhold_vrai_ms for part in replay.parts or [replay])
        return trial(session, replay, finding.oracle, finding_kind(finding), strict=False)
    finally:
        _close(session)
        shutil.rmtree(scratch, ignore_errors=True)    # our own folder: cores of the replay, if any


def _close(session: Session) -> None:
    """Stop the controller and wait until what it wrote has been passed on (before the verdict)."""
    session.close()
    if session.supervisor is not None:
        session.supervisor.output()


def replay_corpus_case(entry: Any, settings: Settings, target_cmd: Optional[str],
                       log: Optional[IO[bytes]] = None, core: bool = True) -> list[Trigger]:
    """Play one corpus case (`--corpus` file) and wait out the oracles' windows: what fired (the
    controller's output goes to `log`)."""
    from .guided import case_of
    supervisor = Supervisor(target_cmd, log, core=core) if target_cmd else None
    scratch = Path(tempfile.mkdtemp(prefix="vm110-replay-"))
    session = Session(settings, supervisor, scratch)
    try:
        start_target(session)
        case = case_of(entry, 0, "corpus", "corpus case")
        session.run_steps(TRIAL, [(st.build, st.delay_ms, st.expect_ack) for st in case.steps], case.pause_vrpi_ms,
                          case.withhold_vrai_ms, case.stream, case.settle_ms)
        limits = settings.limits
        session.pump(time.time() + limits.ack_timeout_ms / 1000 + 0.3)
        return list(session.monitor.triggers)
    finally:
        _close(session)
        shutil.rmtree(scratch, ignore_errors=True)
