"""One monitoring run: bytes from a source, through the stream reader and the intake into the
analysis; each second of capture time the live view (dashboard, --json-lines), findings as they
come, evidence around alarms; at the end the report of `analyze`.

The time is the capture's: the timestamps of the packets, and between packets the last one's
plus the time waited since it arrived (so that a silent link is seen to be silent while it is);
with `--realtime` the capture's timeline is laid on the wall clock.
"""
from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import IO, Optional

from .. import closedpipe
from ..analysis.commands import Retiring
from ..analysis.incremental import Analysis
from ..errors import CliError
from ..analysis.periodic import SpilledFloats
from ..capture.spool import named
from ..timefmt import utc_iso
from ..capture.stream import StreamReader
from . import dashboard as dash
from .evidence import Evidence
from .intake import Intake
from .live import Live, finding, item
from .outlet import Outlet
from .sources import Source
from .stopping import Signals, hung_up

TICK_S = 0.1                 # the loop looks at the time at least this often
DRAW_S = 1.0
DECIDE_WAIT_S = 1.0          # a live link: the CRC variant is chosen after this at the latest
LATE_S = 2.0                 # a live link: no packet comes this much later than its timestamp
FINDINGS_SHOWN = 200
UNWRITABLE = (OSError, closedpipe.StdoutUnwritable)   # standard output's write errors (cli.py wraps it)
RATE_LIMITED = {"lost", "illegal", "restarts", "failed"}   # at most one line per second per sender
LIMITED_MAX = 4096           # (rule, sender) pairs the rate limit keeps; beyond, the old ones' lines are told
UNSAID_MAX = 100             # warnings kept for after the dashboard (a disk full for days fails every window)
END_WAIT_S = 5.0             # at the end, standard output's reader has this long to take what waits
REST_S = 2.0                 # at the end, dumpcap has this long to give its last blocks (what it dropped)
SENDERS_SAID = 10_000        # senders heard: said at this many, and at each tenfold (docs/monitor.md, "Memory")
STALL_S = 60.0               # a followed file not grown this long is said to have stopped (tcpdump without
                             # -U writes a block of 64 KiB: a minute of one BU and its controller)


@dataclass
class Settings:
    name: str                           # the capture's name in the report
    port: int
    crc: str
    crc_order: str
    realtime: bool = False
    live: bool = False                  # a live link (dumpcap, stdin): wall clock matters
    duration: Optional[float] = None
    dashboard: bool = False
    lines: bool = True                  # one line per finding (no dashboard) ...
    lines_to_stderr: bool = False       # ... on stdout, or on stderr where a report goes to stdout
    json_lines: Optional[IO[str]] = None
    evidence: Optional[Evidence] = None


class Session:
    def __init__(self, source: Source, opt, cfg: Settings, signals: Optional[Signals] = None) -> None:
        self.source, self.opt, self.cfg = source, opt, cfg
        self.signals = signals or Signals()      # (entered by the caller, before the source started)
        self.spool = tempfile.TemporaryFile(prefix="vm110-monitor-")   # noqa: SIM115 -- the session owns it; close()
        spool = self.spool
        self.analysis = Analysis(opt, floats=lambda: SpilledFloats(spool), spool=spool)
        self.command_spool = tempfile.TemporaryFile(prefix="vm110-monitor-")   # noqa: SIM115 -- as the spool
        self.retiring = Retiring(self.analysis.tracker, self.command_spool)
        self.fed_until = -math.inf            # the latest time the analysis has been fed
        self.reader = StreamReader(named(cfg.name))
        self.intake = Intake(cfg.name, cfg.port, cfg.crc, cfg.crc_order, self)
        self.intake.got.on_illegal = self._illegal
        self.live = Live(self.analysis, opt, self.emit, self.intake.got.sources)
        self.ticking: Optional[float] = None   # the time of the live view's judgement under way
        self.findings: collections.deque = collections.deque(maxlen=FINDINGS_SHOWN)
        self.active: dict = {}
        self.limited: dict = {}             # (rule, sender) -> (time of last line, suppressed since)
        self.counts: collections.Counter = collections.Counter()
        self.out = Outlet(sys.stdout, self._left_out)   # lines, JSON lines, the dashboard: never waited on
        self.board = dash.Dashboard(self.out) if cfg.dashboard else None
        self.last_ts: Optional[float] = None
        self.last_mono = 0.0
        self.first_mono: Optional[float] = None
        self.first_ts: Optional[float] = None
        self.second: Optional[int] = None   # the capture second being counted
        self.frames_at_second = 0
        self.done = 0                       # frames processed (a paced replay parses ahead)
        self.rate = 0.0
        self.next_draw = 0.0
        self.ended = False                  # the run ended itself (--duration in a replay, stdout gone)
        self.input_ended = False
        self.failure: Optional[str] = None
        self.no_capture = False                # the input ended before a capture header was whole
        self.unsaid: list[str] = []            # warnings kept from the dashboard's screen till its end
        self.unsaid_more = 0                   # ... and those beyond UNSAID_MAX, counted
        self.hung_up = False                   # the terminal hung up: the summary goes to standard error
        self.stalled = False                   # the followed file has not grown for STALL_S (said)
        self.senders_said = SENDERS_SAID       # the next number of senders heard that is said
        if cfg.evidence is not None:
            cfg.evidence.warn = self.warn

    # -- the analysis sees the intake's records through here -------------------------------------
    def feed(self, rec, sources) -> None:
        self.analysis.feed(rec, sources)
        if len(rec):
            self.fed_until = max(self.fed_until, float(rec["ts"].max()))

    def report_state(self):
        """The Collected to build the report from (retired commands back in place)."""
        self.retiring.restore()
        return self.intake.got

    # -- time ----------------------------------------------------------------------------------
    def now(self) -> Optional[float]:
        if self.last_ts is None:
            return None
        mono = time.monotonic()
        if self.cfg.realtime and self.first_mono is not None and self.first_ts is not None:
            return max(self.last_ts, self.first_ts + (mono - self.first_mono))
        if not self.cfg.live:
            # A file read as fast as it goes: its time is the capture's, and waiting at its end
            # is not silence on the link (a growing file's watchdog comes with its next packet).
            return self.last_ts
        return self.last_ts + (mono - self.last_mono)

    # -- the loop ------------------------------------------------------------------------------
    def run(self) -> None:
        started = time.monotonic()
        deadline = None if self.cfg.duration is None else started + self.cfg.duration
        self.deadline = deadline
        try:
            while not self.stop:
                data = self.source.read(TICK_S)
                if data is None:
                    self.input_ended = not self.stop
                    self.failure = self.source.failure()
                    break
                if data:
                    self._packets(self.reader.feed(data))
                elif self.intake.deciding and self.first_mono is not None:
                    self.intake.decide()           # the input is idle: choose from what came
                    self._flush()
                if self.reader.stopped:
                    break
                self._still()
                self._periodic()
                if deadline is not None and time.monotonic() >= deadline:
                    break
        except CliError as exc:          # unreadable input (not a capture, a read error): said at the end
            self.failure = str(exc)
        except KeyboardInterrupt:         # a second Ctrl-C: leave the terminal as it was
            if self.board is not None:
                with contextlib.suppress(*UNWRITABLE):
                    self.board.close()
                    self.out.flush(TICK_S)
            raise
        self._end()

    @property
    def stop(self) -> bool:
        """The run is to end: a signal asked (Ctrl-C, SIGTERM, SIGHUP), or the run itself."""
        return self.ended or self.signals.asked is not None

    def _packets(self, packets: list) -> None:
        intake, evidence, reader = self.intake, self.cfg.evidence, self.reader
        for ts, frame, link, data, dgram in packets:
            if self.first_mono is None:
                self.first_mono, self.first_ts = time.monotonic(), ts
                if evidence is not None:
                    evidence.ts_digits = reader.ts_digits
            if self.cfg.realtime:
                self._pace(ts)
            second = math.floor(ts) if math.isfinite(ts) else None
            if self.second is None:
                self.second = second
            elif second is not None and second > self.second:
                self._second(ts, second)
            self.last_ts = ts           # the last record's own time: a step back is no silence
            self.last_mono = time.monotonic()
            self.done = frame
            if evidence is not None:
                evidence.frame(ts, frame, link, data)
            if dgram is not None:
                src, sport, dport, payload = dgram
                intake.datagram(reader, ts, src, sport, dport, payload, frame)
        self._flush()

    def _pace(self, ts: float) -> None:
        """--realtime: wait until the packet is due on the capture's timeline laid on the clock.
        Once the run is to end, the packets already read (a small read's worth) go on unpaced, so
        that the report counts exactly what was judged."""
        assert self.first_mono is not None and self.first_ts is not None
        while not self.stop:
            wait = self.first_mono + (ts - self.first_ts) - time.monotonic()
            if wait <= 0:
                return
            time.sleep(min(wait, TICK_S))
            self._flush()
            self._periodic()
            if self.deadline is not None and time.monotonic() >= self.deadline:
                self.ended = True

    def _flush(self) -> None:
        """The analysis gets the records gathered (a chunk's worth: its cost is per batch)."""
        if not self.intake.deciding:
            self.intake.got.flush()
            self._live()

    def _live(self) -> None:
        """The live view gets the legal packets so far (it is cheap per packet)."""
        rows = self.intake.got.live
        if rows and not self.intake.deciding:
            self.live.feed(rows)
            rows.clear()

    def _second(self, ts: float, second: int) -> None:
        """Capture second `self.second` ended (the packet at `ts` begins a later one). The analysis
        gets that second's records first: a file read faster than real time comes in reads of
        many seconds, and its findings are told in their second, not at the read's end."""
        self._flush()
        self._tick(ts)
        self.live.close_second()
        # What is finished by the time every event before is applied stays finished (asked only
        # with commands to retire; a sender stuck on one serial is never all decided).
        retiring = self.retiring
        if any(retiring.pending[code] or seen > retiring.seen[code] for code, seen in self.live.cmd_seen.items()):
            retiring.retire(min(self.fed_until, self.analysis.applied_until()), self.live.cmd_seen)
        frames = self.done
        self.rate = float(frames - self.frames_at_second) / max(1, second - (self.second or second))
        self.frames_at_second = frames
        self.second = second
        if len(self.limited) > LIMITED_MAX:     # (many senders: spoofed, or a restart every few seconds)
            self._held_back(older_than=ts - 1.0)
        heard = len(self.analysis.senders)
        if heard >= self.senders_said:           # (each is kept to the end, for the report: said, not hidden)
            while self.senders_said <= heard:
                self.senders_said *= 10
            self.warn(f"{heard} senders heard (an address, port and origin each: a fuzzer, spoofed packets, or a "
                      "device on a new port for every packet?): each is kept for the report, those heard least "
                      "recently in a temporary file, some 4 kB of disk each (docs/monitor.md, \"Memory for long "
                      "runs\")")
        if self.cfg.json_lines is not None:
            self._write_line(self.snapshot(float(second)))
        if self.cfg.evidence is not None:
            self.cfg.evidence.tick(ts)

    def _periodic(self) -> None:
        try:
            self.out.flush()                # (what waits for a reader that stalled and goes on)
        except UNWRITABLE as exc:
            self._stdout_failed(exc)
        mono = time.monotonic()
        if self.intake.deciding and self.first_mono is not None and (self.cfg.live or self.cfg.realtime) \
                and mono - self.first_mono >= DECIDE_WAIT_S:
            self.intake.decide()
            self._flush()
        now = self.now()
        if now is not None and not self.intake.deciding:
            if self.cfg.live or self.cfg.realtime:
                # (the analysis clock moves with packets: on a silent link its waits end on this one)
                self.analysis.advance(now - LATE_S)
            self._tick(now)
            second = math.floor(now) if math.isfinite(now) else None
            if second is not None and self.second is not None and second > self.second:
                self._second(now, second)
            if self.cfg.evidence is not None:
                self.cfg.evidence.tick(now)
        if self.board is not None and mono >= self.next_draw:
            self.next_draw = mono + DRAW_S
            self.draw("input stalled" if self.stalled else "running")

    def _still(self) -> None:
        """A followed file that stopped growing is said to have (its writer may have died: else the
        watch would wait in silence for ever), with a record it ends in the middle of; and when it
        grows again. On standard error, in --json-lines (`"type": "input"`) and the dashboard's status."""
        quiet = self.source.quiet()
        if quiet is None or (quiet >= STALL_S) == self.stalled:
            return
        self.stalled = not self.stalled
        if self.stalled:
            cut = f"; it ends in {self._cut()}" if self.reader.buf and not self.reader.stopped else ""
            message = f"{self.cfg.name} has not grown for {quiet:.0f} s (its writer stopped?){cut}"
        else:
            message = f"{self.cfg.name} grows again"
        if self.cfg.json_lines is not None:
            self._write_line({"type": "input", "event": "stalled" if self.stalled else "growing",
                              "message": message, "at": self.now()})
        self.warn(message)

    def _cut(self) -> str:
        """The record (or the capture's header) the input ends in the middle of."""
        what = "a record" if self.reader.bytes_read else "the capture's header"
        return f"{what} cut short at byte {self.reader.bytes_read} ({len(self.reader.buf)} bytes)"

    # -- findings ------------------------------------------------------------------------------
    def _illegal(self, frame: int, ts: float, src: str, ptype: str, reasons: list) -> None:
        self.emit(finding("illegal", "found", item(frame, ts, src, type=ptype, reasons=list(reasons)),
                          f"illegal {ptype or 'packet'}: {', '.join(reasons)}"))

    def _tick(self, now: float, final: bool = False) -> None:
        """The live view judges at `now`: what it tells then, it tells at `now` (self.now() may
        lag the packet that began a new second, timed by the kernel before we read it)."""
        self.ticking = now
        try:
            self.live.tick(now, final)
        finally:
            self.ticking = None

    def emit(self, f: dict) -> None:
        rule, sender = f["rule"], f.get("sender")
        f["at"] = self.now() if self.ticking is None else self.ticking   # the capture time it was told at
        self.counts[rule] += 1
        if rule == "watchdog":
            if f["event"] == "raised":
                self.active[(rule, sender, f["item"].get("type"))] = f
            else:
                self.active.pop((rule, sender, f["item"].get("type")), None)
        if rule in RATE_LIMITED:
            last, suppressed = self.limited.get((rule, sender), (None, 0))
            if last is not None and 0 <= f["time"] - last < 1.0:
                self.limited[(rule, sender)] = (last, suppressed + 1)
                return
            if suppressed:
                f["suppressed_before"] = suppressed
            self.limited[(rule, sender)] = (f["time"], 0)
        self.findings.append(f)
        if self.cfg.json_lines is not None:
            self._write_line(f)
        if self.cfg.lines and self.board is None:
            self._say(dash.finding_line(f))      # (its display filter included)
        if self.cfg.evidence is not None and f["severity"] == "error" and f["event"] in ("raised", "found"):
            now = self.now()
            self.cfg.evidence.alarm(f, f["time"] if now is None else max(now, f["time"]))

    def _held_back(self, older_than: Optional[float] = None) -> None:
        """What the rate limit held back after a sender's last line of a rule: one line each, so
        that the lines and their `suppressed_before` add up to every finding. `older_than`: only of
        the pairs whose last line came before that time, which the limit then forgets."""
        at = self.now()
        for (rule, sender), (last, suppressed) in list(self.limited.items()):
            if older_than is not None:
                if last is None or last >= older_than:
                    continue
                del self.limited[(rule, sender)]
            if not suppressed:
                continue
            if older_than is None:
                self.limited[(rule, sender)] = (None, 0)
            if self.cfg.json_lines is not None:
                self._write_line({"type": "suppressed", "rule": rule, "sender": sender, "count": suppressed,
                                  "at": at})
            if self.cfg.lines and self.board is None:
                who = f" of {dash.short(sender)}" if sender else ""
                when = "-" if at is None else utc_iso(at)
                self._say(f"{when} {rule}: {suppressed} more line{'s' if suppressed > 1 else ''}{who} "
                          "not shown (at most one a second)")

    def warn(self, message: str) -> None:
        """A trouble of our own output (the watch goes on): on standard error at once, or after the
        dashboard, which it would garble."""
        if self.board is not None and self.board.on:
            if len(self.unsaid) < UNSAID_MAX:
                self.unsaid.append(message)
            else:
                self.unsaid_more += 1
        else:
            try:
                print(f"vm110 monitor: {message}", file=sys.stderr, flush=True)
            except OSError:                 # its terminal hung up: nowhere to say it
                self._hang_up()

    def _say(self, line: str) -> None:
        """A finding line: on stdout, or on stderr where a report goes to stdout."""
        if self.cfg.lines_to_stderr:
            try:
                print(line, flush=True, file=sys.stderr)
            except OSError:                # (its terminal hung up: the end's check says so)
                self.cfg.lines = False
            return
        try:
            self.out.write(line + "\n")
        except UNWRITABLE as exc:
            self._stdout_failed(exc)

    def _stdout_failed(self, exc: BaseException) -> None:
        """Standard output cannot be written any more. Its reader went away (`| head -1`) or its
        terminal hung up (the SSH session closed): the run ends as at Ctrl-C, the report files and
        the --fail-on exit code still follow (cli.py, closedpipe), the summary of a hung-up terminal
        on standard error (a log, when it goes to one). It is full (a disk): said once, and what
        went there ends; the watch goes on, as for --json-lines, and the exit code is 2."""
        gone = isinstance(exc, BrokenPipeError) or self._hang_up()
        if not gone and closedpipe.said.unwritable is None:
            closedpipe.said.unwritable = getattr(exc, "strerror", None) or str(exc)
            self.warn(f"cannot write standard output: {closedpipe.said.unwritable}")
        closedpipe.silence_stdout()
        self.out.drop()
        if not self.cfg.lines_to_stderr:
            self.cfg.lines = False
        if self.cfg.json_lines is sys.stdout:
            self.cfg.json_lines = None
        self.board = None                   # (nothing more drawn, nor the screen left: it is gone)
        self.ended = self.ended or gone

    def _hang_up(self) -> bool:
        """Whether the terminal hung up: standard output and error on it go to /dev/null from now
        on, so that nothing fails writing to it (a traceback at the end, the report lost)."""
        for stream in (sys.stdout, sys.stderr):
            if hung_up(stream):
                closedpipe.silence_stdout(stream)
                self.hung_up = True
        return self.hung_up

    def _write_line(self, obj: dict) -> None:
        out = self.cfg.json_lines
        assert out is not None
        try:
            text = json.dumps(obj, allow_nan=False, default=_plain)
        except ValueError:                 # inf/nan from damaged timestamps: as null
            text = json.dumps(_finite(obj), default=_plain)
        before = None
        try:
            if out is sys.stdout:
                self.out.write(text + "\n")
            else:
                before = _size(out)
                out.write(text + "\n")
                out.flush()
        except UNWRITABLE as exc:
            if out is sys.stdout:
                self._stdout_failed(exc)
                return
            assert isinstance(exc, OSError)
            # A full disk: the lines end, the watch goes on. The line written in part is taken back:
            # a reader of the file (jq, a log shipper) gets whole lines only.
            self.cfg.json_lines = None
            _close_at(out, before)
            self.warn(f"--json-lines {out.name}: cannot write: {exc.strerror or exc}; no more lines are written")

    # -- views ---------------------------------------------------------------------------------
    def snapshot(self, now: Optional[float]) -> dict:
        got = self.intake.got
        view = self.live.view(now if now is not None else 0.0)
        return {"type": "snapshot", "time": now, "packets": self.done, "rate_pps": self.rate,
                "eglink_packets": got.eglink, "illegal": got.illegal,
                "alarms": [a["item"] | {"rule": a["rule"]} for a in self.active.values()],
                "findings": dict(sorted(self.counts.items())), **view,
                "senders_heard": len(self.analysis.senders), "memory_kb": rss_kb(),
                "evidence_files": len(self.cfg.evidence.written) if self.cfg.evidence else None,
                "evidence_over_limit": self.cfg.evidence.over_limit if self.cfg.evidence else None}

    def draw(self, status: str) -> None:
        assert self.board is not None
        if self.out.busy:                 # (the last screen is not shown yet: no stale ones queued behind it)
            return
        now = self.now()
        got = self.intake.got
        header = {"source": self.cfg.name, "now": now, "status": status, "packets": self.done,
                  "rate": self.rate, "eglink": got.eglink, "illegal": got.illegal,
                  "alarms": [a["item"] | {"rule": a["rule"]} for a in self.active.values()]}
        width, height = self.board.size()
        try:
            self.board.draw(dash.render(header, self.live.view(now or 0.0), list(self.findings), width, height))
        except UNWRITABLE as exc:
            self._stdout_failed(exc)

    # -- the end -------------------------------------------------------------------------------
    def _end(self) -> None:
        self.intake.decide()
        try:
            if self.input_ended:
                self.reader.close()
            else:                              # stopped by us: a record still arriving is not damage
                # (dumpcap's last blocks: its statistics say what it dropped; after a failure, input that
                # is no capture say, what the reader holds is no capture header still being written)
                if self.failure is None:
                    self._packets(self.reader.feed(self.source.rest(REST_S)))
                    if self.reader.buf and self.source.quiet() is not None and not self.reader.stopped:
                        self.warn(f"{self.cfg.name}: {self._cut()}, not read (still being written, or its writer "
                                  "stopped there)")
                self.reader.buf = b""
        except CliError as exc:            # not a capture at all: said at the end
            self.failure = self.failure or str(exc)
            self.no_capture = True
        self._flush()
        # A live link still open when we stop was watched until now, not until its last packet: one
        # that died meanwhile is silent to the end, in the last judgement and in the report. An
        # input that ended (a file, a pipe closed) ends at its last record, as in analyze.
        end = self.now() if self.cfg.live and not self.input_ended else self.last_ts
        self.analysis.finish()      # as the report does: a sender still choosing its serial scope chooses now
        if end is not None:
            self._tick(end, final=True)        # what the end of the input can tell
        self._held_back()
        self.intake.sync(self.reader)
        got = self.intake.got
        if end is not None and got.last_ts is not None and end > got.last_ts:
            # (the span watched too: else the report says records out of time order, its duration short)
            got.last_ts, got.latest_ts = end, max(got.latest_ts, end)
        got.analysis = self.analysis     # the report is built from it (report.build)
        if self.cfg.evidence is not None:
            self.cfg.evidence.tick(None)
        self._hang_up()                      # (SIGHUP: the SSH session closed, nothing failed yet)
        if self.board is not None:
            try:
                self.board.close()
            except UNWRITABLE as exc:
                self._stdout_failed(exc)
        self._caught_up()
        for message in self.unsaid:
            print(f"vm110 monitor: {message}", file=sys.stderr)
        if self.unsaid_more:
            print(f"vm110 monitor: and {self.unsaid_more} more warning(s), not kept", file=sys.stderr)

    def _left_out(self, count: int) -> str:
        """What the reader of standard output is told of the lines it missed while it read nothing."""
        at = self.now()
        if self.cfg.json_lines is sys.stdout:
            return json.dumps({"type": "left_out", "count": count, "at": at}) + "\n"
        return (f"{'-' if at is None else utc_iso(at)} standard output was not read: {count} "
                f"line{'s' if count > 1 else ''} left out\n")

    def _caught_up(self) -> None:
        """The reader of standard output takes what waits, or, still stalled after END_WAIT_S, is
        left as one gone away (`| head`): the summary, report files and exit code follow, not a
        hang until it reads."""
        try:
            if self.out.flush(END_WAIT_S):
                return
        except UNWRITABLE as exc:
            self._stdout_failed(exc)
            return
        shared = _same_file(sys.stdout, sys.stderr)      # (`2>&1 | less`: the warning would wait too)
        closedpipe.silence_stdout()
        if shared:
            closedpipe.silence_stdout(sys.stderr)
        self.out.drop()
        self.warn(f"standard output not read for {END_WAIT_S:g} s: the rest of it is left out")

    def close(self) -> None:
        self.spool.close()
        self.command_spool.close()


def _size(out: IO[str]) -> Optional[int]:
    """The size of the file `out` writes to (appends: where its next line begins), None without one."""
    try:
        return os.fstat(out.fileno()).st_size
    except (AttributeError, ValueError, OSError):
        return None


def _close_at(out: IO[str], size: Optional[int]) -> None:
    """Close `out`, its file cut back to `size` bytes (None: as it is). Its buffer, written at the
    close if it can be, is cut too; a file cut shorter meanwhile (logrotate's copytruncate) is left."""
    fd = None
    with contextlib.suppress(AttributeError, ValueError, OSError):
        fd = os.dup(out.fileno())
    with contextlib.suppress(OSError):
        out.close()
    if fd is None:
        return
    with contextlib.suppress(OSError):
        if size is not None and os.fstat(fd).st_size > size:
            os.ftruncate(fd, size)
    os.close(fd)


def _same_file(a: IO[str], b: IO[str]) -> bool:
    try:
        x, y = os.fstat(a.fileno()), os.fstat(b.fileno())
    except (AttributeError, ValueError, OSError):
        return False
    return (x.st_dev, x.st_ino) == (y.st_dev, y.st_ino)


def rss_kb() -> Optional[int]:
    """Resident memory of this process (Linux), in KiB."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024
    except (OSError, ValueError, IndexError):
        return None


def _plain(obj):
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, (set, tuple)):
        return list(obj)
    return str(obj)


def _finite(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj
