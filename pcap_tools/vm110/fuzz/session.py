"""The base-unit role over real UDP: a valid VRPI stream every 125 ms, VRAI for each VRCO, the
cases' packets at a limited rate, and every packet shown to the oracles.

One thread, one socket: `pump` runs the stream, reads the controller, polls the supervised
process, ticks the oracles and resends the unacknowledged VRCI until a given time.

As the base unit does (TS-0006 5.1.3), each valid VRCI of ours a case sends is resent every
`Settings.resend_ms` (100 ms) on the next serial until its VRAO comes or the oracle's ack timeout
passes (while `Monitor.resending`: a VRAO with a wrong ID, or an illegal one, does not stop it);
a mutated or illegal one, or a duplicate frame, is not. A replay plays its packets through the
same session, and so resends as the run did.
"""
from __future__ import annotations

import collections
import select
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from .. import constants as C
from . import mutate as M
from .link import Link
from .memory import Watch
from .oracles import MEMORY, Limits, Monitor, Trigger
from .supervisor import Supervisor

_TICK_S = 0.005
_RATE_CREDIT_S = 0.01
_AVERAGE_FROM = 1000.0
_TRAFFIC_S = 12.0     # traffic kept for the pcap of a finding


@dataclass
class Settings:
    target: tuple[str, int]
    listen: tuple[str, int]
    group: Optional[str] = None
    rate: float = 100.0                     # case packets per second
    limits: Limits = field(default_factory=Limits)
    startup_s: float = 10.0                 # time allowed for the first VRPO
    vrco_wait_s: float = 3.0                # withhold cases wait this long for a fresh VRCO
    allow_remote: bool = False              # a target other than loopback (never a broadcast address)
    resend_ms: float = float(C.COMMAND_RESEND_MS)   # unacknowledged VRCI resent this often (0: never)


@dataclass
class Sent:
    """A packet a case sent: what replay needs."""

    time: float
    data: bytes
    twin: bytes
    delay_ms: float
    expect_ack: bool


class TargetLost(Exception):
    """The controller sends no VRPO and cannot be restarted."""


class Session:
    def __init__(self, settings: Settings, supervisor: Optional[Supervisor] = None,
                 evidence_dir: Path = Path("."), memory: Optional[Watch] = None) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.link = Link(settings.target, settings.listen, settings.group, settings.allow_remote)
        now = time.time()
        self.monitor = Monitor(settings.limits, now)
        self.serial = 0
        self.stream: dict[str, Any] = dict(M.ARMED_VRPI)
        self.next_vrpi = now
        self.vrpi_paused_until = 0.0
        self.withheld: dict[int, float] = {}     # VRCO IDs seen while withholding -> first seen
        self.traffic: collections.deque[tuple[float, bool, bytes, tuple[str, int]]] = collections.deque()
        self.last_case_send = 0.0
        self.next_case_send = 0.0
        self.exit_reported = False
        self.crashes = 0
        self.evidence_dir = evidence_dir
        self.memory = memory          # the supervised controller's RSS (None: not watched)
        self.last_case = -1           # of the run's cases (not replays): what a memory sample counts
        self.case_packets = 0
        self.resends: dict[int, tuple[float, bytes, int]] = {}   # command ID -> (next resend, VRCI, case)

    # --- the loop ---------------------------------------------------------------------------------
    def pump(self, until: float) -> None:
        while True:
            now = time.time()
            if now >= self.next_vrpi:
                if now >= self.vrpi_paused_until:
                    self._send(M.build(C.PacketType.VRPI, self._take_serial(), self.stream))
                self.next_vrpi += C.VRPI_PERIOD_MS / 1000
                if self.next_vrpi <= now:
                    self.next_vrpi = now + C.VRPI_PERIOD_MS / 1000
            for t, data, src in self.link.receive():
                self._on_rx(t, data, src)
            if self.supervisor is not None and not self.exit_reported:
                code = self.supervisor.poll()
                if code is not None:
                    self.exit_reported = True
                    t = time.time()
                    self.crashes += 1
                    crash = self.supervisor.evidence(self.evidence_dir, f".crash-{self.crashes}")
                    self.monitor.on_exit(t, code, crash)
                elif self.memory is not None and self.supervisor.proc is not None:
                    self._sample_memory(self.supervisor.proc.pid)
            self.monitor.tick(time.time())
            if self.resends:
                self._resend()
            now = time.time()
            if now >= until:
                return
            wait = max(0.0, min(until, self.next_vrpi, now + _TICK_S) - now)
            select.select([self.link], [], [], wait)

    def _sample_memory(self, pid: int) -> None:
        assert self.memory is not None
        now = time.time()
        assert self.supervisor is not None
        evidence = self.memory.sample(now, pid, self.supervisor.starts, self.last_case, self.case_packets)
        if evidence is not None:
            self.monitor.fire(Trigger(MEMORY, now, evidence["detail"], kind="rss", memory=evidence))

    def _resend(self) -> None:
        """Resend the VRCI due, on the next serial, while their acks are awaited: one acknowledged
        (or given up on, or owed by a controller since restarted, or by the run while a replay has
        the monitor) is dropped."""
        now = time.time()
        for command_id, (due, data, index) in list(self.resends.items()):
            if not self.monitor.resending(command_id, now):
                del self.resends[command_id]
            elif now >= due:
                again = M.reserial(data, self._take_serial())
                t = self._send(again)
                self.monitor.on_tx(t, again, again, index, expect_ack=False)
                self.resends[command_id] = (t + self.settings.resend_ms / 1000, data, index)

    def _take_serial(self) -> int:
        serial, self.serial = self.serial, (self.serial + 1) % C.SERIAL_MODULUS
        return serial

    def _send(self, data: bytes) -> float:
        t = self.link.send(data)
        self._log(t, True, data, self.settings.target)
        return t

    def _log(self, t: float, outbound: bool, data: bytes, peer: tuple[str, int]) -> None:
        self.traffic.append((t, outbound, data, peer))
        while self.traffic and self.traffic[0][0] < t - _TRAFFIC_S:
            self.traffic.popleft()

    def _on_rx(self, t: float, data: bytes, src: tuple[str, int]) -> None:
        self._log(t, False, data, src)
        fields = self.monitor.on_rx(t, data, src)
        if fields["problems"] or fields.get("type") != C.PacketType.VRCO.value:
            return
        command_id = fields["command_id"]
        if self.monitor.withholding:
            self.withheld.setdefault(command_id, t)
        else:
            self.ack_vrco(command_id)

    def ack_vrco(self, command_id: int) -> None:
        data = M.build(C.PacketType.VRAI, self._take_serial(), dict(command_id=command_id))
        self.monitor.on_vrai(self._send(data), command_id, data)

    # --- cases ------------------------------------------------------------------------------------
    def send_case_packet(self, index: int, build: Any, delay_ms: float, expect_ack: bool) -> Sent:
        """Wait `delay_ms` and for the rate limit, then build the packet on the next serial and send it."""
        if delay_ms:
            self.pump(time.time() + delay_ms / 1000)
        self.pump(self.next_case_send)
        data, twin = build(self._take_serial())
        t = self._send(data)
        self.last_case_send = t
        # Packets at least 1/rate apart; above _AVERAGE_FROM packets/s (intervals shorter than a
        # sleep can time on a loaded machine) the rate holds on average instead: time lost to a late
        # wake-up may be made up within _RATE_CREDIT_S, so that a high --rate is reached, never exceeded.
        interval = 1.0 / self.settings.rate
        credit = _RATE_CREDIT_S if self.settings.rate >= _AVERAGE_FROM else 0.0
        self.next_case_send = max(self.next_case_send, t - credit) + interval
        awaited = self.monitor.on_tx(t, data, twin, index, expect_ack)
        if awaited is not None and self.settings.resend_ms:
            self.resends[awaited] = (t + self.settings.resend_ms / 1000, data, index)
        if index >= 0:
            self.case_packets += 1
            if self.memory is not None:
                self.memory.note(data)
        return Sent(t, data, twin, delay_ms, expect_ack)

    def run_steps(self, index: int, steps: list[tuple[Any, float, bool]], pause_vrpi_ms: float = 0.0,
                  withhold_vrai_ms: float = 0.0, stream: Optional[dict[str, Any]] = None,
                  settle_ms: float = 0.0) -> list[Sent]:
        """Play one case: (builder, delay ms, expect ack) steps, then its stream pause or VRAI withholding."""
        self.monitor.note_case(time.time(), index)
        if index >= 0:
            self.last_case = index
        if stream is not None:
            self.stream = dict(stream)
        sent = [self.send_case_packet(index, build, delay, expect) for build, delay, expect in steps]
        if pause_vrpi_ms:
            self.vrpi_paused_until = time.time() + pause_vrpi_ms / 1000
            self.pump(self.vrpi_paused_until)
            self.next_vrpi = time.time()
        if withhold_vrai_ms:
            self._withhold(index, withhold_vrai_ms)
        if settle_ms:
            self.pump(time.time() + settle_ms / 1000)
        self.stream = dict(M.ARMED_VRPI)
        return sent

    def _withhold(self, index: int, hold_ms: float) -> None:
        """Leave the next fresh VRCO unacknowledged for `hold_ms`, then acknowledge it."""
        if not self.monitor.vrco_seen:
            return    # this controller has sent no VRCO yet: nothing to withhold
        self.monitor.withholding = True
        self.withheld.clear()
        deadline = time.time() + self.settings.vrco_wait_s
        while not self.withheld and time.time() < deadline:
            self.pump(min(deadline, time.time() + 0.05))
        if self.withheld:
            self.pump(min(self.withheld.values()) + hold_ms / 1000)
        self.monitor.withholding = False
        self.monitor.note_case(time.time(), index)
        for command_id in list(self.withheld):
            self.ack_vrco(command_id)
        self.withheld.clear()

    # --- the controller's life --------------------------------------------------------------------
    def wait_for_vrpo(self, since: float, timeout: float) -> bool:
        """Pump until a VRPO newer than `since` arrives; False after `timeout` seconds, or as soon as
        the supervised controller has exited (nothing more can come)."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            if self.monitor.last_vrpo is not None and self.monitor.last_vrpo > since:
                return True
            if self.supervisor is not None and self.supervisor.poll() is not None:
                self.pump(time.time() + 0.05)      # (what it sent before it went)
                break
            self.pump(min(deadline, time.time() + 0.02))
        return self.monitor.last_vrpo is not None and self.monitor.last_vrpo > since

    def restart_target(self) -> None:
        """Restart the supervised controller and wait for its first VRPO (TargetLost if none)."""
        assert self.supervisor is not None
        self.supervisor.stop()
        # What the stopped process sent before it went (a VRPO due when SIGTERM came) is its, not
        # the new one's: kept for the pcap, not judged (its serial would make the new process's
        # first serials 'not incrementing'). Nothing of it can come later: it is dead.
        for t, data, src in self.link.receive():
            self._log(t, False, data, src)
        self.supervisor.start()
        now = time.time()
        self.exit_reported = False
        self.monitor.reset_controller(now)
        if not self.wait_for_vrpo(now, self.settings.startup_s):
            code = self.supervisor.poll()
            raise TargetLost("controller restarted but sent no VRPO within "
                             f"{self.settings.startup_s:.0f} s" + (f" (exit code {code})" if code is not None else "")
                             + self.supervisor.last_words())
        self.settle()

    def settle(self) -> None:
        """After the controller's first VRPO: let it see a VRPI first. Every start waits the same,
        so that a replay (`--replay` included) plays its case as far into the controller's life,
        and its cycle, as the run's confirming replay did: a bug that needs a command to come
        early in a scan cycle replays there too."""
        self.pump(time.time() + C.VRPI_PERIOD_MS / 1000 + 0.01)

    def healthy(self) -> bool:
        """Alive and sending VRPO."""
        if self.supervisor is not None and self.supervisor.poll() is not None:
            return False
        last = self.monitor.last_vrpo
        return last is not None and time.time() - last < max(0.5, 3 * self.monitor.vrpo_interval)

    def close(self) -> None:
        if self.supervisor is not None:
            self.supervisor.stop()
        self.link.close()
