"""The Lua dissector as tshark loads it: which file ($VM110_DISSECTOR, else the one this installation
ships), and whether tshark registered its protocol."""
from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

from . import resources

PLUGIN_ENV = "VM110_DISSECTOR"
ROOT_HINT = ("Wireshark 4.4 and later load no Lua plugin when run as root (unless the global init.lua sets "
             "run_user_scripts_when_superuser = true): run it as a normal user")


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


def skips_lua_as_root(version: str) -> bool:
    """Whether this tshark (`tshark -v`'s first line) runs as root and is 4.4 or later."""
    found = re.search(r"\(Wireshark\) (\d+)\.(\d+)", version)
    newer = found is not None and (int(found[1]), int(found[2])) >= (4, 4)
    return newer and hasattr(os, "geteuid") and os.geteuid() == 0


def lua_errors(stderr: str) -> list[str]:
    """tshark's Lua messages on stderr (a message may go on over several lines), without the
    warning about running as root."""
    return [line.rstrip() for line in stderr.splitlines()
            if line.strip() and not line.startswith("Running as user")]
