"""`vm110 monitor` live: dumpcap on the loopback of a network namespace this test creates, the
simulated base unit and the reference controller talking unicast over it (nothing leaves the
namespace); and the dashboard in tmux on a capture replayed at the pace of its timestamps."""
from __future__ import annotations

import contextlib
import copy
import json
import os
import pty
import select
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from vm110.capture.reader import CaptureReader
from vm110.cli import main

ROOT = Path(__file__).resolve().parent.parent
VM110 = [sys.executable, "-m", "vm110"]
BU, CTL = "127.0.0.10", "127.0.0.20"
STALL = (3.0, 5.0)              # the BU hangs: sends nothing from 3 s to 5 s of its run


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
def test_watchdog_alarm_evidence_and_recovery_on_a_live_link(netns, tmp_path):
    ns = ["ip", "netns", "exec", netns]
    lines, evidence, report = tmp_path / "live.jsonl", tmp_path / "evidence", tmp_path / "report.json"
    evidence.mkdir()
    monitor = subprocess.Popen(ns + VM110 + ["monitor", "-i", "lo", "--no-dashboard", "--quiet", "--duration", "60",
                                             "--json-lines", str(lines), "--evidence", str(evidence), "--before", "2",
                                             "--after", "1", "--json", str(report)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(1.5)                     # dumpcap running before the traffic starts
    if monitor.poll() is not None:
        _, early = monitor.communicate()
        pytest.skip(f"dumpcap cannot capture here: {early.decode().strip()}")
    sim = VM110 + ["simulate"]
    ctl = subprocess.Popen(ns + sim + ["controller", "--listen", f"{CTL}:5825", "--peer", f"{BU}:5827", "--source",
                                       f"{CTL}:5827", "--duration", "6.5", "--quiet"], stdout=subprocess.DEVNULL)
    bu = subprocess.run(ns + sim + ["bu", "--listen", f"{BU}:5827", "--peer", f"{CTL}:5825", "--source", f"{BU}:5825",
                                    "--duration", "6.5", "--quiet", "--stall", f"{STALL[0]}:{STALL[1]}"],
                        stdout=subprocess.DEVNULL, timeout=30)
    ctl.wait(timeout=30)
    # Stopped 2 s after the link died, however late a loaded machine started the simulators (a fixed
    # --duration raced them), by Ctrl-C as a user stops it.
    time.sleep(2.0)
    monitor.send_signal(signal.SIGINT)
    _, err = monitor.communicate(timeout=60)
    assert bu.returncode == 0 and monitor.returncode in (0, 1), err.decode()
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    findings = [o for o in objects if o["type"] == "finding" and o["rule"] == "watchdog"
                and o["item"].get("type") == "VRPI"]
    raised = [f for f in findings if f["event"] == "raised"]
    cleared = [f for f in findings if f["event"] == "cleared"]
    assert raised and cleared, findings
    first = raised[0]
    # Raised while the BU was still silent, within a second of the 500 ms limit ...
    assert 0.5 < first["at"] - first["item"]["time"] <= 1.5
    assert first["item"].get("until_end") is True
    # ... and cleared by the BU's return, after the stall (about 2 s of silence).
    back = cleared[0]
    assert back["time"] > first["at"] and 1.5 < back["item"]["gap_ms"] / 1000 < 3.0
    # While silent, the dashboard's numbers said so.
    during = [o for o in objects if o["type"] == "snapshot" and first["at"] < o["time"] < back["time"]]
    assert during and all(any(a["rule"] == "watchdog" for a in s["alarms"]) for s in during)
    # The evidence: the packets of [alarm - 2 s, alarm + 1 s]: BU status before the silence, the
    # controller's outputs during it, nothing of the BU in it.
    files = sorted(p for p in evidence.iterdir() if p.suffix == ".pcapng" and "watchdog" in p.name)
    assert files
    meta = json.loads(files[0].with_suffix(".json").read_text())
    frames = list(CaptureReader(str(files[0])))
    assert len(frames) == meta["frames"]["count"] > 10
    start, end = meta["window"]["start"], meta["window"]["end"]
    assert all(start <= f[0] <= end for f in frames)
    silent_from = first["item"]["time"]
    bu_times = [f[0] for f in frames if f[2] == 5825]
    ctl_times = [f[0] for f in frames if f[2] == 5827]
    assert bu_times and max(t for t in bu_times if t <= silent_from + 0.001) == pytest.approx(silent_from)
    assert not [t for t in bu_times if silent_from + 0.001 < t <= meta["time"]]
    assert [t for t in ctl_times if t > silent_from]
    # The report at the end has the same violation.
    rep = json.loads(report.read_text())
    violations = [v for p in rep["periodic"] if p["type"] == "VRPI" for v in p["watchdog"]["violations"]]
    assert any(1.5 < v["gap_ms"] / 1000 < 3.0 for v in violations)
    # The link died about 2 s before the monitor stopped: silent to the end, in the last judgement
    # and in the report (it used to end at the last packet, with a clean verdict).
    assert [v for v in violations if v["until_end"] and v["gap_ms"] > 1000]
    assert rep["capture"]["last_time"] - rep["capture"]["first_time"] > 7.5
    assert [f for f in raised if f["item"].get("until_end") and f["time"] > back["time"]]
    # Stopped, dumpcap ends its capture with its statistics of the interface (what it dropped), which
    # the report gives as analyze gives them from dumpcap's file (the monitor stopped reading before).
    [lo] = rep["capture"]["dropped"]["interfaces"]
    assert lo["name"] == "lo" and lo["ifdrop"] is not None


def _capturing(monitor: subprocess.Popen, timeout: float = 30) -> None:
    """Until the monitor's dumpcap captures in its namespace (a packet socket there: nothing else in
    it opens one) and its filter is set; a skip without the rights to capture, a failure when the
    monitor ended otherwise. A fixed wait raced a dumpcap a busy machine (tests in parallel) started
    late: the first packets went unseen."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and monitor.poll() is None:
        with contextlib.suppress(OSError):
            if len(Path(f"/proc/{monitor.pid}/net/packet").read_text().splitlines()) > 1:
                time.sleep(0.5)            # (libpcap drops what comes before it sets the filter)
                break
        time.sleep(0.05)
    if monitor.poll() is not None:
        err = monitor.communicate()[1].decode().strip()
        if "capturing needs rights" in err:
            pytest.skip(f"dumpcap cannot capture here: {err}")
        pytest.fail(f"the monitor ended before the traffic: {err}")


_SEND_FRAGMENTED = """
import socket, sys, time
from vm110 import constants as C, encode
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, 10, 0)       # IP_MTU_DISCOVER: IP_PMTUDISC_DONT, fragmented
s.bind((sys.argv[1], 5827))
for serial in range(5):
    s.sendto(encode.packet(C.PacketType.VRPO, encode.vrpo_payload(0, bytes(488)), serial=serial), (sys.argv[2], 5827))
    time.sleep(0.05)
"""


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
@pytest.mark.parametrize("iface", ["lo", "any"])
def test_a_vrpo_fragmented_by_a_small_mtu_is_monitored_whole(iface, netns, tmp_path):
    """A VRPO of 488 data bytes over a link of MTU 400 arrives in IP fragments, which the base
    unit's stack and `analyze` put back together; dumpcap's filter kept only the first fragment
    (the others show no UDP port), so that the monitor counted no VRPO and raised its watchdog.
    `-i any` (Linux cooked frames, no VLAN tags: libpcap refuses a filter that names `vlan` there)."""
    ns = ["ip", "netns", "exec", netns]
    subprocess.run(["ip", "-n", netns, "link", "set", "lo", "mtu", "400"], check=True)
    report = tmp_path / "report.json"
    monitor = subprocess.Popen(ns + VM110 + ["monitor", "-i", iface, "--no-dashboard", "--quiet", "--duration", "60",
                                             "--json", str(report)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _capturing(monitor)
    subprocess.run(ns + [sys.executable, "-c", _SEND_FRAGMENTED, CTL, BU], check=True, timeout=30,
                   env={**os.environ, "PYTHONPATH": str(ROOT / "pcap_tools")})
    time.sleep(0.5)
    monitor.send_signal(signal.SIGINT)
    _, err = monitor.communicate(timeout=60)
    got = json.loads(report.read_text())
    assert monitor.returncode in (0, 1), err.decode()
    assert (got["capture"]["eglink_packets"], got["capture"]["fragments"]) == (5, 0)
    assert got["senders"][0]["by_type"] == {"VRPO": 5} and got["vrpo_bursts"]["complete"] == 5


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed")
def test_dashboard_in_tmux(tmp_path):
    capture = ROOT / "captures" / "bu-watchdog.pcap"     # controller silent 3.1 s from 4.9 s on
    session = f"vm110-dash-{os.getpid()}-{uuid.uuid4().hex[:8]}"      # unique: runs in parallel share the tmux server
    cmd = " ".join([*VM110, "monitor", "--read", str(capture), "--realtime", "--idle", "0", "--duration", "20",
                    "--quiet"])
    subprocess.run(["tmux", "new-session", "-d", "-s", session, "-x", "80", "-y", "24", cmd], check=True,
                   cwd=str(ROOT))
    try:
        # The alarm comes 4.9 s + 2 s into the capture; the silence ends at 8 s: look until then.
        for _ in range(60):
            time.sleep(0.25)
            pane = subprocess.run(["tmux", "capture-pane", "-p", "-t", session], capture_output=True, text=True,
                                  check=True).stdout
            if "WATCHDOG" in pane:
                break
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    rows = pane.splitlines()
    assert len(rows) <= 24 and all(len(r) <= 80 for r in rows)
    assert rows[0].startswith("vm110 monitor") and "running" in rows[0]
    text = "\n".join(rows)
    assert "CTL 10.0.0.20:5827 0x0000" in text and "WATCHDOG" in text
    assert "BU  10.0.0.10:5825 0x0101" in text and "ALIVE" in text
    assert "ALARM watchdog 10.0.0.20:5827" in text
    assert "watchdog ! 10.0.0.20:5827 0x0000: VRPO watchdog" in text
    assert "relays OPEN" in text      # the BU opened the ES-Link relays: its own watchdog on VRPO


def _dumpcap_under(pid: int) -> int | None:
    """The pid of the dumpcap among the descendants of `pid`, if one runs yet."""
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/task/{p}/children") as f:
                todo += [int(c) for c in f.read().split()]
            with open(f"/proc/{p}/comm") as f:
                if f.read().strip() == "dumpcap":
                    return p
        except OSError:
            continue
    return None


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
@pytest.mark.parametrize("how", ["SIGTERM at start-up", "SIGINT at start-up", "SIGHUP", "SIGKILL"])
def test_no_dumpcap_outlives_the_monitor(how, netns, tmp_path):
    """Whatever ends the monitor, signalled alone (not its process group), its dumpcap ends with it.
    "at start-up": the signal comes between dumpcap's start and the monitor's first read (held
    there with SIGSTOP, as a loaded machine holds it), where it used to kill the monitor and leave
    dumpcap capturing for ever. A monitor that can catch the signal ends with its report."""
    report = tmp_path / "r.json"
    monitor = subprocess.Popen(["ip", "netns", "exec", netns, *VM110, "monitor", "-i", "lo", "--no-dashboard",
                                "--quiet", "--json", str(report)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        dumpcap = None
        for _ in range(6000):            # (a loaded machine takes seconds to start the monitor)
            dumpcap = _dumpcap_under(monitor.pid)
            if dumpcap is not None or monitor.poll() is not None:
                break
            time.sleep(0.005)
        if dumpcap is None:              # (it waited for ever on a monitor still starting after 2 s)
            pytest.skip(f"dumpcap did not start here: {monitor.communicate(timeout=30)[1].decode().strip()}")
        sig = getattr(signal, how.split()[0])
        if how.endswith("start-up"):
            monitor.send_signal(signal.SIGSTOP)
            time.sleep(1.0)               # dumpcap has written its header: the pipe no longer ends it
            monitor.send_signal(sig)
            monitor.send_signal(signal.SIGCONT)
        else:
            time.sleep(1.5)
            monitor.send_signal(sig)
        _, err = monitor.communicate(timeout=30)
        for _ in range(100):
            if not _alive(dumpcap):
                break
            time.sleep(0.05)
        assert not _alive(dumpcap), f"dumpcap {dumpcap} outlived the monitor ({how})"
        if sig != signal.SIGKILL:
            assert monitor.returncode == 0, err.decode()
            assert json.loads(report.read_text())["capture"]["packets"] == 0
    finally:
        if monitor.poll() is None:
            monitor.kill()
            monitor.wait()
        pids = subprocess.run(["ip", "netns", "pids", netns], capture_output=True, text=True).stdout.split()
        for pid in pids:
            with contextlib.suppress(OSError):
                os.kill(int(pid), signal.SIGKILL)


def _without_the_end(report: dict) -> tuple[dict, dict]:
    """The report less what depends on when the watch ended (a live link is watched until the
    monitor stops, a file ends at its last packet: docs/monitor.md, "Which clock"), and the
    silences to the end apart: (sender, type) -> their starts."""
    r = copy.deepcopy(report)
    ends = {}
    for p in r["periodic"]:
        told = p["watchdog"]["violations"]
        ends[(p["sender"], p["type"])] = [v["start"] for v in told if v["until_end"]]
        p["watchdog"]["violations"] = [v for v in told if not v["until_end"]]
    for key in ("file", "last_time", "latest_time", "duration_s"):
        del r["capture"][key]
    del r["totals"]["watchdog"]
    r["verdict"]["findings"] = [f for f in r["verdict"]["findings"] if f["rule"] != "watchdog"]
    return r, ends


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
def test_a_live_session_tells_what_analyze_of_the_same_traffic_tells(netns, tmp_path):
    """Both simulators over the specification's multicast with impairments (loss, duplicates, bad
    CRCs, a hung BU, a hung controller), the monitor on the namespace's loopback through dumpcap,
    and beside it a dumpcap writing the same traffic to a file for `vm110 analyze`. The monitor's
    report is analyze's but for the end of the watch; its finding lines, with those the rate
    limit held back, are the report's items; each watchdog violation was raised and cleared live."""
    ns = ["ip", "netns", "exec", netns]
    ref, lines, report = tmp_path / "ref.pcapng", tmp_path / "live.jsonl", tmp_path / "monitor.json"
    options = ["--vrci-fail", "300"]          # (the VRCIs the hung controller leaves waiting fail)
    capture = subprocess.Popen(ns + ["dumpcap", "-q", "-i", "lo", "-f", "udp and (port 5825 or port 5827)",
                                     "-w", str(ref)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    monitor = subprocess.Popen(ns + VM110 + ["monitor", "-i", "lo", "--no-dashboard", "--quiet", "--duration", "60",
                                             "--json-lines", str(lines), "--json", str(report), *options],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        time.sleep(1.5)                     # both dumpcaps running before the traffic starts
        if capture.poll() is not None or monitor.poll() is not None:
            pytest.skip("dumpcap cannot capture here")
        sim = [*ns, *VM110, "simulate"]
        ctl = subprocess.Popen(sim + ["controller", "--iface", "127.0.0.1", "--duration", "6.5", "--quiet", "--seed",
                                      "3", "--loss", "5", "--corrupt", "3", "--stall", "3:3.6"],
                               stdout=subprocess.DEVNULL)
        time.sleep(0.3)                     # the BU's commands all come while the controller runs
        bu = subprocess.run(sim + ["bu", "--iface", "127.0.0.1", "--duration", "5", "--quiet", "--seed", "4",
                                   "--loss", "5", "--duplicate", "5", "--command-every", "0.4", "--stall", "1.5:2.5"],
                            stdout=subprocess.DEVNULL, timeout=30)
        assert ctl.wait(timeout=30) == 0 and bu.returncode == 0
        time.sleep(2.5)                     # both streams silent beyond their limits (500, 2000 ms)
        monitor.send_signal(signal.SIGINT)
        _, err = monitor.communicate(timeout=60)
        assert monitor.returncode in (0, 1), err.decode()
    finally:
        for proc in (monitor, capture):
            if proc.poll() is None:
                proc.terminate()
            proc.communicate(timeout=30)
    assert main(["analyze", str(ref), "--quiet", "--json", str(tmp_path / "analyze.json"), *options]) in (0, 1)
    live, ana = json.loads(report.read_text()), json.loads((tmp_path / "analyze.json").read_text())
    assert live["capture"]["last_time"] >= ana["capture"]["last_time"] + 2.0
    live_rest, live_ends = _without_the_end(live)
    ana_rest, ana_ends = _without_the_end(ana)
    assert live_rest == ana_rest
    # Silent to the end: the BU as analyze says (it stopped 1.5 s before the controller), the
    # controller too for the monitor, which watched on after the traffic.
    assert {k: v for k, v in ana_ends.items() if v} == {k: v for k, v in live_ends.items() if k[1] == "VRPI"}
    assert all(len(v) == 1 for v in live_ends.values()) and len(live_ends) == 2
    # The scenario did what it is for.
    totals = ana["totals"]
    assert totals["lost"] and totals["duplicates"] and totals["illegal"] and totals["failed"]
    assert [v for p in ana["periodic"] if p["type"] == "VRPI" for v in p["watchdog"]["violations"]
            if not v["until_end"]]
    # The lines told live, and those held back, are the report's items.
    objects = [json.loads(line) for line in lines.read_text().splitlines()]
    found = [o for o in objects if o["type"] == "finding"]
    for rule in ("lost", "illegal", "failed"):
        told = [f for f in found if f["rule"] == rule]
        held = sum(f.get("suppressed_before", 0) for f in told)
        held += sum(o["count"] for o in objects if o["type"] == "suppressed" and o["rule"] == rule)
        items = [i for f in live["verdict"]["findings"] if f["rule"] == rule for i in f["items"]]
        assert len(told) + held == len(items), rule
    watchdog = [f for f in found if f["rule"] == "watchdog"]
    for p in live["periodic"]:
        starts = sorted(v["start"] for v in p["watchdog"]["violations"])
        raised = sorted(f["item"]["time"] for f in watchdog if f["event"] == "raised"
                        and (f["sender"], f["item"]["type"]) == (p["sender"], p["type"]))
        cleared = [f for f in watchdog if f["event"] == "cleared" and f["sender"] == p["sender"]]
        assert raised == pytest.approx(starts, abs=1e-6) and len(cleared) == len(starts) - 1, p["type"]


def _on_a_terminal(cmd: list[str], log: Path | None) -> tuple[subprocess.Popen, int]:
    """`cmd` on a terminal of its own (a pty, its controlling terminal, as an SSH session gives),
    standard error into `log` or on the terminal too; its master side (the SSH end) returned."""
    master, slave = pty.openpty()
    with open(log or os.devnull, "wb") as err:
        proc = subprocess.Popen(["setsid", "--ctty", *cmd], stdin=slave, stdout=slave,
                                stderr=slave if log is None else err, cwd=str(ROOT))
    os.close(slave)
    return proc, master


def _screen_until(master: int, text: bytes, seconds: float) -> bytes:
    screen, end = b"", time.monotonic() + seconds
    while text not in screen and time.monotonic() < end:
        if select.select([master], [], [], 0.2)[0]:
            try:
                screen += os.read(master, 1 << 16)
            except OSError:                 # (the monitor gone: EIO)
                break
    return screen


@pytest.mark.skipif(shutil.which("setsid") is None, reason="setsid (util-linux) not installed")
@pytest.mark.parametrize("log", [True, False], ids=["stderr to a log", "stderr on the terminal"])
def test_a_closed_terminal_ends_the_dashboard_s_run_with_its_report(log, tmp_path):
    """Trial: with the dashboard on an SSH session's terminal, the session closing (the terminal
    hangs up: SIGHUP, and every write to it fails with EIO) ended the monitor at its next write,
    'cannot write standard output: Input/output error', exit 2: no --json report, no summary in
    the log, the verdict lost. Now it ends as on SIGTERM: evidence and report written, the
    summary on standard error when that still goes somewhere (a log), the verdict's exit code."""
    evidence, report, err = tmp_path / "evidence", tmp_path / "r.json", tmp_path / "monitor.log"
    evidence.mkdir()
    capture = ROOT / "captures" / "bu-watchdog.pcap"     # controller silent 3.1 s from 4.9 s on
    proc, master = _on_a_terminal(VM110 + ["monitor", "--read", str(capture), "--realtime", "--evidence",
                                           str(evidence), "--before", "1", "--after", "0.5", "--json", str(report),
                                           "--fail-on", "watchdog>0"], err if log else None)
    try:
        assert b"ALARM watchdog" in _screen_until(master, b"ALARM watchdog", 30)
    finally:
        os.close(master)                    # the SSH session closed
    assert proc.wait(timeout=30) == 1       # the verdict (--fail-on watchdog>0), not 2
    seen = json.loads(report.read_text())
    assert seen["totals"]["watchdog"] >= 1 and 0 < seen["capture"]["packets"]
    assert [p for p in evidence.iterdir() if p.name.endswith("-watchdog.pcapng")]
    if log:
        said = err.read_text()
        assert "VERDICT: FAIL" in said and "Traceback" not in said and "cannot write" not in said, said
        assert said.rstrip().endswith("(rule watchdog>0)")


@pytest.mark.skipif(shutil.which("dumpcap") is None or shutil.which("setsid") is None,
                    reason="dumpcap or setsid (util-linux) not installed")
def test_a_closed_terminal_stops_dumpcap_with_the_monitor(netns, tmp_path):
    """The dashboard of a live capture on an SSH session's terminal that closes: the monitor ends
    with its report (exit 0), and its dumpcap with it."""
    report, err = tmp_path / "r.json", tmp_path / "monitor.log"
    proc, master = _on_a_terminal(["ip", "netns", "exec", netns, *VM110, "monitor", "-i", "lo", "--json",
                                   str(report)], err)
    try:
        drawn = _screen_until(master, b"running", 30)
        dumpcap = _dumpcap_under(proc.pid)
        if dumpcap is None:
            pytest.skip(f"dumpcap did not start here: {err.read_text().strip()}")
        assert b"UTC  interface lo" in drawn
    finally:
        os.close(master)                    # the SSH session closed
    assert proc.wait(timeout=30) == 0, (proc.returncode, err.read_text())
    for _ in range(100):
        if not _alive(dumpcap):
            break
        time.sleep(0.05)
    assert not _alive(dumpcap)
    assert json.loads(report.read_text())["capture"]["packets"] == 0
    said = err.read_text()
    assert "VERDICT: " in said and "Traceback" not in said and "cannot write" not in said, said


_SEND_TAGGED = """
import socket, sys
import site_captures as S
s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
s.bind((sys.argv[1], 0))
mac = S.multicast_mac(S.GROUP)
for serial, tags in enumerate([(), ((0x8100, 42),), ((0x88A8, 100), (0x8100, 42))] * 2):
    d = S.Datagram(0, S.CTRL_IP, 5827, S.GROUP, 5827, S.vrpo(serial, 0, bytes(488)))
    body = S.udp(d.src, d.sport, d.dst, d.dport, d.payload)
    parts = S.ipv4_fragments(d.src, d.dst, body, 400, serial) if serial % 2 else [S.ipv4(d.src, d.dst, body)]
    parts.append(S.ipv4(d.src, d.dst, S.udp(d.src, 9999, d.dst, 9999, bytes(20))))   # not EG-Link: left out
    for part in parts:
        s.send(S.ether(S.CTRL_MAC, mac, 0x0800, part, tags))
"""


@pytest.mark.skipif(shutil.which("dumpcap") is None, reason="dumpcap not installed")
def test_eg_link_behind_vlan_tags_on_a_trunk_is_monitored(netns, tmp_path):
    """A trunk's EG-Link traffic tagged 802.1Q, or QinQ, some of it in fragments (MTU 400), as
    analyze reads it from a capture of the trunk. dumpcap's filter read the ports and fragment
    offsets where an untagged frame has them: every frame whose tag the kernel left in it (those
    sent on the trunk, and the inner tag of QinQ) was dropped, and the monitor saw no VRPO."""
    ns = ["ip", "netns", "exec", netns]
    for cmd in (["link", "add", "va", "type", "veth", "peer", "name", "vb"], ["link", "set", "va", "up"],
                ["link", "set", "vb", "up"]):
        subprocess.run(["ip", "-n", netns, *cmd], check=True, capture_output=True)
    report = tmp_path / "report.json"
    monitor = subprocess.Popen(ns + VM110 + ["monitor", "-i", "va", "--no-dashboard", "--quiet", "--duration", "60",
                                             "--json", str(report)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _capturing(monitor)
    subprocess.run(ns + [sys.executable, "-c", _SEND_TAGGED, "va"], check=True, timeout=30,
                   env={**os.environ, "PYTHONPATH": f"{ROOT / 'pcap_tools'}{os.pathsep}{ROOT / 'tests'}"})
    time.sleep(0.5)
    monitor.send_signal(signal.SIGINT)
    _, err = monitor.communicate(timeout=60)
    assert monitor.returncode in (0, 1), err.decode()
    got = json.loads(report.read_text())["capture"]
    # 3 VRPO whole, 3 in two fragments each; nothing else
    assert (got["packets"], got["eglink_packets"], got["fragments"], got["other_udp_packets"]) == (9, 6, 0, 0)
