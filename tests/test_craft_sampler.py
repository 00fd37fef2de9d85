"""`vm110 craft`: the sampler is well-formed traffic, each command before its acknowledgement,
that the analysis passes and the dissector pairs."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

import tshark_runner as T

ACKS = {"VRAO": "VRCI", "VRAI": "VRCO"}      # each acknowledgement and the command it answers


def vm110(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=60)


@pytest.fixture
def sampler(tmp_path):
    capture = tmp_path / "craft.pcap"
    done = vm110("craft", "--out", str(capture))
    assert done.returncode == 0, done.stderr
    return capture


def test_every_acknowledgement_follows_its_command(sampler):
    done = vm110("decode", str(sampler), "--json")
    packets = [json.loads(line) for line in done.stdout.splitlines()]
    seen: set[tuple[str, int]] = set()
    for p in packets:
        if p["type"] in ACKS:
            assert (ACKS[p["type"]], p["command_id"]) in seen, p
        seen.add((p["type"], p.get("command_id", -1)))
    assert {p["type"] for p in packets} == {"VRPI", "VRPO", "VRCI", "VRAO", "VRCO", "VRAI"}
    assert all(not p["problems"] for p in packets)


def test_the_sampler_analyses_without_errors(sampler, tmp_path):
    report_path = tmp_path / "report.json"
    done = vm110("analyze", str(sampler), "--json", str(report_path))
    assert done.returncode == 0, done.stderr
    verdict = json.loads(report_path.read_text())["verdict"]
    errors = [f for f in verdict["findings"] if f["severity"] == "error"]
    assert errors == [] and verdict["ok"], verdict
    assert not [f for f in verdict["findings"] if f["rule"] == "acks_without_command"]
    assert "VERDICT: OK" in done.stdout


def test_wireshark_pairs_every_acknowledgement(sampler, tmp_path):
    try:
        T.HOST.check()
    except T.TsharkUnavailable as exc:
        pytest.skip(str(exc))
    with T.HOST.workspace(tmp_path / "ws") as ws:
        frames, output = T.dissect_pdml(ws, sampler, {"vm110.analysis": "TRUE"}, ("-2",))   # pairs commands
    experts = [(f.number, e.message) for f in frames for e in f.experts]
    assert T.LUA_ERROR not in output and all(f.vm110 for f in frames) and len(frames) == 6
    assert experts == []            # no [Ack Without Command], no command never acknowledged
