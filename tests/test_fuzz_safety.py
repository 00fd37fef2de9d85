"""Issue 17 for `vm110 fuzz`: nothing run or sent that was not asked for, every bad number refused,
findings and summaries never lost.

Network safety: nothing here sends beyond loopback. Refusals are tested with `Link.send` and the
controller's start replaced by a failing stand-in; the one test that sends to a non-loopback
address does so inside a network namespace whose only interface is its own loopback.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
from scapy.layers.inet import UDP
from scapy.utils import PcapReader

from loopback import free_ports
from vm110 import cli
from vm110.commands import fuzz as fuzz_command
from vm110 import constants as C
from vm110 import encode
from vm110.errors import CliError
from vm110.fuzz import destination, findings, mutate
from vm110.fuzz.link import Link
from vm110.fuzz.supervisor import Supervisor

NEVER = " (refused even with --allow-remote)"


def vm110(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def nothing_leaves(monkeypatch):
    """Any packet sent or controller started fails the test."""
    def send(self, data: bytes) -> float:
        pytest.fail(f"a packet was sent to {self.target}")

    def start(self) -> None:
        pytest.fail(f"a command was run: {self.command}")
    monkeypatch.setattr(Link, "send", send)
    monkeypatch.setattr(Supervisor, "start", start)


def fuzz_in_process(capsys, *args: str) -> tuple[int, str]:
    code = cli.main(["fuzz", *args])
    return code, capsys.readouterr().err


def one_line(err: str) -> str:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def local_broadcasts() -> list[str]:
    """The broadcast addresses of this machine's subnets: loopback's always, others where iproute2 says."""
    found = {"127.255.255.255"}
    if shutil.which("ip"):
        out = subprocess.run(["ip", "-j", "-4", "addr"], capture_output=True, text=True).stdout or "[]"
        found |= {a["broadcast"] for link in json.loads(out) for a in link.get("addr_info", []) if "broadcast" in a}
    return sorted(found)


# --- where the fuzzer sends -------------------------------------------------------------------------
@pytest.mark.parametrize("address, allow, refusal", [
    ("255.255.255.255", True, "broadcast address"),
    ("0.0.0.0", True, "unspecified address"),
    ("::", True, "unspecified address"),
    ("::ffff:255.255.255.255", True, "broadcast address"),
    (C.MULTICAST_GROUP, False, "multicast group"),
    ("224.0.0.1", False, "multicast group"),
    ("ff02::1", False, "multicast group"),
    ("192.0.2.7", False, "not a loopback address"),
    ("2001:db8::1", False, "not a loopback address"),
    ("::ffff:192.0.2.7", False, "not a loopback address"),
    ("localhost", True, "not an IP address"),
])
def test_destination_refusals(address, allow, refusal):
    with pytest.raises(CliError, match=refusal):
        destination.check(address, "--target", allow)


@pytest.mark.parametrize("address, allow", [("127.0.0.1", False), ("127.1.2.3", False), ("::1", False),
                                            ("::ffff:127.0.0.1", False), (C.MULTICAST_GROUP, True),
                                            ("192.0.2.7", True), ("2001:db8::1", True)])
def test_destination_allowed(address, allow):
    destination.check(address, "--target", allow)


@pytest.mark.parametrize("address", local_broadcasts())
def test_subnet_broadcasts_are_refused_even_with_allow_remote(address):
    assert destination.is_local_broadcast(__import__("ipaddress").IPv4Address(address))
    with pytest.raises(CliError, match="broadcast address"):
        destination.check(address, "--target", True)


def test_the_link_itself_refuses():
    """The last gate: a Link is never made towards a refused address, whatever its caller checked."""
    listen = ("127.0.0.1", free_ports(1)[0])
    with pytest.raises(CliError, match="not a loopback"):
        Link(("192.0.2.7", 5825), listen)
    with pytest.raises(CliError, match="broadcast"):
        Link(("255.255.255.255", 5825), listen, allow_remote=True)


@pytest.mark.parametrize("target, allow, refusal", [
    ("255.255.255.255", True, "broadcast address"),
    ("0.0.0.0", True, "unspecified address"),
    ("127.255.255.255", True, "broadcast address"),
    (C.MULTICAST_GROUP, False, "multicast group"),
    ("192.0.2.7", False, "not a loopback address"),
    ("[ff02::1]", False, "multicast group"),
])
def test_fuzz_refuses_targets_without_sending(capsys, nothing_leaves, tmp_path, target, allow, refusal):
    marker = tmp_path / "started"
    code, err = fuzz_in_process(capsys, "--target", f"{target}:5825", *(["--allow-remote"] if allow else []),
                                "--target-cmd", f"touch {marker}", "--cases", "1", "--out", str(tmp_path / "out"))
    line = one_line(err)
    assert code == 2 and refusal in line and "--target" in line, line
    assert not marker.exists()
    if allow:
        assert line.endswith(NEVER)
    else:
        assert "--allow-remote" in line


@pytest.mark.parametrize("address", [a for a in local_broadcasts() if a != "127.255.255.255"])
def test_fuzz_refuses_this_machines_subnet_broadcast(capsys, nothing_leaves, tmp_path, address):
    code, err = fuzz_in_process(capsys, "--target", f"{address}:5825", "--allow-remote", "--cases", "1",
                                "--out", str(tmp_path))
    assert code == 2 and "broadcast address" in one_line(err)


def test_allow_remote_prints_the_resolved_address_before_the_first_packet(capsys, monkeypatch, tmp_path):
    """A loopback name with --allow-remote: resolved once, printed before anything is sent."""
    rx, listen = free_ports(2)
    lookups = []
    real_getaddrinfo = socket.getaddrinfo

    def getaddrinfo(host, *args, **kwargs):
        lookups.append(host)
        return real_getaddrinfo(host, *args, **kwargs)
    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    before_first: list[str] = []

    def send(self, data: bytes) -> float:
        if not before_first:
            before_first.append(capsys.readouterr().err)
        assert self.target == ("127.0.0.1", rx)
        return 0.0
    monkeypatch.setattr(Link, "send", send)
    code, err = fuzz_in_process(capsys, "--target", f"localhost:{rx}", "--listen", f"127.0.0.1:{listen}",
                                "--allow-remote", "--startup", "0.3", "--cases", "1", "--out", str(tmp_path))
    assert code == 2 and "no VRPO" in err      # nobody answers: the run stops after its first VRPI
    assert before_first and f"sending to 127.0.0.1:{rx} only (--target localhost:{rx})" in before_first[0]
    assert lookups.count("localhost") == 1


def test_allow_remote_sends_to_a_non_loopback_address_inside_a_namespace(netns, tmp_path):
    """In a namespace whose only interface is its loopback: a remote-looking address is refused
    without --allow-remote, printed and used with it; its subnet's broadcast is refused either way."""
    def inside(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", netns, sys.executable, "-m", "vm110", "fuzz", *args,
                               "--startup", "0.5", "--cases", "1", "--out", str(tmp_path)],
                              capture_output=True, text=True, timeout=60)
    subprocess.run(["ip", "-n", netns, "addr", "add", "10.99.8.1/24", "broadcast", "10.99.8.255", "dev", "lo"],
                   check=True)
    refused = inside("--target", "10.99.8.7:5825", "--listen", "10.99.8.1:5827")
    assert refused.returncode == 2 and "not a loopback address" in one_line(refused.stderr)
    sent = inside("--target", "10.99.8.7:5825", "--listen", "10.99.8.1:5827", "--allow-remote")
    assert sent.returncode == 2 and "no VRPO" in sent.stderr
    assert sent.stderr.splitlines()[0] == "vm110 fuzz: sending to 10.99.8.7:5825 only (--target 10.99.8.7:5825)"
    broadcast = inside("--target", "10.99.8.255:5825", "--listen", "10.99.8.1:5827", "--allow-remote")
    assert broadcast.returncode == 2 and "broadcast address" in one_line(broadcast.stderr)


def test_a_unicast_listen_port_in_use_is_refused():
    """The fuzzer bound its --listen port with SO_REUSEADDR, so a second process on it (another
    fuzz run, a simulator) shared the port silently and took the controller's packets: 'no VRPO
    from the controller', one possible cause of a CI run's failure), or findings judged on half
    the traffic."""
    [port] = free_ports(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind(("127.0.0.1", port))
        with pytest.raises(CliError, match=f"cannot listen on 127.0.0.1:{port}: Address already in use"):
            Link(("127.0.0.1", 5825), ("127.0.0.1", port))


# --- replay: the finding is data ---------------------------------------------------------------------
def a_finding(**changes: Any) -> dict[str, Any]:
    packet = mutate.build(C.PacketType.VRCI, 5, mutate.default_fields(C.PacketType.VRCI, 7))
    finding = findings.Finding(
        oracle="missing_ack", seed=1, case_index=3, family="sweep-vrci", mutation="a VRCI", detail="no VRAO",
        packet_hex=packet.hex(), original_hex=packet.hex(), valid_hex=packet.hex(), differences=0, minimised=True,
        steps=[{"hex": packet.hex(), "valid_hex": packet.hex(), "delay_ms": 0.0, "expect_ack": True}],
        stream=dict(mutate.ARMED_VRPI), target="127.0.0.1:5825", listen="127.0.0.1:5827")
    return {**json.loads(json.dumps(asdict(finding))), **changes}


def save(tmp_path: Path, finding: dict[str, Any], name: str = "finding.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(finding))
    return path


def test_a_target_port_another_process_receives_on_is_refused_before_the_controller_starts(capsys, tmp_path):
    """Trial: a controller left running by a fuzz run that was killed (SIGKILL) kept the target
    port; the next run's controller could not bind it and exited, and the run fuzzed the one left
    running, which it had not started and could not watch: '0 findings', no crash."""
    rx, listen = free_ports(2)
    marker = tmp_path / "started"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as left_running:
        left_running.bind(("127.0.0.1", rx))
        code, err = fuzz_in_process(capsys, "--target", f"127.0.0.1:{rx}", "--listen", f"127.0.0.1:{listen}",
                                    "--target-cmd", f"touch {marker}", "--cases", "1", "--out", str(tmp_path / "out"))
    line = one_line(err)
    assert code == 2 and f"another process already receives on 127.0.0.1:{rx}" in line, line
    assert not marker.exists()


@pytest.mark.parametrize("listen", ["127.0.0.1", "0.0.0.0"])
def test_a_listen_address_that_is_the_target_is_refused(capsys, nothing_leaves, tmp_path, listen):
    """Trial: --listen on the target's own port had the fuzzer receive what it sent; with
    --target-cmd the run blamed 'another process ... left running by an earlier run', itself."""
    rx = free_ports(1)[0]
    marker = tmp_path / "started"
    code, err = fuzz_in_process(capsys, "--target", f"127.0.0.1:{rx}", "--listen", f"{listen}:{rx}",
                                "--target-cmd", f"touch {marker}", "--cases", "1", "--out", str(tmp_path / "out"))
    line = one_line(err)
    assert code == 2 and f"--listen {listen}:{rx} is the --target" in line, line
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_replay_never_runs_the_stored_command(tmp_path):
    marker = tmp_path / "stored-command-ran"
    rx, listen = free_ports(2)
    path = save(tmp_path, a_finding(target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}",
                                    target_cmd=f"touch {marker}"))
    result = vm110("fuzz", "--replay", str(path), "--startup", "0.5")
    assert not marker.exists(), "the command stored in the finding ran"
    assert result.returncode == 2 and "no VRPO" in result.stderr
    assert "not running the command stored in" in result.stderr and "touch" in result.stderr


def test_replay_runs_only_the_command_line_command(tmp_path):
    stored, given = tmp_path / "stored-ran", tmp_path / "given-ran"
    rx, listen = free_ports(2)
    path = save(tmp_path, a_finding(target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}",
                                    target_cmd=f"touch {stored}"))
    result = vm110("fuzz", "--replay", str(path), "--startup", "0.5", "--target-cmd", f"touch {given}")
    assert given.exists() and not stored.exists()
    assert result.returncode == 2 and "not running the command" not in result.stderr


def test_replay_shows_the_controllers_output_and_writes_nothing_beside_the_finding(tmp_path):
    """Trial: --replay appended to a target.log beside the finding, through a symbolic link there,
    and a FIFO there made it refuse to run."""
    rx, listen = free_ports(2)
    elsewhere = tmp_path / "not-ours.txt"
    elsewhere.write_text("someone's file\n")
    for name, make in (("link", lambda p: p.symlink_to(elsewhere)), ("fifo", os.mkfifo)):
        folder = tmp_path / name
        folder.mkdir()
        make(folder / "target.log")
        path = save(folder, a_finding(target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}"))
        result = vm110("fuzz", "--replay", str(path), "--startup", "0.5", "--target-cmd", "echo controller says hi")
        assert result.returncode == 2 and "exited with code 0 before sending any VRPO" in result.stderr
        assert "controller says hi" in result.stderr, "its output is on the terminal"
        assert sorted(p.name for p in folder.iterdir()) == ["finding.json", "target.log"]
    assert elsewhere.read_text() == "someone's file\n"


def test_replay_joins_no_group_the_file_names(capsys, monkeypatch, tmp_path):
    """Trial: a finding file's `group` was joined on the host's interfaces (an IGMP report out of
    eth0) with no option saying so."""
    rx, listen = free_ports(2)
    path = save(tmp_path, a_finding(target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}", group=C.MULTICAST_GROUP))
    joined = []
    monkeypatch.setattr(Link, "send", lambda self, data: 0.0)
    real = Link.__init__

    def init(self, target: Any, listen: Any, group: Any = None, *args: Any, **kwargs: Any) -> None:
        joined.append(group)
        real(self, target, listen, group, *args, **kwargs)
    monkeypatch.setattr(Link, "__init__", init)
    code, err = fuzz_in_process(capsys, "--replay", str(path), "--startup", "0.3")
    assert code == 2 and "no VRPO" in err and joined and not any(joined)
    assert f"not joining the multicast group stored in {path}" in err


@pytest.mark.parametrize("target, allow, refusal", [
    ("192.0.2.7:5825", False, "not a loopback address"),
    (f"{C.MULTICAST_GROUP}:5825", False, "multicast group"),
    ("255.255.255.255:5825", True, "broadcast address"),
    ("0.0.0.0:5825", True, "unspecified address"),
    ("127.255.255.255:5825", True, "broadcast address"),
    ("crane.example:5825", True, "not an IP address"),     # a file never makes us look a name up
])
def test_replay_stored_target_obeys_the_target_rules(capsys, nothing_leaves, tmp_path, target, allow, refusal):
    path = save(tmp_path, a_finding(target=target, target_cmd="touch never"))
    code, err = fuzz_in_process(capsys, "--replay", str(path), *(["--allow-remote"] if allow else []))
    line = one_line(err)
    assert code == 2 and refusal in line and f"the target stored in {path}" in line, line


def test_replay_target_on_the_command_line_overrides_the_stored_one(capsys, monkeypatch, tmp_path):
    rx, listen = free_ports(2)
    path = save(tmp_path, a_finding(target="192.0.2.7:5825", listen=f"127.0.0.1:{listen}"))
    sent_to = set()
    monkeypatch.setattr(Link, "send", lambda self, data: sent_to.add(self.target) or 0.0)
    code, err = fuzz_in_process(capsys, "--replay", str(path), "--target", f"127.0.0.1:{rx}", "--startup", "0.3")
    assert code == 2 and "no VRPO" in err and sent_to == {("127.0.0.1", rx)}


@pytest.mark.parametrize("target", [[], ["--target", "127.0.0.1:5825"]])
def test_replay_stored_listen_is_an_address_and_named_as_the_file_s(capsys, monkeypatch, tmp_path, target):
    """Trial: with --target on the command line, a name stored as the finding's listen address was
    looked up (a DNS query a file decided), and either way a bad one was blamed on '--listen',
    which the command line did not have."""
    lookups: list[str] = []
    real_getaddrinfo = socket.getaddrinfo

    def getaddrinfo(host, *args, **kwargs):
        if not (args[4] if len(args) > 4 else kwargs.get("flags", 0)) & socket.AI_NUMERICHOST:
            lookups.append(host)       # a name looked up
            if host == "crane.example":
                raise socket.gaierror("no lookups in tests")
        return real_getaddrinfo(host, *args, **kwargs)
    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    for listen, refusal in (("crane.example:5827", "not an IP address"), ("127.0.0.1:0", "must be HOST:PORT")):
        path = save(tmp_path, a_finding(listen=listen))
        code, err = fuzz_in_process(capsys, "--replay", str(path), *target)
        line = one_line(err)
        assert code == 2 and refusal in line and f"the listen address stored in {path}" in line, line
    assert "crane.example" not in lookups


HOSTILE: dict[str, Any] = {
    "missing packet_hex": lambda f: f.pop("packet_hex"),
    "missing steps": lambda f: f.pop("steps"),
    "steps not a list": lambda f: f.update(steps={"hex": "00"}),
    "step not an object": lambda f: f.update(steps=[7]),
    "step without hex": lambda f: f["steps"][0].pop("hex"),
    "hex not hex": lambda f: f["steps"][0].update(hex="zz"),
    "hex a number": lambda f: f.update(packet_hex=12),
    "huge packet": lambda f: f.update(packet_hex="00" * 70000),
    "too many steps": lambda f: f.update(steps=f["steps"] * 1000),
    "delay NaN": lambda f: f["steps"][0].update(delay_ms=math.nan),
    "delay inf": lambda f: f["steps"][0].update(delay_ms=math.inf),
    "delay huge": lambda f: f["steps"][0].update(delay_ms=1e308),
    "delay negative": lambda f: f["steps"][0].update(delay_ms=-5),
    "delay a string": lambda f: f["steps"][0].update(delay_ms="5"),
    "expect_ack a number": lambda f: f["steps"][0].update(expect_ack=1),
    "pause NaN": lambda f: f.update(pause_vrpi_ms=math.nan),
    "withhold -inf": lambda f: f.update(withhold_vrai_ms=-math.inf),
    "settle a list": lambda f: f.update(settle_ms=[1]),
    "settle true": lambda f: f.update(settle_ms=True),
    "seed huge": lambda f: f.update(seed=10**30),
    "seed a float": lambda f: f.update(seed=1.5),
    "oracle unknown": lambda f: f.update(oracle="rm -rf"),
    "mutation a dict": lambda f: f.update(mutation={"a": 1}),
    "target a number": lambda f: f.update(target=5825),
    "target_cmd a list": lambda f: f.update(target_cmd=["sh"]),
    "group a number": lambda f: f.update(group=3),
    "stream a list": lambda f: f.update(stream=[1]),
    "stream unknown field": lambda f: f["stream"].update(spare=1),
    "stream value too big": lambda f: f["stream"].update(joystick1=10**30),
    "stream value a string": lambda f: f["stream"].update(joystick1="1"),
    "schema 99": lambda f: f.update(schema=99),
    "a list": lambda f: f.clear(),
}


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_finding_files_are_one_line_errors(capsys, nothing_leaves, tmp_path, name):
    finding = a_finding()
    HOSTILE[name](finding)
    path = tmp_path / "finding.json"
    path.write_text(json.dumps([] if name == "a list" else finding))
    code, err = fuzz_in_process(capsys, "--replay", str(path))
    line = one_line(err)
    assert code == 2 and str(path) in line and "finding" in line, line


@pytest.mark.parametrize("text", ["{", "", "NaN", '{"oracle": "crash", "steps": [], "seed": ' + "9" * 5000 + "}",
                                  "\xff\xfe", "[" * 100_000 + "]" * 100_000])    # (the last: a RecursionError)
def test_unreadable_finding_files_are_one_line_errors(capsys, nothing_leaves, tmp_path, text):
    path = tmp_path / "finding.json"
    path.write_bytes(text.encode("latin-1"))
    code, err = fuzz_in_process(capsys, "--replay", str(path))
    assert code == 2 and str(path) in one_line(err)


def test_a_file_of_bytes_that_are_no_text_is_said_plainly(capsys, nothing_leaves, tmp_path):
    """Trial: a file beginning with zero bytes was "'utf-32-be' codec can't decode bytes in position
    4-7: code point not in range(0x110000)", the words of Python's codec (json takes zero bytes for
    UTF-32)."""
    path = tmp_path / "finding.json"
    path.write_bytes(b'\x00\x00{"oracle": 1, \xff}')
    code, err = fuzz_in_process(capsys, "--replay", str(path))
    assert code == 2 and one_line(err).endswith(f"{path} is not JSON: not text (UTF-8, UTF-16 or UTF-32) at byte 4")


def test_a_number_of_too_many_digits_is_said_plainly(capsys, nothing_leaves, tmp_path):
    """Trial: the line ended "...use sys.set_int_max_str_digits() t", cut mid-word, Python's internals."""
    path = tmp_path / "finding.json"
    path.write_text('{"oracle": "crash", "steps": [], "seed": ' + "9" * 5000 + "}")
    code, err = fuzz_in_process(capsys, "--replay", str(path))
    assert code == 2 and one_line(err) == f"vm110 fuzz: {path} is not JSON: a number of 5000 digits (at most 4300)"


def test_a_device_as_a_finding_or_dictionary_is_one_line_errors(capsys, nothing_leaves, tmp_path):
    """Trial: --replay /dev/zero and --dict /dev/zero read until the kernel killed the process (a
    device has no size to check first): at most the limit is read."""
    code, err = fuzz_in_process(capsys, "--replay", "/dev/zero")
    assert code == 2 and "/dev/zero is not a vm110 fuzz finding or corpus case: larger than 16 MiB" in one_line(err)
    from vm110.fuzz.corpus import load_dictionary
    with pytest.raises(CliError, match="--dict /dev/zero: larger than 1 MiB"):
        load_dictionary("/dev/zero")


@pytest.fixture
def within_5_s():
    """Fail, not hang, when the test blocks."""
    def expired(signum, frame):
        pytest.fail("blocked for 5 s")        # (not an OSError, which the code may catch)
    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(5)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def test_a_fifo_as_a_finding_or_a_corpus_case_does_not_block(capsys, nothing_leaves, tmp_path, within_5_s):
    """Trial: a FIFO named id-000901.json in the --corpus folder held the run at '0 cases' until it
    was killed (its open() waited for a writer), and --replay of one never returned."""
    os.mkfifo(tmp_path / "finding.json")
    code, err = fuzz_in_process(capsys, "--replay", str(tmp_path / "finding.json"))
    assert code == 2 and "is not JSON" in one_line(err)
    from vm110.fuzz.corpus import CorpusDir
    os.mkfifo(tmp_path / "id-000901.json")
    (tmp_path / "id-000902.json").mkdir()
    store = CorpusDir(tmp_path)
    assert store.load() == [] and store.skipped[0].startswith("id-000901.json: ")
    # Named, not a file descriptor; and said in full, not cut at 100 characters with a long path.
    assert store.skipped[1] == "id-000902.json: Is a directory"


MS_RANGE = "is out of range: must be a number of milliseconds from 0 to 60000"
OUT_OF_RANGE: dict[str, Any] = {
    "settle 1e300": (lambda f: f.update(settle_ms=1e300), f"settle_ms {MS_RANGE}"),
    "settle -5": (lambda f: f.update(settle_ms=-5), f"settle_ms {MS_RANGE}"),
    "delay 1e300": (lambda f: f["steps"][0].update(delay_ms=1e300), f"steps[0].delay_ms {MS_RANGE}"),
    "pause NaN": (lambda f: f.update(pause_vrpi_ms=math.nan), "pause_vrpi_ms is not a finite number"),
    "withhold -inf": (lambda f: f.update(withhold_vrai_ms=-math.inf), "withhold_vrai_ms is not a finite number"),
    "time inf": (lambda f: f.update(time=math.inf), "time is not a finite number"),
    "time 1e300": (lambda f: f.update(time=1e300), "time is out of range: must be from 0 to 9223372036854775807"),
    "seed 10**30": (lambda f: f.update(seed=10**30), "seed is out of range: must be from 0 to 18446744073709551615"),
    "case_index -1": (lambda f: f.update(case_index=-1), "case_index is out of range: must be from 0 to"),
    "differences 10**6": (lambda f: f.update(differences=10**6), "differences is out of range: must be from 0 to 65507"),
    "schema 10**30": (lambda f: f.update(schema=10**30), "schema of 31 digits (this version"),
}


@pytest.mark.parametrize("name", sorted(OUT_OF_RANGE))
def test_out_of_range_numbers_in_a_finding_give_the_range(capsys, nothing_leaves, tmp_path, name):
    """1e300 was "not a finite number below 2**63" (it is finite); NaN and infinities say so."""
    change, message = OUT_OF_RANGE[name]
    finding = a_finding()
    change(finding)
    code, err = fuzz_in_process(capsys, "--replay", str(save(tmp_path, finding)))
    line = one_line(err)
    assert code == 2 and f"is not a valid vm110 fuzz finding: {message}" in line, line


def test_a_finding_without_steps_is_refused_unless_no_case_caused_it(capsys, nothing_leaves, tmp_path):
    """Trial: `"steps": []` replayed nothing and said "does not trigger any more", exit 0, of a
    controller that still crashed (a CI gate would have passed)."""
    code, err = fuzz_in_process(capsys, "--replay", str(save(tmp_path, a_finding(steps=[], stream=None))))
    assert code == 2 and "is not a valid vm110 fuzz finding: steps is empty" in one_line(err)
    spontaneous = a_finding(steps=[], family="none", mutation="none: the base unit's normal VRAI", stream=None)
    gap = a_finding(steps=[], family="sequence", mutation="VRPI gap of 2100 ms", pause_vrpi_ms=2100.0, stream=None)
    for finding in (spontaneous, gap):
        path = save(tmp_path, finding)
        assert findings.finding_from_json(json.loads(path.read_text()), str(path)).steps == []


def test_a_crash_finding_is_replayed_only_with_target_cmd(capsys, nothing_leaves, tmp_path):
    """Without --target-cmd no exit can be seen: a crash replayed that way always 'did not trigger'."""
    path = save(tmp_path, a_finding(oracle="crash"))
    code, err = fuzz_in_process(capsys, "--replay", str(path))
    assert code == 2 and f"{path} is a crash finding: give --target-cmd" in one_line(err)


def test_every_seed_the_option_takes_is_a_valid_finding(tmp_path):
    """A run with --seed 2**64-1 wrote a finding its replay refused (numbers stopped below 2**63)."""
    path = save(tmp_path, a_finding(seed=2**64 - 1))
    assert findings.finding_from_json(json.loads(path.read_text()), str(path)).seed == 2**64 - 1


def test_a_hostile_finding_file_through_the_command(tmp_path):
    path = save(tmp_path, a_finding(pause_vrpi_ms=math.nan, mutation="\x1b[2J"))
    result = vm110("fuzz", "--replay", str(path))
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


# --- number options ---------------------------------------------------------------------------------
@pytest.mark.parametrize("option, value", [
    ("--rate", "nan"), ("--rate", "inf"), ("--rate", "-inf"), ("--rate", "0"), ("--rate", "-1"), ("--rate", "1e18"),
    ("--duration", "nan"), ("--duration", "inf"), ("--duration", "0"), ("--duration", "-1"),
    ("--cases", "0"), ("--cases", "-1"), ("--cases", "1.5"), ("--cases", "1e18"),
    ("--max-findings", "0"), ("--max-findings", "nan"), ("--minimize-budget", "nan"), ("--minimize-budget", "-1"),
    ("--startup", "nan"), ("--startup", "inf"), ("--startup", "0"), ("--seed", "-1"), ("--seed", "nan"),
    ("--target-memory", "nan"), ("--target-memory", "inf"), ("--target-memory", "0"), ("--target-memory", "1e9"),
    ("--memory-growth", "nan"), ("--memory-growth", "-1"), ("--memory-growth", "0.5"),
])
def test_bad_numbers_are_refused(capsys, nothing_leaves, option, value):
    with pytest.raises(SystemExit) as info:
        cli.main(["fuzz", "--target", "127.0.0.1:5825", f"{option}={value}"])   # = : "-inf" is not an option
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert info.value.code == 2 and "Traceback" not in err
    assert f"argument {option}:" in last and repr(value) in last and "must be" in last, last


def test_a_memory_limit_needs_a_controller_the_fuzzer_starts(tmp_path, capsys, nothing_leaves):
    code, err = fuzz_in_process(capsys, "--target", "127.0.0.1:5825", "--target-memory", "64", "--out",
                                str(tmp_path / "out"))
    assert code == 2 and "--target-memory needs --target-cmd" in one_line(err)
    assert not (tmp_path / "out").exists()


def test_rate_nan_ends_at_once():
    """It ran forever before: the rate limit waited for NaN seconds."""
    result = vm110("fuzz", "--target", "127.0.0.1:9", "--rate", "nan", "--cases", "1", timeout=20)
    assert result.returncode == 2 and "--rate" in result.stderr.strip().splitlines()[-1]


def test_every_number_option_shows_its_range():
    parser = cli.build_parser()
    fuzz = next(a for a in parser._subparsers._group_actions[0].choices.items() if a[0] == "fuzz")[1]
    numeric = [a for a in fuzz._actions if a.type is not None]
    assert {o for a in numeric for o in a.option_strings} >= {"--rate", "--duration", "--cases", "--seed",
                                                               "--max-findings", "--minimize-budget", "--startup"}
    for action in numeric:
        assert action.type.range_text in action.help, action.option_strings


# --- the fuzzer's files -----------------------------------------------------------------------------
def test_a_fifo_for_the_summary_is_refused_before_the_run(capsys, nothing_leaves, tmp_path):
    """It blocked for ever before: the summary was written into the FIFO at the end of the run."""
    os.mkfifo(tmp_path / "findings.json")
    code, err = fuzz_in_process(capsys, "--target", "127.0.0.1:5825", "--cases", "1", "--out", str(tmp_path))
    assert code == 2 and "previous run's files (findings.json)" in one_line(err)
    assert stat.S_ISFIFO((tmp_path / "findings.json").lstat().st_mode)


def test_a_directory_for_the_target_log_is_refused(capsys, nothing_leaves, tmp_path):
    (tmp_path / "target.log").mkdir()
    code, err = fuzz_in_process(capsys, "--target", "127.0.0.1:5825", "--cases", "1", "--out", str(tmp_path),
                                "--target-cmd", "true")
    assert code == 2 and "target.log" in one_line(err)


@pytest.mark.parametrize("option", ["--out", "--corpus"])
def test_a_file_where_a_folder_goes_is_not_a_directory(capsys, nothing_leaves, tmp_path, option):
    """It said "cannot create afile: File exists"."""
    afile = tmp_path / "afile"
    afile.write_text("mine")
    args = ["--target", "127.0.0.1:5825", "--cases", "1", option, str(afile)]
    if option == "--corpus":
        args += ["--coverage", "--target-cmd", "true", "--out", str(tmp_path / "out")]
    code, err = fuzz_in_process(capsys, *args)
    assert code == 2 and one_line(err) == f"vm110 fuzz: {option} {afile} is not a directory"
    assert afile.read_text() == "mine"


def test_a_previous_run_s_out_is_refused_and_left_as_it_was(capsys, nothing_leaves, tmp_path):
    """Trial: a second run into the same --out overwrote finding-001-* of the first and left its
    finding-002/003 beside a findings.json that did not list them."""
    old = {"findings.json": "{}", "finding-001-crash.json": "first", "finding-002-stall.pcap": "second",
           "id-000000.json": "a corpus case", "notes.txt": "mine"}
    for name, text in old.items():
        (tmp_path / name).write_text(text)
    code, err = fuzz_in_process(capsys, "--target", "127.0.0.1:5825", "--cases", "1", "--out", str(tmp_path))
    line = one_line(err)
    assert code == 2 and f"--out {tmp_path} holds a previous run's files (finding-001-crash.json and 2 more)" in line
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == old


def test_a_corpus_or_other_files_leave_out_usable(tmp_path):
    (tmp_path / "id-000000.json").write_text("a corpus case")
    (tmp_path / "target.log").write_text("a run that could not start")
    findings.check_out(tmp_path)
    findings.check_out(tmp_path / "new")


def test_a_run_that_never_started_leaves_no_summary(capsys, monkeypatch, tmp_path):
    """Else a retry after 'no VRPO' (the controller not up yet) would find --out used."""
    monkeypatch.setattr(Link, "send", lambda self, data: 0.0)
    _, listen = free_ports(2)
    for _ in range(2):
        code, err = fuzz_in_process(capsys, "--target", "127.0.0.1:9", "--listen", f"127.0.0.1:{listen}",
                                    "--startup", "0.2", "--cases", "1", "--out", str(tmp_path))
        assert code == 2 and "no VRPO" in one_line(err)
    assert not (tmp_path / "findings.json").exists()


@pytest.mark.parametrize("bad", ["--dict", "--corpus", "--target-cmd"])
def test_a_bad_option_leaves_no_files(capsys, nothing_leaves, tmp_path, bad):
    """Trial: a bad --dict or --corpus, or a --target-cmd program that is not there, created --out
    and an empty target.log before exit 2 (README: a bad option ends before any work starts)."""
    (tmp_path / "bad.dict").write_text("not a dictionary line\n")
    (tmp_path / "afile").write_text("mine")
    values = {"--dict": str(tmp_path / "bad.dict"), "--corpus": str(tmp_path / "afile"),
              "--target-cmd": str(tmp_path / "missing-controller")}
    args = ["--target", "127.0.0.1:5825", "--cases", "1", "--out", str(tmp_path / "out"), "--coverage",
            "--target-cmd", "true", bad, values[bad]]
    code, err = fuzz_in_process(capsys, *args)
    assert code == 2 and bad in one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "bad.dict"]


def test_a_finding_names_the_frames_of_its_evidence_in_its_pcap(tmp_path):
    """Trial: a finding's pcap held 4 s of traffic, some 130 frames, and neither the finding nor its
    line said which frame was the case's packet or the controller's packet judged (found by hand,
    by serial, with tshark -X lua_script:dissector/vm110.lua)."""
    ctl, bu = ("127.0.0.1", 40000), ("127.0.0.1", 5827)
    case = bytes.fromhex(a_finding()["original_hex"])
    vrpo = encode.packet("VRPO", encode.vrpo_payload(0, b"x"), serial=1)
    vrao = encode.packet("VRAO", encode.ack_payload(9), serial=2)
    traffic = [(1.0, False, vrpo, ctl), (1.1, True, case, ("127.0.0.1", 5825)), (1.2, False, vrao, ctl)]
    finding = findings.Finding(**{**a_finding(oracle="malformed_output", output_hex=vrao.hex()), "pcap": ""})
    findings.write_finding(tmp_path, 1, finding, traffic, bu)
    saved = json.loads((tmp_path / "finding-001-malformed_output.json").read_text())
    assert (saved["frame"], saved["output_frame"]) == (2, 3)
    assert saved["display_filter"] == "frame.number in {2..3}"
    assert _shown_by_tshark(tmp_path / saved["pcap"], saved["display_filter"]) == [2, 3]
    with PcapReader(str(tmp_path / saved["pcap"])) as reader:
        frames = [bytes(frame[UDP].payload) for frame in reader]
    assert frames[saved["frame"] - 1] == case and frames[saved["output_frame"] - 1] == vrao
    alone = findings.Finding(**{**a_finding(), "pcap": ""})          # no output judged, case not in the window
    findings.write_finding(tmp_path, 2, alone, traffic[:1], bu)
    saved = json.loads((tmp_path / "finding-002-missing_ack.json").read_text())
    assert saved["frame"] is None and saved["output_frame"] is None and saved["display_filter"] is None


def test_a_finding_of_several_packets_names_each_of_their_frames(tmp_path):
    """Trial (tests/targets BUG_DEEP under --coverage): the finding kept VRCI "MAINT:" and VRCI
    "ENGAGE", both needed, and its display filter named the second alone."""
    bu = ("127.0.0.1", 5827)
    maint, engage = (encode.packet("VRCI", encode.command_payload(n, text), origin=0x0101, serial=n)
                     for n, text in ((7, b"MAINT:"), (8, b"ENGAGE")))
    vrpi = encode.packet("VRPI", bytes(46), origin=0x0101, serial=9)
    traffic = [(1.0, True, maint, ("127.0.0.1", 5825)), (1.1, True, vrpi, ("127.0.0.1", 5825)),
               (1.2, True, engage, ("127.0.0.1", 5825))]
    steps = [{"hex": p.hex(), "valid_hex": p.hex(), "delay_ms": 0.0, "expect_ack": True} for p in (maint, engage)]
    finding = findings.Finding(**{**a_finding(oracle="crash"), "steps": steps, "original_hex": engage.hex(),
                                  "packet_hex": engage.hex(), "pcap": ""})
    findings.write_finding(tmp_path, 1, finding, traffic, bu)
    saved = json.loads((tmp_path / "finding-001-crash.json").read_text())
    assert saved["frame"] == 3 and saved["display_filter"] == "frame.number in {1, 3}"
    assert _shown_by_tshark(tmp_path / saved["pcap"], saved["display_filter"]) == [1, 3]


def _shown_by_tshark(pcap: Path, display_filter: str) -> list[int]:
    """The frames Wireshark (the host's tshark) shows under a finding's display filter."""
    if shutil.which("tshark") is None:
        pytest.fail("tshark is not installed: run `make setup`")
    shown = subprocess.run(["tshark", "-n", "-r", str(pcap), "-Y", display_filter, "-T", "fields", "-e", "frame.number"],
                           capture_output=True, text=True, timeout=60, check=True)
    return [int(n) for n in shown.stdout.split()]


def test_a_failed_finding_write_keeps_the_previous_files(tmp_path):
    finding = findings.Finding(**{k: v for k, v in a_finding().items() if k != "pcap"})
    good = [(1.0, True, b"VRPI", ("127.0.0.1", 5825))]
    path = findings.write_finding(tmp_path, 1, finding, good, ("127.0.0.1", 5827))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    bad = good + [(2.0, True, b"VRPI", ("not an address", 5825))]
    with pytest.raises(ValueError):
        findings.write_finding(tmp_path, 1, finding, bad, ("127.0.0.1", 5827))
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert json.loads(path.read_text())["oracle"] == "missing_ack"
    (tmp_path / "findings.json").mkdir()
    with pytest.raises(CliError, match="not a regular file"):
        findings.write_summary(tmp_path, {"findings": []})


def test_progress_lines_carry_no_control_characters(capsys):
    """What the runner says quotes bytes it did not write (a sanitizer's frame names, a packet ID)."""
    fuzz_command._progress("finding x: crash in f\x1b[2J\x00 (c.c:1)")
    err = capsys.readouterr().err
    assert err == "vm110 fuzz: finding x: crash in f?[2J? (c.c:1)\n"


def test_a_finding_from_a_pipe_is_replayed(tmp_path):
    """`--replay <(...)`: the file was read twice (once to tell a corpus case from a finding, once
    to load it), and a pipe has nothing left the second time: 'is not a vm110 fuzz finding' (fuzz
    trial). It is read once; a corpus case through a pipe is told apart as well."""
    rx, listen = free_ports(2)
    finding = json.dumps(a_finding(target=f"127.0.0.1:{rx}", listen=f"127.0.0.1:{listen}"))
    entry = json.dumps({"vm110_corpus_entry": 1, "packets": [{"hex": "zz"}]})
    # (no controller runs: the finding gets as far as waiting for one)
    for text, said in ((finding, "no VRPO from the controller"), (entry, "not a valid vm110 corpus case")):
        done = subprocess.run(["bash", "-c", 'exec "$@" --replay <(printf %s "$0")', text, sys.executable, "-m",
                               "vm110", "fuzz", "--target", f"127.0.0.1:{rx}", "--startup", "1"],
                              capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert said in done.stdout + done.stderr and "not a vm110 fuzz finding" not in done.stderr, done.stderr


def test_a_finding_s_display_filter_shows_the_resends_of_its_command(tmp_path):
    """Review: the filter showed the case's VRCI but not the resends the base unit sent of it on
    later serials (every 100 ms until acknowledged), which are part of what the controller saw; a
    copy sent well after the resends stopped (a later case's) is not one of them."""
    bu, ctl, target = ("127.0.0.1", 5827), ("127.0.0.1", 40000), ("127.0.0.1", 5825)
    case = bytes.fromhex(a_finding()["original_hex"])
    again = [mutate.reserial(case, serial) for serial in (6, 8, 9)]
    vrpi = encode.packet("VRPI", bytes(46), origin=0x0101, serial=7)
    vrpo = encode.packet("VRPO", encode.vrpo_payload(0, b"x"), serial=1)
    traffic = [(1.0, True, case, target), (1.05, False, vrpo, ctl), (1.1, True, again[0], target),
               (1.15, True, vrpi, target), (1.2, True, again[1], target), (3.0, True, again[2], target)]
    finding = findings.Finding(**{**a_finding(), "resend_ms": 100.0, "pcap": ""})
    findings.write_finding(tmp_path, 1, finding, traffic, bu)
    saved = json.loads((tmp_path / "finding-001-missing_ack.json").read_text())
    assert saved["frame"] == 1 and saved["display_filter"] == "frame.number in {1, 3, 5}"
    assert _shown_by_tshark(tmp_path / saved["pcap"], saved["display_filter"]) == [1, 3, 5]
    unsent = findings.Finding(**{**a_finding(), "resend_ms": 0.0, "pcap": ""})    # --no-resend: none are
    findings.write_finding(tmp_path, 2, unsent, traffic, bu)
    assert json.loads((tmp_path / "finding-002-missing_ack.json").read_text())["display_filter"] == "frame.number == 1"
