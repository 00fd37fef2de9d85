"""Start, watch, restart and stop the controller under test (`--target-cmd`), and keep what it
leaves behind when it dies: the output of that run (a bounded ring), how it ended, its sanitizer
report and its core file."""
from __future__ import annotations

import collections
import contextlib
import os
import resource
import shlex
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Iterator, Optional

from ..errors import CliError
from . import cores, debugger, program
from .evidence import Crash, parse_assertion, parse_python_traceback, parse_sanitizer

_STOP_WAIT_S = 2.0
RING_BYTES = 256 * 1024
_REPORT_TAIL = 64 * 1024
_READ_WAIT_S = 3.0           # for the rest of a dying controller's report to arrive

# As AFL++ and libFuzzer start their targets: an error ends the process with a signal and a
# symbolised report; leaks are not crashes of a long-running service.
SANITIZER_DEFAULTS = {
    # handle_abort: an abort() (a failed assert) gets AddressSanitizer's report and stack, as a
    # plain build's core does (ASan builds leave no core).
    "ASAN_OPTIONS": "abort_on_error=1:symbolize=1:detect_leaks=0:handle_abort=1",
    "UBSAN_OPTIONS": "abort_on_error=1:halt_on_error=1:print_stacktrace=1:symbolize=1",
    "LSAN_OPTIONS": "symbolize=1",
}


_ASAN_NO_CORE = ("AddressSanitizer turns core files off (its disable_coredump=1 on 64-bit, against a core of its "
                 "whole shadow memory); its report has the stack")


@contextlib.contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Ctrl-C and SIGTERM wait until the block ends. A KeyboardInterrupt raised inside Popen after
    the fork left the controller running with nobody holding its pid (in its own session, so
    nothing else stops it either). Only the main thread can change handlers or receive signals."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    before = {signum: signal.signal(signum, lambda signum, frame: caught.append(signum)) for signum in held}
    try:
        yield
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)
        for pending in caught:
            signal.raise_signal(pending)


class _Ring:
    """The last `limit` bytes a stream delivered."""

    def __init__(self, limit: int = RING_BYTES) -> None:
        self.limit = limit
        self.chunks: collections.deque[bytes] = collections.deque()
        self.size = 0
        self.lock = threading.Lock()

    def add(self, data: bytes) -> None:
        with self.lock:
            self.chunks.append(data)
            self.size += len(data)
            while self.size - len(self.chunks[0]) >= self.limit:
                self.size -= len(self.chunks.popleft())

    def value(self) -> bytes:
        with self.lock:
            return b"".join(self.chunks)[-self.limit:]


class Supervisor:
    """One controller process at a time, in its own process group so that its children go too."""

    def __init__(self, command: str, log: Optional[IO[bytes]] = None, env: Optional[dict[str, str]] = None,
                 core: bool = True, cwd: Optional[Path] = None) -> None:
        try:
            self.argv = shlex.split(command)
        except ValueError as exc:
            raise CliError(f"--target-cmd: {exc}") from None
        if not self.argv:
            raise CliError("--target-cmd is empty")
        self.command = command
        self.log = log
        self.extra_env = dict(env or {})
        self.cwd = cwd or Path.cwd()
        self.proc: Optional[subprocess.Popen[bytes]] = None
        self.starts = 0
        self.started_at = 0.0
        self.ring = _Ring()
        self.reader: Optional[threading.Thread] = None
        self.exe = shutil.which(self.argv[0], path=os.environ.get("PATH")) or str(self.cwd / self.argv[0])
        self._check_program()      # now, before the run makes its files (and at each start)
        # Those that mean something to the program (all when that cannot be told): the summary's.
        applies = program.sanitizer_options(self.argv, self.exe, str(self.cwd))
        self.asan = applies is not None and "ASAN_OPTIONS" in applies
        self.sanitizer_options = {name: ("user" if name in os.environ else value)
                                  for name, value in SANITIZER_DEFAULTS.items() if applies is None or name in applies}
        self.core_hard = resource.getrlimit(resource.RLIMIT_CORE)[1]
        self.core_limit = self.core_hard if core else 0
        self.core_pattern = cores.read_pattern()
        self.no_core_reason = cores.why_no_core(self.core_pattern, self.core_limit)
        # No core to read a native build's stack from, nor a sanitizer to write it: gdb runs it.
        # Unless gdb may not trace here (a container without ptrace): then the controller runs alone.
        gdb = shutil.which("gdb")
        wanted = gdb is not None and bool(self.no_core_reason) and applies == set() \
            and program.native(self.argv, self.exe, str(self.cwd))
        self.untraced = debugger.cannot_trace(gdb) if wanted and gdb else None
        self.gdb = gdb if wanted and self.untraced is None else None
        self.gdb_log: Optional[Path] = None
        self._gdb_read: tuple[int, Optional[int]] = (-1, None)   # (its size when read, what it said of the end)

    def core_files(self) -> str:
        """What the run's summary says of core files: "on", or why a crash will leave none."""
        if self.no_core_reason:
            if self.untraced:
                return f"{self.no_core_reason}; gdb cannot run the controller here ({self.untraced})"
            return self.no_core_reason + ("; gdb runs the controller, for the stack of a crash" if self.gdb else "")
        return _ASAN_NO_CORE if self.asan and self._asan_without_core() else "on"

    def _asan_without_core(self) -> bool:
        return "disable_coredump=0" not in self.environment().get("ASAN_OPTIONS", "")

    def environment(self) -> dict[str, str]:
        env = dict(os.environ)
        for name, value in SANITIZER_DEFAULTS.items():
            env.setdefault(name, value)
        env.update(self.extra_env)
        if self.gdb:
            # gdb's startup shell, one that reads the arguments as gdb quoted them (the
            # controller's own SHELL is given back to it)
            env["SHELL"] = "/bin/sh"
        return env

    def start(self) -> None:
        self.ring = _Ring()
        self._check_program()
        self._drop_gdb_log()
        if self.gdb:
            fd, name = tempfile.mkstemp(prefix="vm110-gdb-", suffix=".log")
            os.close(fd)
            self.gdb_log = Path(name)
        try:
            with _interrupts_deferred():
                self.proc = subprocess.Popen(self._with_core_limit(), stdin=subprocess.DEVNULL,
                                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
                                             env=self.environment(), cwd=self.cwd)
                self.started_at = time.time()
                self.starts += 1
                assert self.proc.stdout is not None
                # (its start too: an interrupt inside Thread.start's wait for the thread left the
                # lock of that wait broken, CPython's "RuntimeError: release unlocked lock")
                self.reader = threading.Thread(target=self._read, args=(self.proc.stdout, self.ring), daemon=True)
                self.reader.start()
        except OSError as exc:
            raise CliError(f"cannot start --target-cmd {self.argv[0]!r}: {exc.strerror}") from None

    def _check_program(self) -> None:
        """The shell in front would report a missing program only as an early exit."""
        if not os.path.isfile(self.exe):
            raise CliError(f"cannot start --target-cmd {self.argv[0]!r}: no such executable")
        if not os.access(self.exe, os.X_OK):
            raise CliError(f"cannot start --target-cmd {self.argv[0]!r}: not executable (chmod +x?)")

    def _with_core_limit(self) -> list[str]:
        """The command behind a shell that sets its core size limit and execs it (same pid): the
        limit is in place before the controller runs, so that a limit the controller sets itself
        (AddressSanitizer's disable_coredump) stands. Set from outside after the start, it raced
        with that and could drop a core into the working folder. (No Python between fork and exec:
        the reader threads.)"""
        limit = "unlimited" if self.core_limit == resource.RLIM_INFINITY else str(self.core_limit)
        # Killed with the fuzzer (SIGKILL, the OOM killer: no stop() runs), a controller would go on
        # in its own session, holding the target port: setpriv has the kernel kill it too.
        setpriv = shutil.which("setpriv")
        tie = [setpriv, "--pdeathsig", "KILL", "--"] if setpriv else []
        argv = self.argv
        if self.gdb and self.gdb_log:
            argv = debugger.command(self.gdb, self.gdb_log, argv)
        return ["/bin/sh", "-c", 'ulimit -S -c "$0" && exec "$@"', limit, *tie, *argv]

    def _read(self, stream: IO[bytes], ring: _Ring) -> None:
        fd = stream.fileno()
        while True:
            try:
                data = os.read(fd, 65536)
            except OSError:
                break
            if not data:
                break
            ring.add(data)
            if self.log is not None:
                try:
                    self.log.write(data)
                    self.log.flush()
                except (OSError, ValueError):
                    pass
        stream.close()

    def dying(self) -> bool:
        """A sanitizer has begun its report: the process ends once it is written (symbolising
        takes a while on a loaded machine)."""
        tail = self.ring.value()[-_REPORT_TAIL:]
        return b"==ERROR: " in tail or b"DEADLYSIGNAL" in tail or b"runtime error: " in tail

    def poll(self) -> Optional[int]:
        """The exit code once the controller has exited (negative: the signal that ended it), else None."""
        code = None if self.proc is None else self.proc.poll()
        if self.proc is None or not self.gdb:
            return code
        # gdb says the signal at once, before its backtrace and its own exit: the crash is seen
        # then, not after cases that went on to a controller stopped in gdb
        said = self._gdb_said()
        return code if said is None else said

    def _gdb_said(self) -> Optional[int]:
        """How gdb's log says the controller ended (None: not yet); read again only when it has
        grown (poll() is asked every few milliseconds)."""
        size, said = self._gdb_read
        if said is None and self.gdb_log is not None:
            with contextlib.suppress(OSError):
                now = self.gdb_log.stat().st_size
                if now != size:
                    self._gdb_read = (now, debugger.returncode(debugger.read_log(self.gdb_log)))
        return self._gdb_read[1]

    def output(self) -> bytes:
        """What this start of the controller wrote (its last RING_BYTES), once its output has ended."""
        if self.reader is not None:
            self.reader.join(_READ_WAIT_S)
        return self.ring.value()

    def last_words(self) -> str:
        """`: its last output line "..."` of a controller that ended (why it would not start), or ""."""
        if self.poll() is None:
            return ""
        lines = [line.strip() for line in self.output().decode("utf-8", "replace").splitlines() if line.strip()]
        if not lines:       # (gdb's, when it could not run the controller)
            lines = [line.strip() for line in debugger.read_log(self.gdb_log).splitlines() if line.strip()]
        if not lines:
            return ""
        text = "".join(c if c.isprintable() else "?" for c in lines[-1][:200])
        return f': its last output line "{text}"'

    def evidence(self, folder: Path, name: str) -> Crash:
        """The crash of the process just ended: its output, sanitizer report, core (moved to
        `folder`/`name`.core) and the backtrace from it."""
        proc = self.proc
        returncode = self.poll()
        assert proc is not None and returncode is not None
        if self.gdb:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(cores.GDB_TIMEOUT_S)        # (writing the backtrace)
        self._kill_group(proc)
        crash = Crash(returncode, self.output())
        text = crash.output.decode("utf-8", "replace")
        crash.sanitizer = parse_sanitizer(text) or parse_python_traceback(text)
        crash.assertion = parse_assertion(text)
        if returncode >= 0:
            crash.core_missing = "the controller exited, no signal: no core"
            return crash
        if self.no_core_reason:
            crash.core_missing = self.no_core_reason
            crash.backtrace_text, crash.backtrace = debugger.stack(debugger.read_log(self.gdb_log))
            crash.stack_missing = self._why_no_stack(crash)
            return crash
        if crash.sanitizer is not None and crash.sanitizer.tool == "asan" and self._asan_without_core():
            crash.core_missing = self._why_missing(crash)
            return crash
        dest = folder / f"{name}.core"
        core = self._core(proc.pid, dest)
        if core is None:
            crash.core_missing = self._why_missing(crash)
            crash.stack_missing = self._why_no_stack(crash)
            return crash
        crash.core = dest.name
        crash.backtrace_text, crash.backtrace = cores.backtrace(self.exe, dest)
        if not crash.backtrace_text and shutil.which("gdb") is None:
            crash.backtrace_text = "(gdb is not installed: no backtrace from the core)"
        crash.stack_missing = self._why_no_stack(crash)
        return crash

    def _why_no_stack(self, crash: Crash) -> Optional[str]:
        """Why a crash by a signal has no stack to tell it from others of that signal (None: it has one)."""
        if crash.own_frames() or crash.sanitizer is not None:
            return None
        if crash.stack():
            return "its stack names none of the controller's functions (a build without symbols?)"
        if self.gdb:
            return "gdb, which ran the controller, wrote no frames"
        if self.untraced:
            return f"gdb cannot run the controller here ({self.untraced}); no core: {crash.core_missing}"
        if shutil.which("gdb") is None:
            return f"gdb is not installed (core: {crash.core or crash.core_missing})"
        return "gdb found no frames in the core" if crash.core else f"no core: {crash.core_missing}"

    def _core(self, pid: int, dest: Path) -> Optional[Path]:
        pattern = self.core_pattern or ""
        if pattern.startswith("|"):
            return cores.coredumpctl_core(pid, dest)
        for _ in range(20):          # the kernel writes the core before the parent sees the exit
            found = cores.find_core(pattern, pid, self.exe, self.cwd, self.started_at)
            if found is not None:
                try:
                    shutil.move(str(found), str(dest))
                except OSError:
                    return None
                return dest
            time.sleep(0.05)
        return None

    def _why_missing(self, crash: Crash) -> str:
        how = crash.how
        if crash.sanitizer is not None and crash.sanitizer.tool == "asan":
            return _ASAN_NO_CORE
        if how.get("signal") in (signal.SIGKILL, signal.SIGTERM, signal.SIGINT):
            return f"{how['signal_name']} does not dump core"
        return f"no core file found by core_pattern {self.core_pattern!r} in {self.cwd}"

    @staticmethod
    def _kill_group(proc: subprocess.Popen[bytes]) -> None:
        """A dead controller's children go too (they would hold its port and output)."""
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass

    def _drop_gdb_log(self) -> None:
        self._gdb_read = (-1, None)
        if self.gdb_log is not None:
            with contextlib.suppress(OSError):
                self.gdb_log.unlink()
            self.gdb_log = None

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        self._drop_gdb_log()
        if proc is None:
            return
        if proc.poll() is not None:
            self._kill_group(proc)
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
