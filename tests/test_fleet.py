"""vm110 fleet build: the dataset's rows say what `vm110 analyze --json` says for each capture;
a Dask LocalCluster builds the same rows as the local engine."""
from __future__ import annotations

import datetime as dt
import hashlib
import html
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from sessionwide import once

ROOT = Path(__file__).resolve().parent.parent
BUNDLED = ROOT / "captures"
VM110 = [sys.executable, "-m", "vm110"]
# site, machine, bundled capture: a small fleet with every kind of trouble the analysis knows
LAYOUT = (("north", "m1", "normal.pcap"), ("north", "m1", "retransmit.pcap"), ("north", "m2", "loss.pcapng"),
          ("south", "m3", "vrco.pcap"), ("south", "m3", "vrpo-split.pcapng"), ("south", "m4", "illegal.pcap"),
          ("east", "m5", "restart.pcapng"), ("east", "m5", "bu-watchdog.pcap"), ("west", "m6", "glink.pcapng"),
          ("west", "m6", "controller-watchdog.pcap"))
TABLES = ("captures", "senders", "streams", "commands", "findings", "errors", "packets")


def vm110(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run([*VM110, *args], capture_output=True, text=True, cwd=ROOT)
    if check and result.returncode != 0:
        raise AssertionError(f"vm110 {' '.join(args)} exited {result.returncode}: {result.stderr}")
    return result


def make_fleet(root: Path) -> dict[str, Path]:
    """The layout under root/sites, plus a capture cut short and a file that is no capture."""
    files = {}
    for site, machine, name in LAYOUT:
        folder = root / "sites" / site / machine
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copy(BUNDLED / name, folder / name)
        files[name] = folder / name
    cut = root / "sites" / "east" / "m5" / "cut.pcap"
    data = (BUNDLED / "normal.pcap").read_bytes()
    cut.write_bytes(data[:len(data) // 2 + 5])
    files["cut"] = cut
    junk = root / "sites" / "west" / "m6" / "junk.pcap"
    junk.write_bytes(b"this is not a capture at all\n" * 4)
    files["junk"] = junk
    (root / "sites" / "north" / "m1" / "normal.pcap.meta.json").write_text(json.dumps({"bu_firmware": "3.2"}))
    files["orphan"] = root / "sites" / "north" / "m2" / "orphan-ack.pcap"
    without_first_command(BUNDLED / "normal.pcap", files["orphan"])
    return files


def without_first_command(source: Path, target: Path) -> None:
    """`source` without the transmissions of its first VRCI command: its acknowledgement is one
    without a command."""
    from scapy.all import rdpcap, wrpcap
    report = json.loads(vm110("analyze", str(source), "--json", "-", "--quiet", check=False).stdout)
    first = report["commands"]["VRCI"]["list"][0]
    assert first["ack_frame"] is not None
    wrpcap(str(target), [p for n, p in enumerate(rdpcap(str(source)), 1) if n not in first["frames"]])


def read_table(dataset: Path, table: str) -> list[dict]:
    """Rows of a table, read with pyarrow from the parts the manifest lists (not through vm110)."""
    manifest = json.loads((dataset / "manifest.json").read_text())
    rows = []
    for entry in manifest["captures"].values():
        for part in entry["parts"]:
            if part.startswith(table + "/"):
                rows += pq.read_table(dataset / part).to_pylist()
    return rows


def make(root: Path) -> None:
    files = make_fleet(root)
    built = vm110("fleet", "build", str(root / "sites"), "--out", str(root / "dataset"), "--packets", "-j", "2",
                  "--meta", "sites/{site}/{machine}/*", check=False)
    readable = [str(p) for k, p in files.items() if k != "junk"]
    vm110("analyze", *readable, "--json", str(root / "reports.json"), "--quiet", check=False)
    junk = vm110("analyze", str(files["junk"]), "--quiet", check=False)
    (root / "results.json").write_text(json.dumps({
        "files": {k: str(v) for k, v in files.items()}, "built": [built.returncode, built.stdout, built.stderr],
        "junk_error": junk.stderr.strip()}))


@pytest.fixture(scope="module")
def fleet():
    """A small fleet built once (with --packets), and `vm110 analyze --json` of the same captures."""
    root = once("rows", make)
    results = json.loads((root / "results.json").read_text())
    reports = json.loads((root / "reports.json").read_text())["reports"]
    return {"root": root, "files": {k: Path(v) for k, v in results["files"].items()}, "dataset": root / "dataset",
            "built": subprocess.CompletedProcess([], *results["built"]),
            "reports": {r["capture"]["file"]: r for r in reports}, "junk_error": results["junk_error"]}


def by_file(rows: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(r["file"], []).append(r)
    return out


def us(seconds):
    return None if seconds is None else dt.datetime(1970, 1, 1) + dt.timedelta(microseconds=round(seconds * 1e6))


def test_build_reports_the_unreadable_file_and_goes_on(fleet):
    built = fleet["built"]
    assert built.returncode == 2
    lines = built.stderr.strip().splitlines()
    assert any("junk.pcap" in line and "not a pcap or pcapng capture" in line for line in lines)
    assert any("damaged" in line and "cut.pcap" in line for line in lines)
    assert "Traceback" not in built.stderr
    assert f"{len(fleet['files'])} analysed" in built.stdout


def test_captures_rows_equal_the_json_reports(fleet):
    rows = {r["file"]: r for r in read_table(fleet["dataset"], "captures")}
    reports = fleet["reports"]
    assert set(reports) <= set(rows) and len(rows) == len(reports) + 1       # + the unreadable one
    for path, report in reports.items():
        row, cap = rows[path], report["capture"]
        data = Path(path).read_bytes()
        assert row["size"] == len(data) and row["sha256"] == hashlib.sha256(data).hexdigest()
        assert row["status"] == ("ok" if cap["problem"] is None else "damaged")
        assert row["problem"] == cap["problem"]
        assert row["format"] == cap["format"]
        assert row["first_time"] == us(cap["first_time"]) and row["last_time"] == us(cap["last_time"])
        assert row["duration_s"] == cap["duration_s"]
        assert row["verdict_ok"] == report["verdict"]["ok"]
        assert row["findings"] == len(report["verdict"]["findings"])
        assert row["crc_variant"] == report["crc"]["variant"] and row["crc_byte_order"] == report["crc"]["byte_order"]
        for name, value in report["totals"].items():
            assert row[name] == value, (path, name)
        parts = Path(path).parts
        assert (row["site"], row["machine"]) == (parts[-3], parts[-2])
        assert row.get("bu_firmware") == ("3.2" if path.endswith("m1/normal.pcap") else None)


def test_senders_and_streams_equal_the_json_reports(fleet):
    senders = by_file(read_table(fleet["dataset"], "senders"))
    streams = by_file(read_table(fleet["dataset"], "streams"))
    for path, report in fleet["reports"].items():
        got = {r["sender"]: r for r in senders.get(path, [])}
        assert set(got) == {s["id"] for s in report["senders"]}
        for s in report["senders"]:
            row = got[s["id"]]
            assert (row["direction"], row["origin"], row["src"], row["serial_scope"]) == \
                   (s["direction"], s["origin"], s["src"], s["serial"]["scope"])
            for key in ("received", "lost", "duplicates", "out_of_order", "wraps", "restarts"):
                assert row[key] == s["serial"][key], (path, s["id"], key)
            for ptype in ("VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO"):
                assert row[ptype] == s["by_type"].get(ptype, 0)
        got_streams = {(r["type"], r["sender"]): r for r in streams.get(path, [])}
        assert set(got_streams) == {(p["type"], p["sender"]) for p in report["periodic"]}
        for p in report["periodic"]:
            row = got_streams[(p["type"], p["sender"])]
            assert row["count"] == p["count"] and row["nominal_ms"] == p["nominal_ms"]
            for q, v in (p["interval_ms"] or {}).items():
                assert row[f"interval_{q}_ms"] == v
            for q, v in (p["jitter_ms"] or {}).items():
                assert row[f"jitter_{q}_ms"] == v
            violations = p["watchdog"]["violations"]
            assert row["watchdog_violations"] == len(violations)
            assert row["watchdog_until_end"] == sum(v["until_end"] for v in violations)
            assert row["watchdog_max_gap_ms"] == (max(v["gap_ms"] for v in violations) if violations else None)
            assert row["bursts"] == p.get("bursts") and row["time_backwards"] == p["time_backwards"]
            assert row["outside_recommended"] == (p["outside_recommended"]["count"] if "outside_recommended" in p
                                                  else None)
            assert row["watchdog_limit_ms"] == p["watchdog"]["limit_ms"]


def test_commands_equal_the_json_reports(fleet):
    commands = by_file(read_table(fleet["dataset"], "commands"))
    checked = 0
    for path, report in fleet["reports"].items():
        rows = commands.get(path, [])
        for ctype, block in report["commands"].items():
            mine = [r for r in rows if r["type"] == ctype]
            assert len(mine) == block["commands"] == len(block["list"])
            assert sum(r["acked"] for r in mine) == block["acked"]
            assert sum(r["failed"] for r in mine) == block["failed"], (path, ctype)
            assert sum(r["interrupted_frame"] is not None for r in mine) == block["interrupted"]
            assert sum(r["retransmissions"] for r in mine) == block["retransmissions"]
            assert sum(r["transmissions"] for r in mine) == block["transmissions"]
            keyed = {(r["sender"], r["command_id"], r["first_frame"]): r for r in mine}
            for c in block["list"]:
                row = keyed[(c["sender"], c["command_id"], c["frames"][0])]
                assert (row["ack_frame"], row["latency_first_ms"], row["latency_last_ms"], row["spurious"]) == \
                       (c["ack_frame"], c["latency_first_ms"], c["latency_last_ms"], c["spurious"])
                assert row["time"] == us(c["time"]) and row["fail_limit_ms"] == block["fail_limit_ms"]
                assert row["transmissions"] == len(c["frames"]) and row["interrupted_frame"] == c["interrupted_frame"]
                checked += 1
    assert checked > 50


def test_findings_equal_the_json_reports(fleet):
    findings = by_file(read_table(fleet["dataset"], "findings"))
    for path, report in fleet["reports"].items():
        rows = findings.get(path, [])
        expected = []
        for f in report["verdict"]["findings"]:
            for n, item in enumerate(f.get("items") or [None]):
                expected.append((f["rule"], f["severity"], f["count"], f["message"], n if item else None,
                                 item and item["frame"], item and item.get("frames"), item and item["filter"],
                                 item and us(item["time"])))
        got = [(r["rule"], r["severity"], r["count"], r["message"], r["item"], r["frame"], r["frames"], r["filter"],
                r["time"]) for r in rows]
        assert sorted(got, key=repr) == sorted(expected, key=repr), path


def test_acknowledgement_findings_name_their_sender(fleet):
    """The rows of acks_without_command and duplicate_acks had no sender (every other located
    finding names one): each is the sender of the acknowledgement's packet, as the packets table
    (read apart from the analysis) and the senders table have it."""
    packets = {(r["capture_id"], r["frame"]): r for r in read_table(fleet["dataset"], "packets")}
    senders = {(r["capture_id"], r["sender"]): r for r in read_table(fleet["dataset"], "senders")}
    seen = set()
    for row in read_table(fleet["dataset"], "findings"):
        if row["rule"] in ("acks_without_command", "duplicate_acks"):
            packet = packets[(row["capture_id"], row["frame"])]
            sender = senders[(row["capture_id"], row["sender"])]
            assert (sender["src"], sender["origin"], packet["type"]) == (packet["src"], packet["origin"], row["type"])
            seen.add(row["rule"])
    assert seen == {"acks_without_command", "duplicate_acks"}


def test_report_names_each_findings_frame_time_and_sender(fleet):
    """Every finding on the page says where it is as the capture's report does: its capture,
    frame, time, sender and display filter (the time and the sender were not on the page)."""
    page = vm110("fleet", "report", str(fleet["dataset"]), "--html", "-").stdout
    table = page[page.index('<table class="findings">'):]
    table = table[:table.index("</table>")]
    head = re.findall(r"<th>([^<]*)</th>", table)
    assert {"capture", "frame", "time (UTC)", "sender", "display filter"} <= set(head)
    rows = [dict(zip(head, (html.unescape(re.sub(r"<[^>]+>", "", c)) for c in re.findall(r"<td[^>]*>(.*?)</td>", r))))
            for r in re.findall(r"<tr><td.*?</tr>", table)]
    items = {(path, f["rule"], item["frame"]): item for path, report in fleet["reports"].items()
             for f in report["verdict"]["findings"] for item in f.get("items") or []}
    assert len(rows) == min(len(items), 500) > 0
    for row in rows:
        item = items[(row["capture"], row["finding"], int(row["frame"]))]
        assert row["time (UTC)"] == us(item["time"]).isoformat(sep=" "), row
        assert row["sender"] == (item.get("sender") or item.get("src") or ""), row
        assert row["display filter"] == item["filter"], row


def test_errors_and_packets(fleet):
    errors = {r["file"]: r for r in read_table(fleet["dataset"], "errors")}
    cut, junk = str(fleet["files"]["cut"]), str(fleet["files"]["junk"])
    assert set(errors) == {cut, junk}
    assert errors[cut]["kind"] == "damaged"
    assert errors[cut]["message"] == fleet["reports"][cut]["capture"]["problem"]
    assert errors[junk]["kind"] == "unreadable"
    # what analyze says, word for word, without the path (the `file` column has it), as a damaged one's
    assert f"vm110 analyze: {junk}: {errors[junk]['message']}" == fleet["junk_error"]
    assert all(path not in row["message"] for path, row in errors.items())
    assert errors[junk]["machine"] == "m6"
    packets = by_file(read_table(fleet["dataset"], "packets"))
    for path, report in fleet["reports"].items():
        rows = packets.get(path, [])
        assert len(rows) == report["capture"]["eglink_packets"]
        assert sum(not r["legal"] for r in rows) == report["illegal"]["total"]


def test_worst_links_and_machines_count_the_same_captures(fleet):
    """Both rankings count every capture of a machine, and say how many could not be read."""
    def counts(what: str) -> dict:
        rows = json.loads(vm110("fleet", "query", str(fleet["dataset"]), "--worst", what, "--format", "json").stdout)
        return {(r["site"], r["machine"]): (r["captures"], r["unreadable"]) for r in rows}
    links = counts("links")
    assert links == counts("machines")
    assert links[("west", "m6")] == (3, 1) and links[("east", "m5")] == (3, 0)     # junk; cut is damaged, not unreadable
    assert sum(n for n, _ in links.values()) == len(read_table(fleet["dataset"], "captures"))


def test_dask_local_cluster_builds_the_same_rows(fleet, tmp_path):
    """A real distributed.LocalCluster with two worker processes, not a mock."""
    dataset = tmp_path / "dask"
    built = vm110("fleet", "build", str(fleet["root"] / "sites"), "--out", f"file://{dataset}", "--packets",
                  "--engine", "dask", "-j", "2", "--meta", "sites/{site}/{machine}/*", check=False)
    assert built.returncode == 2 and f"{len(fleet['files'])} analysed" in built.stdout, built.stderr
    for table in TABLES:
        local = sorted(read_table(fleet["dataset"], table), key=repr)
        remote = sorted(read_table(dataset, table), key=repr)
        assert local == remote, table
        if table != "errors":
            assert local


def test_dask_on_a_given_scheduler(fleet, tmp_path):
    """--scheduler: the build goes to a cluster that is already running (here one started by the test)."""
    from distributed import LocalCluster
    from vm110.fleet.build import build
    from vm110.fleet.sources import MetaPattern
    from vm110.fleet.work import Settings
    paths = [str(fleet["files"][name]) for name in ("normal.pcap", "retransmit.pcap", "cut")]
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as cluster:     # (None still takes 8787: see fleet.engines)
        outcome = build(paths, Settings(dataset=str(tmp_path / "s"), packets=True),
                        MetaPattern("sites/{site}/{machine}/*"), engine="dask", jobs=1,
                        scheduler=cluster.scheduler_address)
    assert outcome.analysed == 3 and len(outcome.damaged) == 1
    for table in TABLES:
        expected = sorted((r for r in read_table(fleet["dataset"], table) if r["file"] in paths), key=repr)
        assert sorted(read_table(tmp_path / "s", table), key=repr) == expected, table


def build_mixed(tmp_path: Path) -> list[Path]:
    """A dataset (tmp_path/ds) of one capture named north/m1 by its sidecar and two without
    metadata (returned)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    shutil.copy(BUNDLED / "loss.pcapng", tmp_path / "a" / "loss.pcapng")
    (tmp_path / "a" / "loss.pcapng.meta.json").write_text(json.dumps({"site": "north", "machine": "m1"}))
    plain = [tmp_path / "b" / name for name in ("retransmit.pcap", "controller-watchdog.pcap")]
    for path in plain:
        shutil.copy(BUNDLED / path.name, path)
    vm110("fleet", "build", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "ds"), "-j", "1")
    return plain


def test_captures_without_metadata_rank_each_under_its_file(tmp_path):
    """A capture without site and machine is its own machine, named by its file, with its own
    figures (a NULL key joined nothing: all such captures were one blank row of zeros)."""
    plain = build_mixed(tmp_path)

    def worst(what: str) -> dict:
        rows = json.loads(vm110("fleet", "query", str(tmp_path / "ds"), "--worst", what, "--format", "json").stdout)
        return {r["file"] or (r["site"], r["machine"]): r for r in rows}
    links, machines = worst("links"), worst("machines")
    assert set(links) == set(machines) == {("north", "m1"), *map(str, plain)}
    for path in plain:
        report = json.loads(vm110("analyze", str(path), "--json", "-", check=False).stdout)
        errors = sum(f["severity"] == "error" for f in report["verdict"]["findings"])
        assert links[str(path)]["lost"] == report["totals"]["lost"] > 0
        assert links[str(path)]["watchdog"] == report["totals"]["watchdog"]
        assert (machines[str(path)]["captures"], machines[str(path)]["error_findings"]) == (1, errors)


def test_report_counts_captures_without_metadata_each_as_a_machine(tmp_path):
    """The report's machines are the rankings': a capture without site and machine is one of its
    own, in the count and in the spread across machines (they were one machine, "None/None")."""
    plain = build_mixed(tmp_path)
    page = vm110("fleet", "report", str(tmp_path / "ds"), "--html", "-").stdout
    assert re.search(r"<p>3 captures of 3 machines", page), page[:2000]
    figure = re.search(r'<figure data-plot="spread-vrpi-jitter">.*?</figure>', page, re.S)
    assert figure and "None" not in figure.group(0)
    for path in plain:
        report = json.loads(vm110("analyze", str(path), "--json", "-", check=False).stdout)
        vrpi = max(p["jitter_ms"]["max"] for p in report["periodic"] if p["type"] == "VRPI")
        row = re.search(rf"<title>{re.escape(str(path))}</title>.*?<title>min ([^,]+), median [^,]+, max ([^ ]+) ms",
                        figure.group(0))
        assert row and float(row.group(1)) == float(row.group(2)) == pytest.approx(vrpi, abs=5e-4), path


def test_a_metadata_field_is_a_column_of_every_table(fleet):
    """`bu_firmware` comes from one capture's sidecar; the unreadable and damaged captures have
    none, and `errors` holds only their rows: the column is there all the same, NULL."""
    out = vm110("fleet", "query", str(fleet["dataset"]), "SELECT bu_firmware, count(*) AS n FROM errors GROUP BY ALL",
                "--format", "json").stdout
    assert json.loads(out) == [{"bu_firmware": None, "n": len(read_table(fleet["dataset"], "errors"))}]
    listed = vm110("fleet", "query", str(fleet["dataset"]), "--list").stdout
    assert all("bu_firmware" in line for line in listed.splitlines() if line.split(":")[0].strip() in TABLES)
