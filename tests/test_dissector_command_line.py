"""Choices the dissector makes from tshark's command line (/proc/self/cmdline), on every version.

Wireshark 4.0's `tshark -T fields` dissects with a visible tree, where every field counts as
referenced; the dissector then builds only the vm110 fields named on the command line (4.4 and
4.6 dissect -T fields with an invisible tree and say by themselves what is referenced). Seen from
outside by a Lua tap of the user's own that reads a vm110 field nobody named, with Field.new: on
4.0 it gets nothing unless the preference vm110.fields_from_command_line is off; on 4.4 and 4.6
its Field.new references the field, so it always gets it. The fields that are named come out as
the full tree has them.
"""
from __future__ import annotations


import shutil

import pytest

import tshark_runner as T
from longrun import runner_params

pytestmark = pytest.mark.tshark

CAPTURE = T.REPO / "captures" / "normal.pcap"


def run(ws: T.Workspace, options: list[str], prefs: dict[str, str] | None = None) -> tuple[list[str], int]:
    """(-e vm110.serial values, vm110.crc.status values a Lua tap of the user's saw)."""
    proc = ws.run(["-n", *T.field_counter(ws, "vm110.crc.status"), "-r", str(ws.dir / CAPTURE.name),
                   *T.pref_args(prefs), *options, *(["-e", "vm110.serial"] if "fields" in "".join(options) else [])])
    assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-2000:]
    return proc.stdout.split(), T.field_count(proc.stderr)


@pytest.fixture(params=runner_params(T.RUNNERS))
def ws(request, tmp_path):
    try:
        with request.param.workspace(tmp_path) as workspace:
            shutil.copyfile(CAPTURE, workspace.dir / CAPTURE.name)
            yield workspace
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


def serials(ws: T.Workspace) -> list[str]:
    """vm110.serial of every packet, from the full tree (PDML)."""
    frames = T.parse_pdml(ws.run(["-n", "-r", str(ws.dir / CAPTURE.name), "-T", "pdml"], shared=True).stdout)
    return [f.first("vm110.serial").show for f in frames if f.first("vm110.serial")]


@pytest.mark.parametrize("options", [["-T", "fields"], ["-Tfields"], ["-qTfields"], ["-T", "fields", "-2"]],
                         ids=["separate", "joined", "grouped", "two-pass"])
def test_fields_named_on_the_command_line_only_on_4_0(ws, options):
    expected = serials(ws)
    values, seen = run(ws, options)
    assert values == expected
    assert seen == (0 if ws.tshark.version == "4.0" else len(expected))


def test_the_preference_builds_every_field(ws):
    values, seen = run(ws, ["-T", "fields"], {"vm110.fields_from_command_line": "FALSE"})
    assert seen == len(values) == len(serials(ws)) > 0


@pytest.mark.parametrize("options", [["-T", "fields", "-V"], ["-T", "pdml"]], ids=["details", "pdml"])
def test_details_printed_build_every_field(ws, options):
    """-V with -T fields, or another output format: the full tree, as before."""
    _, seen = run(ws, options)
    assert seen == len(serials(ws)) > 0
