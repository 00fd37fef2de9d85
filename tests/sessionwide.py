"""Work done once per test session, however many xdist workers need it: the workers share a folder
under pytest's base temporary folder (conftest names it at the start of each), and each piece of
work has a lock there: the first worker does it, the others wait and read what it left."""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
from pathlib import Path
from typing import Callable, Iterator

_ROOT: dict[str, Path] = {}     # "": the folder the workers share, once start() named it


def start(basetemp: Path) -> None:
    """Share `basetemp`'s parent under xdist (every worker's base folder is in it), else `basetemp`."""
    _ROOT[""] = basetemp.parent if os.environ.get("PYTEST_XDIST_WORKER") else basetemp


@contextlib.contextmanager
def _locked(folder: Path, name: str) -> Iterator[None]:
    """`name`'s lock in `folder`, held: one worker at a time does its work."""
    with open(folder / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def once(name: str, make: Callable[[Path], None]) -> Path:
    """The folder `name` made by `make(folder)` once in this session."""
    root = _ROOT[""]                 # (conftest calls start() first)
    folder = root / f"once-{name}"
    with _locked(root, f"once-{name}"):
        if not (folder / ".done").exists():
            if folder.exists():
                shutil.rmtree(folder)        # a half-made one of this session (its maker failed)
            folder.mkdir()
            make(folder)
            (folder / ".done").write_text("")
    return folder


def value(key: str, compute: Callable[[], bytes]) -> bytes:
    """`compute()` once in this session for `key` (outside a session: every time)."""
    if "" not in _ROOT:
        return compute()
    name = hashlib.sha256(key.encode()).hexdigest()[:32]
    folder = _ROOT[""] / "once-values"
    folder.mkdir(exist_ok=True)
    path = folder / name
    with _locked(folder, name):
        if not path.exists():
            fresh = folder / f"{name}.{os.getpid()}"
            fresh.write_bytes(compute())
            os.replace(fresh, path)
    return path.read_bytes()
