"""What makes a run a failure: no exit within the timeout, a time over the budget, an exit code
outside the documented ones (a signal included), a Python traceback or an exception's name in an
error message (a crash turned into one line is still a crash), a Lua error (on stderr, or in the
packet details as tshark_runner and test_dissector_robustness detect it), a dissector bug, and a
report that exit 0 or 1 promised but is missing, unreadable or not as docs/report.schema.json says;
and two engines that disagree: the tshark engine's report on any tshark must be the fast engine's,
but for the engine's name (a second implementation of the rules, held to the first on hostile input)."""
from __future__ import annotations

import json
import re
from typing import Any, Iterator, Sequence

import report_schema

from .tools import Run

TRACEBACK = "Traceback (most recent call last)"
# "cannot analyse x: AttributeError: ..." is a crash the CLI caught; CliError messages name no class.
EXCEPTION_NAME = re.compile(r"\b[A-Z][A-Za-z]*(?:Error|Exception)\b(?=:|$)", re.M)
LUA_ON_STDERR = re.compile(r"lua", re.I)
GLIB_ALARM = re.compile(r"\*\* \(tshark:\d+\): (?:CRITICAL|ERROR)")
IN_DETAILS = ("Lua Error", "[Dissector bug", "Malformed Packet: VM110")


def judge(run: Run, budget: float) -> list[str]:
    """The problems of one run, each a short sentence; [] when it is fine."""
    if run.returncode is None:
        return [f"no exit within {run.seconds:.0f} s (hang)"]
    problems = []
    if run.seconds > budget:
        problems.append(f"took {run.seconds:.1f} s, over the {budget:.0f} s budget")
    if run.returncode not in run.tool.exits:
        problems.append(f"exit {run.returncode}" + (" (killed by a signal)" if run.returncode < 0 else ""))
    if TRACEBACK in run.stderr:
        problems.append("Python traceback: " + run.stderr.strip().splitlines()[-1][:200])
    else:
        problems += [f"exception in the message: {line.strip()[:200]}" for line in run.stderr.splitlines()
                     if EXCEPTION_NAME.search(line)][:1]
    if run.tool.kind == "tshark":
        problems += [f"stderr: {line.strip()[:200]}" for line in run.stderr.splitlines()
                     if LUA_ON_STDERR.search(line) or GLIB_ALARM.search(line)][:3]
        problems += [f"packet details: {_line_with(run.stdout, marker)}" for marker in IN_DETAILS
                     if marker in run.stdout]
    elif run.returncode in (0, 1):
        problems += _reports(run)
    return problems


def _line_with(text: str, marker: str) -> str:
    at = text.index(marker)
    start = text.rfind("\n", 0, at) + 1
    end = text.find("\n", at)
    return text[start:end if end >= 0 else None].strip()[:200]


def _reports(run: Run) -> list[str]:
    """The reports asked for exist and the JSON one parses and matches the schema."""
    problems = []
    for name in ("report.json", "report.html"):
        if f"{run.scratch}/{name}" not in run.command:
            continue
        path = run.scratch / name
        if not path.is_file():
            problems.append(f"exit {run.returncode} but no {name}")
        elif name.endswith(".json"):
            try:
                problems += [f"{name}: {p}" for p in report_schema.problems(json.loads(path.read_text()))[:3]]
            except ValueError as exc:
                problems.append(f"{name} is not JSON: {exc}")
    return problems


ENGINE_NAME = "/tool/engine"
# Frames the fast engine does not read and says so (a tunnel, a link type it does not know; a
# damaged port can make any datagram VXLAN's): the tshark engine unwraps and reads them.
BEYOND_FAST = ("tunnelled_frames", "unread_frames")


def disagreements(runs: Sequence[Run]) -> list[tuple[Run, list[str]]]:
    """Each run of an `agrees` group whose exit code or report differs from the group's first."""
    groups: dict[str, list[Run]] = {}
    for run in runs:
        if run.tool.agrees:
            groups.setdefault(run.tool.agrees, []).append(run)
    out = []
    for first, *others in groups.values():
        for run in others:
            problems = _disagreement(first, run)
            if problems:
                out.append((run, problems))
    return out


def _disagreement(first: Run, run: Run) -> list[str]:
    if first.returncode is None or run.returncode is None:
        return []                                   # (a hang is judged on its own)
    if first.returncode != run.returncode:
        return [f"exit {run.returncode} where {first.tool.label} exits {first.returncode}"]
    if first.returncode not in (0, 1):
        return []
    try:
        # (each tool reads its own copy of the capture: its path is named the same in both)
        ours, theirs = (json.loads((r.scratch / "report.json").read_text().replace(
            json.dumps(str(r.capture))[1:-1], "CAPTURE")) for r in (first, run))
    except (OSError, ValueError):
        return []                                   # (a missing or broken report is judged on its own)
    if any(ours.get("capture", {}).get(what) for what in BEYOND_FAST):
        return []                                   # (the tshark engine reads them: it sees more)
    diffs = [d for d in _differences(ours, theirs, "") if not d.startswith(ENGINE_NAME + ":")]
    if not diffs:
        return []
    return [f"report differs from {first.tool.label}'s in {len(diffs)} place{'s' if len(diffs) > 1 else ''}: "
            + "; ".join(diffs[:3])]


def _differences(a: Any, b: Any, path: str) -> Iterator[str]:
    """`path: a / b` for each leaf where two JSON documents differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            yield from _differences(a.get(key, "(none)"), b.get(key, "(none)"), f"{path}/{key}")
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            yield f"{path}: {len(a)} items / {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            yield from _differences(x, y, f"{path}[{i}]")
    elif a != b:
        yield f"{path}: {_short(a)} / {_short(b)}"


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."
