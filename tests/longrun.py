"""Tests kept out of `make test` for time: `make test-long` (VM110_LONG_TESTS=1, -m slow) runs them.

`make test` must stay within 15 minutes on 2 cores. What it leaves to the long run: runs longer
than the short ones beside them, and some tests repeated on 4.4, where `make test` holds them to 4.0
and 4.6 (4.4 runs the Lua 5.4 of 4.6): the dissector's fast path and display filters, the GUI's
profile and glossary, the command-line fields of 4.0, the random packets against vm110.decode, the
report's filters. Some run on one version in `make test`: Wireshark's reading of damaged captures
(4.0; the three read them alike), the fast path on each bundled capture (two on 4.0, two on 4.6).
The dissector's vectors, goldens, stream analysis, statistics, registration and junk tests run on
all three in `make test`."""
from __future__ import annotations

import os
from typing import Any, Sequence

import pytest

LONG_RUN = (pytest.mark.slow, pytest.mark.skipif(not os.environ.get("VM110_LONG_TESTS"),
                                                  reason="long run: make test-long"))
SHORT_VERSIONS = ("4.0", "4.6")   # where `make test` runs what the long run repeats on 4.4 too


def long_only(*values: Any, id: str | None = None) -> Any:
    """A parameter (set) that only `make test-long` runs."""
    return pytest.param(*values, marks=LONG_RUN, id=id)


def on_runner(runner: Any, *values: Any, id: str, short: Sequence[str] = SHORT_VERSIONS) -> Any:
    """`runner` (a tshark_runner.Tshark) and `values` as a parameter set, which only `make
    test-long` runs unless the runner's version is one of `short`."""
    if runner.version not in short:
        return long_only(runner, *values, id=id)
    return pytest.param(runner, *values, id=id)


def runner_params(runners: Sequence[Any]) -> list[Any]:
    """Every runner as a parameter named after it: on SHORT_VERSIONS in `make test`, the others in
    the long run."""
    return [on_runner(r, id=r.name) for r in runners]
