"""End to end: `vm110 fuzz` against planted-bug controllers (tests/planted) over loopback.

With a fixed seed the fuzzer must find each planted bug within 60 s (`--duration 60`; it stops at
the first finding) and name the right oracle; `--replay` must reproduce the finding, and must not
against the reference controller. Against the reference controller itself it must find nothing.
"""
from __future__ import annotations

import json
import shlex
import socket
import struct
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import pytest
from scapy.layers.inet import UDP
from scapy.utils import PcapReader

from longrun import LONG_RUN
from loopback import free_ports
from planted.bugs import BUGS
from vm110 import cli, constants as C
from vm110.decode import decode
from vm110.fuzz import cases, findings, mutate

PLANTED = Path(__file__).resolve().parent / "planted" / "run.py"
SEED = 1


def controller_cmd(bug: str, rx: int, listen: int) -> str:
    return " ".join(shlex.quote(part) for part in (
        sys.executable, str(PLANTED), bug, "--listen", f"127.0.0.1:{rx}", "--peer", f"127.0.0.1:{listen}"))


def vm110(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=timeout)


def fuzz(out: Path, bug: str, *extra: str) -> tuple[subprocess.CompletedProcess, dict[str, Any]]:
    rx, listen = free_ports(2)
    result = vm110("fuzz", "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}",
                   "--target-cmd", controller_cmd(bug, rx, listen), "--seed", str(SEED), "--out", str(out), *extra)
    summary_path = out / "findings.json"
    assert summary_path.exists(), result.stderr
    return result, json.loads(summary_path.read_text())


def payloads(pcap: Path) -> list[bytes]:
    with PcapReader(str(pcap)) as reader:
        return [bytes(frame[UDP].payload) for frame in reader if UDP in frame]


def command_id(packet: bytes) -> int:
    return struct.unpack_from("<H", packet, C.PREFIX_LEN)[0]


# What each finding's minimised packet must be, beyond naming the oracle.
CHECKS: dict[str, Callable[[dict[str, Any], bytes], None]] = {
    "crash-on-joystick": lambda f, p: (decode(p)["joystick1"] == -32768 and not decode(p)["problems"]) or pytest.fail(f["packet_hex"]),
    "stall-after-oversize": lambda f, p: len(p) == C.MAX_PACKET + 1 or pytest.fail(str(len(p))),
    "ack-bad-crc": lambda f, p: (f["differences"] == 1 and decode(p)["problems"] == [C.Problem.BAD_CRC.value]) or pytest.fail(f["packet_hex"]),
    "no-reack": lambda f, p: (len(f["steps"]) == 2 and len({command_id(bytes.fromhex(s["hex"])) for s in f["steps"]}) == 1) or pytest.fail(str(f["steps"])),
    "bad-crc-after-wrap": lambda f, p: (command_id(p) == 0xFFFF and len(f["steps"]) == 1) or pytest.fail(f["packet_hex"]),
    "resend-after-vrai": lambda f, p: decode(p)["type"] == C.PacketType.VRAI.value or pytest.fail(f["packet_hex"]),
    "no-vrco-resend": lambda f, p: (f["withhold_vrai_ms"] > 0 and "not resent" in f["detail"]) or pytest.fail(f["detail"]),
    # Trial: blind mode never sent command data FF 00 (an opcode with an argument count of 0) in 60 s.
    "crash-on-empty-command": lambda f, p: (decode(p)["command_data"][:2] == b"\xff\0" and not decode(p)["problems"]) or pytest.fail(f["packet_hex"]),
}


@pytest.mark.parametrize("bug", sorted(CHECKS))
def test_planted_bug_is_found_named_and_replayable(tmp_path, bug):
    result, summary = fuzz(tmp_path, bug, "--duration", "60", "--max-findings", "1")
    assert result.returncode == 1, result.stdout + result.stderr
    assert summary["findings"], summary
    first = summary["findings"][0]
    assert first["oracle"] == BUGS[bug].ORACLE, summary
    if BUGS[bug].ORACLE == "crash":
        assert summary["restarts"] >= 1, "restarted after the crash"
    finding = json.loads((tmp_path / first["file"]).read_text())
    assert finding["seed"] == SEED and finding["oracle"] == BUGS[bug].ORACLE
    assert isinstance(finding["case_index"], int) and finding["mutation"]
    packet = bytes.fromhex(finding["packet_hex"])
    CHECKS[bug](finding, packet)
    sent = payloads(tmp_path / finding["pcap"])
    assert len(sent) > 10, "the pcap holds the traffic around the finding"
    if finding["original_hex"]:
        assert bytes.fromhex(finding["original_hex"]) in sent
    if finding["case_index"] < len(cases.sweep(SEED)) and finding["family"] != "none":
        assert cases.generate(SEED, finding["case_index"]).description == finding["mutation"]

    rx, listen = (int(finding[k].rsplit(":", 1)[1]) for k in ("target", "listen"))
    # The finding's stored command is never run: the controller is named on the command line.
    again = vm110("fuzz", "--replay", str(tmp_path / first["file"]), "--target-cmd", controller_cmd(bug, rx, listen))
    assert again.returncode == 1 and "still triggers" in again.stdout, again.stdout + again.stderr
    fixed = vm110("fuzz", "--replay", str(tmp_path / first["file"]),
                  "--target-cmd", controller_cmd("reference", rx, listen))
    assert fixed.returncode == 0 and "does not trigger" in fixed.stdout, fixed.stdout + fixed.stderr


def test_a_malformed_output_replay_says_whether_it_is_the_same_kind(tmp_path):
    """--replay counted a malformed output of any kind: a finding of one kind 'still triggered' on
    a controller that now sent another (a different bug), where a crash's replay compared its
    signature. It now says which, as for a crash."""
    rx, listen = free_ports(2)
    packet = mutate.build(C.PacketType.VRCI, 5, mutate.default_fields(C.PacketType.VRCI, 0xFFFF))
    for kind, verdict in (("VRAO with bad_crc", "still triggers: the same signature"),
                          ("VRAO unknown", "still triggers: another signature (illegal VRAO from the controller: bad_crc")):
        finding = findings.Finding(
            oracle="malformed_output", seed=SEED, case_index=3, family="sweep-vrci", mutation="a VRCI",
            detail="a bad VRAO", packet_hex=packet.hex(), original_hex=packet.hex(), valid_hex=packet.hex(),
            differences=0, minimised=True,
            steps=[{"hex": packet.hex(), "valid_hex": packet.hex(), "delay_ms": 0.0, "expect_ack": True}],
            stream=dict(mutate.ARMED_VRPI), target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}",
            signature=f"malformed_output {kind} (VRCI)")
        path = tmp_path / "finding.json"
        path.write_text(json.dumps(asdict(finding)))
        again = vm110("fuzz", "--replay", str(path), "--target-cmd", controller_cmd("bad-crc-after-wrap", rx, listen))
        assert again.returncode == 1 and verdict in again.stdout, again.stdout + again.stderr


def test_replay_plays_the_case_as_early_as_the_run_confirmed_it(tmp_path):
    """The run confirms a trigger 135 ms after the restarted controller's first VRPO; --replay
    waited 250 ms: a bug of the controller's first 240 ms (or of the early part of its scan cycle)
    was confirmed by the run and then said fixed by --replay (exit 0)."""
    rx, listen = free_ports(2)
    packet = mutate.build(C.PacketType.VRCI, 5, mutate.default_fields(C.PacketType.VRCI, 7))
    finding = findings.Finding(
        oracle="missing_ack", seed=SEED, case_index=3, family="sweep-vrci", mutation="a VRCI",
        detail="no VRAO for command ID 7 within 1000 ms", packet_hex=packet.hex(), original_hex=packet.hex(),
        valid_hex=packet.hex(), differences=0, minimised=True,
        steps=[{"hex": packet.hex(), "valid_hex": packet.hex(), "delay_ms": 0.0, "expect_ack": True}],
        stream=dict(mutate.ARMED_VRPI), target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}",
        signature="missing_ack no ack (VRCI)")
    path = tmp_path / "finding.json"
    path.write_text(json.dumps(asdict(finding)))
    again = vm110("fuzz", "--replay", str(path), "--target-cmd", controller_cmd("no-ack-while-loading", rx, listen))
    assert again.returncode == 1 and "still triggers" in again.stdout, again.stdout + again.stderr


def _clean_run(tmp_path: Path, seconds: str) -> None:
    result, summary = fuzz(tmp_path, "reference", "--duration", seconds)
    assert result.returncode == 0, result.stdout + result.stderr
    rx = int(summary["target"].rsplit(":", 1)[1])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", rx))      # fails while the controller still holds it: it was stopped
    assert summary["findings"] == [] and summary["counts"] == {}
    assert summary["cases_run"] >= len(cases.sweep(SEED)), "the whole sweep ran"
    assert summary["stopped_early"] is None


def test_reference_controller_has_no_findings(tmp_path):
    _clean_run(tmp_path, "15")


@LONG_RUN[0]
@LONG_RUN[1]
def test_reference_controller_has_no_findings_in_60_s(tmp_path):
    _clean_run(tmp_path, "60")


def test_unsupervised_controller(tmp_path):
    """Without --target-cmd: the controller runs on its own, findings are still confirmed by replay."""
    rx, listen = free_ports(2)
    controller = subprocess.Popen(shlex.split(controller_cmd("ack-bad-crc", rx, listen)))
    try:
        result = vm110("fuzz", "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}",
                       "--seed", str(SEED), "--cases", "40", "--out", str(tmp_path))
    finally:
        controller.terminate()
        controller.wait(10)
    summary = json.loads((tmp_path / "findings.json").read_text())
    assert result.returncode == 1, result.stdout + result.stderr
    assert {f["oracle"] for f in summary["findings"]} == {"illegal_acked"}
    assert summary["restarts"] == 0 and summary["cases_run"] == 40


def test_usage_errors_exit_2(tmp_path, capsys):
    """(In this process: a new interpreter a case took 12 s of the suite.)"""
    def fuzz_here(*args: str) -> tuple[int, str]:
        code = cli.main(["fuzz", *args])
        return code, capsys.readouterr().err
    for args in (["--target", "nohostport"], ["--cases", "3"], ["--replay", str(tmp_path / "missing.json")],
                 ["--target", "127.0.0.1:9", "--target-cmd", "'unbalanced"]):
        code, err = fuzz_here(*args, "--out", str(tmp_path))
        assert code == 2 and err.count("\n") == 1, (args, err)
    (tmp_path / "other.json").write_text('{"hello": 1}')
    code, err = fuzz_here("--replay", str(tmp_path / "other.json"))
    assert code == 2 and "not a vm110 fuzz finding" in err
    _, listen = free_ports(2)
    code, err = fuzz_here("--target", "127.0.0.1:9", "--listen", f"127.0.0.1:{listen}", "--startup", "1",
                          "--cases", "3", "--out", str(tmp_path))
    assert code == 2 and "no VRPO" in err


def test_a_run_whose_duration_ends_before_its_first_case_is_no_pass(tmp_path):
    """Trial: `--duration 0.001` ran 0 cases and exited 0, a pass for a CI gate that tested nothing.
    It says so, exit 2; the summary is still written."""
    result, summary = fuzz(tmp_path, "reference", "--duration", "0.001")
    assert result.returncode == 2 and summary["cases_run"] == 0, result.stdout + result.stderr
    assert result.stderr.splitlines()[-1] == ("vm110 fuzz: no case ran: --duration 0.001 s ended before the first "
                                              "case (the controller's start and its first VRPO come first)")


def test_a_controller_that_exits_at_once_is_told_at_once(tmp_path):
    """Trial: --target-cmd true exited at once, and the fuzzer still waited out --startup (10 s)
    before saying so. An empty --target-cmd or --out was taken as none given."""
    rx, listen = free_ports(2)
    started = time.monotonic()
    result = vm110("fuzz", "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}", "--target-cmd", "true",
                   "--startup", "30", "--cases", "3", "--out", str(tmp_path / "out"))
    assert result.returncode == 2 and time.monotonic() - started < 15, result.stderr
    assert "the controller exited with code 0 before sending any VRPO" in result.stderr
    for option in ("--target-cmd", "--out"):
        result = vm110("fuzz", "--target", f"127.0.0.1:{rx}", option, "", "--cases", "3")
        assert result.returncode == 2 and f"{option} is empty" in result.stderr, result.stderr


def test_a_controller_that_will_not_start_is_told_with_its_last_words(tmp_path):
    """Trial: my Python controller could not open its serial port and exited; the fuzzer said only
    'the controller exited with code 1 before sending any VRPO', the reason left in target.log."""
    rx, listen = free_ports(2)
    script = tmp_path / "ctl.py"
    script.write_text('print("starting")\nraise SystemExit("controller: cannot open /dev/ttyS9: no such device")\n')
    result = vm110("fuzz", "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}", "--target-cmd",
                   f"{sys.executable} {script}", "--cases", "3", "--out", str(tmp_path / "out"))
    assert result.returncode == 2, result.stderr
    assert ('the controller exited with code 1 before sending any VRPO to 127.0.0.1:'
            f'{listen}: its last output line "controller: cannot open /dev/ttyS9: no such device"') in result.stderr


def test_two_exceptions_of_a_python_controller_are_two_findings(tmp_path):
    """Trial: a KeyError and a ZeroDivisionError of one controller in Python were one finding,
    `crash exit 1` (the signature had the exit code alone)."""
    result, summary = fuzz(tmp_path, "two-exceptions", "--duration", "90", "--max-findings", "2")
    assert result.returncode == 1, result.stdout + result.stderr
    signatures = sorted(f["signature"] for f in summary["findings"])
    assert [s.split()[:4] for s in signatures] == [["crash", "exit", "1", "python:KeyError"],
                                                   ["crash", "exit", "1", "python:ZeroDivisionError"]], signatures
    assert "crash exit 1 KeyError in on_vrci (bugs.py:" in result.stdout
    # Review: the summary printed ASAN_OPTIONS and the like, which mean nothing to Python.
    assert summary["sanitizer_options"] == {} and "_OPTIONS" not in result.stdout, result.stdout


def _fuzz_wrapped(tmp_path: Path, script: str, rx: int, listen: int, out: Path, *extra: str):
    """`vm110 fuzz` of a controller started by a shell `script` (a file of its keeps state between starts)."""
    wrapper = tmp_path / "controller.sh"
    wrapper.write_text("#!/bin/sh\n" + script)
    wrapper.chmod(0o755)
    return vm110("fuzz", "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}", "--target-cmd",
                 str(wrapper), "--seed", str(SEED), "--out", str(out), *extra)


def test_a_controller_that_cannot_be_restarted_after_a_crash_is_no_pass(tmp_path):
    """Trial: my controller died on a case and, restarted, refused to start (the lock file its dead
    self left): the run said 0 findings, 1 unreproduced trigger, and exited 0, a pass for CI."""
    rx, listen = free_ports(2)
    lock = tmp_path / "controller.lock"
    out = tmp_path / "out"
    result = _fuzz_wrapped(tmp_path, f"test -e {lock} && exit 1\ntouch {lock}\n"
                           f"exec {controller_cmd('crash-on-joystick', rx, listen)}\n", rx, listen, out,
                           "--duration", "60", "--startup", "2")
    assert result.returncode == 1, result.stdout + result.stderr
    summary = json.loads((out / "findings.json").read_text())
    [lost] = summary["unreproduced"]
    assert summary["controller_lost"] and lost["oracle"] == "crash" and "VRPI joystick1=-32768" in lost["suspect_cases"]
    assert "the controller could not be restarted (controller restarted but sent no VRPO within 2 s (exit code 1))" \
        in result.stdout


def test_the_replay_of_an_old_finding_of_several_cases_says_what_it_lacks(tmp_path):
    """Review: a finding of several cases written before each case's stream was kept replays its
    packets under the armed stream; its 'does not trigger any more' may only mean that."""
    rx, listen = free_ports(2)
    packet = mutate.build(C.PacketType.VRCI, 5, mutate.default_fields(C.PacketType.VRCI, 9))
    step = {"hex": packet.hex(), "valid_hex": packet.hex(), "delay_ms": 0.0, "expect_ack": True}
    finding = findings.Finding(
        oracle="missing_ack", seed=SEED, case_index=3, family="sequence-of-cases", mutation="[a] then [b]",
        detail="no VRAO", packet_hex=packet.hex(), original_hex=packet.hex(), valid_hex=packet.hex(),
        differences=0, minimised=False, steps=[step, step], target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}")
    raw = asdict(finding)
    del raw["cases"]                                  # as the version before wrote it
    path = tmp_path / "finding.json"
    path.write_text(json.dumps(raw))
    result = vm110("fuzz", "--replay", str(path), "--target-cmd", controller_cmd("reference", rx, listen))
    assert result.returncode == 0 and "does not trigger" in result.stdout, result.stdout + result.stderr
    assert "its replay sends them under the armed stream" in result.stderr


def test_a_crash_no_replay_makes_again_is_no_pass(tmp_path):
    """Trial: my controller crashed once (on a state its cases alone did not make again) and no
    replay crashed it: the run said 0 findings, 1 unreproduced trigger and exited 0, a pass for CI."""
    rx, listen = free_ports(2)
    once = tmp_path / "crashed-once"
    out = tmp_path / "out"
    result = _fuzz_wrapped(tmp_path, f"test -e {once} && exec {controller_cmd('reference', rx, listen)}\n"
                           f"touch {once}\nexec {controller_cmd('crash-on-joystick', rx, listen)}\n", rx, listen, out,
                           "--cases", "150")
    assert result.returncode == 1, result.stdout + result.stderr
    summary = json.loads((out / "findings.json").read_text())
    assert not summary["findings"] and [u["oracle"] for u in summary["unreproduced"]] == ["crash"]
    assert "the controller crashed 1 time where replaying its cases did not crash it again (crash exit 3)" \
        in result.stdout


# The first cases of seed 1 send valid VRCI twice (case 1) and once (cases 4 and 9).
RESEND_CASES = "10"


def test_a_controller_that_acknowledges_the_resend_of_a_command_has_no_missing_ack(tmp_path):
    """TS-0006 5.1.3: the base unit resends an unacknowledged VRCI every 100 ms. The fuzzer sent
    each once: a controller that missed one (busy, between the reads of its scan cycle) and
    acknowledged the resend was a missing_ack finding."""
    result, summary = fuzz(tmp_path, "acks-resends-only", "--cases", RESEND_CASES, "--max-findings", "1",
                           "--minimize-budget", "2")
    assert result.returncode == 0, result.stdout + result.stderr
    assert summary["findings"] == [] and summary["unreproduced"] == [], summary


def test_a_controller_that_never_acknowledges_is_one_missing_ack_finding_with_its_resends(tmp_path):
    """Resends do not hide a controller that acknowledges nothing, nor make more findings of it: one
    finding for all its missing acks; its pcap holds the resends, valid, on new serials, none after
    the ack timeout; its replay resends as the run did (one that acknowledges only resends passes),
    and with --no-resend does not."""
    result, summary = fuzz(tmp_path, "never-ack", "--cases", RESEND_CASES, "--minimize-budget", "2")
    assert result.returncode == 1, result.stdout + result.stderr
    assert [f["oracle"] for f in summary["findings"]] == ["missing_ack"], summary
    assert summary["buckets"][0]["count"] >= 2, "several commands unacknowledged, one finding"
    finding = json.loads((tmp_path / summary["findings"][0]["file"]).read_text())
    assert finding["resend_ms"] == C.COMMAND_RESEND_MS
    shown = bytes.fromhex(finding["original_hex"])
    steps = [bytes.fromhex(s["hex"]) for s in finding["steps"]]
    vrci = [p for p in payloads(tmp_path / finding["pcap"])
            if decode(p).get("type") == "VRCI" and command_id(p) == command_id(shown)]
    resends = [p for p in vrci if p not in steps]
    assert len(resends) >= 2, "resent while unacknowledged"
    for packet in resends:
        fields = decode(packet)
        assert not fields["problems"] and fields["origin"] == mutate.BU_ORIGIN
        assert packet[C.PREFIX_LEN:-C.CRC_LEN] == shown[C.PREFIX_LEN:-C.CRC_LEN], "same command, same data"
    serials = [decode(p)["serial"] for p in vrci]
    assert serials == sorted(set(serials)), "each transmission on a new serial"
    # Every 100 ms within the 1000 ms ack timeout: at most 10 resends of each of the case's own.
    case = cases.generate(SEED, finding["case_index"])
    own = sum(command_id(st.build(0)[0]) == command_id(shown) for st in case.steps)
    assert len(vrci) <= 11 * own, "no resend after the ack timeout"

    rx, listen = (int(finding[k].rsplit(":", 1)[1]) for k in ("target", "listen"))
    path = str(tmp_path / summary["findings"][0]["file"])
    conformant = controller_cmd("acks-resends-only", rx, listen)
    again = vm110("fuzz", "--replay", path, "--target-cmd", conformant)
    assert again.returncode == 0 and "does not trigger" in again.stdout, again.stdout + again.stderr
    strict = vm110("fuzz", "--replay", path, "--no-resend", "--target-cmd", conformant)
    assert strict.returncode == 1 and "still triggers" in strict.stdout, strict.stdout + strict.stderr
