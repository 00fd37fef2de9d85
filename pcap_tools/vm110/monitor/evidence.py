"""Evidence around each alarm: the frames from `before` seconds before it to `after` seconds
after, as a pcapng named by the alarm's time and rule, with a JSON beside it (the finding, its
item, the options, which frames of the capture the file holds).

Memory is a ring of the recent frames, bounded by time (`before`) and by RING_BYTES, and the
windows still collecting (at most MAX_OPEN, each bounded by WINDOW_BYTES); an alarm while a
window of the same rule and sender is still collecting joins that window instead of opening
another, extending it up to MAX_SPAN_S in all. Files are written atomically (vm110.fileio) and
never over an existing file. A window that cannot be written (disk full, folder gone) is counted
and told to `warn`, and the monitoring goes on: evidence is a by-product of the watch.

Disk: this run's files are bounded by `max_files` windows and `max_mib` MiB in all. The first
evidence is kept: the window that would pass a limit is not written, nor any after it (told to
`warn` once, its alarms and those after counted in `over_limit`), and nothing is ever deleted.
"""
from __future__ import annotations

import collections
import json
import os
import struct
from dataclasses import dataclass, field
from typing import Callable, Optional

from ..capture.writer import build_block, build_option
from ..analysis.findings import frame_filter
from ..errors import CliError
from ..fileio import write_bytes, write_text
from ..timefmt import utc_iso

RING_BYTES = 64 << 20
WINDOW_BYTES = 64 << 20
MAX_OPEN = 64
MAX_SPAN_S = 120.0              # a window that alarms keep extending stops growing at this length
MAX_NUMBERS = 10_000           # frame numbers listed in the JSON (else first and last only)
_SHB = build_block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))


def _idb(link: int, digits: int) -> bytes:
    # Link type, snaplen 0 (no limit), option if_tsresol (10^-digits s), end of options.
    return build_block(1, struct.pack("<HHI", link, 0, 0) + build_option(9, bytes([digits])) + struct.pack("<HH", 0, 0))


def _epb(iface: int, ticks: int, frame: bytes) -> bytes:
    head = struct.pack("<IIIII", iface, (ticks >> 32) & 0xFFFFFFFF, ticks & 0xFFFFFFFF, len(frame), len(frame))
    return build_block(6, head + frame + bytes(-len(frame) % 4))


def pcapng(frames: list[tuple], digits: int) -> bytes:
    """A pcapng file of (ts, frame number, link type, frame bytes), its times in units of 10^-digits s:
    those of the capture they come from, which a float of the epoch holds to a microsecond exactly,
    not to a nanosecond (a time written in ns would not be the capture's own)."""
    links: dict[int, int] = {}
    for _, _, link, _ in frames:
        links.setdefault(link, len(links))
    unit = 10 ** digits
    parts = [_SHB, *(_idb(link, digits) for link in links)]
    parts += [_epb(links[link], round(ts * unit), data) for ts, _, link, data in frames]
    return b"".join(parts)


@dataclass
class Window:
    rule: str
    sender: Optional[str]
    time: float                     # the alarm's capture time
    start: float
    end: float
    findings: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    size: int = 0
    cut: bool = False               # WINDOW_BYTES reached: later frames left out


class Evidence:
    """Writes evidence files into `folder` (an existing directory)."""

    def __init__(self, folder: str, before: float, after: float, options: dict, max_files: int,
                 max_mib: float) -> None:
        self.folder, self.before, self.after, self.options = folder, before, after, options
        self.max_files, self.max_mib = max_files, max_mib
        self.ts_digits = 9          # the input's timestamp resolution (the session sets it)
        self.ring: collections.deque = collections.deque()
        self.ring_bytes = 0
        self.open: list[Window] = []
        self.written: list[str] = []
        self.written_bytes = 0
        self.full: Optional[str] = None    # the limit reached (then nothing more is collected)
        self.over_limit = 0                # alarms without evidence for it
        self.skipped = 0                # alarms beyond MAX_OPEN windows
        self.failed = 0                 # windows that could not be written
        self.error: Optional[str] = None   # why the last one could not
        self.warn: Callable[[str], None] = lambda message: None

    def frame(self, ts: float, number: int, link: int, data: bytes) -> None:
        """Every frame of the capture, in order."""
        if self.full is not None:
            return
        entry = (ts, number, link, data)
        self.ring.append(entry)
        self.ring_bytes += len(data)
        horizon = ts - self.before
        ring = self.ring
        while ring and (ring[0][0] < horizon or self.ring_bytes > RING_BYTES):
            self.ring_bytes -= len(ring.popleft()[3])
        for w in self.open:
            if w.start <= ts <= w.end and not w.cut:
                w.frames.append(entry)
                w.size += len(data)
                w.cut = w.size > WINDOW_BYTES

    def alarm(self, finding: dict, now: float) -> None:
        """An alarm raised at capture time `now`: open a window (or join the open one)."""
        if self.full is not None:
            self.over_limit += 1
            return
        for w in self.open:
            if w.rule == finding["rule"] and w.sender == finding.get("sender"):
                w.findings.append(finding)
                span = max(MAX_SPAN_S, self.before + self.after)
                w.end = min(max(w.end, now + self.after), w.start + span)
                return
        if len(self.open) >= MAX_OPEN:
            self.skipped += 1
            return
        w = Window(finding["rule"], finding.get("sender"), now, now - self.before, now + self.after, [finding])
        w.frames = [e for e in self.ring if e[0] >= w.start]
        w.size = sum(len(e[3]) for e in w.frames)
        self.open.append(w)

    def tick(self, now: Optional[float]) -> None:
        """Write the windows complete at `now` (all of them when None: the input ended)."""
        done = [w for w in self.open if now is None or now > w.end]
        if not done:
            return
        self.open = [w for w in self.open if w not in done]
        for w in done:
            try:
                if self.full is None:
                    self._write(w)
            except CliError as exc:
                self.failed += 1
                self.error = str(exc)
                self.warn(f"evidence not written: {exc}")
            if self.full is not None:
                self.over_limit += len(w.findings)
        if self.full is not None:         # (the windows still collecting will not be written either)
            self.over_limit += sum(len(w.findings) for w in self.open)
            self.open = []
            self.ring.clear()
            self.ring_bytes = 0

    def told(self) -> str:
        """The end's line: the files written, and the alarms left without evidence, and why."""
        parts = [f"evidence: {len(self.written)} file(s) in {self.folder}"]
        if self.over_limit:
            parts.append(f"{self.over_limit} alarm(s) without evidence ({self.full} reached)")
        if self.skipped:
            parts.append(f"{self.skipped} alarm(s) without evidence (more than {MAX_OPEN} windows at once)")
        return "; ".join(parts)

    def _write(self, w: Window) -> None:
        """Write the window's files, unless that would pass a limit (then `full` says which)."""
        if len(self.written) >= self.max_files:
            self._reached(f"--evidence-max-files {self.max_files}")
            return
        base = os.path.join(self.folder, f"{_stamp(w.time)}-{w.rule}")
        name, n = base, 1
        while os.path.exists(name + ".pcapng") or os.path.exists(name + ".json"):
            n += 1
            name = f"{base}-{n}"
        frames = [f[1] for f in w.frames]
        meta = {"rule": w.rule, "sender": w.sender, "time": w.time, "window": {"start": w.start, "end": w.end},
                "findings": _in_file(w.findings, frames),
                "frames": {"count": len(frames), "first": frames[0] if frames else None,
                           "last": frames[-1] if frames else None,
                           "numbers": frames if len(frames) <= MAX_NUMBERS else None,
                           "cut_at_bytes": WINDOW_BYTES if w.cut else None},
                "options": self.options}
        data, text = pcapng(w.frames, self.ts_digits), json.dumps(meta, indent=1, default=str) + "\n"
        size = len(data) + len(text.encode())
        if self.written_bytes + size > self.max_mib * (1 << 20):
            self._reached(f"--evidence-max-size {self.max_mib:g} MiB")
            return
        write_bytes(name + ".pcapng", data)
        write_text(name + ".json", text)
        self.written.append(name + ".pcapng")
        self.written_bytes += size

    def _reached(self, limit: str) -> None:
        self.full = limit
        self.warn(f"evidence: {limit} reached in {self.folder}: the first {len(self.written)} window(s) kept, "
                  "no more evidence is written")


def _stamp(t: float) -> str:
    """A file name's time: UTC to the ms (20250615T150652.902Z); the raw seconds (1e+16s) for a
    time no calendar date can hold (a hostile capture's)."""
    iso = utc_iso(t)
    return iso[:23].replace("-", "").replace(":", "") + "Z" if iso.endswith("Z") else f"{t!r}s"


def _in_file(findings: list[dict], numbers: list[int]) -> list[dict]:
    """The findings, each item told where its frames are in the evidence file too: the file
    numbers them 1, 2, ... while a finding's `filter` names the capture's numbers."""
    position = {n: i + 1 for i, n in enumerate(numbers)}
    out = []
    for f in findings:
        item = f["item"]
        here = [position[n] for n in item.get("frames", [item["frame"]]) if n in position]
        told = frame_filter(here) if here else None          # (the item's filter in the file's numbering)
        out.append({**f, "item": {**item, "evidence_frames": here, "evidence_filter": told}})
    return out

