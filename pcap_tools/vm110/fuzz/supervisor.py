"""Start, watch, restart and stop the controller under test (`--target-cmd`)."""
from __future__ import annotations

import os
import shlex
import signal
import subprocess
from typing import IO, Optional

from ..errors import CliError

_STOP_WAIT_S = 2.0


class Supervisor:
    """One controller process at a time, in its own process group so that its children go too."""

    def __init__(self, command: str, log: Optional[IO[bytes]] = None) -> None:
        try:
            self.argv = shlex.split(command)
        except ValueError as exc:
            raise CliError(f"--target-cmd: {exc}") from None
        if not self.argv:
            raise CliError("--target-cmd is empty")
        self.command = command
        self.log = log
        self.proc: Optional[subprocess.Popen[bytes]] = None
        self.starts = 0

    def start(self) -> None:
        try:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=self.log or subprocess.DEVNULL,
                                         stderr=self.log or subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            raise CliError(f"cannot start --target-cmd {self.argv[0]!r}: {exc.strerror}") from None
        self.starts += 1

    def poll(self) -> Optional[int]:
        """The exit code once the controller has exited, else None."""
        return None if self.proc is None else self.proc.poll()

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                return
            try:
                proc.wait(_STOP_WAIT_S)
                return
            except subprocess.TimeoutExpired:
                continue

    def restart(self) -> None:
        self.stop()
        self.start()
