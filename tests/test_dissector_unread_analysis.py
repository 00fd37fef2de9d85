"""A single-pass tshark whose output reads nothing of the stream analysis does not run it
(dissector/vm110.lua, choose_view): `tshark -T fields -e vm110.serial` prints the same as with the
analysis run, and every reader of the analysis still gets it.

The reference is the same command with a display filter that names an analysis field and keeps
every frame (`vm110.analysis.flags or not vm110.analysis.flags`): a field referenced, so the
analysis runs, and the output is the command's own. What the run without it prints must equal it,
and must hold what the analysis found (a test that could pass with the analysis off everywhere
would prove nothing): the decode fields of every bundled capture, the expert infos (`-z expert`,
`_ws.expert.message`), the Info column's markers, a display filter on `vm110.analysis.flags`, a Lua
script of the user's that reads an analysis field with Field.new, and a machine sub-dissector
(which gets the reassembled periodic data).
"""
from __future__ import annotations

import shutil
import subprocess

import pytest

import tshark_runner as T
from longrun import runner_params

pytestmark = pytest.mark.tshark

CAPTURES = T.REPO / "captures"
LOSSY = CAPTURES / "loss.pcapng"          # serial gaps, late and duplicate packets
EVERY_FRAME = ["-Y", "vm110.analysis.flags or not vm110.analysis.flags"]
COMMAND_LINE_OFF = ["-o", "vm110.fields_from_command_line:FALSE"]


@pytest.fixture(params=runner_params(T.RUNNERS))
def ws(request, tmp_path):
    try:
        with request.param.workspace(tmp_path) as workspace:
            yield workspace
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


def fields(ws: T.Workspace, capture, options: list[str]) -> tuple[str, str]:
    """(stdout, stderr) of a single-pass -T fields run over a copy of `capture`."""
    copy = ws.dir / capture.name
    if not copy.exists():
        shutil.copyfile(capture, copy)     # (a capture made in ws.dir is its own copy)
    proc = ws.run(["-n", "-r", str(copy), "-T", "fields", *options])
    assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-2000:]
    return proc.stdout, proc.stderr


def decode_fields(ws: T.Workspace) -> list[str]:
    """Every vm110 field that is no analysis field, as -e options."""
    decoded = [r[2] for r in T.glossary(ws) if r[0] == "F" and r[2].startswith("vm110.")
               and not r[2].startswith(("vm110.analysis.", "vm110.burst.", "vm110.reassembled"))]
    assert "vm110.serial" in decoded and "vm110.crc.status" in decoded
    return [arg for name in sorted(decoded) for arg in ("-e", name)]


def test_decode_fields_are_those_of_a_run_that_analyses(ws):
    """Every bundled capture, appended into one (mergecap -a: one run each way)."""
    bundled = sorted(p for p in CAPTURES.iterdir() if p.suffix in (".pcap", ".pcapng"))
    appended = ws.dir / "bundled.pcapng"
    subprocess.run(["mergecap", "-a", "-w", str(appended), *map(str, bundled)], check=True)
    options = ["-e", "frame.number", *decode_fields(ws)]
    alone, _ = fields(ws, appended, options)
    analysed, _ = fields(ws, appended, [*options, *EVERY_FRAME])
    assert alone == analysed
    assert len(alone.splitlines()) > 7000 and len(bundled) > 10


@pytest.mark.parametrize("reader, found", [
    (["-e", "frame.number", "-z", "expert"], "Serial gap: packets missing"),
    (["-e", "frame.number", "-e", "_ws.expert.message"], "Serial gap: packets missing"),
    (["-e", "frame.number", "-e", "_ws.col.Info"], "[Serial Gap]"),
], ids=["expert-tap", "expert-field", "info-column"])
def test_a_reader_of_the_analysis_gets_it(ws, reader, found):
    got, _ = fields(ws, LOSSY, ["-e", "vm110.serial", *reader])
    expected, _ = fields(ws, LOSSY, ["-e", "vm110.serial", *reader, *EVERY_FRAME])
    assert got == expected
    assert found in got


def test_a_display_filter_on_the_analysis_gets_its_frames(ws):
    flagged, _ = fields(ws, LOSSY, ["-e", "frame.number", "-e", "vm110.analysis.flags"])
    expected = [line.split("\t")[0] for line in flagged.splitlines() if line.split("\t")[1]]
    got, _ = fields(ws, LOSSY, ["-e", "frame.number", "-Y", "vm110.analysis.flags"])
    assert got.split() == expected and len(expected) > 3


def lua_reader(ws: T.Workspace, field: str, options: list[str]) -> int:
    """How many values of `field` a Lua script of the user's saw (as the same run that analyses)."""
    options = [*T.field_counter(ws, field), *options, "-e", "vm110.serial"]
    counts = [T.field_count(fields(ws, LOSSY, [*options, *extra])[1]) for extra in ([], EVERY_FRAME)]
    assert counts[0] == counts[1]
    return counts[0]


def test_a_lua_script_that_reads_an_analysis_field_gets_it(ws):
    """4.4 and 4.6 say by themselves that a Field.new reads it; 4.0 only with
    vm110.fields_from_command_line off (tests/test_dissector_command_line.py: 4.0 builds the fields
    its command line names)."""
    options = COMMAND_LINE_OFF if ws.tshark.version == "4.0" else []
    assert lua_reader(ws, "vm110.analysis.interval", options) > 100


def test_a_lua_script_that_reads_expert_infos_gets_them_with_the_preference_off(ws):
    """What a Lua script reads of the expert infos the dissector cannot see: the preference that
    README names runs the analysis always."""
    assert lua_reader(ws, "_ws.expert.message", COMMAND_LINE_OFF) > 5


def test_a_machine_sub_dissector_gets_the_reassembled_data(ws):
    crane = ws.dir / "crane.lua"
    shutil.copyfile(T.REPO / "dissector" / "examples" / "crane.lua", crane)
    options = ["-X", f"lua_script:{ws.tshark.inner(crane)}", "-o", "vm110.machine:crane",
               "-e", "frame.number", "-e", "crane.log_count", "-e", "crane.hoist_height", "-e", "crane.opcode"]
    got, _ = fields(ws, CAPTURES / "crane.pcapng", options)
    expected, _ = fields(ws, CAPTURES / "crane.pcapng", [*options, *EVERY_FRAME])
    assert got == expected
    assert any(line.split("\t")[1] for line in got.splitlines())
