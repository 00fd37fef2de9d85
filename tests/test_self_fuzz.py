"""Fuzz ourselves (issue 17, part 6): mutations of the bundled captures (tests/selffuzz: editcap -E,
bit flips, cuts, lying length fields, duplicated and reordered records, EG-Link fields) through
`vm110 decode`, `vm110 analyze` (both engines) and the dissector on every supported tshark: no
traceback, no Lua error, no exit code outside the documented ones, within a time budget, and the
tshark engine's report on each tshark the fast engine's (the two implementations agree). Failing
inputs are kept under out/fuzz-self/. The seed varies per run unless FUZZ_SELF_SEED or CI is set;
`make fuzz-self` is the long soak. Also: the HTML report escapes what comes from a capture or a
file name."""
from __future__ import annotations

import hashlib
import json
import os
import random
import struct
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

import tshark_runner as T
from selffuzz import containers, mutators, oracles, runner, tools
from test_analysis_html import chromium
from vm110 import constants as C
from vm110 import encode

CHUNKS, CASES_PER_CHUNK = 1, 1          # 1 file per run (about 10 s; `make fuzz-self` soaks); the seed varies, the soak goes wide
CI_SEED = 17


@pytest.fixture(scope="module")
def seed(testrun_uid: str) -> int:
    """One seed for the whole run, on every xdist worker (testrun_uid is shared)."""
    if os.environ.get("FUZZ_SELF_SEED"):
        return int(os.environ["FUZZ_SELF_SEED"])
    return CI_SEED if os.environ.get("CI") else int(hashlib.sha256(testrun_uid.encode()).hexdigest()[:8], 16)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    try:
        with runner.session(tmp_path_factory.mktemp("selffuzz"), crc_auto=False) as sess:
            yield sess
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))


def _report(failures: list[tuple[tools.Run, list[str]]]) -> str:
    return "\n".join(f"{run.tool.label}: {'; '.join(problems)}\n  $ {' '.join(run.command)}\n"
                     f"  stderr: {run.stderr.strip()[-500:]}" for run, problems in failures)


def test_same_seed_same_mutations():
    first = [runner.make_case(5, i, small=True) for i in range(8)]
    again = [runner.make_case(5, i, small=True) for i in range(8)]
    assert [(c.base, c.steps, c.data) for c in first] == [(c.base, c.steps, c.data) for c in again]
    assert len({c.data for c in first}) == 8


def test_mutations_reach_every_kind():
    """Each mutation changes the file, and the parsers find the records it needs."""
    data = (runner.REPO / "captures" / "normal.pcap").read_bytes()
    layout = containers.parse(data)
    assert layout and len(layout.packets) == 382
    ng = containers.parse((runner.REPO / "captures" / "loss.pcapng").read_bytes())
    assert ng and len(ng.packets) == 612
    for mutation, _ in mutators.MUTATIONS:
        rng = random.Random(mutation.__name__)
        assert any(mutation(data, layout, rng)[0] != data for _ in range(5)), mutation.__name__


def test_oracles_see_planted_failures(tmp_path):
    """A traceback, a caught exception, a signal, a Lua error and a slow run are each seen."""
    site = tools.Site(T.Workspace(T.HOST, tmp_path), "host")
    lua = tmp_path / "bad.lua"
    lua.write_text('local p = Proto("vm110x", "x")\nfunction p.dissector() error("planted") end\n'
                   'register_postdissector(p)\n')
    cases = {
        "raise KeyError('k')": "Python traceback",
        "import sys; sys.exit('cannot analyse x: AttributeError: ')": "exception in the message",
        "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)": "killed by a signal",
        "import time; time.sleep(0.3)": "over the 0 s budget",
    }
    for code, expected in cases.items():
        tool = tools.Tool("planted", site, "python", lambda f, s, c=code: [sys.executable, "-c", c])
        problems = oracles.judge(tools.run(tool, tmp_path, tmp_path / "s", timeout=10), budget=0.2)
        assert any(expected in p for p in problems), (code, problems)
    tshark = tools.Tool("planted", site, "tshark",
                        lambda f, s: ["tshark", "-X", f"lua_script:{lua}", "-r", str(f), "-V"])
    problems = oracles.judge(tools.run(tshark, runner.SMALL[0], tmp_path / "s", timeout=30), budget=30)
    assert any("Lua Error" in p for p in problems), problems


def test_oracle_holds_the_engines_to_one_report(tmp_path):
    """Reports that differ only in the engine's name agree; a count, a finding or an exit code apart
    is a disagreement, named at its place in the report; unless the fast engine says it left frames
    unread (a tunnel it does not unwrap: the self-fuzz damaged a port into VXLAN's 4789)."""
    site = tools.Site(T.Workspace(T.HOST, tmp_path), "host")
    fast = {"tool": {"name": "vm110", "engine": "fast"}, "packets": {"VRPI": 40}, "findings": [{"rule": "gap"}]}

    def writes(name: str, report: dict, code: int = 0) -> tools.Tool:
        text = json.dumps(report)
        return tools.Tool(name, site, "python", lambda f, s: [
            sys.executable, "-c", f"import sys; open(sys.argv[1], 'w').write({text!r}); sys.exit({code})",
            str(s / "report.json")], versioned=False, agrees="engines")

    def judged(*tried: tools.Tool) -> list[list[str]]:
        runs = [tools.run(t, tmp_path, tmp_path / t.name, timeout=30) for t in tried]
        return [problems for _, problems in oracles.disagreements(runs)]

    same = {**fast, "tool": {"name": "vm110", "engine": "tshark"}}
    assert judged(writes("fast", fast), writes("tshark", same)) == []
    fewer = {**same, "packets": {"VRPI": 39}, "findings": []}
    [[problem]] = judged(writes("fast", fast), writes("tshark", fewer))
    assert "2 places" in problem and "/packets/VRPI: 40 / 39" in problem and "/findings: 1 items / 0 items" in problem
    [[problem]] = judged(writes("fast", fast), writes("tshark", same, code=2))
    assert problem == "exit 2 where fast exits 0"
    # (frames the fast engine says it did not read, the tshark engine reads: no disagreement)
    tunnels = {**fast, "capture": {"tunnelled_frames": 1}}
    assert judged(writes("fast", tunnels), writes("tshark", {**fewer, "capture": {"tunnelled_frames": 0}})) == []


def test_tools_read_an_unmutated_capture(session):
    """Every tool on every tshark reads a good capture (exit 0 or 1): a tool that cannot would pass
    every fuzz oracle below without testing anything."""
    failures = runner.control(session, runner.SMALL[0])
    assert not failures, _report(failures)


@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_mutated_captures(session, seed, chunk):
    outcomes = [session.run(runner.make_case(seed, i, small=True))
                for i in range(chunk * CASES_PER_CHUNK, (chunk + 1) * CASES_PER_CHUNK)]
    failed = [o for o in outcomes if o.failures]
    kept = [runner.keep(o) for o in failed]
    assert not failed, "\n\n".join(f"{o.case.name} kept as {path}\n{o.describe()}\n{_report(o.failures)}"
                                   for o, path in zip(failed, kept))


# --- The HTML report escapes what comes from the input ---------------------------------------------
HOSTILE_NAME = "<img src=x onerror=alert(1)>.pcap"
SCRIPT_DATA = b"<script>alert(1)"            # exactly the 16 bytes of VRCI command data
MARKUP = ("<img", "<script>alert")


class Tags(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, tuple[str, ...]]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, tuple(sorted(name for name, _ in attrs))))


def _tags(text: str) -> list[tuple[str, tuple[str, ...]]]:
    parser = Tags()
    parser.feed(text)
    return parser.tags


def _hostile_capture(path: Path, data: bytes) -> None:
    """A VRCI carrying `data` and its ack, a packet with a markup packet ID, and a VRPI stream."""
    grams = [encode.packet(C.PacketType.VRPI, encode.payload(C.PacketType.VRPI, {}), origin=0x0101, serial=i)
             for i in range(8)]
    grams.append(encode.packet(C.PacketType.VRCI, encode.command_payload(7, data), origin=0x0101, serial=8))
    grams.append(encode.packet(C.PacketType.VRAO, encode.ack_payload(7), serial=1))
    grams.append(encode.packet(b"<img", data, origin=0x0101, serial=9))
    grams.append(b"VRCI" + struct.pack("<HHHHI", 0, 0x0101, 10, 18, 0) + data + b"\"'&<>" + bytes(4))
    T.write_pcap(path, grams, times_us=[i * 125_000 for i in range(len(grams))])


def _analyze_html(session, capture: Path, out: Path) -> str:
    tool = tools.Tool("analyze --html", session.tools[0].site, "python",
                      lambda f, s: [*tools.VM110, "analyze", str(f), "--html", str(out)], versioned=False)
    run = tools.run(tool, capture, out.parent, timeout=60)
    assert run.returncode in (0, 1) and not oracles.judge(run, budget=60), run.stderr
    return out.read_text()


def test_html_escapes_hostile_file_name_and_command_data(session, tmp_path):
    benign = tmp_path / "benign.pcap"
    _hostile_capture(benign, b"plain data 16 b.")
    hostile = tmp_path / HOSTILE_NAME
    _hostile_capture(hostile, SCRIPT_DATA)
    good = _analyze_html(session, benign, tmp_path / "benign.html")
    bad = _analyze_html(session, hostile, tmp_path / "hostile.html")
    assert not [m for m in MARKUP if m in bad]
    assert "&lt;img src=x onerror=alert(1)&gt;.pcap" in bad       # the name is there, escaped
    # the same elements as with a harmless name and data: nothing from the input became markup
    assert sorted(set(_tags(bad))) == sorted(set(_tags(good)))
    dom, console = chromium(tmp_path / "hostile.html", tmp_path)
    assert console == []
    assert "<img" not in dom
