"""The JSON report: rounding that makes it stable across engines, and writing it."""
from __future__ import annotations

import math
from typing import IO, Any, Optional

import orjson

from ..fileio import atomic_writer

SECONDS_DECIMALS = 6   # times to the microsecond, the resolution of a capture's timestamps
MS_DECIMALS = 3        # durations in ms (keys ending in _ms, and everything under them) likewise


# commands.report rounds these itself
PRE_ROUNDED = frozenset({"list", "acks_without_command_list", "duplicate_acks_list"})


def round_s(value: Optional[float]) -> Optional[float]:
    return None if value is None else round(value, SECONDS_DECIMALS)


def round_ms(value: Optional[float]) -> Optional[float]:
    return None if value is None else round(value, MS_DECIMALS)


def normalise(value: Any, ms: bool = False) -> Any:
    """Round every float to the microsecond: an absolute time in a float carries about 0.1 us of
    noise, which differs between engines. Dicts and lists are changed in place (a report of a
    long capture is large); tuples become lists."""
    kind = type(value)
    if kind is float:
        if not math.isfinite(value):
            return None                 # only damaged timestamps get here; JSON has no inf/nan
        return round(value, MS_DECIMALS if ms else SECONDS_DECIMALS)
    if kind is dict:
        for k, v in value.items():
            if type(v) is not int and v is not None and type(v) is not str and k not in PRE_ROUNDED:
                value[k] = normalise(v, ms or k.endswith("_ms"))
        return value
    if kind is list or kind is tuple:
        if all(type(v) is int for v in value):
            return value if kind is list else list(value)   # frame lists: nothing to round
        if kind is tuple:
            value = list(value)
        for i, v in enumerate(value):
            value[i] = normalise(v, ms)
        return value
    return value


def encode(document: dict) -> bytes:
    """The report's JSON text. orjson: json's own encoder indents in Python, and took 4.6 s of CPU
    for the 52 MB report of 20,000 senders (orjson: 0.12 s). As json writes them: keys that are
    not strings (None, a number) as strings, numpy's numbers as numbers."""
    return orjson.dumps(document, option=orjson.OPT_INDENT_2 | orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY
                        | orjson.OPT_APPEND_NEWLINE)


def dump(out: IO[str], document: dict) -> None:
    out.write(encode(document).decode())


def write(path: str, document: dict) -> None:
    """The JSON file, written atomically (a failure leaves what was there)."""
    with atomic_writer(path, binary=True) as out:
        out.write(encode(document))
