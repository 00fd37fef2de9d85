"""`vm110 simulate` speaks the other readings of TS-0006 that `analyze` and the dissector take as
options: a CRC variant and byte order, one serial counter per packet type, VRPO numbered from 1.

Both simulators run over loopback through a tap in the test (it forwards each datagram to the
other side and records it); the recording, written as a capture, must read clean under the
matching options (no illegal packet, no serial anomaly, every VRPO burst complete) and not under
interpretation.md's defaults, in `vm110 analyze` and in the dissector on every Wireshark version.
"""
from __future__ import annotations

import json
import select
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from loopback import LOOPBACK
from vm110 import constants as C
from vm110.capture.writer import UdpFlow, open_writer

READING = ["--crc", "bzip2", "--crc-order", "big", "--serial-scope", "type"]
ANALYZE_READING = [*READING, "--vrpo-start", "1"]
PREFS = ["-o", "vm110.crc_variant:bzip2", "-o", "vm110.crc_byte_order:big", "-o", "vm110.serial_scope:type",
         "-o", "vm110.vrpo_number_start:1"]
ANOMALIES = ("vm110.expert.bad_crc", "vm110.expert.serial_gap", "vm110.expert.serial_duplicate",
             "vm110.expert.serial_out_of_order", "vm110.expert.restart", "vm110.expert.burst_missing",
             "vm110.expert.burst_incomplete")
SECONDS = 3.0
LOGS: dict[str, list[dict]] = {}        # each simulator's JSON log, the summary last


def _tap(routes: dict[socket.socket, tuple[tuple[str, int], bool]], record: list, stop: threading.Event) -> None:
    """Forward what arrives on each socket to its destination; record (time, source, input?, data)."""
    while not stop.is_set():
        for sock in select.select(list(routes), [], [], 0.05)[0]:
            data, src = sock.recvfrom(2048)
            dest, inbound = routes[sock]
            record.append((time.time(), src, inbound, data))
            sock.sendto(data, dest)


def record_pair(path: Path, ctl_args: list[str], bu_args: list[str],
                ctl_seconds: float = SECONDS) -> dict[str, list[dict]]:
    """Run both simulators through the tap for SECONDS (the controller `ctl_seconds`), write what
    passed to `path` (as a tap on the group would show it) and return each one's JSON log, the
    summary last."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(4)]
    tap_in, tap_out, bu_rx, ctl_rx = socks
    for s in socks:
        s.bind((LOOPBACK, 0))
    bu_port, ctl_port = bu_rx.getsockname()[1], ctl_rx.getsockname()[1]
    bu_rx.close()
    ctl_rx.close()
    record: list = []
    stop = threading.Event()
    # tap_in: the BU's inputs, on to the controller; tap_out: the controller's outputs, on to the BU
    routes = {tap_in: ((LOOPBACK, ctl_port), True), tap_out: ((LOOPBACK, bu_port), False)}
    tapper = threading.Thread(target=_tap, args=(routes, record, stop), daemon=True)
    tapper.start()
    common = ["--source", f"{LOOPBACK}:0", "--json"]
    run = [sys.executable, "-m", "vm110", "simulate"]
    ctl = subprocess.Popen([*run, "controller", "--listen", f"{LOOPBACK}:{ctl_port}", "--peer",
                            f"{LOOPBACK}:{tap_out.getsockname()[1]}", *ctl_args, *common,
                            "--duration", str(ctl_seconds)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    bu = subprocess.Popen([*run, "bu", "--listen", f"{LOOPBACK}:{bu_port}", "--peer",
                           f"{LOOPBACK}:{tap_in.getsockname()[1]}", *bu_args, *common, "--duration", str(SECONDS)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        outs = [p.communicate(timeout=60) for p in (ctl, bu)]
    finally:
        stop.set()
        tapper.join()
        for s in (tap_in, tap_out):
            s.close()
    logs = {}
    for role, p, (out, err) in zip(("controller", "bu"), (ctl, bu), outs):
        assert p.returncode == 0, err
        logs[role] = [json.loads(line) for line in out.splitlines()]
    flows: dict = {}
    with open(path, "wb") as stream:
        writer = open_writer(stream)
        frames = []
        for t, (_, port), inbound, data in record:
            if (port, inbound) not in flows:
                ip, dport = ("10.0.0.10", C.INPUT_PORT) if inbound else ("10.0.0.20", C.OUTPUT_PORT)
                flows[(port, inbound)] = UdpFlow(ip, port, C.MULTICAST_GROUP, dport)
            frames.append((round(t * 1e6), flows[(port, inbound)].frame(data)))
        writer.write_many(frames)
        writer.close()
    assert len(record) > 60
    return logs


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A capture of both simulators talking with READING and VRPO numbered from 1."""
    path = tmp_path_factory.mktemp("readings") / "readings.pcap"
    LOGS.update(record_pair(path, [*READING, "--vrpo-start", "1", "--data-size", "1200", "--command-every", "0.7"],
                            [*READING, "--command-every", "0.5"]))
    return path


def test_each_simulator_understood_the_other(capture):
    """Every packet legal to its receiver, and no restart seen where there was none: with one
    counter per packet type, a receiver that followed the peer's serials as one counter took the
    interleaved counters for restarts (and would have carried a retransmitted command out again)."""
    for role, log in LOGS.items():
        assert log[-1]["summary"]["illegal_packets"] == 0, (role, log[-1])
        assert not [e for e in log if e.get("event") in ("bu_restart", "controller_restart")], role
    executed = [e["command_id"] for e in LOGS["controller"] if e.get("event") == "executed"]
    sent = [e["command_id"] for e in LOGS["bu"] if e.get("event") == "command_sent"]
    # (the controller, started first, ends first: under load the BU's last command may find it gone)
    assert executed == sent[:len(executed)] and len(executed) >= max(4, len(sent) - 1), (executed, sent)
    delivered = [e["command_id"] for e in LOGS["bu"] if e.get("event") == "vrco_delivered"]
    assert delivered == [e["command_id"] for e in LOGS["controller"] if e.get("event") == "vrco_sent"][:len(delivered)]
    assert len(delivered) >= 3


def analyze(path: Path, *options: str) -> dict:
    done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(path), "--json", "-", *options],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode in (0, 1), done.stderr
    return json.loads(done.stdout)


def test_analyze_reads_the_simulators_clean_under_the_matching_options(capture):
    totals = analyze(capture, *ANALYZE_READING)["totals"]
    assert totals["illegal"] == totals["crc_invalid"] == 0, totals
    assert totals["lost"] == totals["duplicates"] == totals["out_of_order"] == totals["restarts"] == 0, totals
    assert totals["vrpo_incomplete"] == totals["failed"] == 0, totals
    assert totals["unacked"] <= 1, totals         # (a command sent as the run ended has no ack in it)
    assert totals["commands"] >= 6


@pytest.mark.parametrize("default", [["--crc", "mpeg2", "--crc-order", "little"], ["--serial-scope", "sender"],
                                     ["--vrpo-start", "0"]], ids=["crc", "scope", "vrpo-start"])
def test_each_reading_shows_under_the_default_one(capture, default):
    """The negative control: with interpretation.md's reading of any one of them, the capture is
    not clean (before, `simulate` had no such options and always sent the defaults)."""
    options = list(ANALYZE_READING)
    for name, value in zip(default[::2], default[1::2]):
        options[options.index(name) + 1] = value
    totals = analyze(capture, *options)["totals"]
    assert totals["illegal"] or totals["lost"] or totals["duplicates"] or totals["out_of_order"] \
        or totals["vrpo_incomplete"], (default, totals)


def test_the_dissector_reads_them_clean_under_the_matching_preferences(capture, ws):
    pcap = ws.dir / "readings.pcap"
    pcap.write_bytes(capture.read_bytes())
    status = ws.run(["-r", str(pcap), *PREFS, "-T", "fields", "-e", "vm110.crc.status"]).stdout.split()
    assert status and set(status) == {"1"}                         # every CRC good
    found = ws.run(["-r", str(pcap), *PREFS, "-Y", " || ".join(ANOMALIES), "-T", "fields", "-e", "frame.number"])
    assert found.stdout.split() == []
    default = ws.run(["-r", str(pcap), "-Y", " || ".join(ANOMALIES), "-T", "fields", "-e", "frame.number"])
    assert default.stdout.split()


@pytest.mark.parametrize("restart", ["1.2", "1.2:0"], ids=["same-port", "new-port"])
def test_the_controller_sees_the_bu_restarts_that_analyze_counts(tmp_path, restart):
    """The controller and `analyze` count the same thing: the BU's restarts (a reboot from serial
    40000 back to 0, on the same or a new source port), and every operator command, the ones whose
    IDs the rebooted BU reused within 2 s included, decided once: carried out, or refused while the
    reboot has left no RU armed (TS-0006 4.3)."""
    path = tmp_path / "restart.pcap"
    # (the controller outlives the BU: under load the BU's start, and so its restart at 1.2 s, may
    # come a second or more after the controller's)
    logs = record_pair(path, [], ["--command-every", "0.4", "--serial-start", "40000", "--restart", restart,
                                  "--restart-silence", "0.4"], ctl_seconds=SECONDS + 3)
    report = analyze(path)
    restarts = [e for e in logs["controller"] if e.get("event") == "bu_restart"]
    assert len(restarts) == report["totals"]["restarts"] == 1, report["totals"]
    decided = [e["command_id"] for e in logs["controller"] if e.get("event") in ("executed", "refused")]
    sent = [e["command_id"] for e in logs["bu"] if e.get("event") == "command_sent"]
    # (a command sent as the BU ended may have found no answer: a prefix)
    assert decided == sent[:len(decided)] and len(set(decided)) < len(decided), (decided, sent)
    assert report["totals"]["commands"] == len(sent)
