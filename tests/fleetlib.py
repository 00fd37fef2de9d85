"""Shared by the fleet tests: work done once per test session, however many xdist workers need it."""
from __future__ import annotations

import fcntl
import os
import shutil
from pathlib import Path
from typing import Callable


def once(tmp_path_factory, name: str, make: Callable[[Path], None]) -> Path:
    """The folder `name` made by `make(folder)` once in this session: xdist workers share it (the
    first makes it under a lock, the others wait and read it); without xdist it is this run's own."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = root / f"fleet-{name}"
    with open(root / f"fleet-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / ".done").exists():
            if folder.exists():
                shutil.rmtree(folder)        # a half-made one of this session (its maker failed)
            folder.mkdir()
            make(folder)
            (folder / ".done").write_text("")
    return folder
