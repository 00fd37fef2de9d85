"""The oracles: judge what the controller does, and say which case to blame.

A `Monitor` sees every packet the base unit sends (`on_tx`) and every packet the controller
sends (`on_rx`), the exit of a supervised controller (`on_exit`) and the passing of time
(`tick`); it appends a `Trigger` for each oracle that fires. Tolerances (documented in the
README) make the timing oracles robust on a loaded machine. Commands are judged one by one: a
controller may have several VRCO in flight and must acknowledge every VRCI, in any order
(interpretation.md, "Commands"), of the base unit whose VRPI it hears: a VRCI of another origin
comes from a base unit whose RU state it has no VRPI of (TS-0006 4.3), which it may leave
unacknowledged until it has (as the reference controller, `sim.controller`, does).

The base unit resends an unacknowledged VRCI every 100 ms (TS-0006 5.1.3), as the session does
(`Session`, unless --no-resend): a controller may ignore a VRCI that came while it was busy and
acknowledge a resend. A resend is shown to `on_tx` as no transmission of its own to acknowledge
(`expect_ack` False): the missing ack is reported when no VRAO of the command ID came within
`ack_timeout_ms` of its first transmission, whichever transmission that VRAO answered.
"""
from __future__ import annotations

import collections
import copy
from dataclasses import dataclass, field
from typing import Any, Optional

from .. import constants as C
from ..decode import decode
from ..sim.ledger import REUSE_GAP_MS
from .evidence import Crash
from .fields import COMMAND_ID_AT
from .mutate import BU_ORIGIN

CRASH, STALL, MISSING_ACK, ILLEGAL_ACKED, MALFORMED_OUTPUT, VRCO_RETRANSMIT, MEMORY = ORACLES = (
    "crash", "stall", "missing_ack", "illegal_acked", "malformed_output", "vrco_retransmit", "memory")
_CMD_ID_AT = slice(COMMAND_ID_AT, COMMAND_ID_AT + 2)
_VRCI = C.PacketType.VRCI.value
_HISTORY_S = 10.0
_NEW_PORT_SILENCE_S = 0.25    # a sender silent this long may come back on a new port (interpretation.md)
_MAX_CRASH_SUSPECTS = 400


@dataclass
class Limits:
    """Oracle thresholds in milliseconds."""

    stall_ms: float = C.VRPO_WATCHDOG_MS          # the base unit's VRPO watchdog
    ack_timeout_ms: float = 1000.0                # VRAO must follow each valid VRCI within this (resends too)
    resend_max_ms: float = 250.0                  # "about 100 ms": a resend interval up to this is fine
    after_ack_grace_ms: float = 300.0             # a VRCO in flight when the VRAI went out is fine
    vrco_give_up_ms: float = C.VRCO_GIVE_UP_MS    # no resends are expected past this
    reuse_gap_ms: float = REUSE_GAP_MS            # a VRCO ID again after this long is a new command


@dataclass
class Trigger:
    oracle: str
    time: float
    detail: str
    case_index: Optional[int] = None              # known culprit (acks), else see suspects
    suspects: list[int] = field(default_factory=list)   # most likely first
    output: Optional[bytes] = None                # the controller packet that was judged
    kind: str = ""                                # what went wrong, for de-duplication
    command_id: Optional[int] = None              # the command concerned, if any
    packet: Optional[bytes] = None                # a base-unit packet that is not a case's (a VRAI)
    crash: Optional[Crash] = None                 # the evidence of a crash
    answered: Optional[int] = None                # the open command an ack with a wrong ID answered
    memory: Optional[dict[str, Any]] = None       # the memory oracle's evidence (memory.Watch)


@dataclass
class _Vrco:
    first: float
    last: float
    count: int = 1
    withheld: bool = False
    acked_at: Optional[float] = None
    vrai: Optional[bytes] = None
    reported: bool = False


class Monitor:
    def __init__(self, limits: Limits, now: float) -> None:
        self.limits = limits
        self.triggers: list[Trigger] = []
        self.notes: collections.deque[tuple[float, int]] = collections.deque()   # (time, case index)
        self.pending: dict[int, collections.deque[tuple[float, int]]] = {}      # id -> (deadline, case)
        # Commands answered only by a wrong or illegal VRAO: id -> when their ack was due. The base
        # unit ignores such an ack (TS-0006 5.1.5) and goes on resending until then (`resending`).
        self.unacked: dict[int, float] = {}
        self.illegal_ids: dict[int, tuple[float, int]] = {}     # IDs whose latest VRCI was illegal
        self.sent_at: dict[int, float] = {}      # command ID -> when it was last sent
        self.id_case: dict[int, int] = {}        # command ID -> last case that sent it
        self.withholding = False
        self.vrco_seen = False                    # has this controller ever sent a VRCO?
        self.cut_short: list[int] = []            # cases whose acks a crash cut short, not its suspects
        self._next_purge = 0.0
        self.reset_controller(now)

    # --- state ----------------------------------------------------------------------------------
    def reset_controller(self, now: float) -> None:
        """The controller (re)started: forget what it sent, and what it owed."""
        self.serials: dict[Any, int] = {}
        self.sources: dict[Any, float] = {}      # (address, port) -> its last packet
        self.last_vrpo: Optional[float] = None
        self.vrpo_interval = 0.0
        self.last_rx: Optional[float] = None
        self.vrco: dict[int, _Vrco] = {}
        self.stall_reported = False
        self.exited = False                       # until a restart: a dead controller owes no acks
        # (time, command ID, case, time sent) of the acks owed by a silent controller
        self.held: list[tuple[float, int, int, float]] = []
        self.pending.clear()
        self.unacked.clear()
        self.illegal_ids.clear()

    def fork(self) -> "Monitor":
        """A monitor for a trial: what is known of the controller, none of the expectations."""
        other = Monitor(self.limits, 0.0)
        other.adopt(self)
        other.sent_at = dict(self.sent_at)
        other.id_case = dict(self.id_case)
        return other

    def adopt(self, other: "Monitor") -> None:
        """Take over what `other` learned about the controller's output."""
        self.serials = dict(other.serials)
        self.sources = dict(other.sources)
        self.last_vrpo, self.vrpo_interval, self.last_rx = other.last_vrpo, other.vrpo_interval, other.last_rx
        self.vrco = copy.deepcopy(other.vrco)
        self.vrco_seen = other.vrco_seen
        self.exited = other.exited
        self.sent_at.update(other.sent_at)         # a trial's copy is the newer

    def fire(self, trigger: Trigger) -> None:
        self.triggers.append(trigger)

    def note_case(self, t: float, index: int) -> None:
        self.notes.append((t, index))
        while self.notes and self.notes[0][0] < t - _HISTORY_S:
            self.notes.popleft()

    def _between(self, start: float, end: float) -> list[int]:
        seen: list[int] = []
        for t, index in self.notes:
            if start <= t <= end and index not in seen:
                seen.append(index)
        return seen

    # --- base unit -> controller ---------------------------------------------------------------
    def on_tx(self, t: float, data: bytes, twin: bytes, index: int, expect_ack: bool = True) -> Optional[int]:
        """A packet of case `index` went out. When it is a VRCI whose ack is now awaited (valid, of
        our origin, to a live controller), its command ID: the base unit resends it while `pending`."""
        self.note_case(t, index)
        if len(data) < _CMD_ID_AT.stop or _VRCI.encode() not in (data[:C.ID_LEN], twin[:C.ID_LEN]):
            return None
        fields = decode(data)
        command_id = int.from_bytes(data[_CMD_ID_AT], "little")
        self.sent_at[command_id] = t
        self.id_case[command_id] = index
        if fields.get("type") != _VRCI:
            return None
        if fields["problems"]:
            self.illegal_ids[command_id] = (t, index)
            return None
        self.illegal_ids.pop(command_id, None)      # an ack of this ID is now this VRCI's
        if not expect_ack or self.exited or fields["origin"] != BU_ORIGIN:
            return None
        deadline = t + self.limits.ack_timeout_ms / 1000
        self.pending.setdefault(command_id, collections.deque()).append((deadline, index))
        return command_id

    def on_vrai(self, t: float, command_id: int, data: bytes) -> None:
        entry = self.vrco.get(command_id)
        if entry is not None and entry.acked_at is None:
            entry.acked_at, entry.vrai = t, data

    # --- controller -> base unit ---------------------------------------------------------------
    def on_rx(self, t: float, data: bytes, src: Any) -> dict[str, Any]:
        fields = decode(data)
        self._new_port(t, data, src, fields.get("type", "?"))
        self.last_rx = t
        for when, owed, index, _ in self.held:     # it was not hung: those acks are missing
            self._missing_ack(when, owed, index)
        self.held = []
        ptype = fields.get("type", "?")
        if fields["problems"]:
            command_id = fields.get("command_id") if ptype == C.PacketType.VRAO.value else None
            self._malformed(t, data, f"{ptype} with {'+'.join(fields['problems'])}",
                            f"illegal {ptype} from the controller: {', '.join(fields['problems'])}", command_id)
            if command_id is not None:
                # The command was answered, illegally: that is the bug, not a missing ack as well.
                self._answered(command_id, t, own=False)
            return fields
        if fields.get("direction") != C.Direction.OUTPUT.value:
            self._malformed(t, data, f"{ptype} direction", f"the controller sent an input packet {ptype}")
            return fields
        if fields["origin"] != 0:
            self._malformed(t, data, f"{ptype} origin", f"{ptype} with origin {fields['origin']:#06x} (must be 0)")
        last, serial = self.serials.get(src), fields["serial"]
        step = None if last is None else (serial - last) % C.SERIAL_MODULUS
        if step is not None and (step == 0 or step >= C.SERIAL_HALF):
            self._malformed(t, data, "serial", f"{ptype} serial {serial} after {last}: not incrementing")
        else:
            self.serials[src] = serial
        if ptype == C.PacketType.VRPO.value:
            if self.last_vrpo is not None:
                self.vrpo_interval = max(self.vrpo_interval * 0.9, t - self.last_vrpo)
            self.last_vrpo = t
            self.stall_reported = False
        elif ptype == C.PacketType.VRAO.value:
            self._vrao(t, data, fields["command_id"])
        elif ptype == C.PacketType.VRCO.value:
            self._vrco(t, fields["command_id"])
        return fields

    def _new_port(self, t: float, data: bytes, src: Any, ptype: str) -> None:
        """A controller that restarted on its own (a crash its service manager or watchdog made good)
        comes back on a new port once its old one has fallen silent: its serials start afresh there,
        and, back within the stall limit, nothing else would show it. The cases around its last
        packet are the suspects."""
        known = src in self.sources
        before = [(last, port) for (host, port), last in self.sources.items() if host == src[0]]
        self.sources[src] = t
        if known or not before or self.stall_reported:
            return           # a known port, the first one, or a stall already reported for the silence
        last, port = max(before)
        if t - last >= _NEW_PORT_SILENCE_S:
            self.fire(Trigger(MALFORMED_OUTPUT, t, f"{ptype} from port {src[1]} after port {port} was silent "
                              f"{(t - last) * 1000:.0f} ms: the controller restarted on its own", None,
                              self._around(last), data, "restart"))

    def _malformed(self, t: float, data: bytes, kind: str, detail: str, command_id: Optional[int] = None,
                   answered: Optional[int] = None) -> None:
        """Blame the case that sent the command answered (`answered`, else `command_id`, an ack's),
        then the cases of the last 500 ms."""
        blamed_id = command_id if answered is None else answered
        culprit = None if blamed_id is None else self.id_case.get(blamed_id)
        recent = list(reversed(self._between(t - 0.5, t)))
        suspects = ([culprit] if culprit is not None else []) + [i for i in recent if i != culprit]
        self.fire(Trigger(MALFORMED_OUTPUT, t, detail, None, suspects, data, kind, command_id, answered=answered))

    def resending(self, command_id: int, now: float) -> bool:
        """Whether the base unit still resends the command: its ack is awaited, or only a wrong or
        illegal VRAO came for it and its ack is not yet overdue."""
        if command_id in self.pending:
            return True
        if self.unacked.get(command_id, now) > now:
            return True
        self.unacked.pop(command_id, None)
        return False

    def _answered(self, command_id: int, t: float, own: bool = True) -> bool:
        """The oldest pending command of that ID is answered, and with it every transmission of the
        ID sent by `t`: an ack answers the command ID, not one transmission (a controller that
        acks once per scan cycle answers a burst of retransmissions with one VRAO). An ack not
        `own` (a wrong ID's, an illegal one) is its one finding, but no ack to the base unit: the
        command stays `unacked`, resent. False when none was pending."""
        queue = self.pending.get(command_id)
        if not queue:
            return False
        deadline, _ = queue.popleft()
        if not own:
            self.unacked[command_id] = deadline
        answered_by = t + self.limits.ack_timeout_ms / 1000       # deadline of a transmission at t
        while queue and queue[0][0] <= answered_by:
            queue.popleft()
        if not queue:
            del self.pending[command_id]
        return True

    def _vrao(self, t: float, data: bytes, command_id: int) -> None:
        self.unacked.pop(command_id, None)         # its own ack at last: no more resends
        if self._answered(command_id, t):
            return
        illegal = self.illegal_ids.get(command_id)
        if illegal is not None and t - illegal[0] < _HISTORY_S:
            self.fire(Trigger(ILLEGAL_ACKED, t, f"VRAO for command ID {command_id} of an illegal VRCI",
                              illegal[1], [illegal[1]], data, "acked", command_id))
            return
        sent = self.sent_at.get(command_id)
        if sent is not None and t - sent <= _HISTORY_S:
            return          # one more ack of a command sent lately (a duplicate frame's, a second copy)
        # An ack of no command sent lately has a wrong ID (a sign or width error): it answers, wrongly,
        # the oldest command still open, so that command's missing ack is no second finding; else
        # (an ack of its resend) the oldest one still resent, the same finding again.
        meant = min(self.pending, key=lambda c: self.pending[c][0][0], default=None)
        if meant is not None:
            self._answered(meant, t, own=False)
        else:
            meant = min(self.unacked, key=self.unacked.__getitem__, default=None)
        awaited = "" if meant is None else f" (command ID {meant} awaited its ack)"
        never = "never sent" if sent is None else f"not sent in the last {_HISTORY_S:.0f} s"
        self._malformed(t, data, "VRAO unknown", f"VRAO for command ID {command_id}, {never}{awaited}",
                        command_id, meant)

    def _vrco(self, t: float, command_id: int) -> None:
        self.vrco_seen = True
        entry = self.vrco.get(command_id)
        if entry is None or t - entry.last >= self.limits.reuse_gap_ms / 1000:
            self.vrco[command_id] = _Vrco(t, t, withheld=self.withholding)
            return
        entry.count += 1
        if entry.acked_at is not None and t - entry.acked_at > self.limits.after_ack_grace_ms / 1000 \
                and not entry.reported:
            entry.reported = True
            late = (t - entry.acked_at) * 1000
            # No case to blame: the base unit only acknowledged, as it always does.
            self.fire(Trigger(VRCO_RETRANSMIT, t, f"VRCO {command_id} resent {late:.0f} ms after its VRAI",
                              None, [], None, "resent after VRAI", command_id, entry.vrai))
        entry.last = t

    def on_exit(self, t: float, returncode: int, crash: Optional[Crash] = None) -> None:
        """The controller died: every case since it last spoke is a suspect, oldest first (a
        sanitizer's report takes a while: the cases sent while it was written are innocent)."""
        start = (self.last_rx or t) - 0.05
        suspects = self._between(start, t)[:_MAX_CRASH_SUSPECTS]
        # A dead controller's missing acks are the crash's, not findings of their own: those still
        # open, those of commands sent to it from now on, and those that timed out while it was
        # dying (silent since before the command was sent). Those still open of commands sent
        # before it last spoke were no suspects: their cases are to be judged again (cut_short).
        owed = {index for queue in self.pending.values() for deadline, index in queue
                if deadline - self.limits.ack_timeout_ms / 1000 < start}
        self.cut_short += sorted(owed - set(suspects) - set(self.cut_short))
        self.exited = True
        self.pending.clear()
        self.unacked.clear()
        self.held = []
        self.triggers = [x for x in self.triggers if x.oracle != MISSING_ACK or x.case_index not in suspects]
        crash = crash or Crash(returncode)
        self.fire(Trigger(CRASH, t, crash.headline(), None, suspects, None, crash.signature(), crash=crash))

    # --- time ------------------------------------------------------------------------------------
    def _missing_ack(self, now: float, command_id: int, index: int) -> None:
        self.fire(Trigger(MISSING_ACK, now, f"no VRAO for command ID {command_id} within "
                          f"{self.limits.ack_timeout_ms:.0f} ms", index, [index], None, "no ack", command_id))

    def tick(self, now: float) -> None:
        # A controller silent since a command came (a VRPO of the cycle it came in aside) has hung:
        # that is the stall's finding, not a missing ack as well (one bug, one finding).
        cycle = max(self.vrpo_interval, 0.1) + 0.05
        for command_id in [c for c, q in self.pending.items() if q[0][0] < now]:
            queue = self.pending[command_id]
            while queue and queue[0][0] < now:
                deadline, index = queue.popleft()
                sent = deadline - self.limits.ack_timeout_ms / 1000
                if self.last_vrpo is not None and self.last_rx is not None and self.last_rx < sent + cycle:
                    self.held.append((now, command_id, index, sent))
                else:
                    self._missing_ack(now, command_id, index)
                # One trigger per command: the case's retransmissions of it still open would only
                # repeat it (and each would replay the same case).
                queue = collections.deque(e for e in queue if e[1] != index)
            if queue:
                self.pending[command_id] = queue
            else:
                del self.pending[command_id]
        if self.last_vrpo is not None and not self.stall_reported and not self.exited \
                and now - self.last_vrpo > self.limits.stall_ms / 1000:      # a dead one's silence is the crash
            self.stall_reported = True
            # The commands it may have hung on first: those sent before it missed its next VRPO.
            # Later ones found it silent already, and would push the culprit out of the replays.
            hung = [(index, command_id) for _, command_id, index, sent in self.held
                    if self.last_rx is not None and sent < self.last_rx + cycle]
            first = list(dict.fromkeys(index for index, _ in hung))
            suspects = first + [i for i in self._around(self.last_vrpo) if i not in first]
            self.fire(Trigger(STALL, now, f"no VRPO for {(now - self.last_vrpo) * 1000:.0f} ms",
                              None, suspects, None, "no VRPO", hung[0][1] if hung else None))
            self.held = []
        self._check_resends(now)
        if now >= self._next_purge:      # once a second: thousands of IDs at a high case rate
            self._next_purge = now + 1.0
            for command_id in [c for c, (t, _) in self.illegal_ids.items() if now - t > _HISTORY_S]:
                del self.illegal_ids[command_id]

    def _around(self, t: float) -> list[int]:
        """The cases within a VRPO cycle (and 100 ms) either side of `t`, nearest first: a
        controller that reads its input once a cycle, after its VRPO (a PLC), stops on a case
        sent before that VRPO; one that reads it at once, on a case sent after it."""
        window = max(self.vrpo_interval, 0.1) + 0.1
        near = [(abs(when - t), index) for when, index in self.notes if abs(when - t) <= window]
        seen: list[int] = []
        for _, index in sorted(near):
            if index not in seen:
                seen.append(index)
        return seen

    def _check_resends(self, now: float) -> None:
        limit = self.limits.resend_max_ms / 1000
        give_up = self.limits.vrco_give_up_ms / 1000
        for command_id, entry in self.vrco.items():
            if entry.withheld and entry.acked_at is None and not entry.reported and self.withholding \
                    and now - entry.last > limit and now - entry.first < give_up - limit:
                entry.reported = True
                suspects = list(reversed(self._between(entry.first - 1.0, now)))
                self.fire(Trigger(VRCO_RETRANSMIT, now, f"VRCO {command_id} not resent within "
                                  f"{limit * 1000:.0f} ms while unacknowledged ({entry.count} transmissions)",
                                  None, suspects, None, "not resent"))
