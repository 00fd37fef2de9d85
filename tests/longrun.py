"""Tests kept out of `make test` for time: `make test-long` (VM110_LONG_TESTS=1, -m slow) runs them.

`make test` must stay within 15 minutes on 2 cores. What it leaves to the long run: runs longer
than the short ones beside them, and some tests repeated on 4.4, where `make test` holds them to 4.0
and 4.6 (4.4 runs the Lua 5.4 of 4.6): Wireshark's reading of damaged captures, the dissector's fast
path on the bundled captures, the GUI's profile and glossary. The dissector's vectors, goldens,
stream analysis, statistics, registration and junk tests run on all three in `make test`."""
from __future__ import annotations

import os
from typing import Any

import pytest

LONG_RUN = (pytest.mark.slow, pytest.mark.skipif(not os.environ.get("VM110_LONG_TESTS"),
                                                  reason="long run: make test-long"))
LONG_VERSION = "4.4"        # the version whose repeats of some tests only the long run makes


def long_only(*values: Any, id: str | None = None) -> Any:
    """A parameter (set) that only `make test-long` runs."""
    return pytest.param(*values, marks=LONG_RUN, id=id)


def on_runner(runner: Any, *values: Any, id: str, long: bool = True) -> Any:
    """`runner` (a tshark_runner.Tshark) and `values` as a parameter set: on LONG_VERSION, when
    `long`, one that only `make test-long` runs."""
    if long and runner.version == LONG_VERSION:
        return long_only(runner, *values, id=id)
    return pytest.param(runner, *values, id=id)
