"""The JSON report: rounding that makes it stable across engines, and writing it."""
from __future__ import annotations

import json
from typing import Any

from ..errors import CliError

SECONDS_DECIMALS = 6   # times to the microsecond, the resolution of a capture's timestamps
MS_DECIMALS = 3        # durations in ms (keys ending in _ms, and everything under them) likewise


def normalise(value: Any, ms: bool = False) -> Any:
    """Round every float to the microsecond: an absolute time in a float carries about 0.1 us of
    noise, which differs between engines. Tuples become lists."""
    if isinstance(value, float):
        return round(value, MS_DECIMALS if ms else SECONDS_DECIMALS)
    if isinstance(value, dict):
        return {k: normalise(v, ms or k.endswith("_ms")) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [normalise(v, ms) for v in value]
    return value


def dumps(document: dict) -> str:
    return json.dumps(document, indent=1, allow_nan=False) + "\n"


def write(path: str, document: dict) -> None:
    try:
        with open(path, "w", encoding="utf-8") as out:
            out.write(dumps(document))
    except OSError as exc:
        raise CliError(f"cannot write {path}: {exc.strerror}") from None
