"""A capture's packets as tshark dissects them, through pyshark, without two flaws of pyshark 0.6
in how it ends tshark. Imported only by the tshark engine (and the tests): pyshark is slow to import.

- At the end of tshark's output pyshark kills tshark at once if asyncio has not yet seen it exit.
  `Popen.kill` polls first and so reaps an exited tshark behind asyncio's child watcher, which
  then reports exit 255 ("Unknown child process pid ...") and pyshark a crash: a clean read lost,
  now and then, on a loaded machine. Here tshark is given time to exit on its own.
- pyshark leaves SIGCHLD routed to its event loop after the capture, and raises a crash again from
  `__del__` in whatever code runs when the capture is collected. Both are undone here.
"""
from __future__ import annotations

import asyncio
import contextlib
import os
import signal
from typing import Iterator, Optional, Sequence

import pyshark
from pyshark.capture.capture import TSharkCrashException

EXIT_GRACE_S = 5.0     # tshark has closed its output: how long it may take to exit before it is killed


class TsharkStopped(Exception):
    """tshark ended with an error after the packets yielded so far; the message is its last error line."""


class _Capture(pyshark.FileCapture):
    async def _cleanup_subprocess(self, process) -> None:
        if self._eof_reached and process.returncode is None:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(process.wait(), EXIT_GRACE_S)
        await super()._cleanup_subprocess(process)


def packets(path: str, parameters: Sequence[str], tshark_path: Optional[str] = None) -> Iterator:
    """pyshark's packets of the capture at `path`, tshark run with `parameters`; TsharkStopped
    after the last packet when tshark failed."""
    cap = _Capture(path, keep_packets=False, tshark_path=tshark_path, custom_parameters=list(parameters))
    stopped = None
    try:
        yield from cap
    except TSharkCrashException:
        stopped = cap._last_error_line or "tshark stopped"
    finally:
        try:
            cap.close()
        except TSharkCrashException:
            stopped = cap._last_error_line or "tshark stopped"
            cap._running_processes.clear()      # nothing left for __del__ to raise again
        finally:
            if os.name == "posix":
                cap.eventloop.remove_signal_handler(signal.SIGCHLD)
    if stopped is not None:
        raise TsharkStopped(stopped)
