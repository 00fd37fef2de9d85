"""Writing output files so that a failure never costs what was there before.

A file is written to a temporary file of our own in the same folder, flushed to disk and renamed
over the target only when complete: an error at any point leaves the old file exactly as it was,
and the only file ever removed is that temporary one. A target that exists and is not a regular
file (a device, a FIFO, a directory) is refused up front: renaming over it would replace the node.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import stat
from pathlib import Path
from typing import IO, Iterator, Union

from .errors import CliError

PathLike = Union[str, "os.PathLike[str]"]


def open_input(path: PathLike) -> IO[bytes]:
    """An input file opened for reading without waiting for a writer: a FIFO that no process
    writes to reads as empty (open() would block for ever); one that is being written reads as usual."""
    f = open(path, "rb", opener=lambda name, flags: os.open(name, flags | os.O_NONBLOCK))  # noqa: SIM115 -- the caller's
    os.set_blocking(f.fileno(), True)
    return f


def read_at_most(path: PathLike, limit: int) -> bytes:
    """The bytes of an input file of at most `limit` bytes; ValueError when it has more (read no
    further: a device such as /dev/zero, or a FIFO, has no size to check first)."""
    with open_input(path) as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise ValueError(f"larger than {limit >> 20} MiB" if limit >= 1 << 20 else f"larger than {limit} bytes")
    return data


def check_target(path: PathLike) -> Path:
    """The path written to (symbolic links followed, so that a link stays a link); CliError when
    it exists and is not a regular file."""
    if not os.fspath(path):
        raise CliError("refusing to write a file with an empty name")
    real = Path(os.path.realpath(path))
    try:
        # (the path itself: /dev/stdout on a pipe resolves to "/proc/<pid>/fd/pipe:[...]", no file,
        # and was taken for a new one, then "No such file or directory")
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return real
    except OSError as exc:
        raise CliError(f"cannot write {os.fspath(path)}: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise CliError(f"refusing to write {os.fspath(path)}: it exists and is not a regular file")
    return real


def check_distinct(outputs: dict[str, str], inputs: list[str]) -> None:
    """Output files (option -> path, "-" for standard output) are neither an input nor one another:
    CliError before anything is read or written (a report written over its capture destroyed it,
    and two reports on one path kept only the last)."""
    def identity(path: str) -> tuple:
        try:
            st = os.stat(path)
            return (st.st_dev, st.st_ino)
        except OSError:                       # not there yet: its resolved path
            return (os.path.realpath(path),)
    read = {identity(p): p for p in inputs if p != "-"}
    seen: dict[tuple, str] = {}
    for option, path in outputs.items():
        if path == "-":
            continue
        key = identity(path)
        if key in read:
            raise CliError(f"{option} {path} is the input {read[key]}: refusing to write over it")
        if key in seen:
            raise CliError(f"{seen[key]} and {option} name the same file {path}: one would be lost")
        seen[key] = option


def check_report_target(path: PathLike) -> Path:
    """check_target, and the folder a new file goes into exists and is writable: a report file
    that cannot be written is said before the work, not after it."""
    real = check_target(path)
    if not real.exists():
        if not real.parent.is_dir():
            raise CliError(f"cannot write {os.fspath(path)}: no folder {real.parent}")
        if not os.access(real.parent, os.W_OK | os.X_OK):
            raise CliError(f"cannot write {os.fspath(path)}: the folder {real.parent} is not writable")
    return real


@contextlib.contextmanager
def atomic_writer(path: PathLike, binary: bool = True) -> Iterator[IO]:
    """A file object to write `path` through; it replaces `path` when the block ends without an
    exception. OSError becomes a CliError naming `path`; other exceptions pass through, and in
    every failure the temporary file is removed and `path` is untouched."""
    real = check_target(path)
    try:
        fd, temp = _create_temp(real)
    except OSError as exc:
        raise CliError(f"cannot write {os.fspath(path)}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb" if binary else "w", encoding=None if binary else "utf-8") as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        _keep_mode(real, temp)
        check_target(real)    # again: it may have become a device or a directory meanwhile
        os.replace(temp, real)
        _sync_folder(real.parent)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temp)
        if isinstance(exc, OSError):
            raise CliError(f"cannot write {os.fspath(path)}: {exc.strerror or exc}") from None
        raise


def write_bytes(path: PathLike, data: bytes) -> None:
    """`data` as the whole of `path`, atomically."""
    with atomic_writer(path) as stream:
        stream.write(data)


def write_text(path: PathLike, text: str) -> None:
    """`text` (UTF-8) as the whole of `path`, atomically."""
    with atomic_writer(path, binary=False) as stream:
        stream.write(text)


def _create_temp(real: Path) -> tuple[int, str]:
    """A new file of ours beside `real` (O_EXCL: never one that was there), mode 0666 less umask."""
    while True:
        temp = str(real.parent / f".{real.name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666), temp
        except FileExistsError:
            continue


def _keep_mode(real: Path, temp: str) -> None:
    """A replaced file keeps its permissions."""
    try:
        mode = real.stat().st_mode
    except FileNotFoundError:
        return
    os.chmod(temp, stat.S_IMODE(mode))


def _sync_folder(folder: Path) -> None:
    """Make the rename itself durable."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass    # some file systems cannot sync a directory; the rename has happened all the same
    finally:
        os.close(fd)
