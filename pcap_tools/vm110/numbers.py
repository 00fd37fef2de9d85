"""One validated number type for command-line options: finite, in a documented range, with a unit.

`number(...)` returns an argparse `type=` callable. NaN, infinities and values outside the range
are refused with a message that gives the range and the unit; argparse adds the option's name, and
the command ends with exit code 2. `port(...)` is a UDP port, `fields(...)` several numbers joined
by ":" (START:END, AT[:PORT]), each through its own number type.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Optional, Union

Number = Union[int, float]


@dataclass(frozen=True)
class NumberType:
    """Parses one option value; `range_text` is what the help and the error messages show."""

    low: Number
    high: Number
    unit: str = ""
    integer: bool = False
    allow_zero: bool = True
    least: Number = 0             # the smallest value above 0 (an interval finer than a clock is 0)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low <= self.high):
            raise ValueError(f"bad range {self.low}..{self.high}")

    @property
    def range_text(self) -> str:
        """E.g. "1 to 1000", "above 0 and at most 3600 s", "-10 to 10 mm, not 0"."""
        unit = f" {self.unit}" if self.unit else ""
        if self.low == 0 and self.least:
            return f"0 or {_show(self.least)} to {_show(self.high)}{unit}"
        if self.low == 0 and not self.allow_zero:
            return f"above 0 and at most {_show(self.high)}{unit}"
        excluded = ", not 0" if self.low < 0 < self.high and not self.allow_zero else ""
        return f"{_show(self.low)} to {_show(self.high)}{unit}{excluded}"

    def __call__(self, text: str) -> Number:
        value = self._parse(text)
        inside = math.isfinite(value) and self.low <= value <= self.high
        if not inside or (value == 0 and not self.allow_zero) or 0 < value < self.least:
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is out of range: must be {self.range_text}")
        return value

    def _parse(self, text: str) -> Number:
        try:
            if not text.isascii():    # int() and float() also read other scripts' digits
                raise ValueError(text)
            if not self.integer:
                return float(text)
            try:
                return int(text)
            except ValueError:
                return int(text, 0)    # 0x1f and the like; plain int() first keeps "010" decimal
        except ValueError:    # also integers of more digits than Python converts
            kind = "an integer" if self.integer else "a number"
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is not {kind}: must be {self.range_text}") from None


def number(low: Number, high: Number, unit: str = "", integer: bool = False,
           allow_zero: bool = True, least: Number = 0) -> NumberType:
    """An argparse `type=` for a value in [low, high] (both included; 0 left out when not
    `allow_zero`; with `least`, nothing between 0 and it), in `unit`; integers only when `integer`."""
    return NumberType(low, high, unit, integer, allow_zero, least)


def port(room_above: int = 0) -> NumberType:
    """A UDP port (1-65535), leaving `room_above` ports above it (an input port whose output port
    is the input port + 2)."""
    return NumberType(1, 0xFFFF - room_above, integer=True)


@dataclass(frozen=True)
class FieldsType:
    """Parses "A:B[:C]": each field through its own NumberType; the first `required` must be given,
    and with `increasing` each given field is above the one before (END after START)."""

    names: tuple[str, ...]
    types: tuple[NumberType, ...]
    required: int
    increasing: bool = False

    @property
    def form(self) -> str:
        """E.g. "START:END", "AT[:NEW_PORT]"."""
        given, optional = self.names[:self.required], self.names[self.required:]
        return ":".join(given) + "".join(f"[:{name}]" for name in optional)

    @property
    def range_text(self) -> str:
        """E.g. "START:END, each 0 to 60 s, END after START", "AT[:PORT]: AT 0 to 60 s, PORT 1 to 65535"."""
        if len(set(self.types)) == 1:
            parts = f", each {self.types[0].range_text}"
        else:
            parts = ": " + ", ".join(f"{name} {kind.range_text}" for name, kind in zip(self.names, self.types))
        order = "".join(f", {b} after {a}" for a, b in zip(self.names, self.names[1:])) if self.increasing else ""
        return f"{self.form}{parts}{order}"

    def __call__(self, text: str) -> tuple[Optional[Number], ...]:
        pieces = text.split(":")
        if not self.required <= len(pieces) <= len(self.names):
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is not {self.form}: must be {self.range_text}")
        values = []
        for name, kind, piece in zip(self.names, self.types, pieces):
            try:
                values.append(kind(piece))
            except argparse.ArgumentTypeError as exc:
                raise argparse.ArgumentTypeError(f"{name} {exc}") from None
        if self.increasing:
            for i in range(1, len(values)):
                if values[i] <= values[i - 1]:
                    raise argparse.ArgumentTypeError(
                        f"{text[:40]!r}: {self.names[i]} must be after {self.names[i - 1]}")
        return tuple(values) + (None,) * (len(self.names) - len(values))


def fields(names: tuple[str, ...], types: tuple[NumberType, ...], required: Optional[int] = None,
           increasing: bool = False) -> FieldsType:
    """An argparse `type=` for numbers joined by ":" (all of them required unless `required` says
    how many); the value is a tuple with None for fields not given."""
    if len(names) != len(types):
        raise ValueError("one type per field")
    return FieldsType(names, types, len(names) if required is None else required, increasing)


def span(bound: NumberType) -> FieldsType:
    """START:END, both within `bound`, END after START."""
    return fields(("START", "END"), (bound, bound), increasing=True)


def _show(value: Number) -> str:
    """Whole numbers in full (2592000, not 2.592e+06)."""
    return str(int(value)) if value == int(value) else f"{value:g}"
