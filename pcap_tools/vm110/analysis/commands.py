"""Command transmissions and acknowledgements (docs/rules.md, "Commands").

A command is (kind, sender, command ID); a sender may have any number open. A VRCI (VRCO) is a
retransmission of its sender's command with the same ID when that command's previous
transmission was less than the reuse gap ago and the sender has not restarted since; otherwise
it begins a new command. VRAO (VRAI) acknowledges the VRCI (VRCO) with its ID, from any sender,
not interrupted, that began last. A sender's restart interrupts its commands that were neither
acknowledged nor past their fail limit. Duplicates were removed before this point.
"""
from __future__ import annotations

import pickle
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterable, Optional

from .. import constants as C
from . import timing
from .report_json import round_ms, round_s
from .collect import CODE

COMMAND_TYPES = (C.PacketType.VRCI, C.PacketType.VRCO)
_ACK_OF_CODE = {CODE[ack]: CODE[cmd] for ack, cmd in C.ACK_OF.items()}
_COMMAND_CODES = {CODE[t] for t in COMMAND_TYPES}
RESTART = -1          # the type code of a restart marker in the event stream
REUSE_GAP_MS = 2000.0


@dataclass(slots=True)         # one per command, all kept: no __dict__ each
class Command:
    sender: str
    command_id: int
    frames: list
    times: list
    ack_frame: Optional[int] = None
    ack_time: Optional[float] = None
    last_before_ack: Optional[float] = None
    spurious_frames: list = field(default_factory=list)
    interrupted_frame: Optional[int] = None
    interrupted_time: Optional[float] = None

    @property
    def latency_first_ms(self) -> Optional[float]:
        return None if self.ack_time is None else (self.ack_time - self.times[0]) * timing.MS

    @property
    def latency_last_ms(self) -> Optional[float]:
        if self.ack_time is None or self.last_before_ack is None:
            return None
        return (self.ack_time - self.last_before_ack) * timing.MS

    def failed(self, fail_ms: float, end: Optional[float]) -> bool:
        """Acknowledged after the fail limit, or never while the capture (ending at `end`) lasted
        beyond it: one still in flight at the end of the capture has not failed (yet)."""
        if self.interrupted_frame is not None:
            return False
        if self.ack_time is None:
            return end is not None and timing.longer(end - self.times[0], fail_ms)
        return timing.longer(self.ack_time - self.times[0], fail_ms)


@dataclass
class Tally:
    commands: list = field(default_factory=list)
    id_wraps: int = 0
    orphan_acks: list = field(default_factory=list)       # (frame, time, command_id, its sender)
    duplicate_acks: list = field(default_factory=list)    # (frame, time, command_id, command's first frame, its sender)
    # The times above are the analysis clock's (rules.md); a frame's own timestamp where it differs
    # (a step back of the capture's clock), which is what the report names.
    shown: dict = field(default_factory=dict)

    def time_of(self, frame: int, t: float) -> float:
        """The own timestamp of a frame of the tally (`t`: its time on the analysis clock)."""
        return self.shown.get(frame, t)


class Tracker:
    """Commands and acknowledgements, applied as a stream of events in capture order:
    (frame, ts, type code, sender id, command ID, own timestamp) for commands and acks, and (frame,
    ts, RESTART, sender id, None, None) where a sender restarted (before that frame's own packet);
    ts is the analysis clock. `fail_ms`: the
    fail limit per command type code. The state is the commands (they are the report) and the
    latest command per (sender, ID) and per ID."""

    def __init__(self, fail_ms: dict[int, float], reuse_gap_ms: float = REUSE_GAP_MS) -> None:
        self.tallies = {CODE[t]: Tally() for t in COMMAND_TYPES}
        self.fail_ms = fail_ms
        self.reuse_ms = reuse_gap_ms
        self.open: dict[tuple[int, str, int], Command] = {}      # (code, sender, ID) -> its latest command
        self.by_id: dict[tuple[int, int], list[Command]] = {}    # (code, ID) -> not interrupted, in order of start
        self.last_id: dict[tuple[int, str], int] = {}            # (code, sender) -> ID of its latest new command

    def apply(self, events: Iterable[tuple]) -> None:
        tallies, open_, by_id, last_id, reuse_ms = self.tallies, self.open, self.by_id, self.last_id, self.reuse_ms
        cmd: Optional[Command]
        for frame, ts, code, sender, cid, own in events:
            if code == RESTART:
                for key in [k for k in open_ if k[1] == sender]:
                    cmd = open_.pop(key)
                    if cmd.ack_frame is None and not timing.longer(ts - cmd.times[0], self.fail_ms[key[0]]):
                        cmd.interrupted_frame, cmd.interrupted_time = frame, ts
                        by_id[(key[0], key[2])].remove(cmd)
                for code_ in _COMMAND_CODES:
                    last_id.pop((code_, sender), None)
            elif code in _COMMAND_CODES:
                tally = tallies[code]
                if own != ts:
                    tally.shown[frame] = own
                cmd = open_.get((code, sender, cid))
                if cmd is not None and timing.shorter(ts - cmd.times[-1], reuse_ms):
                    cmd.frames.append(frame)
                    cmd.times.append(ts)
                    if cmd.ack_frame is not None:
                        cmd.spurious_frames.append(frame)
                    continue
                previous = last_id.get((code, sender))
                # A wrap passes 65535 to 0: the ID goes on forward (as serials do). A fall back
                # within the range (IDs counted from 0 again) is none (a trial saw 0, 1, 2, 0
                # counted as wraps).
                if previous is not None and cid < previous and (cid - previous) & 0xFFFF < 0x8000:
                    tally.id_wraps += 1
                last_id[(code, sender)] = cid
                cmd = Command(sender, cid, [frame], [ts])
                open_[(code, sender, cid)] = cmd
                by_id.setdefault((code, cid), []).append(cmd)
                tally.commands.append(cmd)
            else:
                target = _ACK_OF_CODE[code]
                tally = tallies[target]
                if own != ts:
                    tally.shown[frame] = own
                live = by_id.get((target, cid))
                cmd = live[-1] if live else None
                if cmd is None:
                    tally.orphan_acks.append((frame, ts, cid, sender))
                elif cmd.ack_frame is not None:
                    tally.duplicate_acks.append((frame, ts, cid, cmd.frames[0], sender))
                else:
                    cmd.ack_frame, cmd.ack_time, cmd.last_before_ack = frame, ts, cmd.times[-1]


class Retiring:
    """For a run of days (`vm110 monitor`): takes out of the Tracker's memory the commands that
    can no longer change, and hands them back for the report.

    A command can no longer change once it is acknowledged or interrupted and its last
    transmission lies more than the reuse gap before the current time: no retransmission can
    join it, no restart can interrupt it, and an acknowledgement of its ID either goes to a later
    command or is a duplicate of its own. Its place in `Tally.commands` becomes None (8 bytes) and
    the command goes to `spool`; what an acknowledgement still needs of it (its first frame, that
    it is acknowledged) stays as a stub in `by_id`, and the commands before it there, which no
    acknowledgement can reach any more, go. `restore()` puts every command back in its place.
    The caller retires at a time before which every event has been applied
    (`Analysis.applied_until`, at most the latest packet's): any event still to come is later."""

    def __init__(self, tracker: Tracker, spool) -> None:
        self.tracker, self.spool = tracker, spool
        self.seen = dict.fromkeys(tracker.tallies, 0)
        self.pending: dict[int, list[int]] = {code: [] for code in tracker.tallies}
        self.retired = 0

    def retire(self, now: float, upto: Optional[dict[int, int]] = None) -> None:
        """Retire what can be at time `now` (among the first `upto[code]` commands of each kind)."""
        t = self.tracker
        for code, tally in t.tallies.items():
            cmds = tally.commands
            end = len(cmds) if upto is None else min(upto[code], len(cmds))
            self.pending[code] += range(self.seen[code], end)
            self.seen[code] = max(self.seen[code], end)
            keep = []
            for i in self.pending[code]:
                cmd = cmds[i]
                done = cmd.interrupted_frame is not None or cmd.ack_frame is not None
                if not done or not timing.longer(now - max(cmd.times), t.reuse_ms):
                    keep.append(i)
                    continue
                self._retire(code, i, cmd)
            self.pending[code] = keep

    def _retire(self, code: int, i: int, cmd: Command) -> None:
        t = self.tracker
        key = (code, cmd.sender, cmd.command_id)
        if t.open.get(key) is cmd:
            del t.open[key]
        if cmd.ack_frame is not None:
            live = t.by_id.get((code, cmd.command_id), [])
            for k, other in enumerate(live):
                if other is cmd:
                    live[k] = Command(cmd.sender, cmd.command_id, cmd.frames[:1], cmd.times[:1],
                                      ack_frame=cmd.ack_frame)
                    del live[:k]
                    break
        pickle.dump((code, i, cmd), self.spool, protocol=pickle.HIGHEST_PROTOCOL)
        t.tallies[code].commands[i] = None
        self.retired += 1

    def restore(self) -> None:
        """Every retired command back in its place (before the report)."""
        self.spool.flush()
        self.spool.seek(0)
        while True:
            try:
                code, i, cmd = pickle.load(self.spool)
            except EOFError:
                break
            self.tracker.tallies[code].commands[i] = cmd
        self.spool.seek(0)
        self.spool.truncate()


def report(tally: Tally, fail_ms: float, resend_ms: float, end: Optional[float]) -> dict:
    """The `commands.<TYPE>` section."""
    cmds = tally.commands
    transmissions = sum(len(c.frames) for c in cmds)
    acked = [c for c in cmds if c.ack_frame is not None]
    interrupted = [c for c in cmds if c.interrupted_frame is not None]
    failed = [c.failed(fail_ms, end) for c in cmds]
    resend = [(b - a) * timing.MS for c in cmds for a, b in zip(c.times, c.times[1:])]
    histogram = Counter(len(c.frames) - 1 for c in cmds)
    first = [c.latency_first_ms for c in acked]
    last = [c.latency_last_ms for c in acked]
    keys = ("min", "p50", "p95", "max")
    return {
        "commands": len(cmds),
        "transmissions": transmissions,
        "retransmissions": transmissions - len(cmds),
        "acked": len(acked),
        "unacked": len(cmds) - len(acked) - len(interrupted),
        "interrupted": len(interrupted),
        "failed": sum(failed),
        "spurious_retransmissions": sum(len(c.spurious_frames) for c in cmds),
        "acks_without_command": len(tally.orphan_acks),
        "duplicate_acks": len(tally.duplicate_acks),
        "command_id_wraps": tally.id_wraps,
        "ack_latency_ms": timing.summary(first, keys),
        "ack_latency_last_ms": timing.summary(last, keys),
        "resend_interval_ms": {**timing.summary(resend, ("min", "mean", "p50", "p95", "max")),
                               "nominal": resend_ms, "count": len(resend)},
        "retransmission_histogram": {str(k): histogram[k] for k in sorted(histogram)},
        "fail_limit_ms": fail_ms,
        # Long lists: rounded here, so that report_json.normalise need not walk them (PRE_ROUNDED).
        "list": [{"sender": c.sender, "command_id": c.command_id, "frames": c.frames,
                  "ack_frame": c.ack_frame, "latency_first_ms": round_ms(c.latency_first_ms),
                  "latency_last_ms": round_ms(c.latency_last_ms),
                  "time": round_s(tally.time_of(c.frames[0], c.times[0])),
                  "retransmissions": len(c.frames) - 1, "spurious": len(c.spurious_frames),
                  "spurious_frames": c.spurious_frames, "interrupted_frame": c.interrupted_frame,
                  "failed": f}
                 for c, f in zip(cmds, failed)],
        "acks_without_command_list": [{"frame": f, "time": round_s(tally.time_of(f, t)), "command_id": i}
                                      for f, t, i, _ in tally.orphan_acks],
        "duplicate_acks_list": [{"frame": f, "time": round_s(tally.time_of(f, t)), "command_id": i,
                                 "command_frame": c} for f, t, i, c, _ in tally.duplicate_acks],
    }
