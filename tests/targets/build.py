"""Builds of tests/targets/controller.c for the fuzzer's tests and benchmark.

    python tests/targets/build.py OUT_DIR [VARIANT ...]      (default: every variant)
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "controller.c"
_ASAN = ["gcc", "-g", "-O1", "-fno-omit-frame-pointer", "-fsanitize=address"]
_PLAIN = ["gcc", "-g", "-O0"]
_AFL = ["afl-clang-fast", "-g", "-O1"]
# name -> compiler command (without source and output) and planted bug
VARIANTS: dict[str, list[str]] = {
    "asan-correct": _ASAN,
    "asan-heap-overflow": _ASAN + ["-DBUG_HEAP_OVERFLOW"],
    "asan-abort": _ASAN + ["-DBUG_ABORT"],
    "asan-churn": _ASAN + ["-DCHURN"],        # correct: a buffer per command, freed (ASan's quarantine keeps it)
    "plain-correct": _PLAIN,
    "plain-null-call": _PLAIN + ["-DBUG_NULL_CALL"],
    "plain-deep": _PLAIN + ["-DBUG_DEEP"],
    "plain-leak": _PLAIN + ["-DBUG_LEAK"],
    "plain-leak-unknown": _PLAIN + ["-DBUG_LEAK_UNKNOWN"],
    "plain-two-segv": _PLAIN + ["-DBUG_NULL_CALL", "-DBUG_LAP_SLOT"],      # two bugs, both SIGSEGV
    "afl-correct": _AFL,
    "afl-deep": _AFL + ["-DBUG_DEEP"],
    "afl-null-call": _AFL + ["-DBUG_NULL_CALL"],
    "afl-heap-overflow": _AFL + ["-DBUG_HEAP_OVERFLOW"],
    "afl-asan-heap-overflow": _AFL + ["-fno-omit-frame-pointer", "-DBUG_HEAP_OVERFLOW"],
}
_ENV = {"afl-asan-heap-overflow": {"AFL_USE_ASAN": "1"}}     # AFL++ adds -fsanitize=address


def missing_tools(variant: str) -> list[str]:
    return [tool for tool in {VARIANTS[variant][0], "gdb"} if shutil.which(tool) is None]


def build(variant: str, out: Path) -> Path:
    """The program for `variant` in `out` (built when missing or older than the source)."""
    exe = out / f"controller-{variant}"
    if exe.exists() and exe.stat().st_mtime >= SOURCE.stat().st_mtime:
        return exe
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, AFL_QUIET="1", **_ENV.get(variant, {}))
    temp = out / f".{exe.name}.{os.getpid()}"
    cmd = VARIANTS[variant] + ["-Wall", "-Wextra", "-Werror", str(SOURCE), "-o", str(temp)]
    subprocess.run(cmd, check=True, env=env, capture_output=True)
    os.replace(temp, exe)       # whole or not at all, whoever builds it at the same time
    return exe


if __name__ == "__main__":
    folder = Path(sys.argv[1])
    for name in sys.argv[2:] or list(VARIANTS):
        print(build(name, folder))
