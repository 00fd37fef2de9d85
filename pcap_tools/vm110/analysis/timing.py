"""Intervals, percentiles, RFC 3550-style jitter and watchdog violations of a periodic stream."""
from __future__ import annotations

import math
from itertools import islice
from operator import sub
from typing import Optional, Sequence

PERCENTILES = (("p50", 50.0), ("p95", 95.0), ("p99", 99.0), ("p999", 99.9))
MS = 1000.0


def intervals_ms(times: Sequence[float]) -> list[float]:
    """Differences of consecutive times, in milliseconds."""
    return [d * MS for d in map(sub, islice(times, 1, None), times)]


def percentile(ordered: Sequence[float], q: float) -> Optional[float]:
    """The q-th percentile of sorted values, linear between closest ranks (numpy's default)."""
    if not ordered:
        return None
    pos = (len(ordered) - 1) * q / 100.0
    low = math.floor(pos)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (pos - low)


def summary(values: Sequence[float], keys: tuple = ("min", "mean", *(k for k, _ in PERCENTILES), "max")) -> dict:
    """min, mean, percentiles and max of values (None each when there are none)."""
    ordered = sorted(values)
    out: dict = {}
    for key in keys:
        if not ordered:
            out[key] = None
        elif key == "min":
            out[key] = ordered[0]
        elif key == "max":
            out[key] = ordered[-1]
        elif key == "mean":
            out[key] = math.fsum(ordered) / len(ordered)
        else:
            out[key] = percentile(ordered, dict(PERCENTILES)[key])
    return out


def jitter_ms(times: Sequence[float], period_ms: float) -> dict:
    """Interarrival jitter J += (|D| - J)/16 with D = (R_j - R_i) - k*T, k = max(1, round(dR/T)).

    round() is half-up. Returns the final J, the mean of J over every update and its maximum.
    """
    j = total = peak = 0.0
    n = 0
    t = period_ms
    for delta in intervals_ms(times):
        k = math.floor(delta / t + 0.5)
        if k < 1:
            k = 1
        j += (abs(delta - k * t) - j) / 16.0
        total += j
        n += 1
        if j > peak:
            peak = j
    if not n:
        return {"final": None, "mean": None, "max": None}
    return {"final": j, "mean": total / n, "max": peak}


def violations(times: Sequence[float], gaps_ms: Sequence[float], limit_ms: float) -> list[dict]:
    """Intervals above the limit: start (time of the packet before the gap) and gap."""
    return [{"start": times[i], "gap_ms": g} for i, g in enumerate(gaps_ms) if g > limit_ms]


def outside(gaps_ms: Sequence[float], low: float, high: float) -> int:
    return sum(1 for g in gaps_ms if g < low or g > high)
