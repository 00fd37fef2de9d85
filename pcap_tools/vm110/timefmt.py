"""Times as the command line shows them: ISO 8601 UTC with µs, and seconds from a start.

Capture timestamps come from the file (hostile): a value no calendar date can hold (past year
9999, NaN) is shown as its raw seconds rather than raising.
"""
from __future__ import annotations

import datetime
import math

_EPOCH = datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)


def utc_iso(seconds: float) -> str:
    """E.g. 2025-06-15T15:06:40.125000Z; the raw number (e.g. "1e+300 s") when it is no date."""
    if not math.isfinite(seconds):
        return f"{seconds} s"
    micro = round(seconds * 1_000_000)      # whole µs first: no float drift in the fraction
    try:
        when = _EPOCH + datetime.timedelta(microseconds=micro)
    except OverflowError:
        return f"{seconds!r} s"
    return when.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def datetime_iso(when: datetime.datetime) -> str:
    """A calendar time (a naive one is UTC) in the form of utc_iso: 2025-06-15T15:06:40.125000Z."""
    if when.tzinfo is not None:
        when = when.astimezone(datetime.timezone.utc).replace(tzinfo=None)
    return when.isoformat(timespec="microseconds") + "Z"


def since(seconds: float | None, start: float) -> str:
    """Seconds from `start`, e.g. "+12.345678"; "-" for an unknown (damaged) time."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    return f"{seconds - start:+.6f}"


def stamp(seconds: float | None, start: float) -> str:
    """Both forms: "2025-06-15T15:06:40.125000Z (+0.125000 s)"; "-" for an unknown time."""
    if seconds is None:
        return "-"
    return f"{utc_iso(seconds)} ({since(seconds, start)} s)"
