"""Findings on disk: one JSON and one pcap per finding, and `findings.json` for the run."""
from __future__ import annotations

import json
import math
import os
import struct
import time
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Optional

from .. import constants as C
from ..analysis.findings import frame_filter
from ..capture.writer import PcapWriter, UdpFlow
from ..decode import decode
from ..errors import CliError
from ..fileio import atomic_writer, write_bytes, write_text
from ..layers import PAYLOAD_CLASSES
from . import mutate as M
from .evidence import SIGNATURE_VERSION, Crash
from .oracles import ORACLES

SCHEMA = 1
# What a finding file may hold, beyond its types: it is data from anywhere, never trusted.
MAX_FILE = 16 << 20
MAX_STEPS = 64                   # packets a case may send (the longest made here has 20)
# Cases a run keeps for replays: a crash's suspects, and so the cases a finding may play in turn
# (all of them when the budget cut its bisection short)
MAX_CASES = 2000
_MAX_PACKET = 65_507             # the largest UDP payload over IPv4
_MAX_MS = 60_000.0               # delays, pauses and withholding
_RESEND_GAPS = 5                 # a VRCI copy this many resend intervals after the last is a new send
_MAX_INT = (1 << 63) - 1
NO_CASE = "none"                 # the family of a finding that the controller made on its own
_STREAM_FIELDS = frozenset(f.name for f in PAYLOAD_CLASSES[C.PacketType.VRPI].fields_desc)


@dataclass
class Finding:
    oracle: str
    seed: int
    case_index: int
    family: str
    mutation: str                 # what the case did
    detail: str                   # what the oracle saw
    packet_hex: str               # the minimised packet (or the case's packet when it could not be)
    original_hex: str             # the packet as the case sent it
    valid_hex: str                # its valid twin: the minimised packet differs from this
    differences: int              # bytes that differ between packet_hex and valid_hex
    minimised: bool
    steps: list[dict[str, Any]]   # the case for replay: [{"hex", "valid_hex", "delay_ms", "expect_ack"}]
    pause_vrpi_ms: float = 0.0
    withhold_vrai_ms: float = 0.0
    stream: Optional[dict[str, Any]] = None
    settle_ms: float = 0.0
    output_hex: Optional[str] = None     # the controller packet judged (malformed_output)
    target: str = ""
    listen: str = ""
    group: Optional[str] = None
    target_cmd: Optional[str] = None
    time: float = field(default_factory=time.time)
    pcap: str = ""
    schema: int = SCHEMA
    signature: str = ""                  # the bug's: findings with one signature are one bucket
    crash: Optional[dict[str, Any]] = None   # a crash's evidence; its files are named in it
    valid_triggers: bool = False         # the valid twin triggers too: the case's changes are not the cause
    frame: Optional[int] = None          # the case's packet in the pcap (None: not in its window)
    output_frame: Optional[int] = None   # the controller's packet judged, in the pcap
    display_filter: Optional[str] = None  # those frames, for Wireshark or tshark -Y
    # A finding that needs several cases played in turn (bisected from a crash): each case's index,
    # mutation, number of `steps` and what the base unit did meanwhile (its stream, pause, withholding).
    cases: Optional[list[dict[str, Any]]] = None
    memory: Optional[dict[str, Any]] = None  # the memory oracle's evidence: RSS series, growth per case, rerun
    # How often the base unit resent an unacknowledged VRCI (its replay does the same); 0: never
    # (--no-resend, and findings written before the fuzzer resent).
    resend_ms: float = 0.0

    def name(self, number: int) -> str:
        return f"finding-{number:03d}-{self.oracle}"


def write_finding(out: Path, number: int, finding: Finding,
                  traffic: list[tuple[float, bool, bytes, tuple[str, int]]], local: tuple[str, int]) -> Path:
    """Write `<name>.pcap` and `<name>.json`; returns the JSON path."""
    base = finding.name(number)
    finding.pcap = f"{base}.pcap"
    finding.frame = _frame_of(traffic, finding.original_hex, outbound=True)
    finding.output_frame = _frame_of(traffic, finding.output_hex, outbound=False)
    # Several packets kept (MAINT: then ENGAGE): each is part of the cause, not only the one shown.
    steps = [_frame_of(traffic, st["hex"], outbound=True) for st in finding.steps] if len(finding.steps) > 1 else []
    found = [n for n in (finding.frame, *steps) if n is not None]
    streamed = _stream_frames(traffic, finding, min(found, default=1))
    resent = _resend_frames(traffic, found, finding.resend_ms)
    shown = sorted({n for n in (*found, *streamed, *resent, finding.output_frame) if n is not None})
    finding.display_filter = frame_filter(shown) if shown else None     # (runs as ranges: a short line)
    write_pcap(out / finding.pcap, traffic, local)
    path = out / f"{base}.json"
    write_text(path, json.dumps(asdict(finding), indent=2) + "\n")
    return path


def _frame_of(traffic: list[tuple[float, bool, bytes, tuple[str, int]]], packet_hex: Optional[str],
              outbound: bool) -> Optional[int]:
    """The frame of the pcap written from `traffic` (one frame per entry) that holds the packet
    (its last copy: a case's packet has the serial it was sent with), if it is there."""
    if not packet_hex:
        return None
    packet = bytes.fromhex(packet_hex)
    for n in range(len(traffic) - 1, -1, -1):
        if traffic[n][1] == outbound and traffic[n][2] == packet:
            return n + 1
    return None


def _resend_frames(traffic: list[tuple[float, bool, bytes, tuple[str, int]]], frames: list[int],
                   resend_ms: float) -> list[int]:
    """The base unit's resends of the packets at `frames` (a VRCI resent every `resend_ms` until
    acknowledged, TS-0006 5.1.3): the copies on later serials that follow each, every one at most
    _RESEND_GAPS intervals after the one before (a later case's copy is no resend)."""
    out: list[int] = []
    for frame in frames if resend_ms else []:
        last, _, packet, _ = traffic[frame - 1]
        for n in range(frame, len(traffic)):
            t, outbound, data, _ = traffic[n]
            if t - last > _RESEND_GAPS * resend_ms / 1000:
                break
            if outbound and len(data) == len(packet) and data[:C.ID_LEN] == packet[:C.ID_LEN] and \
                    data == M.reserial(packet, int.from_bytes(data[M.SERIAL_OFFSET:M.SERIAL_OFFSET + 2], "little")):
                out.append(n + 1)
                last = t
    return out


def _stream_frames(traffic: list[tuple[float, bool, bytes, tuple[str, int]]], finding: Finding,
                   start: int) -> list[int]:
    """The first VRPI from frame `start` on that the base unit streamed with each case's own fields
    (a disarmed base unit, a battery of 0): what a case changed may be that, not its packets."""
    out = []
    vrpi = C.PacketType.VRPI.value.encode()
    for case in played(finding):
        if not case["stream"]:
            continue
        for n in range(start - 1, len(traffic)):
            _, outbound, data, _ = traffic[n]
            if outbound and data[:C.ID_LEN] == vrpi and data == M.build(
                    C.PacketType.VRPI, decode(data).get("serial", 0), case["stream"]):
                out.append(n + 1)
                break
    return out


def write_crash(out: Path, base: str, crash: Crash) -> dict[str, Any]:
    """The evidence files of a crash finding (`base`.output.txt, .core, .backtrace.txt) and what
    the finding's JSON says of them."""
    info: dict[str, Any] = {"headline": crash.headline(), **crash.how, "signature": crash.signature(),
                            "signature_version": SIGNATURE_VERSION}
    info["sanitizer"] = crash.sanitizer.to_json() if crash.sanitizer else None
    info["top_frames"] = [{"function": f.function, "location": f.location} for f in crash.own_frames()]
    info["output"] = f"{base}.output.txt"
    write_bytes(out / info["output"], crash.output)
    info["core"] = None
    if crash.core is not None:
        try:
            (out / crash.core).rename(out / f"{base}.core")     # the core we moved here for this crash
            info["core"] = f"{base}.core"
        except OSError as exc:
            crash.core_missing = f"cannot keep the core: {exc.strerror}"
    info["core_missing"] = None if info["core"] else crash.core_missing
    info["stack_missing"] = crash.stack_missing
    info["backtrace"] = None
    if crash.backtrace_text:
        info["backtrace"] = f"{base}.backtrace.txt"
        write_text(out / info["backtrace"], crash.backtrace_text)
    return info


def discard_core(out: Path, crash: Optional[Crash]) -> None:
    """Remove the core of a crash that is not kept (a repeat of a known bug, a replay): the
    fuzzer moved it into `out` itself."""
    if crash is not None and crash.core is not None:
        try:
            (out / crash.core).unlink()
        except OSError:
            pass
        crash.core = None


@dataclass
class Bucket:
    """One bug: every trigger with its signature."""

    signature: str
    oracle: str
    file: str
    first: float
    last: float
    count: int = 1
    headline: str = ""
    number: int = 0               # of the finding file
    size: int = 0                 # of its reproducer (see runner._size)
    tries: int = 0                # replays of smaller cases tried
    replaced: int = 0             # times a smaller case became the reproducer

    def hit(self, t: float) -> None:
        self.count += 1
        self.last = max(self.last, t)

    def to_json(self) -> dict[str, Any]:
        return {"signature": self.signature, "oracle": self.oracle, "count": self.count, "first": self.first,
                "last": self.last, "file": self.file, "headline": self.headline, "reproducer_replaced": self.replaced}


def write_pcap(path: Path, traffic: list[tuple[float, bool, bytes, tuple[str, int]]], local: tuple[str, int]) -> None:
    """The traffic as a tap on the fuzzer's host would see it (Ethernet/IPv4/UDP)."""
    flows: dict[tuple[Any, ...], UdpFlow] = {}
    with atomic_writer(path) as stream, PcapWriter(stream) as writer:
        for t, outbound, data, peer in traffic:
            src, dst = (local, peer) if outbound else (peer, local)
            key = (src, dst)
            if key not in flows:
                flows[key] = UdpFlow(src[0], src[1], dst[0], dst[1])
            writer.write(int(t * 1_000_000), flows[key].frame(data))


def make_folder(folder: Path, what: str) -> None:
    """Create `folder` (and its parents) unless it is there; CliError (one line) when it cannot be,
    saying so when something that is not a folder has its name."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:     # mkdir's exist_ok forgives only a folder
        raise CliError(f"{what} {folder} is not a directory") from None
    except OSError as exc:
        raise CliError(f"cannot create {what} {folder}: {exc.strerror}") from None


# What a run leaves in --out (crash cores wait there as .crash-N.core until kept or removed). Not
# target.log: a run that could not start leaves only that, and each run appends under a header.
_RUN_FILES = frozenset({"findings.json", "coverage.html"})
_RUN_PREFIXES = ("finding-", ".crash-")


def check_out(out: Path) -> None:
    """CliError (one line) when `out` is not a folder or holds a previous run's files: a run
    never overwrites another's evidence, nor leaves findings that its findings.json does not list.
    A corpus there (`id-*.json`) is no run's output: --corpus may be the same folder."""
    if not out.exists():
        return
    if not out.is_dir():
        raise CliError(f"--out {out} is not a directory")
    try:
        used = sorted(n for n in os.listdir(out) if n in _RUN_FILES or n.startswith(_RUN_PREFIXES))
    except OSError as exc:
        raise CliError(f"cannot read --out {out}: {exc.strerror}") from None
    if used:
        more = f" and {len(used) - 1} more" if len(used) > 1 else ""
        raise CliError(f"--out {out} holds a previous run's files ({used[0]}{more}): give a new --out "
                       "(nothing is overwritten)")


def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    path = out / "findings.json"
    write_text(path, json.dumps(summary, indent=2) + "\n")
    return path


def finding_from_json(raw: Any, path: str) -> Finding:
    """The finding written by `write_finding` whose JSON `raw` was read from `path`, every value
    checked; CliError (one line) when it is not one. Nothing in it is run: the stored command is
    only a hint."""
    if not isinstance(raw, dict) or raw.get("oracle") not in ORACLES or not isinstance(raw.get("steps"), list):
        raise CliError(f"{path} is not a vm110 fuzz finding")
    try:
        return _checked(raw)
    except _Bad as exc:
        raise CliError(f"{path} is not a valid vm110 fuzz finding: {exc}") from None


class _Bad(Exception):
    pass


# Finding's annotations -> the JSON types they allow (bool is an int to Python, not here).
_KINDS: dict[str, tuple[type, ...]] = {
    "str": (str,), "int": (int,), "float": (int, float), "bool": (bool,), "Optional[str]": (str, type(None)),
    "Optional[int]": (int, type(None)),
    "list[dict[str, Any]]": (list,), "Optional[list[dict[str, Any]]]": (list, type(None)),
    "Optional[dict[str, Any]]": (dict, type(None)),
}


def _checked(raw: dict[str, Any]) -> Finding:
    values = {}
    for f in fields(Finding):
        if f.name not in raw:
            if f.default is MISSING and f.default_factory is MISSING:
                raise _Bad(f"{f.name} is missing")
            continue
        value = values[f.name] = raw[f.name]
        kinds = _KINDS[str(f.type)]
        if (isinstance(value, bool) and bool not in kinds) or not isinstance(value, kinds):
            raise _Bad(f"{f.name} is not of type {f.type}")
    finding = Finding(**values)
    if finding.schema != SCHEMA:
        raise _Bad(f"schema {_short(finding.schema)} (this version reads {SCHEMA})")
    for name, (low, high) in _RANGES.items():
        _in_range(name, getattr(finding, name), low, high)
    for name in ("pause_vrpi_ms", "withhold_vrai_ms", "settle_ms", "resend_ms"):
        _milliseconds(name, getattr(finding, name))
    _packet("packet_hex", finding.packet_hex)
    if finding.cases is not None:
        _cases(finding.cases, len(finding.steps))
    if not finding.steps and finding.family != NO_CASE and not any(
            c["pause_vrpi_ms"] or c["withhold_vrai_ms"] or c["stream"] for c in played(finding)):
        # Replaying nothing would say "does not trigger any more" of any bug.
        raise _Bad("steps is empty (only a finding no case caused, family 'none', or a case of the base "
                   "unit's doing, a VRPI pause, a VRAI withheld or a stream, has none)")
    most = MAX_STEPS * (MAX_CASES if finding.cases else 1)
    if len(finding.steps) > most:
        raise _Bad(f"{len(finding.steps)} steps (at most {most})")
    for n, step in enumerate(finding.steps):
        if not isinstance(step, dict):
            raise _Bad(f"steps[{n}] is not an object")
        for key in ("hex", "valid_hex"):
            _packet(f"steps[{n}].{key}", step.get(key))
        _milliseconds(f"steps[{n}].delay_ms", step.get("delay_ms"))
        if not isinstance(step.get("expect_ack"), bool):
            raise _Bad(f"steps[{n}].expect_ack is not true or false")
    if finding.stream is not None:
        _stream(finding.stream)
    return finding


def played(finding: Finding) -> list[dict[str, Any]]:
    """The cases a finding plays in turn: its `cases`, else its own one (all of its steps)."""
    if finding.cases:
        return finding.cases
    return [{"case_index": finding.case_index, "mutation": finding.mutation, "packets": len(finding.steps),
             "pause_vrpi_ms": finding.pause_vrpi_ms, "withhold_vrai_ms": finding.withhold_vrai_ms,
             "stream": finding.stream, "settle_ms": finding.settle_ms}]


def _cases(cases: list[Any], steps: int) -> None:
    if not cases or len(cases) > MAX_CASES:
        raise _Bad(f"cases: {len(cases)} cases (1 to {MAX_CASES})")
    for n, case in enumerate(cases):
        if not isinstance(case, dict):
            raise _Bad(f"cases[{n}] is not an object")
        if not isinstance(case.get("mutation"), str):
            raise _Bad(f"cases[{n}].mutation is not a string")
        for name, high in (("case_index", _MAX_INT), ("packets", MAX_STEPS)):
            value = case.get(name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise _Bad(f"cases[{n}].{name} is not an integer")
            _in_range(f"cases[{n}].{name}", value, 0, high)
        for name in ("pause_vrpi_ms", "withhold_vrai_ms", "settle_ms"):
            _milliseconds(f"cases[{n}].{name}", case.get(name))
        if "stream" not in case or not isinstance(case["stream"], (dict, type(None))):
            raise _Bad(f"cases[{n}].stream is not an object or null")
        if case["stream"] is not None:
            _stream(case["stream"])
    if sum(case["packets"] for case in cases) != steps:
        raise _Bad(f"cases: their packets add up to {sum(case['packets'] for case in cases)}, not the "
                   f"{steps} steps")


# The other numbers of a finding (its millisecond values are checked by _milliseconds).
_RANGES: dict[str, tuple[int, int]] = {
    "seed": (0, (1 << 64) - 1), "case_index": (0, _MAX_INT), "differences": (0, _MAX_PACKET), "time": (0, _MAX_INT),
}


def _in_range(name: str, value: float, low: int, high: int) -> None:
    _finite(name, value)
    if not low <= value <= high:
        raise _Bad(f"{name} is out of range: must be from {low} to {high}")


def _short(number: int) -> str:
    text = str(number)
    return text if len(text) <= 20 else f"of {len(text)} digits"


def _finite(name: str, value: float) -> None:
    """NaN and infinities (which Python's JSON reads) have no range to be out of."""
    if isinstance(value, float) and not math.isfinite(value):
        raise _Bad(f"{name} is not a finite number")


def _milliseconds(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Bad(f"{name} is not a number of milliseconds")
    _finite(name, value)
    if not 0 <= value <= _MAX_MS:
        raise _Bad(f"{name} is out of range: must be a number of milliseconds from 0 to {_MAX_MS:.0f}")


def _packet(name: str, value: Any) -> None:
    if isinstance(value, str) and len(value) <= 2 * _MAX_PACKET:
        try:
            bytes.fromhex(value)
            return
        except ValueError:
            pass
    raise _Bad(f"{name} is not a packet in hex (at most {_MAX_PACKET} bytes)")


def _stream(stream: dict[str, Any]) -> None:
    """The VRPI fields the base unit streamed during the case: known names, values that fit."""
    for key, value in stream.items():
        if key not in _STREAM_FIELDS or isinstance(value, bool) or not isinstance(value, int):
            raise _Bad(f"stream: {str(key)[:40]!r} is not a VRPI field with an integer value")
    try:
        M.build(C.PacketType.VRPI, 0, stream)
    except (ValueError, struct.error):
        raise _Bad("stream: a value does not fit its VRPI field") from None
