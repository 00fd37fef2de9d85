"""What a crashed controller left behind: how it ended, its sanitizer report, its core and backtrace.

Everything here reads text the controller (or gdb) wrote: it is parsed defensively, bounded, and
never run. A crash's signature (signal or exit code, sanitizer error type, top frames of the
target's own code) is what groups crashes into one finding per bug.
"""
from __future__ import annotations

import re
import signal
from dataclasses import dataclass, field
from typing import Any, Optional

TOP_FRAMES = 3
# The rules a crash's signature was made by, kept in its finding: 3, the crashing frame's file and
# line (two crash sites in one function are two bugs), a failed assertion's site where there is no
# stack, and the controller's functions named str... its own; 2, a UBSan error's own type (1:
# ASan's ABRT of the abort it made) and glibc's assert frames not the controller's own.
# (A crash by a signal with no stack, in a finding of any version, is compared by how it ended
# alone: without a stack, it cannot be told from another bug of that signal.)
SIGNATURE_VERSION = 3
_MAX_FRAMES = 64

# Frames that are not the target's own code: libc start-up, the sanitizer runtimes, signal delivery.
_FOREIGN_FUNCTIONS = re.compile(
    r"^(__asan|__ubsan|__lsan|__sanitizer|__interceptor_|__libc_|_start$|__GI_|__pthread|raise$|abort$|__assert|"
    r"gsignal$|__restore_rt|__kernel|__afl|___interceptor_|__wrap_|_dl_|__memset|__memcpy|__strlen|"
    r"mem(cpy|set|move|cmp|chr)$|str(n?(len|cpy|cat|cmp|dup)|chr|rchr|str|tok|tok_r|spn|cspn|pbrk|casecmp|ncasecmp|"
    r"casestr|chrnul|error|sep|coll|xfrm|[fp]time|lcpy|lcat|signal|to[a-z]+)$|stpn?cpy$|"
    r"malloc$|calloc$|realloc$|free$|operator (new|delete))")
_FOREIGN_FILES = re.compile(r"(^|/)(sanitizer_common|asan|ubsan|lsan|libsanitizer|compiler-rt|sysdeps|csu|nptl|"
                            r"libc\.so|libasan|libubsan|ld-linux|glibc|\.\./sysdeps)(/|\.|$)")
_ASAN_FRAME = re.compile(r"^\s*#(\d+)\s+0x[0-9a-fA-F]+\s+(?:in\s+(.+?)\s+)?(\S+|\(.*\))\s*$")
_GDB_FRAME = re.compile(r"^#(\d+)\s+(?:0x[0-9a-fA-F]+\s+in\s+)?(\S+)\s*\(.*?\)(?:\s+(?:at|from)\s+(\S+))?\s*$")
_ERROR = re.compile(r"==\d+==\s*ERROR:\s*(AddressSanitizer|LeakSanitizer|ThreadSanitizer|MemorySanitizer):\s*"
                    r"([\w-]+)")
_UBSAN = re.compile(r"^(\S+:\d+(?::\d+)?): runtime error: (.*)$")
_PY_FRAME = re.compile(r'^  File "(.+)", line (\d+), in (.+)$')
_PY_ERROR = re.compile(r"^([A-Za-z_][\w.]*)(?::|$)")
_PY_LIBRARY = re.compile(r"(^<frozen |/lib/python\d[\d.]*/(?!site-packages/))")
_SUMMARY = re.compile(r"^SUMMARY:\s*(\w+):\s*(.*)$")
# glibc's `prog: file.c:96: on_vrci: Assertion `n < 4' failed.` (the function as the compiler names it)
_ASSERTION = re.compile(r"^(?:.*?: )?([^:\s]+):(\d+): (.+?): Assertion `.*' failed\.$")
_SITE = re.compile(r"@\S+")
_TOOL_NAMES = {"AddressSanitizer": "asan", "LeakSanitizer": "lsan", "UndefinedBehaviorSanitizer": "ubsan",
               "ThreadSanitizer": "tsan", "MemorySanitizer": "msan"}


@dataclass
class Frame:
    function: str
    location: str = ""            # file:line[:column] when symbolised, else the module

    def own(self) -> bool:
        """The target's own code, not libc's or a sanitizer runtime's."""
        if not self.function or self.function in ("??", "<unknown>") or _FOREIGN_FUNCTIONS.match(self.function):
            return False
        return not _FOREIGN_FILES.search(self.location)

    def place(self) -> str:
        """`ctl.c:96` (no folder, no column), or "" when the frame has no line."""
        where = re.sub(r"^(.+?:\d+):\d+$", r"\1", self.location.rsplit("/", 1)[-1])
        return where if re.search(r":\d+$", where) else ""

    def short(self) -> str:
        return f"{self.function} ({self.place()})" if self.place() else self.function


@dataclass
class SanitizerReport:
    tool: str                      # asan, ubsan, lsan ...
    error_type: str                # heap-buffer-overflow, SEGV, signed-integer-overflow ...
    summary: str
    frames: list[Frame] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"tool": self.tool, "error_type": self.error_type, "summary": self.summary,
                "frames": [{"function": f.function, "location": f.location} for f in self.frames]}


def signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def ended(returncode: int) -> dict[str, Any]:
    """How a process ended, from Popen's returncode (negative: killed by that signal)."""
    if returncode < 0:
        return {"signal": -returncode, "signal_name": signal_name(-returncode)}
    return {"exit_code": returncode}


def _frames(lines: list[str], start: int) -> list[Frame]:
    """The first block of `#N` frame lines at or after `start` (the crashing thread's stack)."""
    out: list[Frame] = []
    for line in lines[start:]:
        m = _ASAN_FRAME.match(line)
        if m is None:
            if out:
                break
            continue
        function = (m.group(2) or "").strip()
        location = m.group(3).strip("()")
        out.append(Frame(function, location))
        if len(out) >= _MAX_FRAMES:
            break
    return out


def parse_sanitizer(text: str) -> Optional[SanitizerReport]:
    """The last sanitizer report in a controller's output, or None when there is none."""
    lines = text.splitlines()
    start = None
    tool = error_type = ""
    ubsan: Optional[tuple[int, str]] = None     # the last UBSan error: (line, type)
    for n, line in enumerate(lines):
        m = _ERROR.search(line)
        if m:
            start, tool, error_type = n, _TOOL_NAMES.get(m.group(1), m.group(1)), m.group(2)
            continue
        u = _UBSAN.match(line)
        if u:
            start, tool = n, "ubsan"
            error_type = _ubsan_type(u.group(2))
            ubsan = (n, error_type)
    if start is None:
        return None
    frames = _frames(lines, start + 1)
    if error_type == "ABRT" and ubsan is not None and any(f.function.startswith("__ubsan") for f in frames):
        # ASan's report of the abort a UBSan error made (abort_on_error with handle_abort, the
        # fuzzer's defaults): the bug is that error.
        (start, error_type), tool = ubsan, "ubsan"
        frames = _frames(lines, start + 1)
    summary = lines[start].strip()[:500] if tool == "ubsan" else ""
    for n in range(start, len(lines)):
        if _SUMMARY.match(lines[n]):
            summary = lines[n].strip()[:500]
            break
        if n > start and (_ERROR.search(lines[n]) or _UBSAN.match(lines[n])):
            break                                # the next report's
    if tool == "lsan" and error_type == "detected":
        error_type = "memory-leak"
    return SanitizerReport(tool, error_type, summary, frames)


def parse_python_traceback(text: str) -> Optional[SanitizerReport]:
    """The last Python traceback in a controller's output (a controller in Python that died of an
    exception), as a report of tool "python": the exception's type, and its frames innermost first
    (the standard library's left out), so that two exceptions are two bugs."""
    lines = text.splitlines()
    starts = [n for n, line in enumerate(lines) if line.startswith("Traceback (most recent call last):")]
    if not starts:
        return None
    frames: list[Frame] = []
    for n in range(starts[-1] + 1, len(lines)):
        line = lines[n]
        m = _PY_FRAME.match(line)
        if m:
            if not _PY_LIBRARY.search(m.group(1)):
                frames.append(Frame(m.group(3), f"{m.group(1)}:{m.group(2)}"))
            continue
        if line.startswith(" "):
            continue
        error = _PY_ERROR.match(line)
        if error is None:
            return None
        frames.reverse()
        return SanitizerReport("python", error.group(1).rsplit(".", 1)[-1], line.strip()[:500], frames[:_MAX_FRAMES])
    return None


def _ubsan_type(message: str) -> str:
    """A stable name for a UBSan runtime error (its message carries values that change)."""
    known = (("signed integer overflow", "signed-integer-overflow"), ("division by zero", "integer-divide-by-zero"),
             ("shift exponent", "shift-exponent"), ("left shift", "shift-base"), ("out of bounds", "bounds"),
             ("null pointer", "null"), ("misaligned", "alignment"), ("load of value", "invalid-value"),
             ("unsigned integer overflow", "unsigned-integer-overflow"))
    for needle, name in known:
        if needle in message:
            return name
    return re.sub(r"[^a-z]+", "-", message.split(":")[0].lower()).strip("-")[:40] or "undefined-behavior"


def parse_assertion(text: str) -> Optional[Frame]:
    """The site of the last failed assertion glibc reported in the output, as a frame."""
    for line in reversed(text.splitlines()):
        m = _ASSERTION.match(line.strip())
        if m:
            return Frame(m.group(3)[:200], f"{m.group(1)}:{m.group(2)}")
    return None


def parse_gdb_backtrace(text: str) -> list[Frame]:
    """Frames of `gdb -batch -ex bt` output."""
    out: list[Frame] = []
    for line in text.splitlines():
        m = _GDB_FRAME.match(line.strip())
        if m and (not out or int(m.group(1)) == len(out)):
            out.append(Frame(m.group(2), m.group(3) or ""))
            if len(out) >= _MAX_FRAMES:
                break
    return out


@dataclass
class Crash:
    """One death of the supervised controller, and its evidence."""

    returncode: int
    output: bytes = b""
    sanitizer: Optional[SanitizerReport] = None
    core: Optional[str] = None            # where the core file is now (moved next to the findings)
    core_missing: Optional[str] = None    # why there is none
    backtrace: list[Frame] = field(default_factory=list)
    backtrace_text: str = ""
    assertion: Optional[Frame] = None     # glibc's failed assertion: its site, where no stack names it
    stack_missing: Optional[str] = None   # why a crash by a signal has no stack (its signature is the signal's)

    @property
    def how(self) -> dict[str, Any]:
        return ended(self.returncode)

    def stack(self) -> list[Frame]:
        """The crashing thread's frames: the sanitizer's, else gdb's, else a failed assertion's site."""
        if self.sanitizer and self.sanitizer.frames:
            return self.sanitizer.frames
        return self.backtrace or ([self.assertion] if self.assertion else [])

    def own_frames(self, count: int = TOP_FRAMES) -> list[Frame]:
        return [f for f in self.stack() if f.own()][:count]

    def ending(self) -> str:
        how = self.how
        return how["signal_name"] if "signal" in how else f"exit {how['exit_code']}"

    def signature(self) -> str:
        """Signal or exit code, sanitizer error type, the top frames of the target's own code, the
        first with its file and line (`on_vrci@ctl.c:96`): two assertions, two bad reads in one
        function are two bugs; the callers by name only, as a line of theirs moves with any edit."""
        parts = [self.ending()]
        if self.sanitizer is not None:
            parts.append(f"{self.sanitizer.tool}:{self.sanitizer.error_type}")
        frames = self.own_frames()
        parts += [f"{f.function}@{f.place()}" if n == 0 and f.place() else f.function for n, f in enumerate(frames)]
        return " ".join(parts)

    def same_bug(self, stored: Any) -> bool:
        """Whether a finding's `crash` object is this crash's bug. One written by the rules of
        today compares signatures; an older one what both rules give alike: how it ended, the
        sanitizer's error type (an old ASan ABRT may be a UBSan error's abort) and its top frames,
        those today's rules call the controller's own. Not an object of either form: False."""
        if not isinstance(stored, dict):
            return False
        if self.signal_only(stored):
            return {k: stored.get(k) for k in self.how} == self.how and self.sanitizer is None \
                and stored.get("sanitizer") is None
        if stored.get("signature_version") == SIGNATURE_VERSION:
            theirs = stored.get("signature")
            # (the crash site's line may have moved with an edit of the controller: site_moved says so)
            return isinstance(theirs, str) and _SITE.sub("", theirs) == _SITE.sub("", self.signature())
        if {k: stored.get(k) for k in self.how} != self.how:
            return False
        tool = stored.get("sanitizer")
        if isinstance(tool, dict) != (self.sanitizer is not None):
            return False
        frames = stored.get("top_frames")
        if isinstance(tool, dict):
            old = (tool.get("tool"), tool.get("error_type"))
            new = (self.sanitizer.tool, self.sanitizer.error_type) if self.sanitizer else None
            if old != new and not (old == ("asan", "ABRT") and new and new[0] == "ubsan"):
                return False
            if tool.get("frames"):
                frames = tool["frames"]      # the whole stack, re-judged (top_frames was cut at 3)
        if not isinstance(frames, list) or not all(
                isinstance(f, dict) and isinstance(f.get("function"), str) and isinstance(f.get("location", ""), str)
                for f in frames):
            return False
        old_own = [f["function"] for f in frames if Frame(f["function"], f.get("location", "")).own()][:TOP_FRAMES]
        own = [f.function for f in self.own_frames()]
        return old_own == own[:len(old_own)] and bool(old_own) == bool(own)

    def signal_only(self, stored: Any) -> bool:
        """Whether this crash or a finding's `crash` is one by a signal with no stack of the
        controller's: it cannot be told from another bug of that signal, which is all to compare."""
        return ("signal" in self.how and self.sanitizer is None and not self.own_frames()) or _stackless(stored)

    def site_moved(self, stored: Any) -> bool:
        """The same bug as a finding's `crash` of today's rules, with its crash site at another line."""
        return self.same_bug(stored) and stored.get("signature_version") == SIGNATURE_VERSION \
            and stored.get("signature") != self.signature() and not self.signal_only(stored)

    def headline(self) -> str:
        """`crash SIGSEGV in dispatch_state (controller.c:141)`, with the sanitizer's error type."""
        text = f"crash {self.ending()}"
        if self.sanitizer is not None:
            text += f" {self.sanitizer.error_type}"
        top = self.own_frames(1)
        if top:
            text += f" in {top[0].short()}"
        elif self.stack_missing:
            text += " (no stack: every such crash is one finding, though it may be several bugs)"
        return text


def _stackless(stored: Any) -> bool:
    """A finding's `crash` of a signal with no stack of the controller's (nor a sanitizer's report)."""
    return isinstance(stored, dict) and "signal" in stored and stored.get("sanitizer") is None \
        and not stored.get("top_frames")
