"""Command transmissions and acknowledgements (interpretation.md, "Commands").

A VRCI (VRCO) with the command ID of its sender's current command is a retransmission; a new ID
supersedes the current command. VRAO acknowledges the latest not-superseded VRCI with its ID,
VRAI the VRCO. Duplicated frames (a repeated serial) were removed before this point.
"""
from __future__ import annotations

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


@dataclass
class Command:
    sender: str
    command_id: int
    frames: list
    times: list
    ack_frame: Optional[int] = None
    ack_time: Optional[float] = None
    last_before_ack: Optional[float] = None
    spurious: int = 0

    @property
    def latency_first_ms(self) -> Optional[float]:
        return None if self.ack_time is None else (self.ack_time - self.times[0]) * timing.MS

    @property
    def latency_last_ms(self) -> Optional[float]:
        return None if self.ack_time is None else (self.ack_time - self.last_before_ack) * timing.MS


@dataclass
class Tally:
    commands: list = field(default_factory=list)
    acks_without_command: int = 0
    duplicate_acks: int = 0
    id_wraps: int = 0
    orphan_acks: list = field(default_factory=list)   # (frame, time, command_id)


def track(events: Iterable[tuple]) -> dict[int, Tally]:
    """events: (frame, ts, type code, sender id, command ID) in capture order, commands and acks."""
    tallies = {CODE[t]: Tally() for t in COMMAND_TYPES}
    current: dict[tuple[int, str], Command] = {}          # (code, sender) -> current command
    for frame, ts, code, sender, cid in events:
        if code in _COMMAND_CODES:
            tally = tallies[code]
            cmd = current.get((code, sender))
            if cmd is not None and cmd.command_id == cid:
                cmd.frames.append(frame)
                cmd.times.append(ts)
                if cmd.ack_frame is not None:
                    cmd.spurious += 1
                continue
            if cmd is not None and cid < cmd.command_id:
                tally.id_wraps += 1
            cmd = Command(sender, cid, [frame], [ts])     # supersedes the sender's previous one
            current[(code, sender)] = cmd
            tally.commands.append(cmd)
        else:
            target = _ACK_OF_CODE[code]
            tally = tallies[target]
            live = [c for (k, _), c in current.items() if k == target and c.command_id == cid]
            cmd = max(live, key=lambda c: c.frames[0]) if live else None
            if cmd is None:
                tally.acks_without_command += 1
                tally.orphan_acks.append((frame, ts, cid))
            elif cmd.ack_frame is not None:
                tally.duplicate_acks += 1
            else:
                cmd.ack_frame, cmd.ack_time, cmd.last_before_ack = frame, ts, cmd.times[-1]
    return tallies


def report(tally: Tally, fail_ms: Optional[float], resend_ms: float) -> dict:
    """The `commands.<TYPE>` section."""
    cmds = tally.commands
    transmissions = sum(len(c.frames) for c in cmds)
    acked = [c for c in cmds if c.ack_frame is not None]
    failed = 0
    if fail_ms is not None:
        failed = sum(1 for c in cmds if c.ack_frame is None or c.latency_first_ms > fail_ms)
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
        "unacked": len(cmds) - len(acked),
        "failed": failed,
        "spurious_retransmissions": sum(c.spurious for c in cmds),
        "acks_without_command": tally.acks_without_command,
        "duplicate_acks": tally.duplicate_acks,
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
                  "latency_last_ms": round_ms(c.latency_last_ms), "time": round_s(c.times[0]),
                  "retransmissions": len(c.frames) - 1, "spurious": c.spurious} for c in cmds],
        "acks_without_command_list": [{"frame": f, "time": round_s(t), "command_id": i}
                                      for f, t, i in tally.orphan_acks],
    }

