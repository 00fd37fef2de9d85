"""The demo fleet (`make fleet-demo`): built, queried and reported; the named queries find the
machines the demo planted (vm110.fleet.demo says which), and only those."""
from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

import numpy
import pytest
from sessionwide import once
from vm110.cli import main
from vm110.fleet import demo


def vm110(*args: str, code: int = 0) -> str:
    """The command's standard output; in this process (queries are quick, a new interpreter is not)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(list(args)) == code
    return out.getvalue()


def make(root: Path) -> None:
    paths = demo.captures(str(root))
    assert len(paths) == 40
    out = vm110("fleet", "build", str(root / "sites"), "--out", str(root / "ds"), "-j", "1",
                "--meta", "sites/{site}/{machine}/*.pcap", code=2)      # (2: the damaged capture it plants)
    assert "40 analysed (1 damaged, 0 unreadable)" in out


@pytest.fixture(scope="module")
def dataset() -> Path:
    return once("demo", make) / "ds"


def query(dataset: Path, *args: str) -> list[dict]:
    return json.loads(vm110("fleet", "query", str(dataset), *args, "--format", "json"))


def test_worst_links_are_the_planted_ones(dataset):
    rows = query(dataset, "--worst", "links")
    assert len(rows) == len(demo.MACHINES)
    troubled = {r["machine"] for r in rows if r["loss_pct"] > 1 or r["watchdog"] > 0}
    # the failing-commands machine loses its commands on the link too
    assert troubled == set(demo.BAD_LINKS) | set(demo.FAILING_COMMANDS)
    top = [r["machine"] for r in rows[:len(troubled)]]
    assert set(top) == troubled
    sites = {m: s for s, m, *_ in demo.MACHINES}
    assert all(r["site"] == sites[r["machine"]] for r in rows)


def test_watchdog_this_month_and_failing_commands(dataset):
    watchdog = query(dataset, "--named", "watchdog")
    assert [r["machine"] for r in watchdog] == list(demo.WATCHDOG)
    assert watchdog[0]["month"] == "2025-06" and watchdog[0]["captures"] == demo.WEEKS
    assert query(dataset, "--named", "watchdog", "--month", "2025-07") == []
    failing = query(dataset, "--worst", "commands")
    assert {r["machine"] for r in failing} == set(demo.FAILING_COMMANDS)


def test_trend_errors_and_sql(dataset):
    weeks = query(dataset, "--trend", "jitter", "--by", "week")
    assert [r["week"] for r in weeks] == ["2025-06-02", "2025-06-09", "2025-06-16", "2025-06-23"]
    assert [r["captures"] for r in weeks] == [10] * 4
    by_firmware = query(dataset, "--trend", "loss", "--by", "bu_firmware")
    assert {r["bu_firmware"] for r in by_firmware} == {"3.2", "3.4"}
    errors = query(dataset, "--named", "errors")
    _, machine, week = demo.DAMAGED
    assert [(r["machine"], r["kind"]) for r in errors] == [(machine, "damaged")]
    assert errors[0]["file"].endswith(f"{machine}-w{week + 1}.pcap")
    rows = query(dataset, "SELECT site, count(DISTINCT machine) AS machines FROM captures GROUP BY site ORDER BY site")
    assert rows == [{"site": "east", "machines": 2}, {"site": "north", "machines": 3},
                    {"site": "south", "machines": 3}, {"site": "west", "machines": 2}]
    csv = vm110("fleet", "query", str(dataset), "SELECT machine, lost FROM senders WHERE lost > 0 ORDER BY lost DESC "
                "LIMIT 1", "--format", "csv")
    assert csv.splitlines()[0] == "machine,lost" and len(csv.splitlines()) == 2
    table = vm110("fleet", "query", str(dataset), "--list")
    assert "worst-links" in table and "captures:" in table


def test_the_latency_trend_gives_each_device_s_acks_apart(dataset):
    """Fleet trial: "which BU firmware acks slowest" (--trend latency --by bu_firmware) mixed the
    controller's acks of VRCI with the base unit's of VRCO in one p95. Each is held to the commands
    table's own latencies, the quantile interpolated here (numpy's linear, as quantile_cont)."""
    rows = query(dataset, "--trend", "latency", "--by", "bu_firmware")
    commands = query(dataset, "SELECT c.bu_firmware, t.type, t.latency_first_ms, t.failed FROM commands t "
                              "JOIN captures c USING (capture_id)")
    for row in rows:
        for kind in ("VRCI", "VRCO"):
            mine = [c for c in commands if c["bu_firmware"] == row["bu_firmware"] and c["type"] == kind]
            latencies = [c["latency_first_ms"] for c in mine if c["latency_first_ms"] is not None]
            key = kind.lower()
            assert row[f"{key}_commands"] == len(mine) > 0
            assert row[f"{key}_failed"] == sum(c["failed"] for c in mine)
            assert row[f"{key}_ack_p95_ms"] == pytest.approx(round(float(numpy.quantile(latencies, 0.95)), 3), abs=1e-3)
            assert row[f"{key}_ack_max_ms"] == max(latencies)


def test_report_page(dataset, tmp_path):
    page_path = tmp_path / "fleet.html"
    vm110("fleet", "report", str(dataset), "--html", str(page_path))
    page = page_path.read_text()
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    assert not re.search(r"""(src|href)\s*=|<script|@import|url\(""", page)       # self-contained
    for _, machine, *_ in demo.MACHINES:
        assert machine in page
    ranked = page.index("Machines ranked by findings")
    first_rows = page[ranked:page.index("</table>", ranked)]
    first_machine = re.findall(r"<td>(crane-\d+)</td>", first_rows)[0]
    assert first_machine in set(demo.BAD_LINKS) | set(demo.FAILING_COMMANDS)
    for plot in ("trend-loss", "trend-jitter", "trend-latency", "spread-vrpi-jitter", "spread-ack-latency"):
        assert f'data-plot="{plot}"' in page
    assert "frame.number" in page and "wireshark -r" in page


def test_the_demo_builds_afresh_over_its_dataset_of_an_older_format(tmp_path, capsys):
    """`make fleet-demo` after an upgrade that changed the dataset format failed: its build and
    queries refused the demo's own dataset of before (exit 2). The demo now removes that one, and
    nothing else: not a dataset of the current format, not a folder that is no dataset."""
    from vm110.fleet.dataset import FORMAT, FORMAT_VERSION, MANIFEST
    for name, doc in (("old", {"format": FORMAT, "format_version": FORMAT_VERSION - 1}),
                      ("current", {"format": FORMAT, "format_version": FORMAT_VERSION}),
                      ("other", {"format": "something else", "format_version": 0})):
        (tmp_path / name).mkdir()
        (tmp_path / name / MANIFEST).write_text(json.dumps(doc))
        (tmp_path / name / "part.parquet").write_bytes(b"x")
        demo._drop_older_dataset(str(tmp_path / name))
    (tmp_path / "none").mkdir()
    demo._drop_older_dataset(str(tmp_path / "none"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["current", "none", "other"]
    assert f"format version {FORMAT_VERSION - 1}" in capsys.readouterr().out
