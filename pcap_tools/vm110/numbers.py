"""One validated number type for command-line options: finite, in a documented range, with a unit.

`number(...)` returns an argparse `type=` callable. NaN, infinities and values outside the range
are refused with a message that gives the range and the unit; argparse adds the option's name, and
the command ends with exit code 2.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Union

Number = Union[int, float]


@dataclass(frozen=True)
class NumberType:
    """Parses one option value; `range_text` is what the help and the error messages show."""

    low: Number
    high: Number
    unit: str = ""
    integer: bool = False
    allow_zero: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low <= self.high):
            raise ValueError(f"bad range {self.low}..{self.high}")

    @property
    def range_text(self) -> str:
        """E.g. "1 to 1000", "above 0 and at most 3600 s", "-10 to 10 mm, not 0"."""
        unit = f" {self.unit}" if self.unit else ""
        if self.low == 0 and not self.allow_zero:
            return f"above 0 and at most {_show(self.high)}{unit}"
        excluded = ", not 0" if self.low < 0 < self.high and not self.allow_zero else ""
        return f"{_show(self.low)} to {_show(self.high)}{unit}{excluded}"

    def __call__(self, text: str) -> Number:
        value = self._parse(text)
        inside = math.isfinite(value) and self.low <= value <= self.high
        if not inside or (value == 0 and not self.allow_zero):
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is out of range: must be {self.range_text}")
        return value

    def _parse(self, text: str) -> Number:
        try:
            return int(text) if self.integer else float(text)
        except ValueError:    # also integers of more digits than Python converts
            kind = "an integer" if self.integer else "a number"
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is not {kind}: must be {self.range_text}") from None


def number(low: Number, high: Number, unit: str = "", integer: bool = False,
           allow_zero: bool = True) -> NumberType:
    """An argparse `type=` for a value in [low, high] (both included; 0 left out when not
    `allow_zero`), in `unit`; integers only when `integer`."""
    return NumberType(low, high, unit, integer, allow_zero)


def _show(value: Number) -> str:
    """Whole numbers in full (2592000, not 2.592e+06)."""
    return str(int(value)) if value == int(value) else f"{value:g}"
