"""vm110 fleet on bad input (one line, exit 2, nothing in the dataset lost) and rebuilding
(skipped when unchanged, replaced when changed, continued after a kill)."""
from __future__ import annotations

import contextlib
import glob
import gzip
import hashlib
import io
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from vm110.cli import main
from vm110.errors import CliError

ROOT = Path(__file__).resolve().parent.parent
BUNDLED = ROOT / "captures"
NAMES = ("normal.pcap", "disarmed.pcap", "retransmit.pcap", "vrco.pcap", "bu-stops.pcap", "controller-watchdog.pcap")


def vm110(*args: str) -> subprocess.CompletedProcess:
    """The command run in this process (quicker than a new interpreter), as a CompletedProcess."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:          # argparse's usage errors
            code = int(exc.code or 0)
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def rows(dataset: Path, table: str = "captures") -> list[dict]:
    manifest = json.loads((dataset / "manifest.json").read_text())
    out = []
    for entry in manifest["captures"].values():
        out += [r for part in entry["parts"] if part.startswith(table + "/")
                for r in pq.read_table(dataset / part).to_pylist()]
    return sorted(out, key=lambda r: r["file"])


def by_name(table_rows: list[dict]) -> dict[str, list[dict]]:
    """Rows by capture file name, without the columns that name the file."""
    out: dict[str, list[dict]] = {}
    for r in table_rows:
        out.setdefault(Path(r["file"]).name, []).append(
            {k: v for k, v in r.items() if k not in ("file", "capture_id")})
    return {k: sorted(v, key=repr) for k, v in out.items()}


def one_line_error(result: subprocess.CompletedProcess, *words: str) -> None:
    assert result.returncode == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vm110 fleet"), result.stderr
    for word in words:
        assert word in lines[0], lines[0]


@pytest.fixture
def src(tmp_path) -> Path:
    folder = tmp_path / "src"
    folder.mkdir()
    for name in NAMES:
        shutil.copy(BUNDLED / name, folder / name)
    return folder


@pytest.fixture
def built(src, tmp_path) -> Path:
    dataset = tmp_path / "ds"
    result = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1")
    assert result.returncode == 0, result.stderr
    return dataset


def test_rebuild_skips_unchanged_and_replaces_changed(src, built, tmp_path):
    before = snapshot(built)
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert again.returncode == 0 and "0 analysed" in again.stdout and f"{len(NAMES)} already" in again.stdout
    assert snapshot(built) == before                          # not a byte rewritten
    old = {r["file"]: r for r in rows(built)}
    shutil.copy(BUNDLED / "loss.pcapng", src / "normal.pcap")   # the file changes
    changed = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert changed.returncode == 0 and "1 analysed" in changed.stdout and "1 replaced" in changed.stdout
    new = {r["file"]: r for r in rows(built)}
    path = str(src / "normal.pcap")
    assert new[path]["sha256"] != old[path]["sha256"] and new[path]["format"] == "pcapng"
    assert {k: v for k, v in new.items() if k != path} == {k: v for k, v in old.items() if k != path}
    manifest = json.loads((built / "manifest.json").read_text())
    listed = {p for e in manifest["captures"].values() for p in e["parts"]}
    on_disk = {str(p.relative_to(built)) for p in built.rglob("*.parquet")}
    assert on_disk == listed                                   # the replaced capture's parts are gone
    assert len(rows(built)) == len(NAMES)


@pytest.mark.parametrize("stop, jobs", [(signal.SIGKILL, "1"), (signal.SIGINT, "2")], ids=["kill", "ctrl-c"])
def test_stopped_build_continues_where_it_stopped(src, built, tmp_path, stop, jobs):
    """A kill (nothing runs after it) and Ctrl-C to the whole process group (pool workers too)."""
    # Captures take milliseconds: a loaded machine may finish the whole job between two looks at
    # the dataset (the signal then lands on a process already ending). Such a try proves nothing:
    # again with a job twice as big.
    copies, made = 10, 0
    for _ in range(4):
        for n in range(made, copies):
            for name in NAMES:     # (not the same bytes: a copy is not analysed again; sigfigs is unused)
                data = bytearray((src / name).read_bytes())
                data[12:16] = (n + 1).to_bytes(4, "little")
                (src / f"copy{n}-{name}").write_bytes(data)
        made, total = copies, (copies + 1) * len(NAMES)
        dataset = tmp_path / f"killed-{copies}"
        command = [sys.executable, "-m", "vm110", "fleet", "build", str(src), "--out", str(dataset), "-j", jobs]
        # Ctrl-C as at a terminal: a test run in the background (`make test &`) hands its children
        # SIGINT ignored, and Python keeps an inherited ignore; a handled signal is reset by exec.
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
        finally:
            signal.signal(signal.SIGINT, previous)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if (dataset / "captures").exists() and len(list((dataset / "captures").glob("part-*.parquet"))) >= 3:
                break
            time.sleep(0.02)
        if proc.poll() is None:
            os.killpg(proc.pid, stop)
        _, err = proc.communicate(timeout=60)
        done_before = len(list((dataset / "captures").glob("part-*.parquet")))
        if done_before < total:
            break
        copies *= 2
    if stop == signal.SIGINT:                                   # stopped quietly, no traceback
        assert proc.returncode == 130 and err == "", (proc.returncode, err, f"{done_before}/{total} done")
    assert 3 <= done_before < total
    resumed = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1")
    assert resumed.returncode == 0, resumed.stderr
    analysed = int(resumed.stdout.split(": ")[1].split()[0])
    assert analysed <= total - done_before + 1                 # finished work is kept (one may be mid-write)
    assert not [p for p in dataset.rglob("*") if p.name.endswith(".tmp")]
    # Every capture as a build without a stop has it: a copy's rows are its original's (in `built`).
    for table in ("captures", "senders", "streams", "commands", "findings"):
        expected = by_name(rows(built, table))
        got = by_name(rows(dataset, table))
        if table == "captures":
            assert len(got) == total
        assert {n.split("-", 1)[1] if n.startswith("copy") else n for n in got} == set(expected), table
        for name, got_rows in got.items():
            if name.startswith("copy"):     # (the same rows but for the content hash)
                have = [{k: v for k, v in r.items() if k != "sha256"} for r in got_rows]
                want = [{k: v for k, v in r.items() if k != "sha256"} for r in expected[name.split("-", 1)[1]]]
            else:
                have, want = got_rows, expected[name]
            assert have == want, (table, name)


def test_a_running_build_writes_what_it_adds_not_the_whole_manifest(src, built):
    """The manifest was rewritten whole every 2 s while a build ran: a cost that grew with the
    dataset (quadratic over a build of many thousands). Each update is now a journal batch of the
    captures completed since the last; query sees them; a kill keeps them; the next build writes
    the manifest whole. (Checkpoints after every capture here, to see each one.)"""
    manifest = (built / "manifest.json").read_bytes()
    for n in range(40):                 # (not the same bytes: a copy is not analysed again)
        data = bytearray((BUNDLED / "normal.pcap").read_bytes())
        data[12:16] = (n + 1).to_bytes(4, "little")
        (src / f"more{n:02d}.pcap").write_bytes(data)
    run = ("import sys, vm110.fleet.build as b; from vm110.cli import main; b.CHECKPOINT_S = 0; "
           "sys.exit(main(sys.argv[1:]))")
    proc = subprocess.Popen([sys.executable, "-c", run, "fleet", "build", str(src), "--out", str(built), "-j", "1"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": str(ROOT / "pcap_tools")})
    journal = built / "journal"
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline and len(list(journal.glob("*.json"))) < 3:
        time.sleep(0.005)
    proc.kill()
    proc.communicate(timeout=60)
    batches = sorted(journal.glob("*.json"))
    assert proc.returncode == -signal.SIGKILL and len(batches) >= 3
    assert (built / "manifest.json").read_bytes() == manifest          # not rewritten while it ran
    added = [json.loads(b.read_text())["captures"] for b in batches]
    assert all(len(batch) == 1 for batch in added)                      # each batch: one capture, not all
    files = {e["file"] for batch in added for e in batch.values()}
    assert len(files) == len(batches) and all(Path(f).name.startswith("more") for f in files)
    seen = vm110("fleet", "query", str(built), "--format", "json", "SELECT file FROM captures")
    assert {r["file"] for r in json.loads(seen.stdout)} >= files | {str(src / n) for n in NAMES}
    (journal / f".{len(batches):09d}.json.0123abcd.tmp").write_text("{")     # a batch the kill cut short
    resumed = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert resumed.returncode == 0, resumed.stderr
    assert int(resumed.stdout.split(": ")[1].split()[0]) <= 40 - len(batches)      # the journal's are kept
    assert list(journal.glob("*")) == []
    listed = json.loads((built / "manifest.json").read_text())["captures"]
    assert sorted(Path(e["file"]).name for e in listed.values()) == sorted([*NAMES, *(f"more{n:02d}.pcap"
                                                                                      for n in range(40))])
    want = [{k: v for k, v in r.items() if k not in ("capture_id", "file", "sha256")}
            for r in rows(built) if r["file"] == str(src / "normal.pcap")]
    for name in ("more00.pcap", "more39.pcap"):
        got = [{k: v for k, v in r.items() if k not in ("capture_id", "file", "sha256")}
               for r in rows(built) if r["file"] == str(src / name)]
        assert got == want, name


def test_a_reader_of_the_manifest_a_build_writes_whole_meanwhile_reads_it_again(built, monkeypatch):
    """A query read manifest.json, then the build wrote it whole (its journal folded in) and went
    on with a new batch: the new batch applied to the old file would lose the captures folded in
    (and list parts the build has since removed). The reader sees the batch does not follow its
    file and reads the manifest again."""
    from vm110.fleet.dataset import Dataset
    entry = {"size": 1, "sha256": "0" * 64, "status": "ok", "parts": [], "message": None, "meta": {}}
    builder = Dataset(str(built))
    doc = builder.read_manifest()
    gone = sorted(doc["captures"])[0]
    old = (built / "manifest.json").read_bytes()                   # what the reader reads first
    builder.journal({"y" * 24: {**entry, "file": "/y.pcap"}}, [])
    doc["captures"]["y" * 24] = {**entry, "file": "/y.pcap"}
    builder.write_manifest(doc)
    builder.journal({"z" * 24: {**entry, "file": "/z.pcap"}}, [gone])
    reader = Dataset(str(built))
    real_open, opened = reader.fs.open, []

    def stale_once(path, mode="rb", **kwargs):
        if path.endswith("manifest.json") and not opened:
            opened.append(path)
            return io.BytesIO(old)
        return real_open(path, mode, **kwargs)
    monkeypatch.setattr(reader.fs, "open", stale_once)
    got = reader.read_manifest()["captures"]
    assert opened and set(got) == (set(doc["captures"]) - {gone}) | {"z" * 24}


def test_unreadable_capture_is_an_error_row(src, built):
    (src / "broken.pcap").write_bytes(b"\xd4\xc3\xb2\xa1" + b"\x00" * 3)       # a pcap magic, then nothing
    before = rows(built)
    result = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "broken.pcap" in lines[0]
    after = rows(built)
    assert [r for r in after if r["file"] != str(src / "broken.pcap")] == before
    errors = rows(built, "errors")
    assert [(r["file"], r["kind"]) for r in errors] == [(str(src / "broken.pcap"), "unreadable")]
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")      # tried again, every time
    assert again.returncode == 2 and "1 analysed" in again.stdout and f"{len(NAMES)} already" in again.stdout
    assert rows(built, "errors") == errors and len(rows(built)) == len(NAMES) + 1


def test_gzip_compressed_captures_in_a_folder_are_built(tmp_path):
    """A `.pcap.gz` (tcpdump -z gzip) is analysed as its plain capture is (the build passed over
    them in silence, trial), and is that capture: `gzip plain.pcap` (which removes plain.pcap)
    moves it, and a .pcap.gz beside its .pcap is a copy. Both were a second capture, counted
    twice in every sum (trial-fleet)."""
    folder = tmp_path / "caps"
    folder.mkdir()
    data = (BUNDLED / "retransmit.pcap").read_bytes()
    (folder / "plain.pcap").write_bytes(data)
    dataset = tmp_path / "ds"
    assert vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1").returncode == 0
    plain = {t: by_name(rows(dataset, t))["plain.pcap"] for t in ("captures", "senders", "commands", "findings")}
    (folder / "packed.pcap.gz").write_bytes(gzip.compress(data))
    (folder / "plain.pcap").unlink()
    result = vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1")
    assert result.returncode == 0 and "1 analysed" in result.stdout and "1 replaced" in result.stdout, result
    assert [Path(r["file"]).name for r in rows(dataset)] == ["packed.pcap.gz"]
    assert rows(dataset)[0]["sha256"] == hashlib.sha256(data).hexdigest()
    for table, want in plain.items():
        got = by_name(rows(dataset, table))["packed.pcap.gz"]
        if table == "captures":
            for r in got + want:
                del r["size"]
        assert got == want != [], table
    (folder / "plain.pcap").write_bytes(data)        # the plain capture back beside it: a copy
    again = vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1")
    assert again.returncode == 0 and "1 copy not counted" in again.stdout, again
    assert again.stderr == (f"vm110 fleet: copy, counted once: {folder / 'plain.pcap'}: the same capture as "
                            f"{folder / 'packed.pcap.gz'}\n")
    assert [Path(r["file"]).name for r in rows(dataset)] == ["packed.pcap.gz"]


def test_folder_without_captures(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no captures here")
    one_line_error(vm110("fleet", "build", str(empty), "--out", str(tmp_path / "ds")), "no captures")
    assert not (tmp_path / "ds").exists()
    one_line_error(vm110("fleet", "build", str(tmp_path / "missing"), "--out", str(tmp_path / "ds")), "no such")


def test_a_datagram_split_by_a_ring_buffer_s_file_boundary_is_said(tmp_path):
    """A VRPO whose two fragments a ring buffer wrote to two files is in neither capture's rows
    (each is analysed on its own), but in each file's ip_fragments warning; merged, the VRPO is
    analysed. docs/fleet.md said nothing of what spans two files (trial-fleet)."""
    import site_captures as S
    records = []
    for serial in range(1, 5):
        body = S.udp(S.CTRL_IP, 5827, S.GROUP, 5827, S.vrpo(serial, 0, bytes(488)))
        d = S.Datagram(serial * 0.1, S.CTRL_IP, 5827, S.GROUP, 5827, b"")
        records += [S.Record(d.ts_ns + i * 1000, S.on_ethernet()(d, part))
                    for i, part in enumerate(S.ipv4_fragments(S.CTRL_IP, S.GROUP, body, 400, serial))]
    ring = tmp_path / "m1"
    ring.mkdir()
    halves = (S.pcapng([S.Interface(1)], records[:5]), S.pcapng([S.Interface(1)], records[5:]))
    for n, half in enumerate(halves, start=1):
        (ring / f"ring_0000{n}.pcapng").write_bytes(half)
    (tmp_path / "merged.pcapng").write_bytes(b"".join(halves))     # (two sections, as `cat` gives)
    for src, dataset in ((ring, tmp_path / "ds"), (tmp_path / "merged.pcapng", tmp_path / "merged")):
        assert vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1").returncode == 0
    assert [r["eglink_packets"] for r in rows(tmp_path / "ds")] == [2, 1]
    assert [(r["rule"], r["count"]) for r in rows(tmp_path / "ds", "findings")] == [("ip_fragments", 1)] * 2
    assert [r["eglink_packets"] for r in rows(tmp_path / "merged")] == [4] and rows(tmp_path / "merged", "findings") == []
    doc = " ".join((ROOT / "docs" / "fleet.md").read_text().split())
    assert "what spans two files of a ring buffer is not seen" in doc


@pytest.mark.parametrize("version", [99, 1, 5])
def test_dataset_of_another_version(version, src, built, tmp_path):
    """(1: built before the severity note; its warnings would have mixed with a new build's notes.
    5: built before IP reassembly; a fragmented VRPO missing from its rows, present in a new build's.)"""
    manifest = built / "manifest.json"
    doc = json.loads(manifest.read_text())
    doc["format_version"] = version
    manifest.write_text(json.dumps(doc))
    before = snapshot(built)
    one_line_error(vm110("fleet", "build", str(src), "--out", str(built)), f"version {version}")
    one_line_error(vm110("fleet", "query", str(built), "SELECT 1"), f"version {version}")
    one_line_error(vm110("fleet", "report", str(built), "--html", str(tmp_path / "r.html")), f"version {version}")
    assert snapshot(built) == before and not (tmp_path / "r.html").exists()


def test_foreign_folder_and_other_options(src, built, tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "mine.txt").write_text("keep me")
    one_line_error(vm110("fleet", "build", str(src), "--out", str(foreign)), "not empty")
    assert snapshot(foreign) == {"mine.txt": b"keep me"}
    before = snapshot(built)
    one_line_error(vm110("fleet", "build", str(src), "--out", str(built), "--vrpi-watchdog", "400"),
                   "other analysis options", "vrpi_watchdog_ms")
    assert snapshot(built) == before
    one_line_error(vm110("fleet", "build", str(src), "--out", str(tmp_path / "x"), "--meta", "{site"), "names no field")
    # Two fields side by side split "north7" any way: refused, not guessed (it was accepted).
    one_line_error(vm110("fleet", "build", str(src), "--out", str(tmp_path / "x"), "--meta", "sites/{site}{machine}/*"),
                   "{site}{machine} has nothing between them")
    assert not (tmp_path / "x").exists()
    one_line_error(vm110("fleet", "build", str(src), "--out", str(tmp_path / "x"), "-j", "nan"), "-j")


def test_failing_sql_changes_nothing(built, tmp_path):
    before = snapshot(built)
    one_line_error(vm110("fleet", "query", str(built), "SELEC nothing"), "query failed")
    one_line_error(vm110("fleet", "query", str(built), "SELECT nope FROM captures"), "query failed", "nope")
    part = next((built / "captures").glob("*.parquet"))
    one_line_error(vm110("fleet", "query", str(built), f"COPY captures TO '{part}' (FORMAT parquet)"), "query failed")
    one_line_error(vm110("fleet", "query", str(built), "SELECT * FROM read_csv('/etc/passwd')"), "query failed")
    one_line_error(vm110("fleet", "query", str(built), "--trend", "colour"), "--trend")
    one_line_error(vm110("fleet", "query", str(tmp_path / "nothing")), "not a vm110 fleet dataset")
    assert snapshot(built) == before
    good = vm110("fleet", "query", str(built), "SELECT count(*) AS n FROM captures", "--format", "json")
    assert json.loads(good.stdout) == [{"n": len(NAMES)}]


def test_fsspec_url_dataset():
    """Any fsspec URL holds a dataset: here memory://, built, queried and rebuilt in this process."""
    from vm110.fleet.build import build
    from vm110.fleet.query import Fleet
    from vm110.fleet.work import Settings
    settings = Settings(dataset="memory://vm110-fleet-test")
    paths = [str(BUNDLED / "normal.pcap"), str(BUNDLED / "retransmit.pcap")]
    first = build(paths, settings, jobs=1)
    assert (first.analysed, first.skipped) == (2, 0)
    fleet = Fleet(settings.dataset)
    got = dict(fleet.run("SELECT file, lost FROM captures").rows)
    reports = {p: json.loads(vm110("analyze", p, "--json", "-", "--quiet").stdout) for p in paths}
    assert got == {p: r["totals"]["lost"] for p, r in reports.items()}
    again = build(paths, settings, jobs=1)
    assert (again.analysed, again.skipped) == (0, 2)


def test_metadata_from_path_and_sidecar(tmp_path):
    from vm110.errors import CliError
    from vm110.fleet.sources import MetaPattern, metadata
    pattern = MetaPattern("sites/{site}/**/{machine}-*.pcap")
    capture = tmp_path / "sites" / "north" / "hall 2" / "crane-7-w1.pcap"
    capture.parent.mkdir(parents=True)
    capture.write_bytes(b"")
    assert metadata(str(capture), pattern) == {"site": "north", "machine": "crane-7"}     # greedy, as a glob
    assert metadata(str(tmp_path / "elsewhere.pcap"), pattern) == {"site": None, "machine": None}
    side = Path(str(capture) + ".meta.json")
    side.write_text(json.dumps({"bu_firmware": 3.4, "commissioned": True, "note": None}))
    assert metadata(str(capture), pattern) == {"site": "north", "machine": "crane-7", "bu_firmware": "3.4",
                                               "commissioned": "true", "note": None}
    for bad, words in (({"machine": "other"}, "by --meta"), ({"a b": 1}, "not a column name"),
                       ({"x": [1]}, "only text"), ([1, 2], "JSON object"), ("NaN", "not a metadata file")):
        side.write_text(bad if isinstance(bad, str) else json.dumps(bad))
        with pytest.raises(CliError, match=words):
            metadata(str(capture), pattern)
    for bad_pattern in ("{site", "sites/*.pcap", "{a}/{a}"):
        with pytest.raises(CliError):
            MetaPattern(bad_pattern)


def test_a_meta_pattern_s_double_star_is_no_folder_or_many_as_in_glob(tmp_path):
    """`sites/{site}/**/{machine}/*.pcap` matched no capture right in its machine's folder below its
    site (`**` between slashes wanted a folder at least), and left its site and machine empty
    (trial). The captures it matches are those glob matches with each field a `*`."""
    from vm110.fleet.sources import MetaPattern
    for where in ("north/crane-01", "south/yard/crane-02", "east/a/b/crane-03", "crane-04"):
        (tmp_path / "sites" / where).mkdir(parents=True)
        (tmp_path / "sites" / where / "w1.pcap").write_bytes(b"")
    pattern = MetaPattern("sites/{site}/**/{machine}/*.pcap")
    globbed = set(glob.glob(str(tmp_path / "sites/*/**/*/*.pcap"), recursive=True))
    assert len(globbed) == 3
    for path in map(str, tmp_path.rglob("*.pcap")):
        fields = pattern.fields(path)
        parts = Path(path).relative_to(tmp_path / "sites").parts
        assert fields == ({"site": parts[0], "machine": parts[-2]} if path in globbed else None), path


def test_a_meta_pattern_that_matches_no_capture_path_is_said(src, tmp_path):
    """A --meta pattern that matched none of a build's captures (a typo) left every site and
    machine empty without a word (trial). The count is of the captures found, copies too (it
    said 7 of 6, trial-fleet)."""
    dataset = tmp_path / "ds"
    shutil.copy(src / "normal.pcap", src / "z-copy.pcap")
    result = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1", "--meta", "site/{site}/{machine}.pcap")
    assert result.returncode == 0, result.stderr
    copy, line = result.stderr.splitlines()
    assert line.startswith(f"vm110 fleet: --meta 'site/{{site}}/{{machine}}.pcap' does not match the path of "
                           f"{len(NAMES) + 1} of {len(NAMES) + 1} captures (the first: {src}/")
    assert copy.startswith("vm110 fleet: copy, counted once: ")
    assert "their site, machine are empty unless a sidecar gives them" in line
    assert {r["site"] for r in rows(dataset)} == {None}
    again = vm110("fleet", "build", str(src), "--out", str(tmp_path / "ds2"), "-j", "1", "--meta", "{machine}.pcap*")
    assert again.returncode == 0 and "does not match" not in again.stderr, again.stderr


def test_meta_pattern_may_not_shadow_a_column(src, tmp_path):
    """A --meta field named after a column is a usage error, before anything is written (a
    sidecar's is its capture's error row: test_bad_sidecars_are_error_rows_and_the_build_goes_on)."""
    one_line_error(vm110("fleet", "build", str(src), "--out", str(tmp_path / "x"), "--meta", "{lost}.pcap"),
                   "'lost'", "column")
    assert not (tmp_path / "x").exists()


def test_progress_bar(src, tmp_path, capsys):
    from vm110.fleet.build import build
    from vm110.fleet.work import Settings
    build([str(src)], Settings(dataset=str(tmp_path / "p")), jobs=1, progress=True)
    err = capsys.readouterr().err
    assert f"] {len(NAMES)}/{len(NAMES)} captures" in err and "\r" in err
    assert err.endswith("\r\033[K")                       # the line is cleared at the end


def test_one_build_at_a_time(src, built):
    from vm110.fleet.dataset import Dataset
    before = snapshot(built)
    with Dataset(str(built)).lock():                      # as a build that is running holds it
        one_line_error(vm110("fleet", "build", str(src), "--out", str(built)), "another build")
    assert snapshot(built) == before
    assert vm110("fleet", "build", str(src), "--out", str(built)).returncode == 0


def test_query_takes_options_between_dataset_and_sql(built):
    """argparse alone takes an optional SQL as absent once an option follows DATASET."""
    got = vm110("fleet", "query", str(built), "--format", "json", "SELECT count(*) AS n FROM captures")
    assert got.returncode == 0, got.stderr
    assert json.loads(got.stdout) == [{"n": len(NAMES)}]
    csv = vm110("fleet", "query", "--format", "csv", str(built), "SELECT 1 AS one")
    assert (csv.returncode, csv.stdout) == (0, "one\n1\n"), csv.stderr


@pytest.mark.parametrize("args, words", [
    (("SELECT 1", "SELECT 2"), ("unrecognized arguments: SELECT 2",)),
    (("--bogus",), ("unrecognized arguments: --bogus",)),
    (("--format", "xml", "SELECT 1"), ("--format", "xml")),
    (("--limit", "0"), ("--limit",)),
    ((), ("give SQL",)),
    (("-- nothing but a comment;",), ("query failed", "no statement")),                                    # the command's own check (CliError)
    (("SELECT 1", "--worst", "links"), ("give one of",)),
    # An option the query does not take was passed over: a month's worst links were all months'.
    (("--worst", "links", "--month", "2025-06"), ("--month does not apply to worst-links", "watchdog")),
    (("--trend", "loss", "--limit", "3"), ("--limit does not apply to trend",)),
    (("--named", "errors", "--by", "month"), ("--by does not apply to errors", "trend")),
    (("SELECT 1", "--month", "2025-06"), ("--month does not apply to SQL",)),
])
def test_query_errors_are_one_line_of_the_command(built, args, words):
    """`vm110 fleet: ...` (as every command's: `vm110 <command>: ...`), not the top-level `vm110: ...`."""
    result = vm110("fleet", "query", str(built), *args)
    one_line_error(result, *words)
    assert result.stderr.startswith("vm110 fleet: "), result.stderr


def test_build_takes_sources_after_options(src, tmp_path):
    dataset = tmp_path / "ds"
    got = vm110("fleet", "build", str(src / NAMES[0]), "--out", str(dataset), "-j", "1", str(src / NAMES[1]))
    assert got.returncode == 0 and "2 analysed" in got.stdout, got.stderr
    missing = vm110("fleet", "build", str(src))
    one_line_error(missing, "--out")
    assert missing.stderr.startswith("vm110 fleet: ")


def test_bad_sidecars_are_error_rows_and_the_build_goes_on(src, tmp_path):
    """Each bad sidecar: its capture gets an `unreadable` row with every problem of that sidecar,
    one line each on standard error; the other captures are built; fixed, it is analysed."""
    sidecars = {"normal.pcap": json.dumps({"machine": "crane-9", "bu_firmware": "3.4"}),      # --meta says normal
                "disarmed.pcap": "{not json",
                "vrco.pcap": json.dumps({"a b": 1, "lost": "none", "x": [1]})}
    for name, text in sidecars.items():
        (src / f"{name}.meta.json").write_text(text)
    dataset = tmp_path / "ds"
    result = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1", "--meta", "{machine}.pcap")
    assert result.returncode == 2
    assert f"{len(NAMES)} analysed (0 damaged, 3 unreadable)" in result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith("vm110 fleet: ") for line in lines), lines
    line = {name: next(x for x in lines if f"{src / name}: " in x) for name in sidecars}
    assert "'crane-9' in its sidecar" in line["normal.pcap"] and "'normal' by --meta" in line["normal.pcap"]
    assert "normal.pcap.meta.json" in line["normal.pcap"]
    assert "not a metadata file" in line["disarmed.pcap"]
    for words in ("'a b' is not a column name", "'lost' is a column", "x: only text"):      # all, at once
        assert words in line["vrco.pcap"], line["vrco.pcap"]
    captures = {Path(r["file"]).name: r for r in rows(dataset)}
    assert len(captures) == len(NAMES)
    assert {n for n, r in captures.items() if r["status"] == "unreadable"} == set(sidecars)
    assert captures["normal.pcap"]["machine"] == "normal" and captures["retransmit.pcap"]["status"] == "ok"
    errors = {Path(r["file"]).name: r for r in rows(dataset, "errors")}
    assert set(errors) == set(sidecars) and {r["kind"] for r in errors.values()} == {"unreadable"}
    assert all(r["file"] not in r["message"] for r in errors.values())
    (src / "normal.pcap.meta.json").write_text(json.dumps({"bu_firmware": "3.4"}))           # fixed
    again = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1", "--meta", "{machine}.pcap")
    assert again.returncode == 2 and "3 analysed (0 damaged, 2 unreadable)" in again.stdout
    assert "1 replaced" in again.stdout and len(again.stderr.strip().splitlines()) == 2
    captures = {Path(r["file"]).name: r for r in rows(dataset)}
    assert len(captures) == len(NAMES) and captures["normal.pcap"]["status"] == "ok"
    assert captures["normal.pcap"]["bu_firmware"] == "3.4"
    assert {Path(r["file"]).name for r in rows(dataset, "errors")} == {"disarmed.pcap", "vrco.pcap"}


def test_unreadable_entries_of_a_folder(src, tmp_path):
    """A broken link, a FIFO (never opened: reading it would wait for a writer) and a link out of
    the folder given: an unreadable row each. A link that stays inside the folder is its target,
    taken once (under the target's name)."""
    (src / "gone.pcap").symlink_to(tmp_path / "nothing.pcap")
    os.mkfifo(src / "fifo.pcap")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copy(BUNDLED / "loss.pcapng", elsewhere / "loss.pcapng")
    (src / "out.pcapng").symlink_to(elsewhere / "loss.pcapng")
    (src / "in.pcap").symlink_to(src / "normal.pcap")
    (src / "folder.pcap").mkdir()                          # a folder is walked, not a capture
    dataset = tmp_path / "ds"
    command = [sys.executable, "-m", "vm110", "fleet", "build", str(src), "--out", str(dataset), "-j", "1"]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert f"{len(NAMES) + 3} analysed (0 damaged, 3 unreadable)" in result.stdout
    assert len(result.stderr.strip().splitlines()) == 3, result.stderr
    captures = {Path(r["file"]).name: r for r in rows(dataset)}
    assert {n for n, r in captures.items() if r["status"] == "unreadable"} == {"gone.pcap", "fifo.pcap", "out.pcapng"}
    assert "in.pcap" not in captures and captures["normal.pcap"]["status"] == "ok"
    errors = {Path(r["file"]).name: r["message"] for r in rows(dataset, "errors")}
    assert "broken symbolic link" in errors["gone.pcap"] and "FIFO" in errors["fifo.pcap"]
    assert "outside" in errors["out.pcapng"] and str(elsewhere / "loss.pcapng") in errors["out.pcapng"]
    assert all(str(src) not in message for message in errors.values())
    # A glob names each path it matches: the link out is taken; a FIFO is still never opened.
    command[5] = str(src / "*.pcap*")
    command[7] = str(tmp_path / "g")
    globbed = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert globbed.returncode == 2 and "2 unreadable" in globbed.stdout, globbed.stderr
    taken = [Path(r["file"]).name for r in rows(tmp_path / "g") if r["status"] == "ok"]
    assert "out.pcapng" in taken and "in.pcap" not in taken and taken.count("normal.pcap") == 1


def test_a_pattern_round_a_link_loop_takes_each_file_once(tmp_path):
    """`loop/**` with loop/self -> ../loop: glob went round the link until the path was too long,
    and one capture was 41 rows (and an unreadable one), every sum 41 times too much."""
    loop = tmp_path / "loop"
    loop.mkdir()
    shutil.copy(BUNDLED / "normal.pcap", loop / "c.pcap")
    (loop / "self").symlink_to("../loop")
    (loop / "latest.pcap").symlink_to("c.pcap")
    command = [sys.executable, "-m", "vm110", "fleet", "build", str(loop / "**"), "--out", str(tmp_path / "ds"), "-j", "1"]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "1 analysed (0 damaged, 0 unreadable)" in result.stdout, result.stdout + result.stderr
    assert [Path(r["file"]) for r in rows(tmp_path / "ds")] == [loop / "c.pcap"]


@pytest.mark.parametrize("damage", ["garbage", "gone"])
def test_a_damaged_or_missing_part_is_one_line(built, tmp_path, damage):
    """Trial: a Parquet part overwritten or deleted after the build made `fleet query` and `fleet
    report` end in a DuckDB traceback."""
    part = next((built / "senders").glob("*.parquet"))
    if damage == "garbage":
        part.write_text("garbage")
    else:
        part.unlink()
    one_line_error(vm110("fleet", "query", str(built), "SELECT count(*) FROM senders"), "the dataset cannot be read")
    one_line_error(vm110("fleet", "report", str(built), "--html", str(tmp_path / "r.html")),
                   "the dataset cannot be read")
    assert not (tmp_path / "r.html").exists()


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_sidecar_that_is_no_file_is_an_error_row(src, tmp_path, kind):
    """Trial: a sidecar that was a FIFO or a folder was ignored in silence (status ok, no metadata)."""
    side = src / "normal.pcap.meta.json"
    os.mkfifo(side) if kind == "fifo" else side.mkdir()
    result = vm110("fleet", "build", str(src), "--out", str(tmp_path / "ds"), "-j", "1")
    assert result.returncode == 2 and "not a metadata file: not a regular file" in result.stderr, result.stderr
    captures = {Path(r["file"]).name: r for r in rows(tmp_path / "ds")}
    assert captures["normal.pcap"]["status"] == "unreadable"


def test_json_output_of_values_json_has_no_type_for(built):
    """An INTERVAL, TIME or UUID in a query's result is text in JSON, as in the table and CSV."""
    sql = "SELECT INTERVAL 90 MINUTE AS i, TIME '01:02:03' AS t, '5f2b6a1e-0c1d-4e5f-8a9b-0c1d2e3f4a5b'::UUID AS u"
    got = vm110("fleet", "query", str(built), "--format", "json", sql)
    assert got.returncode == 0, got.stderr
    csv = vm110("fleet", "query", str(built), "--format", "csv", sql)
    assert list(json.loads(got.stdout)[0].values()) == csv.stdout.splitlines()[1].split(",")
    assert json.loads(got.stdout) == [{"i": "1:30:00", "t": "01:02:03", "u": "5f2b6a1e-0c1d-4e5f-8a9b-0c1d2e3f4a5b"}]


def test_a_renamed_capture_is_counted_once(src, built):
    """A capture moved or renamed (its old path gone) replaces its old entry: it was kept beside
    the new one, and every sum counted the capture twice. A removed capture is still kept."""
    os.rename(src / "retransmit.pcap", src / "retransmit-renamed.pcap")
    os.remove(src / "normal.pcap")
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert again.returncode == 0 and "1 analysed" in again.stdout and "1 replaced" in again.stdout, again.stdout
    files = [Path(r["file"]).name for r in rows(built)]
    assert sorted(files) == sorted(n if n != "retransmit.pcap" else "retransmit-renamed.pcap" for n in NAMES)
    report = json.loads(vm110("analyze", str(src / "retransmit-renamed.pcap"), "--json", "-").stdout)
    lost = vm110("fleet", "query", str(built), "--format", "json", "SELECT sum(lost) AS lost FROM captures "
                 "WHERE file LIKE '%retransmit%'")
    assert json.loads(lost.stdout) == [{"lost": report["totals"]["lost"]}] and report["totals"]["lost"] > 0
    manifest = json.loads((built / "manifest.json").read_text())
    listed = {p for e in manifest["captures"].values() for p in e["parts"]}
    assert {str(p.relative_to(built)) for p in built.rglob("*.parquet")} == listed     # the old parts are gone


@pytest.mark.parametrize("entry, where", [("not an entry", "manifest.json"), ("parts outside", "manifest.json"),
                                          ("parts outside", "journal")])
def test_a_damaged_manifest_is_one_line_and_nothing_outside_is_removed(src, built, tmp_path, entry, where):
    """A manifest (or a batch of its journal) whose capture entry is not one a build writes: a
    traceback (query), or parts outside the dataset that a build removed as a replaced capture's
    (build)."""
    victim = tmp_path / "victim.txt"
    victim.write_text("not the tool's")
    manifest = json.loads((built / "manifest.json").read_text())
    if where != "manifest.json":                 # the batch a reader applies next
        where = f"journal/{manifest.get('journal', 0):09d}.json"
        manifest = {"captures": {}, "dropped": []}
        (built / "journal").mkdir(exist_ok=True)  # (a build slower than the journal's 2 s leaves it)
    manifest["captures"]["0" * 24] = 5 if entry == "not an entry" else {
        "file": str(src / "normal.pcap"), "size": 1, "sha256": "0" * 64, "status": "ok", "message": None,
        "meta": {}, "parts": ["../victim.txt"]}
    (built / where).write_text(json.dumps(manifest))
    one_line_error(vm110("fleet", "query", str(built), "--worst", "links"), where)
    one_line_error(vm110("fleet", "build", str(src), "--out", str(built), "-j", "1"), where)
    assert victim.read_text() == "not the tool's"


@pytest.mark.parametrize("out", ["foreign", "other options"])
def test_a_wrong_out_is_said_before_any_capture_is_read(src, built, tmp_path, monkeypatch, out):
    """A build into someone else's folder, or a dataset of other options, is refused before the
    captures are hashed (they were all read first: hours, for a large fleet)."""
    from vm110.fleet import build as fleet_build
    from vm110.fleet.work import Settings
    read = []
    monkeypatch.setattr(fleet_build, "content_hash", lambda path: read.append(path) or (0, ""))
    if out == "foreign":
        (tmp_path / "foreign").mkdir()
        (tmp_path / "foreign" / "notes.txt").write_text("mine")
        settings = Settings(dataset=str(tmp_path / "foreign"))
    else:
        settings = Settings(dataset=str(built), port=6000)
    with pytest.raises(CliError, match="not empty" if out == "foreign" else "other analysis options"):
        fleet_build.build([str(src)], settings)
    assert read == []


def test_a_file_name_with_control_characters_stays_on_its_row(tmp_path):
    """Trial: a capture named "a<newline>b.pcapng" split each of its rows of the text table in two,
    and an escape sequence in a name would have reached the terminal. Names are shown escaped."""
    src = tmp_path / "caps"
    src.mkdir()
    shutil.copyfile(BUNDLED / "loss.pcapng", src / "a\nb\x1b[2J.pcapng")
    assert vm110("fleet", "build", str(src), "--out", str(tmp_path / "ds")).returncode == 0
    done = vm110("fleet", "query", str(tmp_path / "ds"), "--named", "findings")
    rows = done.stdout.splitlines()[2:-1]
    assert done.returncode == 0 and rows and all(row.startswith(f"{src}/a\\nb\\x1b[2J.pcapng  ") for row in rows), rows
    assert "\x1b" not in done.stdout


def test_csv_cells_from_metadata_are_no_formulas_and_no_line_breaks(tmp_path):
    """Trial: `--format csv` wrote metadata as it came: a folder named `@SUM(1+1)` or a sidecar's
    `=HYPERLINK(...)` became a formula when the CSV was opened in Excel or LibreOffice, and a newline
    in a value broke the row (CSV injection). Text cells that begin with = + - @ begin with a single
    quote (OWASP), control characters are escaped as in the table; numbers stay numbers; JSON keeps
    the values as they are."""
    import csv
    folder = tmp_path / "@SUM(1+1)"
    folder.mkdir()
    shutil.copy(BUNDLED / "disarmed.pcap", folder / "disarmed.pcap")
    site = '=HYPERLINK("http://example.invalid","x")'
    (folder / "disarmed.pcap.meta.json").write_text(json.dumps({"site": site, "note": "-1\r\n+2,\tthree"}))
    built = vm110("fleet", "build", str(folder), "--out", str(tmp_path / "ds"), "--meta", "{machine}/*.pcap")
    assert built.returncode == 0, built.stderr
    sql = "SELECT site, machine, note, -1 AS minus_one, file FROM captures"
    given = json.loads(vm110("fleet", "query", str(tmp_path / "ds"), sql, "--format", "json").stdout)
    assert [(r["site"], r["machine"], r["note"]) for r in given] == [(site, "@SUM(1+1)", "-1\r\n+2,\tthree")]
    out = vm110("fleet", "query", str(tmp_path / "ds"), sql, "--format", "csv").stdout
    assert len(out.splitlines()) == 2 and "\r" not in out and "\t" not in out, out
    assert list(csv.reader(io.StringIO(out))) == [
        ["site", "machine", "note", "minus_one", "file"],
        ["'" + site, "'@SUM(1+1)", "'-1\\r\\n+2,\\tthree", "-1", str(folder / "disarmed.pcap")]]


def test_a_copy_of_a_capture_is_counted_once(src, built):
    """The same capture under a second path (an archive folder, a file copied to two machines'
    folders) is not analysed again: each copy added every one of its packets and findings to the
    fleet's sums a second time. It is said, with the capture it copies; once the original is gone,
    the copy takes its place."""
    (src / "archive").mkdir()
    shutil.copy(src / "retransmit.pcap", src / "archive" / "retransmit.pcap")     # after the first build
    shutil.copy(BUNDLED / "loss.pcapng", src / "loss.pcapng")                       # new, with its copy
    shutil.copy(BUNDLED / "loss.pcapng", src / "z-loss-copy.pcapng")
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert again.returncode == 0, again.stderr
    assert "1 analysed" in again.stdout and "2 copies not counted" in again.stdout, again.stdout
    assert again.stderr.splitlines() == [
        (f"vm110 fleet: copy, counted once: {src / 'archive' / 'retransmit.pcap'}: the same capture as "
         f"{src / 'retransmit.pcap'}"),
        f"vm110 fleet: copy, counted once: {src / 'z-loss-copy.pcapng'}: the same capture as {src / 'loss.pcapng'}"]
    assert sorted(Path(r["file"]).name for r in rows(built)) == sorted([*NAMES, "loss.pcapng"])
    report = json.loads(vm110("analyze", str(BUNDLED / "loss.pcapng"), "--json", "-").stdout)
    lost = vm110("fleet", "query", str(built), "--format", "json", "SELECT sum(lost) AS lost FROM captures "
                 "WHERE file LIKE '%loss%'")
    assert json.loads(lost.stdout) == [{"lost": report["totals"]["lost"]}] and report["totals"]["lost"] > 0

    os.remove(src / "retransmit.pcap")               # the original gone: its copy is the capture now
    last = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert last.returncode == 0 and "1 replaced" in last.stdout and "1 copy not counted" in last.stdout, last
    files = sorted(r["file"] for r in rows(built) if "retransmit" in r["file"])
    assert files == [str(src / "archive" / "retransmit.pcap")]


def test_which_copy_is_kept_does_not_depend_on_which_build_saw_it_first(tmp_path):
    """Trial: of two copies of a capture the one kept was the one a build had first, else the first
    in path order: the archive folder built before the machines' folders kept the capture there,
    without the machine --meta gives it (and `archive` sorts before `sites` too), and the same files
    built in one go or in two gave two datasets. The copy kept is the one whose metadata gives the
    most fields, then the one in the fewest folders, then the first path: whatever the history."""
    data = tmp_path / "data"
    archive, machine = data / "archive" / "w1.pcap", data / "sites" / "n" / "m1" / "w1.pcap"
    for path in (archive, machine):
        path.parent.mkdir(parents=True)
        shutil.copy(BUNDLED / "disarmed.pcap", path)
    shutil.copy(BUNDLED / "bu-watchdog.pcap", data / "sites" / "n" / "w0.pcap")      # --meta does not match it
    meta = ("--meta", "sites/{site}/{machine}/*.pcap")
    sql = "SELECT file, site, machine FROM captures WHERE file LIKE '%w1.pcap'"
    kept = [{"file": str(machine), "site": "n", "machine": "m1"}]
    said = f"vm110 fleet: copy, counted once: {archive}: the same capture as {machine}"
    # in one go; the archive alone first, then all; the archive alone first, then the machines' folders
    for n, builds in enumerate(([data], [archive.parent, data], [archive.parent, data / "sites"])):
        dataset = tmp_path / f"ds{n}"
        for src in builds:
            done = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1", *meta)
            assert done.returncode == 0, done.stderr
        assert said in done.stderr.splitlines() and "1 copy not counted" in done.stdout, done
        unmatched = [p for p in src.rglob("*.pcap") if p.parent.parent.parent.name != "sites"]
        assert f"does not match the path of {len(unmatched)} of {len(list(src.rglob('*.pcap')))} captures" \
            in done.stderr, done.stderr
        assert json.loads(vm110("fleet", "query", str(dataset), sql, "--format", "json").stdout) == kept
        again = vm110("fleet", "build", str(data), "--out", str(dataset), "-j", "1", *meta)
        assert "0 analysed" in again.stdout and "2 already in the dataset" in again.stdout and said in again.stderr


def _without_read_rights() -> list[str]:
    """The prefix that runs a command without the right to read what its mode bits forbid (root
    reads every folder: the command then runs without that capability)."""
    return ["setpriv", "--bounding-set", "-dac_override,-dac_read_search", "--"] if os.geteuid() == 0 else []


@pytest.mark.skipif(os.geteuid() == 0 and shutil.which("setpriv") is None, reason="as root, needs setpriv")
def test_a_folder_that_cannot_be_read_is_said(src, tmp_path):
    """A sub-folder the build may not list hid its captures in silence (rglob passes over it): it is
    an unreadable row with the reason, exit 2; a SRC folder that cannot be read is one line. Once
    it can be read, its captures are analysed and the folder's row goes."""
    locked = src / "site-b"
    locked.mkdir()
    shutil.copy(BUNDLED / "loss.pcapng", locked / "loss.pcapng")
    locked.chmod(0)
    dataset = tmp_path / "ds"
    try:
        command = [*_without_read_rights(), sys.executable, "-m", "vm110", "fleet", "build", str(src), "--out",
                   str(dataset), "-j", "1"]
        result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        assert f"{len(NAMES) + 1} analysed (0 damaged, 1 unreadable)" in result.stdout, result.stdout
        assert result.stderr.splitlines() == [(f"vm110 fleet: {locked}: a folder that cannot be read: Permission "
                                               "denied; the captures in it are not seen")]
        assert [(r["file"], r["kind"]) for r in rows(dataset, "errors")] == [(str(locked), "unreadable")]
        command[-5] = str(locked)
        command[-3] = str(tmp_path / "other")
        alone = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
        one_line_error(alone, str(locked), "cannot be read")
        assert not (tmp_path / "other").exists()
    finally:
        locked.chmod(0o755)
    again = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1")
    assert again.returncode == 0, again.stderr
    assert "1 analysed (0 damaged, 0 unreadable)" in again.stdout and "1 unreadable no longer there" in again.stdout
    assert rows(dataset, "errors") == []
    assert sorted(r["file"] for r in rows(dataset)) == sorted([*(str(src / n) for n in NAMES),
                                                                str(locked / "loss.pcapng")])


@pytest.mark.skipif(os.geteuid() == 0 and shutil.which("setpriv") is None, reason="as root, needs setpriv")
@pytest.mark.parametrize("pattern", ["**/*.pcap*", "*/*.pcap*", "*/loss.pcapng"])
def test_a_folder_a_glob_cannot_look_into_is_said(src, tmp_path, pattern):
    """glob passed over a folder it may not list (`*`, `**` below it) or search (a name below it)
    in silence: exit 0, the fleet seemingly complete without the folder's captures. It is an
    unreadable row with the reason, exit 2, as a folder the walk cannot list; once the glob can look
    into it, its captures are analysed and the folder's row goes."""
    locked = src / "site-b"
    locked.mkdir()
    shutil.copy(BUNDLED / "loss.pcapng", locked / "loss.pcapng")
    (src / "site-a").mkdir()
    shutil.copy(BUNDLED / "restart.pcapng", src / "site-a" / "loss.pcapng")     # (another capture of that name)
    dataset = tmp_path / "ds"
    build = ["fleet", "build", str(src / pattern), "--out", str(dataset), "-j", "1"]
    locked.chmod(0)
    try:
        result = subprocess.run([*_without_read_rights(), sys.executable, "-m", "vm110", *build], cwd=ROOT,
                                capture_output=True, text=True, timeout=120)
    finally:
        locked.chmod(0o755)
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines() == [(f"vm110 fleet: {locked}: a folder that cannot be read: Permission "
                                           "denied; the captures in it are not seen")]
    assert [(r["file"], r["kind"]) for r in rows(dataset, "errors")] == [(str(locked), "unreadable")]
    assert str(src / "site-a" / "loss.pcapng") in {r["file"] for r in rows(dataset)}
    again = vm110(*build)
    assert again.returncode == 0, again.stderr
    assert "1 analysed (0 damaged, 0 unreadable)" in again.stdout and "1 unreadable no longer there" in again.stdout
    assert rows(dataset, "errors") == []
    assert str(locked / "loss.pcapng") in {r["file"] for r in rows(dataset)}


def test_an_unreadable_capture_a_glob_found_that_is_gone_is_no_longer_counted(src, tmp_path):
    """As for a folder walked: a file a glob pattern found, unreadable, then removed, kept its
    unreadable row for ever (the pattern no longer names it). The next build of that pattern removes
    it; another pattern's build keeps it."""
    (src / "gone.pcap").symlink_to(src / "nothing.pcap")
    dataset, pattern = tmp_path / "ds", str(src / "*.pcap")
    first = vm110("fleet", "build", pattern, "--out", str(dataset), "-j", "1")
    assert first.returncode == 2 and "1 unreadable" in first.stdout, first
    (src / "gone.pcap").unlink()
    other = vm110("fleet", "build", str(src / "normal.pcap*"), "--out", str(dataset), "-j", "1")
    assert other.returncode == 0 and "removed" not in other.stdout, other
    assert [Path(r["file"]).name for r in rows(dataset, "errors")] == ["gone.pcap"]
    last = vm110("fleet", "build", pattern, "--out", str(dataset), "-j", "1")
    assert last.returncode == 0 and "0 analysed" in last.stdout, last
    assert "1 unreadable no longer there (removed)" in last.stdout
    assert rows(dataset, "errors") == [] and sorted(Path(r["file"]).name for r in rows(dataset)) == sorted(NAMES)


def test_an_unreadable_capture_that_is_gone_is_no_longer_counted(src, built):
    """A capture that could not be read (removed while a build ran, a broken link) and is then gone
    from the folder stayed an unreadable row for ever: a failing capture of its machine in every
    ranking, with nothing left to try again. The next build of that folder removes it; an
    unreadable row of a folder the build does not walk is kept, as everything of it is."""
    (src / "gone.pcap").symlink_to(src / "nothing.pcap")
    first = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert first.returncode == 2 and "1 unreadable" in first.stdout, first
    (src / "gone.pcap").unlink()
    other = src.parent / "other"
    other.mkdir()
    shutil.copy(BUNDLED / "loss.pcapng", other / "one.pcapng")
    elsewhere = vm110("fleet", "build", str(other), "--out", str(built), "-j", "1")
    assert elsewhere.returncode == 0 and "removed" not in elsewhere.stdout, elsewhere
    assert [Path(r["file"]).name for r in rows(built, "errors")] == ["gone.pcap"]
    last = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert last.returncode == 0 and "0 analysed" in last.stdout, last
    assert "1 unreadable no longer there (removed)" in last.stdout
    assert rows(built, "errors") == [] and all(r["status"] == "ok" for r in rows(built))
    worst = json.loads(vm110("fleet", "query", str(built), "--worst", "machines", "--format", "json").stdout)
    assert sum(m["unreadable"] for m in worst) == 0 and sum(m["captures"] for m in worst) == len(NAMES) + 1
    manifest = json.loads((built / "manifest.json").read_text())
    listed = {p for e in manifest["captures"].values() for p in e["parts"]}
    assert {str(p.relative_to(built)) for p in built.rglob("*.parquet")} == listed


def _mirrored(capture: Path, out: Path) -> None:
    """`capture` (little-endian pcap) with every record twice, as a mirror port shows each packet."""
    data = capture.read_bytes()
    parts, at = [data[:24]], 24
    while at < len(data):
        length = int.from_bytes(data[at + 8:at + 12], "little")
        record = data[at:at + 16 + length]
        parts += [record, record]
        at += 16 + length
    out.write_bytes(b"".join(parts))


def test_loss_share_is_of_the_packets_sent_whatever_the_copies(tmp_path):
    """The loss share counted duplicates among the packets sent: a tap on a mirror port, which shows
    every packet twice, halved it. Lost over sent (each serial once, and the lost ones), from the
    ground truth, for the capture and its mirrored copy alike, in --worst links and --trend loss."""
    name = "controller-watchdog.pcap"
    folder = tmp_path / "src"
    folder.mkdir()
    shutil.copy(BUNDLED / name, folder / name)
    _mirrored(BUNDLED / name, folder / "mirrored.pcap")
    dataset = tmp_path / "ds"
    assert vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1").returncode == 0
    truth = [s["serial"] for s in json.loads((BUNDLED / f"{name}.truth.json").read_text())["senders"]]
    lost = sum(s["lost"] for s in truth)
    share = round(100 * lost / sum(s["received"] - s["duplicates"] + s["lost"] for s in truth), 3)
    assert lost > 0 and all(s["duplicates"] == 0 for s in truth)
    links = json.loads(vm110("fleet", "query", str(dataset), "--worst", "links", "--format", "json").stdout)
    assert {Path(r["file"]).name: (r["lost"], r["loss_pct"]) for r in links} == {
        name: (lost, share), "mirrored.pcap": (lost, share)}
    trend = json.loads(vm110("fleet", "query", str(dataset), "--trend", "loss", "--by", "month", "--format",
                             "json").stdout)
    assert [(r["captures"], r["lost"], r["loss_pct"]) for r in trend] == [(2, 2 * lost, share)]


def _without_eglink(path: Path) -> None:
    """A capture of one frame and no UDP at all (a dead link, the wrong interface)."""
    arp = bytes.fromhex("ffffffffffff 020000000001 0806") + bytes(28)
    header = bytes.fromhex("d4c3b2a1 0200 0400") + bytes(8) + (65535).to_bytes(4, "little") + (1).to_bytes(4, "little")
    record = (1_750_000_000).to_bytes(4, "little") + bytes(4) + len(arp).to_bytes(4, "little") * 2
    path.write_bytes(header + record + arp)


def _built_with_a_dead_capture(tmp_path: Path, bundled: str) -> tuple[Path, Path]:
    """A dataset of a bundled capture and `dead.pcap`, without EG-Link traffic: (sources, dataset)."""
    folder = tmp_path / "src"
    folder.mkdir()
    shutil.copy(BUNDLED / bundled, folder / bundled)
    _without_eglink(folder / "dead.pcap")
    dataset = tmp_path / "ds"
    assert vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1").returncode == 0
    return folder, dataset


def test_a_capture_without_eglink_traffic_is_listed_apart_not_ranked_failing(tmp_path):
    """Trial: a capture without one EG-Link packet (its verdict fails: `no_eglink`, an error) made
    its machine the worst of `--worst machines`, above machines with real failures, though it says
    nothing of the link. It is counted apart (`no_eglink`) in both rankings, not as a failing
    capture nor an error finding, and `--named no-eglink` lists it."""
    folder, dataset = _built_with_a_dead_capture(tmp_path, "bu-watchdog.pcap")
    verdicts = {name: json.loads(vm110("analyze", str(folder / name), "--json", "-").stdout)["verdict"]
                for name in ("bu-watchdog.pcap", "dead.pcap")}
    assert [f["rule"] for f in verdicts["dead.pcap"]["findings"]] == ["no_eglink"]
    errors = sum(f["severity"] == "error" for f in verdicts["bu-watchdog.pcap"]["findings"])
    assert errors > 0 and not verdicts["bu-watchdog.pcap"]["ok"]

    def ranked(what: str) -> list:
        out = json.loads(vm110("fleet", "query", str(dataset), "--worst", what, "--format", "json").stdout)
        return [(Path(r["file"]).name, r) for r in out]
    machines, links = ranked("machines"), dict(ranked("links"))
    assert [(n, r["captures"], r["no_eglink"], r["failing_captures"], r["error_findings"]) for n, r in machines] == [
        ("bu-watchdog.pcap", 1, 0, 1, errors), ("dead.pcap", 1, 1, 0, 0)]
    assert links["dead.pcap"]["no_eglink"] == 1 and links["dead.pcap"]["loss_pct"] is None
    apart = json.loads(vm110("fleet", "query", str(dataset), "--named", "no-eglink", "--format", "json").stdout)
    assert [r["file"] for r in apart] == [str(folder / "dead.pcap")]
    trend = json.loads(vm110("fleet", "query", str(dataset), "--trend", "findings", "--by", "month", "--format",
                             "json").stdout)
    assert [(r["captures"], r["failing_captures"], r["no_eglink"]) for r in trend] == [(2, 1, 1)]


def _first_half(source: Path, target: Path) -> list[float]:
    """The first half of the records of the pcap `source` (little-endian, µs) as `target`, as a
    ring buffer's file of the same period holds them; their times."""
    data = source.read_bytes()
    assert data[:4] == bytes.fromhex("d4c3b2a1")
    records, at = [], 24
    while at < len(data):
        seconds, micros, length = struct.unpack_from("<III", data, at)
        records.append((at, seconds + micros / 1e6))
        at += 16 + length
    end = records[len(records) // 2][0]
    target.write_bytes(data[:end])
    return [t for start, t in records if start < end]


def test_two_captures_of_one_link_at_once_are_said(tmp_path):
    """Trial: two captures of one machine's link that overlap in time (a ring-buffer file and the
    merged file of the same period: other content, so no copy) were both counted in the machine's
    totals, in silence. Every query that sums says each such pair on standard error, with both
    files and the overlap (from the capture's own packet times), and `--named overlaps` lists them;
    another machine's capture of the same addresses at the same time is no overlap."""
    from vm110.timefmt import utc_iso
    m1, m2 = tmp_path / "sites" / "n" / "m1", tmp_path / "sites" / "n" / "m2"
    m1.mkdir(parents=True)
    m2.mkdir(parents=True)
    shutil.copy(BUNDLED / "controller-watchdog.pcap", m1 / "merged.pcap")
    shutil.copy(BUNDLED / "bu-watchdog.pcap", m2 / "other.pcap")      # the same addresses, the same time
    ring = _first_half(m1 / "merged.pcap", m1 / "ring-1.pcap")
    dataset = tmp_path / "ds"
    built = vm110("fleet", "build", str(tmp_path / "sites"), "--out", str(dataset), "-j", "1",
                  "--meta", "sites/{site}/{machine}/*.pcap")
    assert built.returncode == 0 and "3 analysed" in built.stdout, built
    start, end = utc_iso(ring[0]), utc_iso(ring[-1])
    senders = "; ".join(sorted(s["id"] for s in json.loads(vm110("analyze", str(m1 / "ring-1.pcap"), "--json", "-")
                                                            .stdout)["senders"]))
    ranked = vm110("fleet", "query", str(dataset), "--worst", "machines")
    said = [line for line in ranked.stderr.splitlines() if "counted twice" in line]
    assert ranked.returncode == 0 and said == [(
        f"vm110 fleet: overlap, counted twice: {m1 / 'merged.pcap'} and {m1 / 'ring-1.pcap'} hold the same link "
        f"({senders}) from {start} to {end} "
        f"({round(ring[-1] - ring[0], 3):g} s)")], ranked.stderr
    listed = json.loads(vm110("fleet", "query", str(dataset), "--named", "overlaps", "--format", "json").stdout)
    assert [(r["machine"], r["file"], r["other_file"], r["overlap_from"], r["overlap_to"]) for r in listed] == [
        ("m1", str(m1 / "merged.pcap"), str(m1 / "ring-1.pcap"), start, end)]
    assert "overlap" not in vm110("fleet", "query", str(dataset), "--named", "errors").stderr


def test_a_finding_of_the_whole_capture_is_listed(tmp_path):
    """A finding without located items (no EG-Link packet at all: a dead link or the wrong
    interface) was left out of `--named findings` and of the report's list of findings, which
    showed the capture as if it had none. Every finding `vm110 analyze` gives is listed."""
    folder, dataset = _built_with_a_dead_capture(tmp_path, "retransmit.pcap")
    expected = set()
    for name in ("retransmit.pcap", "dead.pcap"):
        report = json.loads(vm110("analyze", str(folder / name), "--json", "-").stdout)
        expected |= {(name, f["rule"], f["severity"], f["message"]) for f in report["verdict"]["findings"]}
    assert ("dead.pcap", "no_eglink", "error", "no EG-Link packets in the capture") in expected
    listed = json.loads(vm110("fleet", "query", str(dataset), "--named", "findings", "--limit", "1000",
                              "--format", "json").stdout)
    assert {(Path(r["file"]).name, r["rule"], r["severity"], r["message"]) for r in listed} == expected
    page = vm110("fleet", "report", str(dataset), "--html", "-").stdout
    table = page[page.index('<table class="findings">'):]
    assert "<td>" + str(folder / "dead.pcap") + '</td><td class="error">no_eglink</td>' in table


def test_query_prints_times_as_decode_and_analyze_do(src, built):
    """A time in a query's output read `2025-06-15T15:06:51` (no zone, the µs dropped when zero),
    where every other command prints `2025-06-15T15:06:51.000000Z` (vm110.timefmt): a finding's
    time is printed as `vm110 decode` prints its frame's (a lost packet's item is its frame), in
    every output format."""
    from vm110.timefmt import utc_iso
    capture = src / "controller-watchdog.pcap"
    report = json.loads(vm110("analyze", str(capture), "--json", "-").stdout)
    expected = [(i["frame"], utc_iso(i["time"])) for f in report["verdict"]["findings"] for i in f["items"]]
    decoded = {p["frame"]: p["time_utc"] for p in map(json.loads, vm110("decode", str(capture), "--json")
                                                          .stdout.splitlines())}
    lost = [i["frame"] for f in report["verdict"]["findings"] if f["rule"] == "lost" for i in f["items"]]
    assert lost and all(utc_iso(i["time"]) == decoded[i["frame"]] for f in report["verdict"]["findings"]
                        if f["rule"] == "lost" for i in f["items"])
    sql = f"SELECT frame, time FROM findings WHERE file = '{capture}' ORDER BY frame"
    found = json.loads(vm110("fleet", "query", str(built), sql, "--format", "json").stdout)
    assert [(r["frame"], r["time"]) for r in found] == sorted(expected)
    assert any(time.endswith(":51.000000Z") for _, time in expected)
    csv_lines = vm110("fleet", "query", str(built), sql, "--format", "csv").stdout.splitlines()
    assert csv_lines[1:] == [f"{r['frame']},{r['time']}" for r in found]
    table = vm110("fleet", "query", str(built), sql).stdout.splitlines()
    assert [line.split()[1] for line in table[2:-1]] == [r["time"] for r in found]


def test_a_folder_gone_while_walked_is_no_row(src, monkeypatch):
    """A sub-folder removed between its listing and its walk (a rotating capture tool) hides no
    capture: no unreadable row for it; one that cannot be read is one."""
    from vm110.fleet.sources import find
    (src / "gone").mkdir()
    (src / "locked").mkdir()
    scandir = os.scandir

    def racing(path):
        if os.path.basename(path) == "gone":
            raise FileNotFoundError(2, "No such file or directory", path)
        if os.path.basename(path) == "locked":
            raise PermissionError(13, "Permission denied", path)
        return scandir(path)
    monkeypatch.setattr(os, "scandir", racing)
    found = find([str(src)])
    assert sorted(Path(p).name for p in found) == sorted([*NAMES, "locked"])
    assert found[str(src / "locked")].startswith("a folder that cannot be read: Permission denied")


def test_the_report_is_never_written_over_the_dataset(built):
    """`fleet report DATASET --html DATASET/manifest.json` wrote the page over the manifest (exit 0)
    and the dataset was lost; over a part, that capture. Refused in one line, nothing changed; a
    new file beside them is written."""
    before = snapshot(built)
    part = next(p for e in json.loads((built / "manifest.json").read_text())["captures"].values() for p in e["parts"])
    for target in (built / "manifest.json", built / part):
        one_line_error(vm110("fleet", "report", str(built), "--html", str(target)), "refusing to write over it")
    assert snapshot(built) == before
    assert vm110("fleet", "report", str(built), "--html", str(built / "report.html")).returncode == 0
    assert vm110("fleet", "query", str(built), "SELECT 1").returncode == 0


def test_the_options_a_named_query_takes(built):
    month = vm110("fleet", "query", str(built), "--named", "watchdog", "--month", "2025-06", "--limit", "1",
                  "--format", "json")
    assert month.returncode == 0 and len(json.loads(month.stdout)) == 1, month.stderr
    trend = vm110("fleet", "query", str(built), "--trend", "loss", "--by", "month", "--format", "json")
    assert trend.returncode == 0 and [r["month"] for r in json.loads(trend.stdout)] == ["2025-06-01"], trend.stderr
    assert vm110("fleet", "query", str(built), "--worst", "machines", "--limit", "2").stdout.endswith("(2 rows)\n")


@pytest.mark.parametrize("schemas", [100, 2], ids=["read-per-schema", "united-file-by-file"])
def test_captures_with_different_metadata_fields_read_together(tmp_path, monkeypatch, schemas):
    """Parts are read per set of metadata fields, united by name (few sets), or file by file
    (many): each capture's own fields and NULL for the others', in every table."""
    import vm110.fleet.query as query
    monkeypatch.setattr(query, "MAX_SCHEMAS", schemas)
    folder = tmp_path / "src"
    folder.mkdir()
    names = ["normal.pcap", "retransmit.pcap", "vrco.pcap", "loss.pcapng"]
    for n, name in enumerate(names):
        shutil.copy(BUNDLED / name, folder / name)
        if n:
            (folder / f"{name}.meta.json").write_text(json.dumps({f"f{n}": str(n), "site": "north"}))
    dataset = tmp_path / "ds"
    assert vm110("fleet", "build", str(folder), "--out", str(dataset), "-j", "1").returncode == 0
    for table in ("captures", "senders"):
        got = json.loads(vm110("fleet", "query", str(dataset), f"SELECT file, site, f1, f2, f3 FROM {table}",
                               "--format", "json").stdout)
        want = {name: {"site": "north" if n else None, **{f"f{k}": str(k) if k == n else None for k in (1, 2, 3)}}
                for n, name in enumerate(names)}
        assert {Path(r["file"]).name: {k: v for k, v in r.items() if k != "file"} for r in got} == want


_KILLER = """
import os, signal, sys
import vm110.fleet.engines as engines
real = engines.build_one

def build_one(source, settings):      # the worker given poison.pcap dies as the OOM killer ends it
    if source.problem is None and source.path.endswith("poison.pcap"):
        os.kill(os.getpid(), signal.SIGKILL)
    return real(source, settings)

engines.build_one = build_one
from vm110.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_worker_that_dies_costs_its_capture_only(src, tmp_path):
    """A worker process killed while it analysed a capture (the out-of-memory killer) left the
    process pool waiting for its result for ever: the build hung, with no line. The capture is an
    unreadable row that says why, every other capture is built, exit 2."""
    shutil.copy(BUNDLED / "loss.pcapng", src / "poison.pcap")
    dataset = tmp_path / "ds"
    command = [sys.executable, "-c", _KILLER, "fleet", "build", str(src), "--out", str(dataset), "-j", "2"]
    try:
        done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60)    # (3 s when well)
    except subprocess.TimeoutExpired:
        pytest.fail("the build hung after a worker died")
    assert done.returncode == 2, done.stderr
    assert f"{len(NAMES) + 1} analysed (0 damaged, 1 unreadable)" in done.stdout
    assert done.stderr.splitlines() == [(f"vm110 fleet: {src / 'poison.pcap'}: the process analysing it ended "
                                         "before it was done: killed (SIGKILL: what the kernel's out-of-memory "
                                         "killer sends)")]
    status = {Path(r["file"]).name: r["status"] for r in rows(dataset)}
    assert status == {**dict.fromkeys(NAMES, "ok"), "poison.pcap": "unreadable"}
    again = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "2")      # tried again: it passes now
    assert again.returncode == 0 and "1 analysed" in again.stdout, again
    assert {r["status"] for r in rows(dataset)} == {"ok"}


_HOLDER = """
import os, sys, time
import vm110.fleet.engines as engines
real = engines.build_one

def build_one(source, settings):      # each capture held until the test lets it go
    open(os.path.join(os.environ["HOLD"], f"started-{os.getpid()}"), "w").close()
    while not os.path.exists(os.path.join(os.environ["HOLD"], "go")):
        time.sleep(0.01)
    return real(source, settings)

engines.build_one = build_one
from vm110.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_the_workers_of_a_build_killed_alone_end(src, tmp_path):
    """SIGTERM to the build alone (`kill PID`, a job scheduler), not its process group: its worker
    processes waited for ever, holding its standard output and error open, so that whatever read
    them (cron, CI, a script) hung too (trial-fleet). They finish their capture and end; the next
    build adopts what they finished."""
    hold, dataset = tmp_path / "hold", tmp_path / "ds"
    hold.mkdir()
    command = [sys.executable, "-c", _HOLDER, "fleet", "build", str(src), "--out", str(dataset), "-j", "2"]
    proc = subprocess.Popen(command, cwd=ROOT, env={**os.environ, "HOLD": str(hold)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        while len(list(hold.glob("started-*"))) < 2 and proc.poll() is None:
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == -signal.SIGTERM
        (hold / "go").touch()
        try:
            proc.communicate(timeout=60)        # the end of its output: no process of the build is left
        except subprocess.TimeoutExpired:
            pytest.fail("the workers of a build killed alone went on, holding its output open")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    again = vm110("fleet", "build", str(src), "--out", str(dataset), "-j", "1")
    assert again.returncode == 0 and f": {len(NAMES) - 2} analysed" in again.stdout, again
    assert "2 already in the dataset" in again.stdout and len(rows(dataset)) == len(NAMES)


_FULL = """
import errno, sys
import vm110.fleet.dataset as dataset
real = dataset.atomic_writer

def atomic_writer(path, *args, **kwargs):      # a disk full once the manifest is written
    if "/part-" in str(path):
        raise OSError(errno.ENOSPC, "No space left on device")
    return real(path, *args, **kwargs)

dataset.atomic_writer = atomic_writer
from vm110.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_full_disk_ends_a_build_with_one_line(src, tmp_path):
    """A dataset on a full disk, built with worker processes: each worker ended with a traceback
    on standard error (trial-fleet). The build ends with one line that says why, exit 2."""
    command = [sys.executable, "-c", _FULL, "fleet", "build", str(src), "--out", str(tmp_path / "ds"), "-j", "2"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done
    [line] = done.stderr.splitlines()
    assert line.startswith(f"vm110 fleet: cannot write {tmp_path / 'ds'}/") and "No space left on device" in line


_DASK_KILLER = """
import os, signal, sys
from dataclasses import dataclass
import vm110.fleet.build as build
from vm110.fleet.sources import Source

@dataclass(frozen=True)
class Poison(Source):            # defined here: Dask pickles it by value, so its workers have it
    @property
    def capture_id(self):
        if self.problem is None and self.path.endswith("poison.pcap"):
            from distributed import get_worker
            try:
                get_worker()
            except ValueError:
                pass              # the driver
            else:
                os.kill(os.getpid(), signal.SIGKILL)      # as the out-of-memory killer ends a worker
        return super().capture_id

if __name__ == "__main__":
    real = build._source
    build._source = lambda *args: Poison(*vars(real(*args)).values())
    from vm110.cli import main
    sys.exit(main(sys.argv[1:]))
"""


def test_a_dask_task_whose_workers_die_is_an_unreadable_row(src, tmp_path):
    """Dask gives up on a task whose workers all died (KilledWorker): the build ended in its
    traceback, with the scheduler's log lines. The capture is an unreadable row that says why."""
    pytest.importorskip("distributed")
    shutil.copy(BUNDLED / "loss.pcapng", src / "poison.pcap")
    dataset = tmp_path / "ds"
    command = [sys.executable, "-c", _DASK_KILLER, "fleet", "build", str(src), "--out", str(dataset),
               "--engine", "dask", "-j", "2"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and all(line.startswith("vm110 fleet: ") for line in
                                                  done.stderr.splitlines()), done.stderr
    lines = [line for line in done.stderr.splitlines() if "poison.pcap" in line]
    assert lines == [(f"vm110 fleet: {src / 'poison.pcap'}: every Dask worker that analysed it died before it "
                      "was done (KilledWorker; the kernel's out-of-memory killer?)")]
    status = {Path(r["file"]).name: r["status"] for r in rows(dataset)}
    assert status["poison.pcap"] == "unreadable" and set(status) == {*NAMES, "poison.pcap"}


def test_a_file_overwritten_with_a_copy_of_another_capture_no_longer_counts_what_it_held(src, built):
    """A capture file overwritten with another capture already in (copied over it by mistake, or a
    .pcap.gz a vm110 before knew by its compressed bytes): the copy is not counted, and neither
    any more is what the file held. Its old rows stayed, figures of a capture no file holds."""
    shutil.copy(src / "normal.pcap", src / "retransmit.pcap")
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert again.returncode == 0 and "1 replaced" in again.stdout and "1 copy not counted" in again.stdout, again
    assert sorted(Path(r["file"]).name for r in rows(built)) == sorted(n for n in NAMES if n != "retransmit.pcap")
    manifest = json.loads((built / "manifest.json").read_text())
    listed = {p for e in manifest["captures"].values() for p in e["parts"]}
    assert {str(p.relative_to(built)) for p in built.rglob("*.parquet")} == listed     # its old parts are gone


def _with_dropped(pcapng: bytes, dropped: int) -> bytes:
    """`pcapng` and an Interface Statistics Block of its first interface: `dropped` (isb_ifdrop)."""
    options = struct.pack("<HHQ", 5, 8, dropped) + struct.pack("<HH", 0, 0)
    body = struct.pack("<III", 0, 0, 0) + options
    return pcapng + struct.pack("<II", 5, 12 + len(body)) + body + struct.pack("<I", 12 + len(body))


def test_the_loss_trend_says_what_the_captures_dropped_themselves(tmp_path):
    """Trial: `--trend loss` showed a capture whose host dropped packets (pcapng statistics) as a
    lossy link, with nothing of the drops that `--worst links` gives beside its loss. The trend
    gives `capture_dropped` beside `lost`, as analyze counts both: once per capture, not per sender."""
    folder = tmp_path / "src"
    folder.mkdir()
    (folder / "dropping.pcapng").write_bytes(_with_dropped((BUNDLED / "loss.pcapng").read_bytes(), 7))
    assert vm110("fleet", "build", str(folder), "--out", str(tmp_path / "ds"), "-j", "1").returncode == 0
    report = json.loads(vm110("analyze", str(folder / "dropping.pcapng"), "--json", "-").stdout)
    assert len(report["senders"]) > 1 and report["totals"]["lost"] > 0
    trend = json.loads(vm110("fleet", "query", str(tmp_path / "ds"), "--trend", "loss", "--by", "month",
                             "--format", "json").stdout)
    assert [(r["captures"], r["lost"], r["capture_dropped"]) for r in trend] == [
        (1, report["totals"]["lost"], report["totals"]["capture_dropped"])]
    assert report["totals"]["capture_dropped"] == 7


def test_parts_of_an_older_vm110_are_read_with_the_new_ones(src, built):
    """A dataset built by a vm110 before the column capture_dropped, built on with this one: each
    query failed (`the dataset cannot be read ... schema mismatch`, or capture_dropped not found
    when an old part came first: the scan takes its first file's columns). Old parts are read by
    name, their capture_dropped NULL (not known); the new ones give it as analyze does."""
    manifest_path = built / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    for entry in manifest["captures"].values():          # as a vm110 before capture_dropped wrote them
        entry.pop("schema", None)
        part = built / next(p for p in entry["parts"] if p.startswith("captures/"))
        pq.write_table(pq.read_table(part).drop_columns(["capture_dropped"]), part)
    manifest_path.write_text(json.dumps(manifest))
    (src / "dropping.pcapng").write_bytes(_with_dropped((BUNDLED / "loss.pcapng").read_bytes(), 7))
    again = vm110("fleet", "build", str(src), "--out", str(built), "-j", "1")
    assert again.returncode == 0 and "1 analysed" in again.stdout, again
    got = vm110("fleet", "query", str(built), "--format", "json",
                "SELECT file, lost, capture_dropped FROM captures ORDER BY file")
    assert got.returncode == 0, got.stderr
    want = []
    for name in sorted([*NAMES, "dropping.pcapng"]):
        totals = json.loads(vm110("analyze", str(src / name), "--json", "-").stdout)["totals"]
        want.append({"file": str(src / name), "lost": totals["lost"],
                     "capture_dropped": totals["capture_dropped"] if name == "dropping.pcapng" else None})
    assert json.loads(got.stdout) == want and {w["capture_dropped"] for w in want} == {None, 7}
    # The ranking by loss says beside it what the capture dropped itself (up to that many of the
    # packets counted lost may be the capture host's, not the link's): it blamed the link alone.
    links = vm110("fleet", "query", str(built), "--worst", "links", "--format", "json")
    assert links.returncode == 0, links.stderr
    assert ({r["file"]: (r["lost"], r["capture_dropped"]) for r in json.loads(links.stdout)}
            == {w["file"]: (w["lost"], w["capture_dropped"]) for w in want})


_WITHOUT = """
import sys
for name in sys.argv[1].split(","):      # as in a plain `pip install vm110`: the fleet extra left out
    sys.modules[name] = None
from vm110.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize(("missing", "action"), [
    ("fsspec,pyarrow,duckdb", ["build", "SRC", "--out", "DS"]),
    ("pyarrow,duckdb", ["query", "DS", "--worst", "links"]),
    ("pyarrow,duckdb", ["report", "DS", "--html", "DS.html"]),
    ("distributed", ["build", "SRC", "--out", "DS", "--engine", "dask", "-j", "1"]),
])
def test_without_the_fleet_extra_one_line_says_how_to_install_it(src, tmp_path, missing, action):
    """A wheel installed without its `fleet` extra: each `vm110 fleet` action ended with a
    ModuleNotFoundError traceback, exit 1 (trial-readme). One line names the extra, exit 2."""
    given = [str(src) if a == "SRC" else a.replace("DS", str(tmp_path / "ds")) for a in action]
    command = [sys.executable, "-c", _WITHOUT, missing, "fleet", *given]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60)
    one_line_error(done, "fleet extra", "'PATH[fleet]'", "is missing")
