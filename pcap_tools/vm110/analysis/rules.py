"""`--fail-on` rules: comma-separated `NAME OP NUMBER` (OP one of > >= < <= == !=), checked
against a report's `totals`; `lost>0,watchdog>0` fails when anything was lost or a watchdog
would have tripped. A bare NAME means NAME>0."""
from __future__ import annotations

import operator
import re
from typing import Callable

from ..errors import CliError

OPS: dict[str, Callable[[float, float], bool]] = {
    ">=": operator.ge, "<=": operator.le, "==": operator.eq, "!=": operator.ne,
    ">": operator.gt, "<": operator.lt,
}
# (ASCII: \d would take other scripts' digits too)
_RULE = re.compile(r"^\s*([A-Za-z_0-9]+)\s*(?:(>=|<=|==|!=|>|<)\s*(-?\d+(?:\.\d+)?))?\s*$", re.ASCII)
Rule = tuple[str, str, float]


def parse(text: str, names: tuple) -> list[Rule]:
    """Rules from the option text; CliError names the first bad one and the valid names."""
    rules = []
    for part in text.split(","):
        match = _RULE.match(part)
        if not match:
            raise CliError(f"bad --fail-on rule {part.strip()!r}: expected NAME OP NUMBER, e.g. lost>0")
        name, op, number = match.group(1), match.group(2) or ">", float(match.group(3) or 0)
        if name not in names:
            hint = f" (names are lower case: {name.lower()!r})" if name.lower() in names else ""
            raise CliError(f"unknown --fail-on name {name!r}{hint}; choose from {', '.join(names)}")
        rules.append((name, op, number))
    return rules


def _number(value: float) -> str:
    """A total or a rule's number in full (`:g` kept 6 digits: 1234567 read 1.23457e+06)."""
    return f"{value:.15g}"


def violations(rules: list[Rule], totals: dict) -> list[str]:
    """Each violated rule, as `name=value (rule name OP number)`."""
    out = []
    for name, op, number in rules:
        value = totals[name]
        if OPS[op](value, number):
            out.append(f"{name}={_number(value)} (rule {name}{op}{_number(number)})")
    return out
