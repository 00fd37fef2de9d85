"""Run tshark on a capture with the bundled Wireshark dissector (dissector/vm110.lua).

For people who have not installed the plugin: everything after the capture goes to tshark
unchanged, e.g. `vm110 dissect cap.pcap -V -Y "vm110.command_id == 17"`; `-` reads the capture
from standard input (`tcpdump -w - ... | vm110 dissect -`). The exit status is tshark's; 2 when
tshark or the dissector cannot be used.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
from pathlib import Path

from ..errors import CliError
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


def run(args: argparse.Namespace) -> int:
    tshark = shutil.which("tshark")
    if tshark is None:
        raise CliError("tshark not found on the PATH: install Wireshark's tshark "
                       "(Debian/Ubuntu: apt-get install tshark)")
    plugin = plugin_path()
    if not plugin.is_file():
        raise CliError(f"the dissector is not at {plugin} (set {PLUGIN_ENV} to its path)")
    if args.capture != "-" and (not os.access(args.capture, os.R_OK) or not os.path.isfile(args.capture)):
        raise CliError(f"cannot read {args.capture}")
    _check_loads(tshark, plugin)
    extra = args.tshark_args[1:] if args.tshark_args[:1] == ["--"] else args.tshark_args
    return subprocess.call([tshark, "-X", f"lua_script:{plugin}", "-r", args.capture, *extra])
