"""Report == ground truth on every key of the truth contract (/work/notes/truth-contract.md):
the bundled captures/ and freshly synthesised ones (`vm110 synth` computes its truth from the
simulators' event log, not by analysing the file)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from vm110.analysis import analyze
from vm110.sim.scenario import SCENARIOS
from vm110.synth import synthesize

CAPTURES = Path(__file__).resolve().parent.parent / "captures"
ALL_CAPTURES = sorted(p for p in CAPTURES.iterdir() if p.suffix in (".pcap", ".pcapng"))
BUNDLED = [p for p in ALL_CAPTURES if Path(f"{p}.truth.json").exists()]
SHORT = {"day": 120.0}      # the long scenario, cut to keep the suite quick


def contract_diff(truth, report, path: str = "") -> list[str]:
    """Every place where the report differs from the truth; keys absent from the truth are free."""
    if isinstance(truth, dict):
        if not isinstance(report, dict):
            return [f"{path}: {report!r} is not an object"]
        out = []
        for key, value in truth.items():
            if key not in report:
                out.append(f"{path}.{key}: missing")
            else:
                out += contract_diff(value, report[key], f"{path}.{key}")
        return out
    if isinstance(truth, list):
        if not isinstance(report, list) or len(report) != len(truth):
            return [f"{path}: {len(truth)} items in the truth, report has {report!r:.200}"]
        return [d for i, (a, b) in enumerate(zip(truth, report)) for d in contract_diff(a, b, f"{path}[{i}]")]
    if truth != report or (type(truth) is bool and type(report) is not bool):
        return [f"{path}: truth {truth!r}, report {report!r}"]
    return []


def test_the_comparison_sees_differences():
    truth = {"a": [{"x": 1, "y": 2.5}], "b": {"c": 3}}
    assert contract_diff(truth, {"a": [{"x": 1, "y": 2.5, "extra": 0}], "b": {"c": 3, "d": 4}}) == []
    assert contract_diff(truth, {"a": [{"x": 1, "y": 2.5}], "b": {"c": 4}}) == [".b.c: truth 3, report 4"]
    assert contract_diff(truth, {"a": [], "b": {}})[0].startswith(".a: 1 items")
    assert contract_diff(truth, {"a": [{"x": 1}], "b": {"c": 3}}) == [".a[0].y: missing"]


@pytest.mark.parametrize("capture", BUNDLED, ids=lambda p: p.name)
def test_bundled_capture_matches_its_truth(capture):
    """The report's truth keys are the truth's; the `lost` finding's items (gaps, less their
    serials that came late) add up to the serials the truth says were lost."""
    truth = json.loads(Path(f"{capture}.truth.json").read_text())
    report = analyze(str(capture))
    assert contract_diff(truth, report) == []
    lost = sum(s["serial"]["lost"] for s in truth["senders"])
    items = [i for f in report["verdict"]["findings"] if f["rule"] == "lost" for i in f["items"]]
    assert sum(i["count"] - i.get("late", 0) for i in items) == lost


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_synthesised_capture_matches_its_truth(scenario, tmp_path):
    seed = 7 + sorted(SCENARIOS).index(scenario)
    fmt = "pcapng" if seed % 2 else "pcap"
    out = tmp_path / f"{scenario}.{fmt}"
    truth = synthesize(scenario, str(out), seed, SHORT.get(scenario), fmt)
    on_disk = json.loads(Path(f"{out}.truth.json").read_text())
    assert on_disk["capture"] == truth["capture"]
    assert contract_diff(on_disk, analyze(str(out))) == []
