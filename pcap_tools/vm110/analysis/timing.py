"""Intervals, percentiles, RFC 3550-style jitter and watchdog violations of a periodic stream.

Times come in as numpy float64 arrays of seconds; results go out as plain floats in ms.
"""
from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np

# A column of numbers: a list or a numpy array (an ndarray is no typing.Sequence).
FloatSeq = Union[Sequence[float], np.ndarray]
IntSeq = Union[Sequence[int], np.ndarray]

PERCENTILES = (("p50", 50.0), ("p95", 95.0), ("p99", 99.0), ("p999", 99.9))
SUMMARY_KEYS = ("min", "mean", *(k for k, _ in PERCENTILES), "max")
MS = 1000.0
JITTER_GAIN = 1.0 / 16.0
_BLOCK = 256          # (16/15)**256 ~ 1.5e7: the block recurrence stays well inside float64
_CHUNK = _BLOCK * 256


def intervals_ms(times: FloatSeq) -> np.ndarray:
    """Differences of consecutive times, in milliseconds to the microsecond: an epoch time in a
    float64 carries about 0.24 us of noise, which would put an interval of exactly 200 ms above
    a 200 ms limit (the dissector rounds to the microsecond as well)."""
    return np.round(np.diff(np.asarray(times, dtype=np.float64)) * 1e6) / MS


def interval_ms(later: float, earlier: float) -> float:
    """One interval as `intervals_ms` gives it: in milliseconds to the microsecond."""
    return round((later - earlier) * 1e6) / MS


def edge_us(limit_ms: float) -> float:
    """An interval is shorter than `limit_ms`, taken to the microsecond (rounded half up, as the
    dissector rounds), exactly when its unrounded microseconds lie below this edge."""
    return round(limit_ms * 1000) - 0.5


def shorter(seconds: float, limit_ms: float) -> bool:
    """Whether an interval of `seconds` is shorter than `limit_ms`, to the microsecond: in floats
    copies exactly a 100 ms duplicate window apart fell inside it in analyze and outside it in the
    dissector (a trial). An infinite interval (never) is not shorter."""
    return seconds * 1e6 < edge_us(limit_ms)


def longer(seconds: float, limit_ms: float) -> bool:
    """Whether an interval of `seconds` is longer than `limit_ms`, to the microsecond."""
    return seconds * 1e6 >= edge_us(limit_ms) + 1.0


def percentile(ordered: FloatSeq, q: float) -> Optional[float]:
    """The q-th percentile of sorted values, linear between closest ranks (numpy's default)."""
    n = len(ordered)
    if not n:
        return None
    pos = (n - 1) * q / 100.0
    low = int(pos)
    high = min(low + 1, n - 1)
    return float(ordered[low] + (ordered[high] - ordered[low]) * (pos - low))


def summary(values: FloatSeq, keys: tuple = SUMMARY_KEYS) -> dict:
    """min, mean, percentiles and max of values (None each when there are none)."""
    return summary_sorted(np.sort(np.asarray(values, dtype=np.float64)), keys)


def summary_sorted(ordered: np.ndarray, keys: tuple = SUMMARY_KEYS) -> dict:
    """`summary` of values already sorted."""
    out: dict = {}
    pct = dict(PERCENTILES)
    for key in keys:
        if not len(ordered):
            out[key] = None
        elif key == "min":
            out[key] = float(ordered[0])
        elif key == "max":
            out[key] = float(ordered[-1])
        elif key == "mean":
            out[key] = float(np.mean(ordered))
        else:
            out[key] = percentile(ordered, pct[key])
    return out


def jitter_of_intervals(delta: np.ndarray, period_ms: float) -> np.ndarray:
    """J after each interval (ms): J += (|D| - J)/16, D = (R_j - R_i) - k*T, k = max(1,
    round(dR/T)), round half up. The recurrence J_i = a*J_(i-1) + x_i (a = 15/16, x = |D|/16) is
    evaluated a block at a time in closed form: J_i = a^(i+1) * (J_0 + cumsum(x_m / a^(m+1)))."""
    out = np.empty(len(delta))
    a = 1.0 - JITTER_GAIN
    powers = a ** np.arange(1, _BLOCK + 1)
    j = 0.0
    # A chunk of intervals at a time (whole blocks): the values are the same, the temporaries small.
    for chunk in range(0, len(out), _CHUNK):
        part = delta[chunk:chunk + _CHUNK]
        k = np.maximum(1.0, np.floor(part / period_ms + 0.5))
        x = np.abs(part - k * period_ms) * JITTER_GAIN
        for start in range(0, len(x), _BLOCK):
            block = x[start:start + _BLOCK]
            pw = powers[:len(block)]
            values = pw * (j + np.cumsum(block / pw))
            out[chunk + start:chunk + start + len(block)] = values
            j = float(values[-1])
    return out


def jitter_summary(delta: np.ndarray, period_ms: Optional[float]) -> dict:
    """Final, mean (over every update) and maximum jitter of the intervals `delta` (ms). A negative
    interval is a step back of the capture's clock (time_backwards), no variation of the period:
    it updates nothing."""
    forward = delta[delta >= 0] if len(delta) and delta.min() < 0 else delta
    series = jitter_of_intervals(forward, period_ms) if period_ms else np.empty(0)
    if not len(series):
        return {"final": None, "mean": None, "max": None}
    return {"final": float(series[-1]), "mean": float(series.mean()), "max": float(series.max())}
