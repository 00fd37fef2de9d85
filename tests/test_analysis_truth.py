"""Report == ground truth on every key of the truth contract (the keys marked ✓ in docs/report.md):
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


@pytest.mark.parametrize("data_size", [488, 976, 1464])
def test_a_data_size_a_multiple_of_488_is_inferred(data_size, tmp_path):
    """docs/rules.md, "VRPO bursts": a controller whose periodic data are a multiple of 488 bytes
    sends no short packet; its bursts of full packets are complete, those that lost a packet are
    not (trial: every burst was incomplete). Expected from the capture alone: VRPO grouped by the
    20 ms gap (bursts 100 ms apart), a group complete when it has all data_size / 488 packets."""
    from vm110.sim.controller import ControllerConfig
    from vm110.sim.impair import Impairment
    from vm110.sim.reading import Reading
    from vm110.sim.scenario import Scenario, _armed, _pair
    from vm110.synth import write_capture
    from scapy.utils import rdpcap

    def build(seed: int, duration: float, reading: Reading) -> list:
        return _pair(seed, reading, _armed(duration), ctl=ControllerConfig(data_size=data_size),
                     ctl_imp=Impairment(loss=4.0, jitter_ms=2.0, only=("VRPO",), seed=seed))
    out = tmp_path / "full.pcap"
    with open(out, "wb") as stream:
        truth = write_capture(stream, Scenario("full", "", 20.0, build), 3, 20.0, "pcap")
    times = [float(p.time) for p in rdpcap(str(out)) if bytes(p)[42:46] == b"VRPO"]
    groups, last = [], None
    for t in times:
        if last is None or t - last >= 0.020:
            groups.append(0)
        groups[-1] += 1
        last = t
    whole = data_size // 488
    assert groups[0] == whole
    expected = {"complete": groups.count(whole), "incomplete": len(groups) - groups.count(whole)}
    assert truth["vrpo_bursts"] == expected and (expected["incomplete"] > 0) == (whole > 1), expected
    assert contract_diff(json.loads(json.dumps(truth)), analyze(str(out))) == []
