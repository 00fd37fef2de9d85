"""`vm110 monitor --evidence`: the disk a run's evidence takes is bounded, the first evidence kept."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from vm110.cli import main

ROOT = Path(__file__).resolve().parent.parent
LOSS = str(ROOT / "captures" / "loss.pcapng")       # a lossy link: 11 windows with --before 1 --after 1


def _watch(folder: Path, lines: Path, *limits: str) -> int:
    folder.mkdir(exist_ok=True)
    return main(["monitor", "--read", LOSS, "--idle", "0", "--no-dashboard", "--evidence", str(folder),
                 "--before", "1", "--after", "1", "--json-lines", str(lines), *limits])


def _windows(folder: Path) -> list[dict]:
    """The windows written, in the order they were (their frames' order), each with its files' size."""
    out = []
    for meta in folder.glob("*.json"):
        pcap = meta.with_suffix(".pcapng")
        out.append({**json.loads(meta.read_text()), "name": meta.stem,
                    "bytes": meta.stat().st_size + pcap.stat().st_size, "pcap": pcap.read_bytes()})
    return sorted(out, key=lambda w: w["window"]["end"])


def _alarms(lines: Path) -> int:
    """The alarms the run told (errors raised or found): each has a window, or is counted without."""
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    return sum(1 for o in objects if o["type"] == "finding" and o["severity"] == "error"
               and o["event"] in ("raised", "found"))


@pytest.fixture(scope="module")
def unlimited(tmp_path_factory) -> list[dict]:
    base = tmp_path_factory.mktemp("unlimited")
    assert _watch(base / "evidence", base / "live.jsonl") == 0
    windows = _windows(base / "evidence")
    assert len(windows) > 4
    return windows


@pytest.mark.parametrize("limit", ["files", "size"])
def test_evidence_stops_at_its_limit_and_keeps_the_first(limit, unlimited, tmp_path, capsys):
    """Trial: --evidence wrote a pcapng (up to 64 MiB) and a JSON for every alarm for as long as
    the run lasted: a lossy link over a weekend filled the disk. Now a run writes at most
    --evidence-max-files windows and --evidence-max-size MiB: the first ones, byte for byte those an
    unbounded run writes; the limit is said once, and the alarms left without evidence are counted
    (at the end and in the snapshots). A file the run did not write is neither counted nor touched."""
    folder, lines = tmp_path / "evidence", tmp_path / "live.jsonl"
    kept = 3
    if limit == "files":
        option = ["--evidence-max-files", str(kept)]
    else:       # room for the first three windows and half of the fourth (the JSONs' options differ a little)
        room = sum(w["bytes"] for w in unlimited[:kept]) + unlimited[kept]["bytes"] // 2
        option = ["--evidence-max-size", repr(room / (1 << 20))]
    foreign = folder / "20250615T150652.902Z-lost-9.pcapng"     # (a name the run could have chosen)
    folder.mkdir()
    foreign.write_bytes(b"not ours" * 100_000)
    assert _watch(folder, lines, *option) == 0
    err = capsys.readouterr().err.splitlines()
    assert foreign.read_bytes() == b"not ours" * 100_000
    foreign.unlink()
    windows = _windows(folder)
    assert [(w["name"], w["pcap"]) for w in windows] == [(w["name"], w["pcap"]) for w in unlimited[:kept]]
    said = [line for line in err if "reached" in line and line.startswith("vm110 monitor: evidence: ")]
    assert len(said) == 1 and option[0] in said[0]
    without = _alarms(lines) - sum(len(w["findings"]) for w in windows)
    assert without == sum(len(w["findings"]) for w in unlimited[kept:]) > 0
    assert f"evidence: {kept} file(s) in {folder}; {without} alarm(s) without evidence ({option[0]} " in "\n".join(err)
    snapshots = [json.loads(line) for line in lines.read_text().splitlines() if '"snapshot"' in line]
    assert snapshots[-1]["evidence_files"] == kept and 0 < snapshots[-1]["evidence_over_limit"] <= without


@pytest.mark.parametrize("option,value", [("--evidence-max-files", v) for v in ("-1", "0", "nan", "inf", "1.5", "x")]
                         + [("--evidence-max-size", v) for v in ("-1", "0", "nan", "inf", "-inf", "x", "2e6")])
def test_evidence_limits_are_validated(option, value, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["monitor", "--read", LOSS, "--evidence", str(tmp_path), f"{option}={value}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and len(err) == 1
    assert err[0].startswith(f"vm110 monitor: argument {option}: {value!r} is ") and "must be" in err[0]
    assert not list(tmp_path.iterdir())


def test_alarms_beyond_the_open_windows_are_counted(tmp_path):
    """Trial: an alarm while 64 windows were collecting (64 senders alarming at once on a mirror
    port) got no evidence, and nothing said so. The end's line now counts them."""
    from vm110.monitor.evidence import MAX_OPEN, Evidence
    evidence = Evidence(str(tmp_path), 1.0, 1.0, {}, 1000, 1024)
    t = 1_700_000_000.0
    evidence.frame(t, 1, 1, bytes(60))
    for n in range(MAX_OPEN + 2):
        evidence.alarm({"rule": "lost", "sender": f"Input 10.0.0.{n}:5825 origin 0x0101", "item": {"frame": 1}}, t)
    evidence.tick(None)
    assert len(list(tmp_path.glob("*.pcapng"))) == len(evidence.written) == MAX_OPEN
    assert evidence.told() == (f"evidence: {MAX_OPEN} file(s) in {tmp_path}; 2 alarm(s) without evidence "
                               f"(more than {MAX_OPEN} windows at once)")


def test_evidence_of_a_capture_beyond_year_9999_is_named_by_its_seconds(tmp_path, capsys):
    """Trial: a pcapng whose times lie past the year 9999 (a hostile or broken capture) ended the
    monitor with a traceback at its first alarm's evidence: the file's name is its UTC date. Such a
    time is now named by its raw seconds, as timefmt shows it, and the watch ends with its report."""
    from test_analysis_craft import Traffic, vrpi
    tr = Traffic()
    far = 1e12                          # some 31,700 years after the crafted captures' start
    for i in range(16):                 # a BU heard for 2 s, then silent: its watchdog alarms
        tr.add(far + i * 0.125, vrpi(i))
    tr.add(far + 4.0, vrpi(16))
    capture = tmp_path / "far.pcapng"
    tr.write(capture, "pcapng")
    folder = tmp_path / "evidence"
    folder.mkdir()
    code = main(["monitor", "--read", str(capture), "--idle", "0", "--no-dashboard", "--quiet", "--evidence",
                 str(folder), "--crc", "mpeg2", "--crc-order", "little"])
    assert code == 0 and "Traceback" not in capsys.readouterr().err
    [meta] = [json.loads(p.read_text()) for p in folder.glob("*.json")]
    assert meta["rule"] == "watchdog" and meta["time"] > far
    assert sorted(p.name for p in folder.iterdir()) == [f"{meta['time']!r}s-watchdog.json",
                                                        f"{meta['time']!r}s-watchdog.pcapng"]
