"""Run tshark on a capture with the bundled Wireshark dissector (dissector/vm110.lua).

For people who have not installed the plugin: everything after the capture goes to tshark
unchanged, e.g. `vm110 dissect cap.pcap -V -Y "vm110.command_id == 17"`; `-` reads the capture
from standard input (`tcpdump -w - ... | vm110 dissect -`), and a named pipe is read as well
(`vm110 dissect <(tcpdump -w - ...)`). The exit status is tshark's; 2 when tshark or the
dissector cannot be used, or the capture is empty.
"""
from __future__ import annotations

import argparse
import array
import contextlib
import fcntl
import os
import select
import shutil
import stat
import subprocess
import termios
from pathlib import Path
from typing import IO, Iterator, Optional

from ..capture.spool import named
from ..errors import CliError
from ..fileio import open_input
from ..plugin import PLUGIN_ENV, ROOT_HINT, list_protocols, lua_errors, plugin_path, skips_lua_as_root


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="pcap or pcapng file, - for standard input")
    rest = parser.add_argument("tshark_args", nargs=argparse.REMAINDER, metavar="TSHARK_ARGS",
                               help="passed to tshark, e.g. -V, -T fields -e vm110.serial, -Y FILTER")
    rest.required = False   # (argparse marks a REMAINDER required: "required: capture, TSHARK_ARGS" misled)


def _check_loads(tshark: str, plugin: Path) -> None:
    """The dissector must register: else tshark's own word why (a Lua error), or the reason it
    gives none (Wireshark 4.4 and later skip Lua plugins as root), instead of decoding nothing."""
    loaded, done = list_protocols(tshark, plugin)
    if loaded:
        return
    errors = lua_errors(done.stderr)
    if errors:
        why = ": " + " ".join(errors)[:500]
    else:
        version = subprocess.run([tshark, "-v"], capture_output=True, text=True, check=False).stdout
        why = f" ({ROOT_HINT})" if skips_lua_as_root(version.split("\n")[0]) else ""
    raise CliError(f"tshark did not load the dissector {plugin}{why}")


def _empty(fd: int) -> bool:
    """Whether the file or pipe on `fd` ends before its first byte, without reading it (tshark reads
    it after): a regular file by its size; a pipe or socket once it holds data or its writer is gone
    (POLLIN either way: nothing to read then is its end); /dev/null. A terminal is tshark's to read."""
    st = os.fstat(fd)
    if stat.S_ISREG(st.st_mode):
        return st.st_size <= os.lseek(fd, 0, os.SEEK_CUR)
    if not (stat.S_ISFIFO(st.st_mode) or stat.S_ISSOCK(st.st_mode)):
        return stat.S_ISCHR(st.st_mode) and os.path.samestat(st, os.stat(os.devnull))
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    poller.poll()
    waiting = array.array("i", [0])
    fcntl.ioctl(fd, termios.FIONREAD, waiting)
    return waiting[0] == 0


def _check_readable(given: str) -> None:
    """CliError for a capture file tshark cannot open: missing, unreadable, a folder or a device.
    A named pipe is read (`<(tcpdump -w - ...)`: it was refused as unreadable)."""
    if given == "-":
        return
    try:
        mode = os.stat(given).st_mode
    except OSError:
        mode = 0
    if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode)) or not os.access(given, os.R_OK):
        raise CliError(f"cannot read {given}")


@contextlib.contextmanager
def _capture(given: str) -> Iterator[tuple[str, Optional[IO[bytes]]]]:
    """What tshark reads the capture `given` from: (its -r argument, its standard input); CliError
    when it is empty, which tshark passes over with exit status 0 as if it held a capture without
    packets (README, "Exit codes": exit 2). A named pipe is opened here, so that what is looked
    at is what tshark reads, and given to tshark as its standard input."""
    with contextlib.ExitStack() as stack:
        try:
            stream = None if given == "-" else stack.enter_context(open_input(given))
            empty = _empty(stream.fileno() if stream else 0)
        except OSError as exc:
            raise CliError(f"cannot read {named(given)}: {exc.strerror or exc}") from None
        if empty:
            raise CliError(f"{named(given)}: empty, not a capture")
        if stream is not None and os.path.isfile(given):
            yield given, None
        else:
            yield "-", stream


def run(args: argparse.Namespace) -> int:
    tshark = shutil.which("tshark")
    if tshark is None:
        raise CliError("tshark not found on the PATH: install Wireshark's tshark "
                       "(Debian/Ubuntu: apt-get install tshark)")
    plugin = plugin_path()
    if not plugin.is_file():
        raise CliError(f"the dissector is not at {plugin} (set {PLUGIN_ENV} to its path)")
    _check_readable(args.capture)
    extra = args.tshark_args[1:] if args.tshark_args[:1] == ["--"] else args.tshark_args
    with _capture(args.capture) as (source, stdin):
        _check_loads(tshark, plugin)
        return subprocess.call([tshark, "-X", f"lua_script:{plugin}", "-r", source, *extra], stdin=stdin)
