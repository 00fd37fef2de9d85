"""Named scenarios for `vm110 synth`: a base unit and the reference controller, and what goes wrong.

Each scenario builds its stations from a seed, a duration (seconds) and the reading of TS-0006
both devices speak (`Reading`). Times of scheduled events are absolute seconds from the start;
operator and controller commands stop `QUIET_TAIL_S` before the end so that every command in a
capture has had its chance to be acknowledged.
"""
from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass
from typing import Any, Callable, Optional

from .. import constants as C
from .bu import BaseUnit, BaseUnitConfig
from .controller import Controller, ControllerConfig
from .impair import Impairment
from .lifecycle import Restart
from .reading import Reading
from .remote import Remote
from .virtual import Station

BU_IP, CONTROLLER_IP = "10.0.0.10", "10.0.0.20"
QUIET_TAIL_S = 2.5
EPOCH_US = 1_750_000_000_000_000      # 2025-06-15 15:06:40 UTC: fixed, so captures are reproducible


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration_s: float
    build: Callable[[int, float, Reading], list[Station]]
    other_traffic: tuple[float, ...] = ()     # times (s) of non-EG-Link frames on the same tap

    def stations(self, seed: int, duration: float, reading: Optional[Reading] = None) -> list[Station]:
        """The stations, speaking `reading` (default: interpretation.md's)."""
        return self.build(seed, duration, reading or Reading())


def _pair(seed: int, reading: Reading, remote: Remote, bu: Optional[BaseUnitConfig] = None,
          ctl: Optional[ControllerConfig] = None, bu_imp: Optional[Impairment] = None,
          ctl_imp: Optional[Impairment] = None, bu_serial: int = 0) -> list[Station]:
    base_unit = BaseUnit(remote, dataclasses.replace(bu or BaseUnitConfig(seed=seed), vrpo_start=reading.vrpo_start),
                         serial_start=bu_serial, **reading.node_options())
    controller = Controller(dataclasses.replace(ctl or ControllerConfig(), first_packet_number=reading.vrpo_start),
                            **reading.node_options())
    return [Station(base_unit, BU_IP, C.INPUT_PORT, bu_imp or Impairment(seed=seed)),
            Station(controller, CONTROLLER_IP, C.OUTPUT_PORT, ctl_imp or Impairment(seed=seed))]


def _until(duration: float) -> float:
    return max(duration - QUIET_TAIL_S, 0.001)


def _armed(duration: float, every: float = 2.0) -> Remote:
    return Remote.simple(armed=True, command_every=every, command_until=_until(duration))


def _vrco(duration: float, every: float, **extra: Any) -> ControllerConfig:
    return ControllerConfig(command_every_s=every, command_until_s=_until(duration), **extra)


def normal(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The BU's serial counter starts near the top and wraps 65535 -> 0 after about 16 s.
    return _pair(seed, reading, _armed(duration), ctl=_vrco(duration, 5.0), bu_serial=65400)


def disarmed(seed: int, duration: float, reading: Reading) -> list[Station]:
    remote = Remote.simple(armed=False, unarmed_rus=2, command_every=3.0, command_until=_until(duration))
    return _pair(seed, reading, remote)


def loss(seed: int, duration: float, reading: Reading) -> list[Station]:
    net: dict[str, Any] = {"loss": 5.0, "duplicate": 3.0, "reorder": 1.0, "jitter_ms": 2.0, "seed": seed}
    return _pair(seed, reading, _armed(duration, 1.0), ctl=_vrco(duration, 2.0),
                 bu_imp=Impairment(**net), ctl_imp=Impairment(**net))


def retransmit(seed: int, duration: float, reading: Reading) -> list[Station]:
    # Lost VRCI and VRAO make the BU resend. Every VRAO is lost from 7.95 s to 10.5 s: the
    # command of 8 s fails. Command IDs start at 65534 and wrap to 0.
    return _pair(seed, reading, _armed(duration, 1.0), bu=BaseUnitConfig(seed=seed, command_id_start=0xFFFE),
                 bu_imp=Impairment(loss=30.0, only=("VRCI",), seed=seed),
                 ctl_imp=Impairment(loss=30.0, only=("VRAO",), drops=((7.95, 10.5, ("VRAO",)),), seed=seed))


def vrco(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The controller sends a VRCO every second; lost VRAI make it resend. Every VRAI is lost
    # from 9.95 s to 12.5 s: the controller gives the command of 10 s up after 2000 ms.
    remote = Remote.simple(armed=True)
    return _pair(seed, reading, remote, ctl=_vrco(duration, 1.0),
                 bu_imp=Impairment(loss=30.0, only=("VRAI",), drops=((9.95, 12.5, ("VRAI",)),), seed=seed))


def vrpo_split(seed: int, duration: float, reading: Reading) -> list[Station]:
    # 1200 bytes of periodic data: bursts of 3 VRPO (488 + 488 + 224); 3 % of them are lost, but
    # not in the first burst: until a short last packet was seen, a burst of 488-byte packets may
    # be a whole one (analysis infers the data size, docs/rules.md), and the truth would be a guess.
    return _pair(seed, reading, _armed(duration, 3.0), ctl=ControllerConfig(data_size=1200),
                 ctl_imp=Impairment(loss=3.0, only=("VRPO",), seed=seed, loss_from=0.05))


BU_ILLEGAL = ((2.0, "bad_crc", "VRPI"), (3.0, "revision", "VRPI"), (4.0, "unknown_id", "VRPI"),
              (5.0, "size_mismatch", "VRPI"), (6.0, "size_too_large", "VRPI"), (7.0, "truncated", "VRPI"),
              (8.0, "revision+bad_crc", "VRPI"), (9.0, "truncated", "VRCI"), (10.0, "bad_crc", "VRAI"))
CONTROLLER_ILLEGAL = ((2.5, "bad_crc", "VRPO"), (3.5, "truncated", "VRAO"), (4.5, "unknown_id", "VRPO"),
                      (5.5, "size_too_large", "VRPO"), (6.5, "size_mismatch", "VRAO"), (7.5, "revision", "VRPO"),
                      (8.5, "truncated", "VRCO"), (9.5, "unknown_id+bad_crc", "VRPO"))


def illegal(seed: int, duration: float, reading: Reading) -> list[Station]:
    # Every reason of interpretation.md on both directions, plus 1 % random CRC corruption.
    # The truncated VRCI of 9 s is ignored by the controller, so the BU resends it.
    return _pair(seed, reading, _armed(duration, 1.0), ctl=_vrco(duration, 2.0),
                 bu_imp=Impairment(corrupt=1.0, mangles=BU_ILLEGAL, seed=seed),
                 ctl_imp=Impairment(corrupt=1.0, mangles=CONTROLLER_ILLEGAL, seed=seed))


def bu_watchdog(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The controller hangs from 5 s to 8 s: no VRPO for 3 s, the BU's watchdog trips at 7 s
    # (EG-Link "No link", BU state "External link error": ES-Link relays open); the operator
    # command of 6 s gets no VRAO and fails.
    return _pair(seed, reading, _armed(duration, 2.0), ctl=ControllerConfig(stalls=((5.0, 8.0),)))


def controller_watchdog(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The BU hangs from 5.0 s to 5.8 s (no VRPI, no serials skipped), and the input path is
    # down from 10 s to 11 s (VRPI lost: serial gap); the controller flags both.
    return _pair(seed, reading, _armed(duration, 2.0), bu=BaseUnitConfig(seed=seed, stalls=((5.0, 5.8),)),
                 bu_imp=Impairment(outages=((10.0, 11.0),), seed=seed))


def glink(seed: int, duration: float, reading: Reading) -> list[Station]:
    # G-Link fallback from 6 s to 16 s: VRPO every 400 ms instead of 100 ms, the RU answers VRCO
    # 250-650 ms late, so the controller resends and the BU acknowledges every copy.
    window = ((6.0, 16.0),)
    return _pair(seed, reading, _armed(duration, 2.0), bu=BaseUnitConfig(seed=seed, glink=window),
                 ctl=_vrco(duration, 1.0, glink=window))


COMMAND_TYPES = ("VRCI", "VRAO", "VRCO", "VRAI")


def overlap(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The operator presses a key every 1.5 s, and every third time a second one 40-90 ms later,
    # so two VRCI are in flight; after a pause from 50 s the BU's command IDs start again at 0
    # (reused after more than the 2000 ms reuse gap). The controller sends a setting (VRCO) every
    # 2 s and, with every fourth, an alarm 50 ms later. 15 % of the commands and acks are lost,
    # every VRAO from 69.9 s to 72.2 s (the operator command of 70 s fails), and 5 % of all
    # packets reach the tap twice, 0.05-3 ms apart (a mirror port).
    rng = random.Random(f"overlap:{seed}")
    until, presses, t = _until(duration), [], 1.0
    while t < until:
        presses.append(t)
        if len(presses) % 4 == 3 and t + 0.1 < until:
            presses.append(round(t + rng.uniform(0.04, 0.09), 3))
        t += 6.0 if 48.0 < t < 50.0 else 1.5
    before = sum(p < 50.0 for p in presses)
    keys = [{"at": p, "data": f"KEY {i}", "id": None if i < before else i - before} for i, p in enumerate(presses)]
    remote = Remote.from_script({"steps": [{"at": 0, "state": "armed", "motion": True}], "commands": keys})
    alarms = tuple((t + 0.05, b"ALARM") for t in range(2, int(until), 8))
    net: dict[str, Any] = {"loss": 15.0, "only": COMMAND_TYPES, "mirror": 5.0, "seed": seed}
    return _pair(seed, reading, remote, ctl=_vrco(duration, 2.0, commands=alarms),
                 bu_imp=Impairment(**net), ctl_imp=Impairment(drops=((69.9, 72.2, ("VRAO",)),), **net))


def bu_stops(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The BU stops at 10 s for good; the controller goes on sending VRPO and VRCO (given up
    # after 2000 ms without VRAI) until the end: the VRPI stream is silent until the end.
    return _pair(seed, reading, _armed(duration, 2.0), bu=BaseUnitConfig(seed=seed, stop_at_s=10.0),
                 ctl=_vrco(duration, 1.5))


CONTROLLER_NEW_PORT = 50123


def restart(seed: int, duration: float, reading: Reading) -> list[Station]:
    # The controller program is restarted at 8 s (back on the same port 1.5 s later, serials and
    # command IDs from 0) and at 20 s (back 2.2 s later on a new source port); the BU, its counter
    # started at 40000, reboots at 25 s (back at 26.5 s from 0). A VRCO of 7.8 s and a VRCI of
    # 24.9 s are in flight at the restarts (their acks lost): interrupted. The VRCO of 19.9 s is
    # past its 2000 ms limit when the controller is back on its new port: failed.
    remote = Remote.from_script({"steps": [{"at": 0, "state": "armed", "motion": True}],
                                 "commands": [{"at": 24.9, "data": "LAST KEY"}],
                                 "command_every": 2.0, "command_until": _until(duration)})
    ctl = _vrco(duration, 2.0, commands=((7.8, b"SETTING"), (19.9, b"SETTING")),
                restarts=(Restart(8.0, 1.5), Restart(20.0, 2.2, port=CONTROLLER_NEW_PORT)))
    bu = BaseUnitConfig(seed=seed, restarts=(Restart(25.0, 1.5),))
    return _pair(seed, reading, remote, bu=bu, ctl=ctl, bu_serial=40000,
                 bu_imp=Impairment(drops=((7.75, 8.0, ("VRAI",)), (19.85, 20.0, ("VRAI",))), seed=seed),
                 ctl_imp=Impairment(drops=((24.85, 25.0, ("VRAO",)),), seed=seed))


def day(seed: int, duration: float, reading: Reading) -> list[Station]:
    # Long captures for benchmarks: normal operation with light loss and duplication.
    net: dict[str, Any] = {"loss": 0.1, "duplicate": 0.05, "seed": seed}
    return _pair(seed, reading, _armed(duration, 5.0), ctl=_vrco(duration, 10.0),
                 bu_imp=Impairment(**net), ctl_imp=Impairment(**net), bu_serial=seed & 0xFFFF)


SCENARIOS = {s.name: s for s in (
    Scenario("normal", "armed RU moving, operator command every 2 s, VRCO every 5 s, BU serial wrap", 20.0, normal),
    Scenario("disarmed", "no RU armed, two unarmed RUs; commands acknowledged, not executed", 15.0, disarmed),
    Scenario("loss", "5 % loss, 3 % duplicates, 1 % reordering, 2 ms jitter on both directions", 30.0, loss),
    Scenario("retransmit", "lost VRCI/VRAO: VRCI retransmissions, one failed command, command ID wrap",
             20.0, retransmit),
    Scenario("vrco", "controller commands: VRCO resent until VRAI, one given up after 2000 ms", 20.0, vrco),
    Scenario("vrpo-split", "1200 bytes of periodic data: VRPO bursts of 3 packets, some incomplete",
             15.0, vrpo_split),
    Scenario("illegal", "every illegal reason in both directions, random CRC errors, other UDP traffic",
             15.0, illegal, other_traffic=(1.5, 5.25, 9.75, 13.1)),
    Scenario("bu-watchdog", "controller stalls 3 s: no VRPO, BU watchdog trips, ES-Link relays open",
             15.0, bu_watchdog),
    Scenario("controller-watchdog", "VRPI gaps (BU stall, input outage): controller VRPI timeout",
             15.0, controller_watchdog),
    Scenario("glink", "G-Link fallback 6-16 s: VRPO every 400 ms, VRCO answered late", 25.0, glink),
    Scenario("overlap", "several commands in flight on both sides, 15 % command loss, mirror duplicates, "
             "command ID reuse after a pause", 90.0, overlap),
    Scenario("bu-stops", "the BU stops at 10 s, the controller goes on: VRPI silent until the end", 15.0, bu_stops),
    Scenario("restart", "controller restarted twice (same port, new port), BU reboots with its counter "
             "above 32767", 40.0, restart),
    Scenario("day", "long normal operation with light loss (for benchmarks)", 3600.0, day),
)}
