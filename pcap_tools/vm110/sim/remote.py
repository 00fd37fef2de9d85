"""A scriptable remote unit (RU) and operator, as the base unit reports them in VRPI and VRCI.

A script is JSON (or the same dict in Python):

    {"steps": [{"at": 0, "state": "armed", "ru": 3079, "battery": 90, "motion": true},
               {"at": 12, "state": "disarmed", "unarmed_rus": 2},
               {"at": 20, "set": {"ru_state": 4, "ru_docked": 1}}],
     "commands": [{"at": 1.5, "data": "START PUMP"}, {"at": 1.55, "data": "HORN"},
                  {"at": 30, "data": "STOP PUMP", "id": 0}],
     "command_every": 2.0, "command_until": 50}

`state` is `armed` or `disarmed` (the VRPI fields that go with it; `ru`, `battery`, `rssi` and
`unarmed_rus` are the armed state's, `unarmed_rus` the disarmed one's too, and refused without it),
`set` overrides VRPI fields by their canonical names (a value that stays), `motion` moves joysticks,
switches and the encoder in deterministic patterns, `battery` drains 1 % a minute from the given
level (an armed step without it: no drain). Commands are sent at their time
even while others are still in flight; `id` gives one its own command ID (a device reusing an
ID after a pause) instead of the next. Times are seconds from start.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

from .. import constants as C
from .. import protocol as P
from ..errors import CliError
from ..fileio import read_at_most
from ..jsonin import loads
from .clock import US_PER_S, seconds

DEFAULT_RU = 0x0C07
_BATTERY_DRAIN_US = 60 * US_PER_S          # 1 % per minute
_JOYSTICK_PERIODS_US = (4_000_000, 6_000_000, 5_000_000, 7_000_000)
VRPI_NAMES = tuple(f.name for f in P.PACKETS[C.PacketType.VRPI].fields)
_VRPI_DEFAULTS = tuple(f.default for f in P.PACKETS[C.PacketType.VRPI].fields)
VRPI_INDEX = {name: i for i, name in enumerate(VRPI_NAMES)}
_MAX_ENTRIES = 100_000   # steps, commands: a 16 MiB script of 1.5 M steps took 1.3 GB before it began
EVERY_LEAST_S = 1e-6     # the clock's step: a shorter interval would be 0, which means none
_RU_FIELDS = tuple(f.name for f in P.PACKETS[C.PacketType.VRPI].fields if f.ru)
_ARMED_RU, _BATTERY, _RU_STATE = VRPI_INDEX["armed_ru"], VRPI_INDEX["ru_battery"], VRPI_INDEX["ru_state"]
_UNARMED = VRPI_INDEX["unarmed_rus"]
_UNARMED_MAX = P.FIELDS["unarmed_rus"].limits[1]
_JOYSTICKS = tuple(VRPI_INDEX[f"joystick{i}"] for i in range(1, C.JOYSTICKS + 1))
_SWITCHES = tuple(VRPI_INDEX[f"switch{i}"] for i in range(1, C.SWITCHES + 1))
_ENCODER, _ENCODER_SWITCH = VRPI_INDEX["encoder"], VRPI_INDEX["encoder_switch"]
# (payload index, period, quarter period, sweep value by phase): a VRPI every 125 ms meets few
# phases, so the values are remembered (up to _KNOWN_PHASES of them).
_SWEEPS: tuple[tuple[int, int, int, dict[int, int]], ...] = tuple(
    (index, period, period // 4, {}) for index, period in zip(_JOYSTICKS, _JOYSTICK_PERIODS_US))
_KNOWN_PHASES = 4096
_SWEEP_CYCLE_US = math.lcm(*_JOYSTICK_PERIODS_US)         # every sweep's period divides it
_STEP_US = 10_000           # switches and encoder move in steps of 10 ms
_PUSHBUTTON, _TOGGLE, _POTENTIOMETER = _SWITCHES[:3]
_SWITCH_STEPS = C.SWITCH_MAX + 1
_ENABLED = C.RuState.ENABLED


# --- what a script may hold ------------------------------------------------------------------------
_MAX_SCRIPT = 16 << 20
_MAX_S = 30 * 86400                        # as simulate's times
_LIMITS = {f.name: f.limits for f in P.PACKETS[C.PacketType.VRPI].fields if f.kind != "bytes"}
_KEYS = {"script": {"steps", "commands", "command_every", "command_until"},
         "step": {"at", "state", "ru", "battery", "rssi", "unarmed_rus", "motion", "set"},
         "command": {"at", "data", "id"}}
_STEP_FIELD = {"ru": "armed_ru", "battery": "ru_battery", "rssi": "ru_rssi", "unarmed_rus": "unarmed_rus"}
_STATE_KEYS = {"armed": ("ru", "battery", "rssi", "unarmed_rus"), "disarmed": ("unarmed_rus",)}


def _number(where: str, value: Any, low: float, high: float, integer: bool = False) -> None:
    kind = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not (math.isfinite(value) and low <= value <= high):
        what = "an integer" if integer else "a number"
        raise CliError(f"remote script: {where} is {str(value)[:30]!r}: must be {what} from {low:g} to {high:g}")


def _object(where: str, value: Any, keys: str) -> Mapping[str, Any]:
    if not isinstance(value, dict):
        raise CliError(f"remote script: {where} must be a JSON object")
    unknown = sorted(set(value) - _KEYS[keys])
    if unknown:
        raise CliError(f"remote script: {where} has unknown key {unknown[0][:30]!r} "
                       f"(allowed: {', '.join(sorted(_KEYS[keys]))})")
    return value


def _list(where: str, value: Any) -> list:
    if not isinstance(value, list):
        raise CliError(f"remote script: {where} must be a JSON list")
    if len(value) > _MAX_ENTRIES:
        raise CliError(f"remote script: {where} has {len(value)} entries (at most {_MAX_ENTRIES})")
    return value


def check_script(script: Any) -> None:
    """CliError naming the first thing a remote script does not allow: unknown keys, values of the
    wrong type, times outside 0 to 30 days, VRPI values and command IDs outside their fields."""
    _object("the script", script, "script")
    for key in ("command_every", "command_until"):
        if key in script:
            _number(key, script[key], 0, _MAX_S)
    if 0 < script.get("command_every", 0) < EVERY_LEAST_S:
        raise CliError(f"remote script: command_every is {script['command_every']!r}: must be 0 (none) "
                       f"or at least {EVERY_LEAST_S:g} s (the clock's step)")
    for i, raw in enumerate(_list("steps", script.get("steps", []))):
        step = _object(f"steps[{i}]", raw, "step")
        _number(f"steps[{i}].at", step.get("at", 0), 0, _MAX_S)
        if "motion" in step and not isinstance(step["motion"], bool):
            raise CliError(f"remote script: steps[{i}].motion must be true or false")
        for key, name in _STEP_FIELD.items():
            if key in step:
                _number(f"steps[{i}].{key}", step[key], *_LIMITS[name], integer=True)
                # They describe the state they come with: without it they would do nothing.
                allowed = _STATE_KEYS.get(str(step.get("state")), ())
                if key not in allowed:
                    raise CliError(f"remote script: steps[{i}].{key} goes with " +
                                   " or ".join(f'"state": "{s}"' for s, keys in _STATE_KEYS.items() if key in keys) +
                                   f' (to change only the field: "set": {{"{name}": ...}})')
        values = step.get("set", {})
        if not isinstance(values, dict):
            raise CliError(f"remote script: steps[{i}].set must be a JSON object")
        for name, value in values.items():
            if name not in _LIMITS:
                raise CliError(f"remote script: steps[{i}].set: {name[:30]!r} is not a VRPI field")
            _number(f"steps[{i}].set.{name}", value, *_LIMITS[name], integer=True)
    for i, raw in enumerate(_list("commands", script.get("commands", []))):
        cmd = _object(f"commands[{i}]", raw, "command")
        _number(f"commands[{i}].at", cmd.get("at"), 0, _MAX_S)
        if "id" in cmd and cmd["id"] is not None:
            _number(f"commands[{i}].id", cmd["id"], 0, 0xFFFF, integer=True)
        data = cmd.get("data", "")
        if not isinstance(data, str):
            raise CliError(f"remote script: commands[{i}].data must be a string")
        # Machine-specific bytes (the crane's are binary), one per character: it was cut to the
        # field, and characters beyond ASCII sent as "?", without a word.
        if len(data) > C.COMMAND_DATA_LEN or any(ord(ch) > 0xFF for ch in data):
            raise CliError(f"remote script: commands[{i}].data {data[:40]!r}: at most {C.COMMAND_DATA_LEN} "
                           "characters, each one byte (U+0000 to U+00FF)")


def armed_fields(ru: int = DEFAULT_RU, battery: int = 90, rssi: int = 80, unarmed_rus: int = 0) -> dict[str, int]:
    return {"bu_state": C.BuState.ARMED, "vlaps": 1, "unarmed_rus": unarmed_rus,
            "eg_link": C.LinkStatus.OPERATIONAL, "ec_link": C.LinkStatus.OPERATIONAL,
            "c_link": C.LinkStatus.OPERATIONAL, "armed_ru": ru, "ru_state": C.RuState.ENABLED,
            "ru_battery": battery, "ru_rssi": rssi, "ru_cable": C.RuCable.WIRELESS,
            "ru_docked": C.RuDocked.NOT_DOCKED, "ru_disabled": C.RuDisabled.ENABLED}


def disarmed_fields(unarmed_rus: int = 0) -> dict[str, int]:
    """No RU data (section 4.1: all RU fields 0, also those an armed step before set); C-Link
    passive when no remote talks to the BU."""
    return {"bu_state": C.BuState.DISARMED, "vlaps": 1, "unarmed_rus": unarmed_rus,
            "eg_link": C.LinkStatus.OPERATIONAL, "ec_link": C.LinkStatus.OPERATIONAL,
            "c_link": C.LinkStatus.OPERATIONAL if unarmed_rus else C.LinkStatus.PASSIVE, "armed_ru": 0,
            **dict.fromkeys(_RU_FIELDS, 0)}


def rebooted_values(values: list[Any], operative: bool) -> list[Any]:
    """What a base unit back from a reboot reports instead of the script's `values`: "Initial, not
    fully operative yet" (TS-0006 4.1.1, no RU data), then, once `operative`, "Disarmed" with the
    RU that was armed among the unarmed ones (a reboot loses the arming: the operator arms it again)."""
    if not operative:
        return _values({**disarmed_fields(), "bu_state": C.BuState.INITIAL})
    return _values(disarmed_fields(min(values[_UNARMED] + (1 if values[_ARMED_RU] else 0), _UNARMED_MAX)))


@dataclass
class _Step:
    at: int
    fields: dict[str, int]
    motion: Optional[bool] = None
    battery: Optional[int] = None    # the level the battery drains from, from this step on
    battery_set: bool = False        # this step sets the battery (arming: the RU's own; None: no drain)


@dataclass
class Remote:
    """The RU and operator script. `fields(t)` gives the VRPI payload fields at time t (µs)."""

    steps: list[_Step] = field(default_factory=list)
    commands: list[tuple[int, bytes, Optional[int]]] = field(default_factory=list)   # (µs, data, ID)
    command_every: int = 0
    command_until: int = 0      # no periodic commands from then on (0: no end)

    @classmethod
    def from_script(cls, script: Mapping[str, Any]) -> "Remote":
        """The remote of a script (module docstring); CliError (one line) for anything it does not allow."""
        check_script(script)
        steps = []
        for raw in script.get("steps", []):
            values: dict[str, int] = {}
            state = raw.get("state")
            if state == "armed":
                values.update(armed_fields(int(raw.get("ru", DEFAULT_RU)), int(raw.get("battery", 90)),
                                           int(raw.get("rssi", 80)), int(raw.get("unarmed_rus", 0))))
            elif state == "disarmed":
                values.update(disarmed_fields(int(raw.get("unarmed_rus", 0))))
            elif state is not None:
                raise CliError(f"remote script: unknown state {state!r} (armed or disarmed)")
            values.update({k: int(v) for k, v in raw.get("set", {}).items()})
            # Arming is another RU's battery: it drains from its `battery` or not at all (it kept
            # draining the previous RU's); a level `set` stays as set.
            given = raw.get("battery")
            steps.append(_Step(seconds(float(raw.get("at", 0))), values, raw.get("motion"),
                               None if given is None else int(given),
                               state == "armed" or "ru_battery" in raw.get("set", {})))
        commands = [(seconds(float(c["at"])), str(c.get("data", "CMD")).encode("latin-1"),
                     None if c.get("id") is None else int(c["id"]))
                    for c in script.get("commands", [])]
        return cls(sorted(steps, key=lambda s: s.at), sorted(commands, key=lambda c: c[0]),
                   seconds(float(script.get("command_every", 0))),
                   seconds(float(script.get("command_until", 0))))

    @classmethod
    def load(cls, path: str) -> "Remote":
        try:
            script = loads(read_at_most(path, _MAX_SCRIPT))
        except OSError as exc:
            raise CliError(f"cannot read remote script {path}: {exc.strerror}") from None
        except ValueError as exc:
            raise CliError(f"cannot read remote script {path}: not JSON: {str(exc)[:120]}") from None
        try:
            return cls.from_script(script)
        except CliError as exc:
            raise CliError(f"{path}: {exc}") from None

    @classmethod
    def simple(cls, armed: bool = True, unarmed_rus: int = 0, motion: bool = True,
               command_every: float = 0.0, ru: int = DEFAULT_RU, command_until: float = 0.0) -> "Remote":
        state = {"at": 0, "state": "armed" if armed else "disarmed", "unarmed_rus": unarmed_rus, "motion": motion,
                 **({"ru": ru} if armed else {})}
        return cls.from_script({"steps": [state], "command_every": command_every, "command_until": command_until})

    def __post_init__(self) -> None:
        # The VRPI values of each step, cumulated, in payload order: one list copy per VRPI.
        current, motion, battery_at = disarmed_fields(), False, 0
        battery: Optional[int] = None
        self._ats = [-1]
        self._states = [(_values(current), motion, battery, battery_at)]
        for step in self.steps:
            current.update(step.fields)
            motion = motion if step.motion is None else step.motion
            if step.battery_set:
                battery, battery_at = step.battery, step.at
            self._ats.append(step.at)
            self._states.append((_values(current), motion, battery, battery_at))

    def values(self, t: int) -> list[Any]:
        """VRPI payload values at time t (µs since start), in the order of the payload layout."""
        base, motion, battery, battery_at = self._states[bisect.bisect_right(self._ats, t) - 1]
        values = base.copy()
        if values[_ARMED_RU]:
            if battery is not None:
                values[_BATTERY] = max(0, battery - (t - battery_at) // _BATTERY_DRAIN_US)
            if motion and values[_RU_STATE] == _ENABLED:
                _move(t, values)
        return values

    def fields(self, t: int) -> dict[str, Any]:
        """VRPI payload fields at time t (µs since start) by canonical name."""
        return dict(zip(VRPI_NAMES, self.values(t)))


def _values(fields: Mapping[str, Any]) -> list[Any]:
    return [fields.get(name, default) for name, default in zip(VRPI_NAMES, _VRPI_DEFAULTS)]


def _sweep(phase: int, quarter: int, limit: int = C.JOYSTICK_LIMIT) -> int:
    """A joystick sweeping 0 up to the limit, down to minus the limit and back, over 4 quarters."""
    if phase < quarter:
        return limit * phase // quarter
    if phase < 3 * quarter:
        return limit - limit * (phase - quarter) // quarter
    return limit * (phase - 3 * quarter) // quarter - limit


def _move(t: int, values: list[Any]) -> None:
    # After 18 minutes t no longer fits one 30-bit digit: reduce it once, then work on small numbers.
    cycle = t % _SWEEP_CYCLE_US
    for index, period, quarter, known in _SWEEPS:
        phase = cycle % period
        try:
            values[index] = known[phase]
        except KeyError:
            values[index] = value = _sweep(phase, quarter)
            if len(known) < _KNOWN_PHASES:
                known[phase] = value
    steps = t // _STEP_US
    values[_PUSHBUTTON] = (steps // 300) % 2                     # every 3 s
    values[_TOGGLE] = (steps // 200) % 3 - 1                     # 3 positions, every 2 s
    values[_POTENTIOMETER] = steps % _SWITCH_STEPS               # a sweep
    values[_ENCODER] = (steps // 25) & 0xFF                      # every 250 ms
    values[_ENCODER_SWITCH] = int((steps // 500) % 4 == 0)       # 5 s of every 20 s
