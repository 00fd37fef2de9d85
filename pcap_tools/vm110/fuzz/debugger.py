"""A native controller run under `gdb -batch` when the kernel will leave no core to read (--no-core,
core_pattern a pipe to apport): at a fatal signal gdb writes the crashing thread's stack, as the
backtrace of a core would be, so that two bugs of one signal are two findings, not one.

gdb's own lines go to a log file of its own, not into the controller's output; how the controller
ended is read from that log (gdb itself exits 0 whatever the controller did)."""
from __future__ import annotations

import functools
import os
import re
import signal
import subprocess
from pathlib import Path
from typing import Optional

from .evidence import Frame, parse_gdb_backtrace

# Stopped at (and not passed on: gdb ends the controller after the backtrace); all others pass.
FATAL_SIGNALS = ("SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT", "SIGSYS")
_MAX_LOG = 64 * 1024
_SIGNALLED = re.compile(r"^Program (?:received|terminated with) signal (SIG\w+)", re.M)
_EXITED = re.compile(r"^\[Inferior \d+ \(process \d+\) exited (?:with code (\d+)|normally)\]", re.M)


def command(gdb: str, log: Path, argv: list[str]) -> list[str]:
    """gdb running `argv`: its output to `log`, a stack at a fatal signal. The program starts
    through gdb's startup shell (/bin/sh: gdb quotes the arguments for a shell), with the
    environment it would have had (SHELL as it was; LINES and COLUMNS, which gdb adds, gone)."""
    shell = os.environ.get("SHELL")
    restore = f"set environment SHELL={shell}" if shell is not None else "unset environment SHELL"
    script = [f"set logging file {log}", "set logging overwrite on", "set logging redirect on",
              "set logging enabled on", "set debuginfod enabled off", "set disable-randomization off", restore,
              "unset environment LINES", "unset environment COLUMNS", "handle all nostop noprint pass",
              f"handle {' '.join(FATAL_SIGNALS)} stop print nopass", "run", "bt"]
    # (no scripts of the program's run: code beside it, and gdb's warnings of them in its output)
    early = ["set auto-load gdb-scripts off", "set auto-load python-scripts off", "set auto-load local-gdbinit off"]
    return [gdb, "-q", "-batch", "-nx", *(a for line in early for a in ("-iex", line)),
            *(a for line in script for a in ("-ex", line)), "--args", *argv]


@functools.lru_cache(maxsize=None)
def cannot_trace(gdb: str) -> Optional[str]:
    """Why `gdb` cannot run a program here (a container that forbids ptrace, a broken install),
    tried once on /bin/true; None when it can."""
    try:
        done = subprocess.run([gdb, "-q", "-batch", "-nx", "-ex", "set debuginfod enabled off", "-ex", "run",
                               "--args", "/bin/true"], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                              errors="replace", timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{gdb}: {exc}"
    if returncode(done.stdout) == 0:
        return None
    said = [line.strip() for line in (done.stderr + done.stdout).splitlines() if line.strip()]
    return "".join(c if c.isprintable() else "?" for c in said[-1][:160]) if said else f"{gdb} ran no program"


def read_log(log: Optional[Path]) -> str:
    if log is None:
        return ""
    try:
        with open(log, "rb") as f:
            return f.read(_MAX_LOG).decode("utf-8", "replace")
    except OSError:
        return ""


def returncode(log_text: str) -> Optional[int]:
    """How the controller gdb ran ended, as Popen says it (negative: that signal); None when gdb
    did not say (it never started the program)."""
    m = _SIGNALLED.search(log_text)
    if m:
        try:
            return -signal.Signals[m.group(1)].value
        except KeyError:
            return None
    m = _EXITED.search(log_text)
    if m:
        return int(m.group(1), 8) if m.group(1) else 0      # gdb writes the exit code in octal
    return None


def stack(log_text: str) -> tuple[str, list[Frame]]:
    """The stack gdb wrote at the fatal signal (from its line on), and its frames; ("", []) when
    the controller did not die of one."""
    m = _SIGNALLED.search(log_text)
    if m is None:
        return "", []
    text = log_text[m.start():]
    return text, parse_gdb_backtrace(text)
