"""captures/crane.pcapng: a crane (dissector/examples/crane.lua) over the EG-Link, with its truths.

Run `python captures/crane.py [OUT]` (the venv's python; `make captures` does): the simulators on
the virtual clock, as `vm110 synth` runs its scenarios, with a controller whose periodic data and
commands are the crane's (layout in crane.lua). Writes OUT (default captures/crane.pcapng),
OUT.truth.json (the analysis truth, as for every synthesised capture) and OUT.machine.json (what
the crane data say, cycle by cycle and command by command, for the dissector test). Deterministic:
no randomness, the same bytes every run.

The crane (20 s): the hoist climbs and lowers a load in a 10 s cycle; the load, the wind and a
slack rope raise alarms at set times and the speed limit follows them. Every second the periodic
data carry the event log of the last 100 events (808 bytes: a VRPO burst of 488 + 320), in
between the latest 0-3 events. The operator sets a speed limit, resets alarms and sounds the horn
(VRCI); the crane shows alarm texts on the remote (VRCO).
"""
from __future__ import annotations

import json
import struct
import sys
from pathlib import Path
from typing import Any

from vm110.capture.writer import format_of
from vm110.fileio import atomic_writer, write_text
from vm110.sim.bu import BaseUnit, BaseUnitConfig
from vm110.sim.clock import US_PER_S
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.remote import Remote
from vm110.sim.reading import Reading
from vm110.sim.scenario import BU_IP, CONTROLLER_IP, EPOCH_US, QUIET_TAIL_S, Scenario
from vm110.sim.virtual import Station
from vm110.synth import truth_path, write_capture

DURATION_S = 20.0
MACHINE_SUFFIX = ".machine.json"
OVERLOAD, HIGH_WIND, SLACK_ROPE, LIMIT_SWITCH = 0x01, 0x02, 0x04, 0x08
FULL_LOG_EVERY = 10                     # cycles (of 100 ms): the whole log once a second
LOG_SIZE = 100
_HEAD, _ENTRY = struct.Struct("<HHBBH"), struct.Struct("<IHH")
# Operator commands (VRCI: opcode, argument) and crane messages (VRCO: 0x81, text), by time (s).
OPERATOR = ((2.0, 0x01, 50), (6.0, 0x03, 1), (6.5, 0x03, 0), (9.0, 0x02, OVERLOAD | HIGH_WIND), (13.0, 0x01, 100))
MESSAGES = ((4.0, "OVERLOAD"), (8.0, "HIGH WIND"), (15.5, "SLACK ROPE"))


def state(cycle: int) -> dict[str, int]:
    """The crane at VRPO cycle `cycle` (every 100 ms): a deterministic function of time."""
    t = cycle % 100                                     # a 10 s lift: up 5 s, down 5 s
    height = 200 + 60 * (t if t < 50 else 100 - t)      # cm: 2 m to 32 m
    load = 4000 + 150 * (cycle % 100) if cycle < 100 else 2500
    alarms = (OVERLOAD if load > 15_000 else 0) | (HIGH_WIND if 80 <= cycle < 130 else 0) \
        | (SLACK_ROPE if 150 <= cycle < 158 else 0) | (LIMIT_SWITCH if height >= 3200 else 0)
    speed = 100 if not alarms else 25 if alarms & (OVERLOAD | HIGH_WIND) else 60
    return {"hoist_height": height, "load": load, "alarms": alarms, "speed_limit": speed}


def events_until(cycle: int) -> list[tuple[int, int, int]]:
    """The last LOG_SIZE events of the log (time s since the epoch, code, value): one per cycle,
    and as many from before the capture (the crane's start-up), so the full log is always full."""
    return [(EPOCH_US // US_PER_S + c // 10, 0x100 + c % 7, (c * 37) % 1000)
            for c in range(cycle + 1 - LOG_SIZE, cycle + 1)]


def periodic(cycle: int) -> tuple[bytes, dict[str, Any]]:
    """The periodic data of a cycle and what they say."""
    fields = state(cycle)
    log = events_until(cycle)
    log = log[-LOG_SIZE:] if cycle % FULL_LOG_EVERY == FULL_LOG_EVERY - 1 else log[-(cycle % 4):] if cycle % 4 else []
    data = _HEAD.pack(fields["hoist_height"], fields["load"], fields["alarms"], fields["speed_limit"], len(log)) \
        + b"".join(_ENTRY.pack(*e) for e in log)
    return data, {**fields, "log": [list(e) for e in log]}


class CraneController(Controller):
    """The reference controller with the crane's periodic data; records each cycle's meaning."""

    def __init__(self, config: ControllerConfig, **node: Any) -> None:
        super().__init__(config, **node)
        self.sent_data: list[dict[str, Any]] = []

    def periodic_data(self, now: int) -> bytes:
        data, meaning = periodic(self.cycle)
        self.sent_data.append({"cycle": self.cycle, "bytes": len(data), **meaning})
        return data


def build(seed: int, duration: float, reading: Reading) -> list[Station]:
    remote = Remote.from_script({
        "steps": [{"at": 0, "state": "armed", "motion": True}],
        "commands": [{"at": t, "data": chr(op) + chr(arg)} for t, op, arg in OPERATOR if t < duration - QUIET_TAIL_S]})
    bu = BaseUnit(remote, BaseUnitConfig(seed=seed), **reading.node_options())
    messages = tuple((t, b"\x81" + text.encode()) for t, text in MESSAGES if t < duration - QUIET_TAIL_S)
    controller = CraneController(ControllerConfig(commands=messages, first_packet_number=reading.vrpo_start),
                                 **reading.node_options())
    return [Station(bu, BU_IP, 5825), Station(controller, CONTROLLER_IP, 5827)]


def machine_truth(stations: list[Station], duration: float) -> dict[str, Any]:
    """What the crane's data say, in the order they were sent."""
    controller = stations[1].node
    argument = {0x01: "set_speed_limit", 0x02: "reset_alarms", 0x03: "horn"}
    commands: list[dict[str, Any]] = [
        {"type": "VRCI", "opcode": op, argument[op]: bool(arg) if op == 0x03 else arg}
        for t, op, arg in OPERATOR if t < duration - QUIET_TAIL_S]
    commands += [{"type": "VRCO", "opcode": 0x81, "alarm_text": text} for t, text in MESSAGES
                 if t < duration - QUIET_TAIL_S]
    return {"periodic": controller.sent_data, "commands": commands}


def generate(out: str, duration: float = DURATION_S) -> dict[str, Any]:
    """Write the capture, its analysis truth and its machine truth; returns the machine truth."""
    built: list[list[Station]] = []

    def keep(seed: int, length: float, reading: Reading) -> list[Station]:
        built.append(build(seed, length, reading))
        return built[-1]
    scenario = Scenario("crane", "a crane's machine data (dissector/examples/crane.lua)", duration, keep)
    with atomic_writer(out) as stream:
        truth = write_capture(stream, scenario, 1, duration, format_of(out))
        write_text(truth_path(out), json.dumps(truth, indent=1) + "\n")
    machine = machine_truth(built[0], duration)
    # One line per cycle and command: readable, and a diff shows which one changed.
    write_text(out + MACHINE_SUFFIX, "{\n" + ",\n".join(
        f' "{key}": [\n  ' + ",\n  ".join(json.dumps(item) for item in items) + "\n ]"
        for key, items in machine.items()) + "\n}\n")
    return machine


if __name__ == "__main__":
    target = sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).with_name("crane.pcapng"))
    result = generate(target)
    print(f"wrote {target} ({len(result['periodic'])} VRPO cycles of crane data, {len(result['commands'])} commands)")
