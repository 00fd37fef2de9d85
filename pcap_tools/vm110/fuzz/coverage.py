"""The AFL coverage map: a System V shared-memory segment the instrumented controller writes edge
hit counts into (its ID goes to the target as `__AFL_SHM_ID`), and the classification of hit
counts into AFL's buckets to tell a case that reached something new."""
from __future__ import annotations

import ctypes
import ctypes.util
import os

from ..errors import CliError

DEFAULT_MAP_SIZE = 65536
_IPC_PRIVATE, _IPC_CREAT, _IPC_EXCL, _IPC_RMID = 0, 0o1000, 0o2000, 0
# AFL's hit-count classes: 1, 2, 3, 4-7, 8-15, 16-31, 32-127, 128+.
COUNT_CLASS = bytes(0 if n == 0 else 1 if n == 1 else 2 if n == 2 else 4 if n == 3 else 8 if n < 8 else
                    16 if n < 16 else 32 if n < 32 else 64 if n < 128 else 128 for n in range(256))


def map_size(env: dict[str, str] = dict(os.environ)) -> int:  # noqa: B006 - read once
    text = env.get("AFL_MAP_SIZE")
    if text is None:
        return DEFAULT_MAP_SIZE
    if not text.isdigit() or not 64 <= int(text) <= 1 << 28:
        raise CliError(f"AFL_MAP_SIZE={text[:40]!r} is not a map size from 64 to {1 << 28} bytes")
    return int(text)


class ShmMap:
    """A private segment, marked for removal at once (Linux lets the target attach it still), so
    that none is left behind whatever happens to the fuzzer."""

    def __init__(self, size: int) -> None:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        libc.shmget.argtypes = [ctypes.c_int, ctypes.c_size_t, ctypes.c_int]
        libc.shmat.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_int]
        libc.shmat.restype = ctypes.c_void_p
        libc.shmdt.argtypes = [ctypes.c_void_p]
        libc.shmctl.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p]
        self._libc, self.size = libc, size
        self.id = libc.shmget(_IPC_PRIVATE, size, _IPC_CREAT | _IPC_EXCL | 0o600)
        if self.id < 0:
            raise CliError(f"cannot create the coverage map: {os.strerror(ctypes.get_errno())}")
        addr = libc.shmat(self.id, None, 0)
        if addr in (None, ctypes.c_void_p(-1).value):
            libc.shmctl(self.id, _IPC_RMID, None)
            raise CliError(f"cannot attach the coverage map: {os.strerror(ctypes.get_errno())}")
        self.addr: int = addr
        libc.shmctl(self.id, _IPC_RMID, None)

    def clear(self) -> None:
        ctypes.memset(self.addr, 0, self.size)

    def read(self) -> bytes:
        return ctypes.string_at(self.addr, self.size)

    def close(self) -> None:
        if self.addr:
            self._libc.shmdt(ctypes.c_void_p(self.addr))
            self.addr = 0


class Virgin:
    """What the run has covered so far, as one integer of classified bits (fast in CPython)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.bits = 0
        self.edges = 0
        self.ever_nonzero = False

    def novel(self, raw: bytes) -> int:
        """How many edges this map reaches for the first time (or, as -1, only a new hit-count
        class of a known edge); 0 when nothing new."""
        classified = int.from_bytes(raw.translate(COUNT_CLASS), "little")
        if not classified:
            return 0
        self.ever_nonzero = True
        new = classified & ~self.bits
        if not new:
            return 0
        before = self.edges
        self.bits |= classified
        self.edges = self.size - self.bits.to_bytes(self.size, "little").count(0)
        return self.edges - before or -1
