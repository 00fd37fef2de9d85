"""The Lua dissector as tshark loads it: which file ($VM110_DISSECTOR, else the one this installation
ships), and whether tshark registered its protocol."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

from . import resources

PLUGIN_ENV = "VM110_DISSECTOR"


def plugin_path() -> Path:
    """$VM110_DISSECTOR, else dissector/vm110.lua as this installation ships it (the wheel's
    package data, or beside the package's source in an editable install: vm110.resources)."""
    env = os.environ.get(PLUGIN_ENV)
    return Path(env) if env else resources.plugin()


def registers_vm110(line: str) -> bool:
    """Whether a line of `tshark -G protocols` is vm110's (name, short name, filter name, then
    flags on 4.6)."""
    return line.split("\t")[2:3] == ["vm110"]


def list_protocols(tshark: str, plugin: Path) -> tuple[bool, subprocess.CompletedProcess]:
    """`tshark -G protocols` with the plugin: whether it registered vm110, and the run itself."""
    done = subprocess.run([tshark, "-G", "protocols", "-X", f"lua_script:{plugin}"],
                          capture_output=True, text=True, check=False)
    return any(registers_vm110(line) for line in done.stdout.splitlines()), done
