"""Which sanitizers the controller's program is built with, from the runtime symbols in its files:
their options mean something to it, the others nothing (a controller in Python has none)."""
from __future__ import annotations

import os
from typing import Optional

# The runtimes' entry points, named in every build that links one (gcc's shared runtime, clang's
# static one) -> the option variables it reads (ASan includes LeakSanitizer).
_MARKERS = {b"__asan_init": ("ASAN_OPTIONS", "LSAN_OPTIONS"), b"__ubsan_handle_": ("UBSAN_OPTIONS",),
            b"__lsan_": ("LSAN_OPTIONS",)}
_OVERLAP = max(len(m) for m in _MARKERS)
_CHUNK = 1 << 20
_MAX_READ = 256 << 20
_SHELLS = frozenset({"sh", "bash", "dash", "zsh", "ksh", "busybox"})


def _kind(path: str) -> str:
    """"elf", "python" (a script run by Python), "script" (any other) or "" (unreadable, other)."""
    try:
        with open(path, "rb") as f:
            head = f.read(256)
    except OSError:
        return ""
    if head.startswith(b"\x7fELF"):
        return "elf"
    if head.startswith(b"#!"):
        words = head[2:].split(b"\n", 1)[0].split()[:2]     # `#!/usr/bin/env python3` names it second
        return "python" if any(os.path.basename(w).startswith(b"python") for w in words) else "script"
    return ""


def native(argv: list[str], exe: str, cwd: str) -> bool:
    """A compiled program, whose crash gdb can show the stack of: not Python (its own traceback
    says where), nor one run through it (`env python3 ctl.py`), nor a script."""
    python = any(os.path.basename(w).startswith("python") or _kind(os.path.join(cwd, w)) == "python" for w in argv)
    return _kind(exe) == "elf" and not python


def _linked(path: str) -> Optional[set[str]]:
    """The option variables of the runtimes in ELF file `path`; None when it is too large to tell."""
    found: set[str] = set()
    try:
        with open(path, "rb") as f:
            tail, read = b"", 0
            while chunk := f.read(_CHUNK):
                blob = tail + chunk
                found.update(o for marker, options in _MARKERS.items() if marker in blob for o in options)
                tail, read = blob[-_OVERLAP:], read + len(chunk)
                if read >= _MAX_READ:
                    return None
    except OSError:
        return None
    return found


def sanitizer_options(argv: list[str], exe: str, cwd: str) -> Optional[set[str]]:
    """The sanitizer option variables that apply to what `argv` runs (`exe`, its first word
    resolved): none for Python, those of the runtimes linked into the program and into a program
    it is given (`env A=1 ./ctl-asan`, `taskset -c 1 ./ctl-asan`). None: it cannot be told (a
    shell or a script may start anything)."""
    first = _kind(exe)
    if os.path.basename(argv[0]).startswith("python") or first == "python":
        return set()
    if os.path.basename(argv[0]) in _SHELLS or first != "elf":
        return None
    options: set[str] = set()
    for path in [exe] + [os.path.join(cwd, w) for w in argv[1:]]:
        if path == exe or (os.path.isfile(path) and os.access(path, os.X_OK)):
            kind = _kind(path)
            found = _linked(path) if kind == "elf" else None if kind == "script" else set()
            if found is None:
                return None
            options |= found
    return options
