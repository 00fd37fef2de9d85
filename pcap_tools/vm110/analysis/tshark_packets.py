"""A capture's packets as tshark dissects them, through pyshark, without four flaws of pyshark 0.6
(two in how it ends tshark). Imported only by the tshark engine (and the tests): pyshark is slow to import.

- At the end of tshark's output pyshark kills tshark at once if asyncio has not yet seen it exit.
  `Popen.kill` polls first and so reaps an exited tshark behind asyncio's child watcher, which
  then reports exit 255 ("Unknown child process pid ...") and pyshark a crash: a clean read lost,
  now and then, on a loaded machine. Here tshark is given time to exit on its own.
- pyshark takes every packet's first two protocols for its general information and frame, and
  fails on a record that has one (an IndexError that ended the analysis): such a record is one
  without layers here; and on a packet with a comment, whose comments come second (an
  AttributeError that ended it): its frame is found by name.
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
from pyshark.tshark.output_parser import tshark_xml

EXIT_GRACE_S = 5.0     # tshark has closed its output: how long it may take to exit before it is killed


class TsharkStopped(Exception):
    """tshark ended with an error after the packets yielded so far; the message is its last error line."""


class _NoFields:
    @staticmethod
    def get_field(name: str) -> None:
        return None


class _Record:
    """A record that is no packet and that tshark gives no frame tree (4.0: a system-call event
    block is a lone `syscall` protocol): no layers, no fields."""
    layers: tuple = ()
    frame_info = _NoFields()


class _Parser(tshark_xml.TsharkXmlParser):
    def _parse_single_packet(self, packet):
        try:
            pkt = super()._parse_single_packet(packet)
        except IndexError:      # pyshark takes every packet's first two protocols for geninfo and frame
            return _Record()
        if pkt.frame_info.layer_name != "frame":      # (4.0: a packet's comments come before its frame)
            frame = next((layer for layer in pkt.layers if layer.layer_name == "frame"), None)
            if frame is not None:
                pkt.layers.remove(frame)
                pkt.frame_info = frame
        return pkt


class _Capture(pyshark.FileCapture):
    def _setup_tshark_output_parser(self):
        return _Parser(parse_summaries=self._only_summaries)

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
