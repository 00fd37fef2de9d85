"""Core files of a crashed controller: where the kernel put one, moving it next to the finding, and
a backtrace from it with `gdb -batch` when gdb is installed. When there is no core, say why."""
from __future__ import annotations

import glob
import os
import re
import shutil
import socket
import subprocess
from pathlib import Path
from typing import Optional

from .evidence import Frame, parse_gdb_backtrace

CORE_PATTERN = Path("/proc/sys/kernel/core_pattern")
CORE_USES_PID = Path("/proc/sys/kernel/core_uses_pid")
GDB_TIMEOUT_S = 60.0
_MAX_BACKTRACE = 64 * 1024


def read_pattern(path: Path = CORE_PATTERN) -> Optional[str]:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def why_no_core(pattern: Optional[str], core_limit: int) -> Optional[str]:
    """Why no core can be had before the target even runs (None: one may appear)."""
    if core_limit == 0:
        return "turned off (--no-core, or the hard core size limit is 0)"
    if pattern is None:
        return "cannot read /proc/sys/kernel/core_pattern"
    if pattern.startswith("|"):
        if "systemd-coredump" in pattern and shutil.which("coredumpctl"):
            return None
        program = pattern[1:].split()[0] if pattern[1:].split() else "?"
        return (f"core_pattern is a pipe to {program} (not systemd-coredump with coredumpctl): "
                "the core goes to that program")
    return None


def _glob_of(pattern: str, pid: int, exe: str, uses_pid: bool) -> str:
    """core_pattern as a glob for one process: %p and %e filled in, the other specifiers any text."""
    values = {"p": str(pid), "P": str(pid), "i": str(pid), "I": str(pid), "e": exe[:15], "h": socket.gethostname(),
              "%": "%"}
    out = re.sub(r"%(.)", lambda m: glob.escape(values[m.group(1)]) if m.group(1) in values else "*",
                 glob.escape(pattern).replace("[%]", "%"))
    if uses_pid and "%p" not in pattern:
        out += f".{pid}"
    return out


def find_core(pattern: str, pid: int, exe: str, cwd: Path, since: float) -> Optional[Path]:
    """The core file a process left by a file `pattern` (relative to `cwd`), newer than `since`."""
    try:
        uses_pid = CORE_USES_PID.read_text().strip() == "1"
    except OSError:
        uses_pid = False
    where = _glob_of(pattern, pid, os.path.basename(exe), uses_pid)
    if not os.path.isabs(pattern):
        where = os.path.join(glob.escape(str(cwd)), where)
    found = []
    for name in glob.glob(where):
        try:
            st = os.lstat(name)
        except OSError:
            continue
        if st.st_mtime >= since - 1 and os.path.isfile(name) and not os.path.islink(name):
            found.append((st.st_mtime, name))
    return Path(max(found)[1]) if found else None


def coredumpctl_core(pid: int, dest: Path) -> Optional[Path]:
    """The core of `pid` from systemd-coredump, written to `dest`."""
    try:
        subprocess.run(["coredumpctl", "--no-pager", "-q", "-o", str(dest), "dump", str(pid)],
                       stdin=subprocess.DEVNULL, capture_output=True, timeout=GDB_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return dest if dest.is_file() and dest.stat().st_size > 0 else None


def backtrace(exe: str, core: Path) -> tuple[str, list[Frame]]:
    """`gdb -batch` backtrace of the crashing thread; ("", []) when gdb is not installed or fails."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return "", []
    try:
        done = subprocess.run([gdb, "-batch", "-nx", "-ex", "set pagination off", "-ex", "bt", exe, str(core)],
                              stdin=subprocess.DEVNULL, capture_output=True, timeout=GDB_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return "", []
    text = done.stdout.decode("utf-8", "replace")[:_MAX_BACKTRACE]
    return text, parse_gdb_backtrace(text)
