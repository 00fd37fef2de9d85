"""Capture analysis: engines read a capture into `Collected` and feed its legal packets to an
`Analysis` as they go; the report is built from both."""
from __future__ import annotations

from typing import Optional

from .. import constants as C
from .engine import FastEngine, Progress
from .report import Options, build


def analyze(path: str, engine: str = "fast", port: int = C.INPUT_PORT, crc: str = "auto",
            crc_order: str = "auto", options: Optional[Options] = None,
            progress: Optional[Progress] = None) -> dict:
    """The report (a JSON-ready dict) of one capture file."""
    opt = options or Options()
    if engine == "tshark":
        from .tshark_engine import TsharkEngine
        got = TsharkEngine(port, crc, crc_order).collect(path, opt)
    else:
        got = FastEngine(port, crc, crc_order, progress).collect(path, opt)
    return build(got)
