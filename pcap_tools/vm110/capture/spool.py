"""Standard input as a capture file: a pipe is copied to a temporary file of our own first.

The readers seek (CRC sniffing, parallel parts, the tshark engine's second pass), which a pipe
cannot; a spooled copy lets `-` be read exactly as a file is, with memory kept flat.
"""
from __future__ import annotations

import contextlib
import shutil
import sys
import tempfile

from ..errors import CliError


def stdin_spool(stack: contextlib.ExitStack) -> str:
    """Copy standard input to a temporary file removed when `stack` closes; its path."""
    folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="vm110-stdin-"))
    path = f"{folder}/stdin"
    try:
        with open(path, "wb") as out:
            shutil.copyfileobj(sys.stdin.buffer, out, 1 << 20)
    except OSError as exc:
        raise CliError(f"cannot read standard input: {exc.strerror or exc}") from None
    return path


def named(given: str) -> str:
    """The capture the user gave as `given`, in words: "-" is "standard input"."""
    return "standard input" if given == "-" else given


def as_given(message: str, path: str, given: str) -> str:
    """A message about the capture at `path` in the words the user gave it: a spooled standard
    input (`given` "-") is "standard input", never the temporary file's name."""
    return message.replace(path, named(given)) if given == "-" else message
