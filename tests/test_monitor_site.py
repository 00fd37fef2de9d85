"""`vm110 monitor` held to `vm110 analyze` on captures as a site records them (tests/site_captures.py,
no bytes of our own tools): the same report read to its end, from a pipe, or followed as the file
is written; the finding lines are the report's items."""
from __future__ import annotations

import gzip
import json
import random
import signal
import subprocess
from pathlib import Path

import pytest

import site_captures as S
from test_monitor import VM110, _wait_read_to_its_end
from test_site_captures import ETHERNET, LAYOUTS, _fragmented
from vm110.cli import main


def _ipv6_other_port(site: S.Site) -> bytes:
    for d in site.datagrams:
        d.sport = 50000 if d.payload[3:4] == b"O" else 40000
    return S.pcap(S.frames(site, S.on_ethernet()), ETHERNET)


def _span(site: S.Site) -> bytes:
    records = []
    for rec, d in zip(S.frames(site, S.on_ethernet()), site.datagrams):
        records += [S.Record(rec.ts_ns, S.on_ethernet([(0x8100, 42)])(d, rec.data[14:])),
                    S.Record(rec.ts_ns + 3000, rec.data)]
    return S.pcap(records, ETHERNET)


def _time_back(site: S.Site) -> bytes:
    records = S.frames(site, S.on_ethernet())
    for rec in records[20:25]:
        rec.ts_ns -= 300_000_000
    return S.pcap(records, ETHERNET)


def _small_mtu(site: S.Site, pcapng: bool = False) -> bytes:
    records, _ = _fragmented(site, 256, broken=5, copied=9)
    return S.pcapng([S.Interface(ETHERNET, 9)], records) if pcapng else S.pcap(records, ETHERNET)


CAPTURES = {name: (build, {}) for name, build in LAYOUTS.items() if name != "pcap-gzip"} | {
    "ipv6-port-6000": (_ipv6_other_port, {"ipv6": True, "port": 6000}),
    "span": (_span, {}),
    "time-back": (_time_back, {}),
    "fragments-ipv4": (_small_mtu, {"vrpo_data": 488}),
    "fragments-ipv6": (_small_mtu, {"vrpo_data": 488, "ipv6": True}),
}


def _capture(name: str, tmp_path: Path) -> tuple[Path, list[str]]:
    build, kw = CAPTURES[name]
    path = tmp_path / f"{name}.cap"
    path.write_bytes(build(S.Site(lost_vrpi=(10,), **kw)))
    return path, ["--port", str(kw["port"])] if "port" in kw else []


def _analyze(path: Path, tmp_path: Path, extra: list[str]) -> dict:
    out = tmp_path / "analyze.json"
    assert main(["analyze", str(path), "--quiet", "--json", str(out), *extra]) in (0, 1)
    return json.loads(out.read_text())


@pytest.mark.parametrize("name", CAPTURES)
def test_monitor_reads_a_site_capture_as_analyze_and_tells_its_items(name, tmp_path):
    path, extra = _capture(name, tmp_path)
    report, lines = tmp_path / "monitor.json", tmp_path / "live.jsonl"
    assert main(["monitor", "--read", str(path), "--idle", "0", "--quiet", "--no-dashboard", "--json", str(report),
                 "--json-lines", str(lines), *extra]) in (0, 1)
    want = _analyze(path, tmp_path, extra)
    assert json.loads(report.read_text()) == want
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    found = [o for o in objects if o["type"] == "finding"]
    for f in want["verdict"]["findings"]:
        told = [o for o in found if o["rule"] == f["rule"]]
        if f["rule"] in ("lost", "illegal", "failed"):
            held = sum(o.get("suppressed_before", 0) for o in told)
            held += sum(o["count"] for o in objects if o["type"] == "suppressed" and o["rule"] == f["rule"])
            assert len(told) + held == len(f["items"]) and all(o["item"] in f["items"] for o in told), f["rule"]
    assert {o["rule"] for o in found} <= {"lost", "illegal", "failed", "watchdog", "restarts"}


def test_a_compressed_site_capture_is_read_from_a_pipe_as_analyze_reads_the_file(tmp_path):
    """A gzip-compressed capture is not read as a file (docs/monitor.md); decompressed into
    `--read -` it gives analyze's report of the compressed file (a VRPO in fragments here)."""
    path, _ = _capture("fragments-ipv4", tmp_path)
    packed = tmp_path / "site.pcap.gz"
    packed.write_bytes(gzip.compress(path.read_bytes()))
    said = subprocess.run(VM110 + ["monitor", "--read", str(packed), "--idle", "0", "--no-dashboard"],
                          capture_output=True, text=True, timeout=60)
    assert said.returncode == 2 and "compressed with gzip, which is not read here" in said.stderr
    out = tmp_path / "monitor.json"
    done = subprocess.run(VM110 + ["monitor", "--read", "-", "--quiet", "--no-dashboard", "--json", str(out)],
                          input=gzip.decompress(packed.read_bytes()), capture_output=True, timeout=60)
    assert done.returncode in (0, 1), done.stderr
    want = _analyze(packed, tmp_path, [])
    assert json.loads(out.read_text()) == {**want, "capture": {**want["capture"], "file": "-"}}


def test_a_site_capture_followed_as_it_is_written_gives_the_report_of_the_whole(tmp_path):
    """A pcapng of nanoseconds with a VRPO in fragments (one never whole, one copied), written in
    pieces cut anywhere (inside a record, between a datagram's fragments), each read before the next."""
    whole = _small_mtu(S.Site(lost_vrpi=(10,), vrpo_data=488), pcapng=True)
    path = tmp_path / "growing.pcapng"
    path.write_bytes(b"")
    report = tmp_path / "monitor.json"
    proc = subprocess.Popen(VM110 + ["monitor", "--read", str(path), "--no-dashboard", "--quiet", "--json",
                                     str(report)], stderr=subprocess.PIPE)
    try:
        cuts = sorted(random.Random(5).sample(range(1, len(whole)), 12)) + [len(whole)]
        at = 0
        for cut in cuts:
            with open(path, "ab") as f:
                f.write(whole[at:cut])
            at = cut
            _wait_read_to_its_end(proc, path)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode in (0, 1), err
    assert json.loads(report.read_text()) == _analyze(path, tmp_path, [])
