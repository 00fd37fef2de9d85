"""What the simulators log: the watchdogs' last packet, and `vm110 simulate`'s stdout and stderr.

Watchdogs on the virtual clock (no sockets); the command line over loopback only (unicast from
127.0.0.1 to the discard port): nothing leaves the machine.
"""
from __future__ import annotations

import datetime
import json
import signal
import subprocess
import sys
import time

from loopback import LOOPBACK
from vm110 import constants as C
from vm110 import encode
from vm110.sim.bu import BaseUnit, BaseUnitConfig
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.lifecycle import Restart
from vm110.sim.remote import Remote
from vm110.sim.virtual import Station, VirtualNetwork

BU_STATION, CTL_STATION = ("10.0.0.10", C.INPUT_PORT), ("10.0.0.20", C.OUTPUT_PORT)


def run_virtual(seconds: float, bu: BaseUnit | None = None, ctl: Controller | None = None) -> list:
    """Run the nodes given (one alone: nobody answers) and return the tap's arrivals."""
    stations = ([Station(bu, *BU_STATION)] if bu else []) + ([Station(ctl, *CTL_STATION)] if ctl else [])
    return [a for batch in VirtualNetwork(stations).run(seconds) for a in batch]


def last_arrival(arrivals: list, ptype: C.PacketType) -> float:
    return max(a[0] for a in arrivals if a[5].ptype is ptype) / 1e6


def test_controller_alone_has_no_last_vrpi():
    ctl = Controller()
    run_virtual(1.0, ctl=ctl)
    [timeout] = ctl.events("vrpi_timeout")
    assert timeout["t"] == 0.5 and timeout["last_vrpi"] is None       # no VRPI ever: none, not start-up


def test_controller_logs_the_vrpi_it_really_heard_last():
    bu = BaseUnit(Remote.simple(armed=True), BaseUnitConfig(stop_at_s=1.0))
    ctl = Controller()
    arrivals = run_virtual(2.0, bu, ctl)
    [timeout] = ctl.events("vrpi_timeout")
    assert timeout["last_vrpi"] == last_arrival(arrivals, C.PacketType.VRPI)
    assert timeout["t"] == timeout["last_vrpi"] + 0.5


def test_controller_restored_gap_is_from_the_vrpi_before_it():
    bu = BaseUnit(Remote.simple(armed=True), BaseUnitConfig(stalls=((1.0, 2.0),)))
    ctl = Controller()
    arrivals = run_virtual(3.0, bu, ctl)
    [timeout], [restored] = ctl.events("vrpi_timeout"), ctl.events("vrpi_restored")
    vrpi = sorted(a[0] / 1e6 for a in arrivals if a[5].ptype is C.PacketType.VRPI)
    before = max(t for t in vrpi if t < 1.0)
    assert timeout["last_vrpi"] == before
    assert restored["gap_ms"] == round((restored["t"] - before) * 1000, 6)


def test_bu_alone_has_no_last_vrpo():
    bu = BaseUnit(Remote.simple(armed=True))
    run_virtual(3.0, bu=bu)
    [trip] = bu.events("vrpo_watchdog")
    assert trip["t"] == 2.0 and trip["last_vrpo"] is None and trip["es_relays_open"]


def test_bu_logs_the_vrpo_it_really_heard_last():
    bu = BaseUnit(Remote.simple(armed=True))
    ctl = Controller(ControllerConfig(stop_at_s=1.0))
    arrivals = run_virtual(4.0, bu, ctl)
    [trip] = bu.events("vrpo_watchdog")
    assert trip["last_vrpo"] == last_arrival(arrivals, C.PacketType.VRPO)
    assert trip["t"] == trip["last_vrpo"] + 2.0


def test_after_a_restart_the_old_packets_are_forgotten():
    bu = BaseUnit(Remote.simple(armed=True), BaseUnitConfig(stop_at_s=0.5))
    ctl = Controller(ControllerConfig(restarts=(Restart(1.0, 0.5),)))
    run_virtual(3.0, bu, ctl)
    timeouts = ctl.events("vrpi_timeout")
    assert [t["last_vrpi"] is None for t in timeouts] == [False, True]     # before and after the restart


# --- the command line ---------------------------------------------------------------------------------

def simulate(role: str, *extra: str) -> subprocess.CompletedProcess:
    """`vm110 simulate ROLE` on loopback, sending to the discard port (nobody answers)."""
    run = [sys.executable, "-m", "vm110", "simulate", role, "--listen", f"{LOOPBACK}:0",
           "--peer", f"{LOOPBACK}:9", "--source", f"{LOOPBACK}:0", *extra]
    return subprocess.run(run, capture_output=True, text=True, timeout=60, check=True)


def utc(stamp: str) -> datetime.datetime:
    return datetime.datetime.strptime(stamp, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=datetime.timezone.utc)


def assert_sockets_line(stderr: str, role: str, before: datetime.datetime) -> None:
    """The sockets line goes to stderr, with the UTC time in front like every log line."""
    [line] = [line for line in stderr.splitlines() if "receiving on" in line]
    stamp, rest = line.split(" ", 1)
    assert before <= utc(stamp) <= datetime.datetime.now(datetime.timezone.utc)
    assert rest.startswith(f"{role}: receiving on {LOOPBACK}:") and f"to {LOOPBACK}:9" in rest


def test_json_stdout_is_json_lines_only():
    before = datetime.datetime.now(datetime.timezone.utc)
    done = simulate("controller", "--duration", "0.8", "--json")
    entries = [json.loads(line) for line in done.stdout.splitlines()]     # every line, the first too
    assert "summary" in entries[-1] and utc(entries[-1]["time_utc"]) >= before
    [timeout] = [e for e in entries if e.get("event") == "vrpi_timeout"]
    assert timeout["last_vrpi"] is None                                   # the JSON null
    assert_sockets_line(done.stderr, "controller", before)


def test_text_log_lines_all_start_with_utc():
    before = datetime.datetime.now(datetime.timezone.utc)
    done = simulate("bu", "--duration", "0.8", "--command-every", "0.3")
    lines = done.stdout.splitlines()
    end = json.loads(lines[-1])                                           # the summary line at the end
    assert end["summary"] and utc(end["time_utc"]) >= before
    assert len(lines) >= 3 and all(utc(line.split()[0]) >= before for line in lines[:-1]), lines
    assert_sockets_line(done.stderr, "bu", before)


def test_events_logged_after_a_stall_keep_the_time_they_happened():
    """A stall's start is logged when the node runs again, and a restart after its silence: their
    `time_utc` said when they were printed (stall_start and stall_end 0.3 ms apart, 2 s in `t`).
    Now every line's `time_utc` is the start's plus `t`; a restart to port 0 names the port taken."""
    done = simulate("bu", "--duration", "2.2", "--json", "--stall", "0.3:1.3", "--restart", "1.5:0",
                    "--restart-silence", "0.4")
    entries = [json.loads(line) for line in done.stdout.splitlines()]
    events = [e for e in entries if "event" in e]
    assert {"stall_start", "stall_end", "down", "restart"} <= {e["event"] for e in events}
    starts = [utc(e["time_utc"]).timestamp() - e["t"] for e in events]
    assert max(starts) - min(starts) < 0.002
    [restart] = [e for e in events if e["event"] == "restart"]
    assert 0 < restart["port"] <= 65535


def test_a_stall_a_restart_and_a_stop_are_logged_when_they_begin():
    """They were logged only once the node ran again: a run that ended within a stall or a
    restart's silence had neither in its log, nor a stop with nobody sending to the node (its
    `stopped` came with the first packet it ignored)."""
    for options, expected in ((["--stop-at", "0.3"], [("stopped", 0.3)]),
                              (["--stall", "0.3:5"], [("stall_start", 0.3)]),
                              (["--restart", "0.3", "--restart-silence", "5"], [("down", 0.3)])):
        done = simulate("bu", "--duration", "0.8", "--json", *options)
        events = [json.loads(line) for line in done.stdout.splitlines()]
        assert [(e["event"], e["t"]) for e in events if e.get("event") not in (None, "sent")] == expected, options


def test_a_restart_logs_the_port_it_sends_from():
    """`--restart AT` (same port) logged `restart serial=0 port=None` (JSON `"port": null`). Now
    the port it sends from, as the sockets line on stderr gives it, and `port_from` only when a
    new port was taken."""
    for extra in ((), ("--json",)):
        same = simulate("bu", "--duration", "0.8", "--restart", "0.2", "--restart-silence", "0.2", *extra)
        moved = simulate("bu", "--duration", "0.8", "--restart", "0.2:0", "--restart-silence", "0.2", *extra)
        for done, new in ((same, False), (moved, True)):
            sending = int(done.stderr.split("sending from ")[1].split(" ")[0].rsplit(":", 1)[1])
            [line] = [line for line in done.stdout.splitlines() if " restart " in line or '"restart"' in line]
            if extra:
                entry = json.loads(line)
                port, port_from = entry["port"], entry.get("port_from")
            else:
                fields = dict(f.split("=") for f in line.split(" restart ")[1].split())
                port, port_from = int(fields["port"]), fields.get("port_from") and int(fields["port_from"])
            assert (port == sending, port_from) == (not new, sending if new else None), line
            assert 0 < port <= 65535 and "None" not in line and "null" not in line


def test_a_log_that_cannot_be_written_ends_with_one_line():
    """Before: a log to a full disk (here /dev/full) ended in two tracebacks, exit 1. Now: one line
    naming standard output, exit 2, for text and JSON logs and the summary alone (--quiet)."""
    for extra in ((), ("--json",), ("--quiet",)):
        run = [sys.executable, "-m", "vm110", "simulate", "bu", "--listen", f"{LOOPBACK}:0",
               "--peer", f"{LOOPBACK}:9", "--source", f"{LOOPBACK}:0", "--duration", "0.5",
               "--command-every", "0.2", *extra]
        with open("/dev/full", "w") as full:
            done = subprocess.run(run, stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert done.stderr.splitlines()[-1] == "vm110 simulate: cannot write standard output: No space left on device"


def test_command_data_cannot_forge_log_lines_or_reach_the_terminal():
    """Command data comes off the network: a VRCI with "GO\\nFAKE LINE\\x1b[2J" printed a log line of
    its own and cleared the controller's terminal (and a VRCO's data the base unit's). Now control
    characters are escaped in the text log; the JSON log (json.dumps) kept them escaped already."""
    lines: list[str] = []
    data = "GO\nFAKE LINE\x1b[2J"
    remote = Remote.from_script({"steps": [{"at": 0, "state": "armed"}], "commands": [{"at": 0.3, "data": data}]})
    bu = BaseUnit(remote, printer=lambda now, line: lines.append(line))
    ctl = Controller(ControllerConfig(commands=((0.5, data.encode()),)), printer=lambda now, line: lines.append(line))
    run_virtual(1.0, bu, ctl)
    shown = [line for line in lines if "data=" in line]
    assert len(shown) == 2 and all(line.endswith(r"data=GO\nFAKE LINE\x1b[2J") for line in shown), shown
    assert not any(c in line for line in lines for c in "\n\x1b")


def test_sigterm_sighup_and_ctrl_c_end_a_run_as_interrupted():
    """A supervisor must tell an interrupted run from a clean end. SIGTERM ended `simulate` with
    exit 0, as `--duration` does, and SIGHUP (its terminal closed) killed it without its summary;
    now each is an interruption like Ctrl-C: the summary still comes last on standard output, one
    line on stderr names the signal, and the exit code is the README's "130 interrupted"."""
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        run = [sys.executable, "-m", "vm110", "simulate", "bu", "--listen", f"{LOOPBACK}:0",
               "--peer", f"{LOOPBACK}:9", "--source", f"{LOOPBACK}:0", "--command-every", "0.2"]
        with subprocess.Popen(run, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
            assert proc.stderr is not None
            assert "receiving on" in proc.stderr.readline()         # the loop is about to run
            time.sleep(0.5)
            proc.send_signal(sig)
            stdout, stderr = proc.communicate(timeout=30)
        assert proc.returncode == 130, (sig, proc.returncode, stderr)
        assert "Traceback" not in stderr and f"bu: stopped by {sig.name}" in stderr
        end = json.loads(stdout.splitlines()[-1])
        assert end["end"] == sig.name and end["summary"]["sent"]["VRPI"] >= 2


def test_a_run_ended_by_a_failure_says_so_in_its_summary():
    """A restart onto a port another program holds ended the run at the restart, exit 2, with a
    summary saying `"end": "duration"`, as if it had run its course. Now `"error"`, and the one
    line on stderr says that the restart failed."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind((LOOPBACK, 0))
        port = taken.getsockname()[1]
        run = [sys.executable, "-m", "vm110", "simulate", "bu", "--listen", f"{LOOPBACK}:0", "--peer",
               f"{LOOPBACK}:9", "--source", f"{LOOPBACK}:0", "--restart", f"0.2:{port}", "--restart-silence", "0.1",
               "--duration", "5", "--quiet"]
        done = subprocess.run(run, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and json.loads(done.stdout.splitlines()[-1])["end"] == "error"
    assert done.stderr.splitlines()[-1] == (f"vm110 simulate: cannot send from {LOOPBACK}:{port} after the restart: "
                                            "Address already in use"), done.stderr


def test_a_run_that_reaches_its_duration_ends_with_exit_0():
    done = simulate("controller", "--duration", "0.3")
    assert done.returncode == 0 and "stopped by" not in done.stderr
    assert json.loads(done.stdout.splitlines()[-1])["end"] == "duration"


def test_the_first_illegal_packet_of_each_reason_is_logged():
    """Two ends given different --crc ignore each other's every packet (bad CRC); the log showed
    only a watchdog, the reason only in the final summary. Now the first of each reason is logged,
    with its source; the rest are counted."""
    from vm110 import encode

    ctl = Controller(crc="bzip2")
    ctl.attach(lambda data, now, meta: None)
    ctl.start(0)
    for serial in range(5):
        ctl.receive(encode.packet(C.PacketType.VRPI, bytes(46), origin=0x0101, serial=serial), serial * 125_000,
                    ("10.0.0.10", C.INPUT_PORT))
    ctl.receive(b"VRXX" + bytes(16), 700_000, ("10.0.0.10", C.INPUT_PORT))
    assert [(e["reasons"], e["src"]) for e in ctl.events("illegal_first")] == [
        ("bad_crc", f"10.0.0.10:{C.INPUT_PORT}"), ("unknown_id", f"10.0.0.10:{C.INPUT_PORT}")]
    assert ctl.illegal["bad_crc"] == 6 and not ctl.received


def test_a_peer_the_kernel_will_not_send_to_ends_the_run_in_one_line():
    """A broadcast --peer (here loopback's, 127.255.255.255: nothing leaves the machine) is refused
    by the kernel at the first send (EACCES). Before: a Python traceback, exit 1. Now the summary
    says `"end": "error"` and one line names the address, exit 2."""
    run = [sys.executable, "-m", "vm110", "simulate", "controller", "--listen", f"{LOOPBACK}:0", "--peer",
           "127.255.255.255:9", "--source", f"{LOOPBACK}:0", "--duration", "5", "--quiet"]
    done = subprocess.run(run, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and json.loads(done.stdout.splitlines()[-1])["end"] == "error"
    assert done.stderr.splitlines()[-1] == "vm110 simulate: cannot send to 127.255.255.255:9: Permission denied", \
        done.stderr


def test_the_first_illegal_packet_is_named_by_its_packet_id_and_serial():
    """A controller whose VRAO alone has a wrong CRC: the BU logged `illegal_first reasons=bad_crc
    src=...` and nothing said which packet. Now its packet ID and serial, as its header gives them
    (none for a datagram too short to hold one); the printed line escapes an ID that is not text."""
    from vm110 import encode

    lines: list[str] = []
    bu = BaseUnit(printer=lambda now, line: lines.append(line))
    bu.attach(lambda data, now, meta: None)
    bu.start(0)
    src = ("10.0.0.20", C.OUTPUT_PORT)
    bu.receive(encode.packet(C.PacketType.VRPO, encode.vrpo_payload(0, b"x"), serial=7), 0, src)
    vrao = bytearray(encode.packet(C.PacketType.VRAO, encode.ack_payload(3), serial=8))
    vrao[-1] ^= 0xFF
    bu.receive(bytes(vrao), 1000, src)
    bu.receive(b"VR\nX" + bytes(16), 2000, src)
    bu.receive(b"VRP", 3000, src)
    assert [(e["reasons"], e.get("packet"), e.get("serial")) for e in bu.events("illegal_first")] == [
        ("bad_crc", "VRAO", 8), ("unknown_id", "VR\nX", 0), ("truncated", None, None)]
    assert lines[1].endswith("illegal_first reasons=unknown_id src=10.0.0.20:5827 packet=VR\\nX serial=0")


def test_a_simulate_run_keeps_no_log_in_memory_yet_prints_and_counts_it_all():
    """`vm110 simulate` runs until interrupted, for days: each node kept every log entry it printed
    (some 400 bytes each; a command a second on both ends, 5 a second: about 170 MB a day, 5 GB in
    the 30 days a run may last). The nodes the command builds now keep none; what they print and
    their summary are as before. (On the virtual clock: 30 s, a command every 0.2 s each way.)"""
    from vm110 import cli
    from vm110.commands.simulate import build_node

    printed: dict[str, list[str]] = {"bu": [], "controller": []}
    nodes = {}
    for role in printed:
        args = cli.build_parser().parse_command(["simulate", role, "--command-every", "0.2"])
        nodes[role] = build_node(args, lambda now, line, role=role: printed[role].append(line))
    run_virtual(30.0, nodes["bu"], nodes["controller"])
    bu, ctl = nodes["bu"], nodes["controller"]
    assert bu.log == [] and ctl.log == []

    def lines(role: str, kind: str) -> int:
        return sum(f" {role} {kind} " in f"{line} " for line in printed[role])
    assert lines("bu", "command_sent") >= 140 and lines("controller", "vrco_sent") >= 140
    assert bu.summary()["commands_acked"] == lines("bu", "command_acked") >= 140
    assert ctl.summary()["executed"] == lines("controller", "executed") == lines("bu", "command_acked")
    assert ctl.summary()["commands_acked"] == lines("controller", "vrco_acked") >= 140


def test_controller_watches_each_bu_on_its_own():
    """Two BUs on the group (origins 0x0101, 0x0202); the second stops at 1 s. Trial: the first
    one's VRPI kept the controller's one watchdog fed, and the BU gone silent was never flagged
    (TS-0006 5.1.1). Now each BU has its own, named in the log."""
    live = BaseUnit(Remote.simple(armed=True))
    gone = BaseUnit(Remote.simple(armed=True), BaseUnitConfig(origin=0x0202, stop_at_s=1.0), name="bu2")
    ctl = Controller()
    stations = [Station(live, *BU_STATION), Station(gone, "10.0.0.11", C.INPUT_PORT), Station(ctl, *CTL_STATION)]
    arrivals = [a for batch in VirtualNetwork(stations).run(2.0) for a in batch]
    last = max(a[0] for a in arrivals if a[5].ptype is C.PacketType.VRPI and a[5].sender == "bu2") / 1e6
    [timeout] = ctl.events("vrpi_timeout")
    assert (timeout["origin"], timeout["last_vrpi"], timeout["t"]) == ("0x0202", last, last + 0.5)


def test_the_summary_accounts_for_every_command_sent():
    """The BU's operator commands, from the wire: the controller answers until it stops at 1.3 s,
    the BU restarts at 4.0 s (down 0.3 s), the run ends at 6.5 s. Trial: the summary said
    "commands_acked 0, commands_failed 0" for a BU with four commands sent and unanswered."""
    end, down = 6.5, 4.0
    bu = BaseUnit(Remote.simple(armed=True, command_every=0.6),
                  BaseUnitConfig(restarts=(Restart(down, 0.3),)))
    ctl = Controller(ControllerConfig(stop_at_s=1.3))
    arrivals = run_virtual(end, bu, ctl)
    first: dict = {}                 # (life, command ID) -> first transmission (s)
    for a in arrivals:
        if a[5].ptype is C.PacketType.VRCI:
            first.setdefault((a[0] / 1e6 >= down, a[5].key), a[0] / 1e6)
    acked = {a[5].key for a in arrivals if a[5].ptype is C.PacketType.VRAO}
    open_ = {k: t for k, t in first.items() if k[1] not in acked or k[0]}
    limit = C.VRCI_FAIL_MS / 1000                 # TS-0006 5.1.3: failed 2000 ms after the first
    summary = bu.summary()
    assert summary["commands_sent"] == len(first) and summary["commands_acked"] == len(acked) == 2
    assert summary["commands_failed"] == sum(not life and t + limit <= down for (life, _), t in open_.items()) >= 1
    assert summary["commands_dropped"] == sum(not life and t + limit > down for (life, _), t in open_.items()) >= 1
    assert summary["commands_in_flight"] == sum(life and t + limit > end for (life, _), t in open_.items()) >= 1
    assert (summary["commands_acked"] + summary["commands_failed"] + summary["commands_dropped"]
            + summary["commands_in_flight"]) == summary["commands_sent"]


def test_a_bad_crc_right_under_another_reading_names_it():
    """TS-0006 3.3 reads as several CRC-32s (interpretation.md): a PLC of another reading had every
    packet logged `bad_crc`, and its engineer had to try the eight --crc/--crc-order pairs. The
    first one now says which one validates it. The CRCs here are zlib's (iso-hdlc), not vm110's."""
    import struct
    import zlib

    bu = BaseUnit()
    bu.attach(lambda data, now, meta: None)
    bu.start(0)
    src = ("10.0.0.20", C.OUTPUT_PORT)
    body = b"VRPO" + struct.pack("<HHHHI", 0, 0, 7, 3, 0) + b"\0\0x"
    bu.receive(body + zlib.crc32(body).to_bytes(4, "big"), 0, src)        # iso-hdlc, stored big-endian
    [named] = bu.events("illegal_first")
    assert (named["reasons"], named["valid_crc"]) == ("bad_crc", "iso-hdlc/big")
    other = BaseUnit()
    other.attach(lambda data, now, meta: None)
    other.start(0)
    other.receive(body + (zlib.crc32(body) ^ 0x5A).to_bytes(4, "big"), 0, src)   # right under none
    [unnamed] = other.events("illegal_first")
    assert unnamed["reasons"] == "bad_crc" and "valid_crc" not in unnamed


class SplittingController(Controller):
    """Sends 1200 bytes of periodic data a cycle, 3 VRPO packets numbered from `first_packet_number`,
    but for two cycles: packet 1 left out in cycle 3 (a burst with a gap), the numbers 0, 2, 3 in
    cycle 6 (a bad sequence)."""

    def vrpo_payloads(self, now):
        payloads = super().vrpo_payloads(now)
        first = self.config.first_packet_number
        if self.cycle == 3:
            return payloads[:1] + payloads[2:]
        if self.cycle == 6:
            return [encode.vrpo_payload(first + n, p[2:]) for n, p in zip((0, 2, 3), payloads)]
        return payloads


def test_the_bu_logs_and_counts_incomplete_vrpo_bursts():
    """Sim trial: the BU took every VRPO packet alone; a burst with a packet missing or numbered
    out of sequence (interpretation.md, "VRPO split into several packets") went unnoticed. Now
    each is logged `vrpo_incomplete` with when it began and the numbers it had, and counted, also
    with the controller numbering from 1 (the BU given the same --vrpo-start)."""
    for start in (0, 1):
        bu = BaseUnit(config=BaseUnitConfig(vrpo_start=start))
        ctl = SplittingController(ControllerConfig(data_size=1200, first_packet_number=start))
        run_virtual(1.0, bu, ctl)
        assert ctl.sent["VRPO"] == 10 * 3 - 1
        cycle_s = ctl.config.period_ms / 1000
        got = [(round(e["at"] / cycle_s, 3), e["packets"], e["numbers"], e["data"]) for e in bu.events("vrpo_incomplete")]
        assert got == [(3.0, 2, f"{start},{start + 2}", 488 + 224),
                       (6.0, 3, f"{start},{start + 2},{start + 3}", 1200)], start
        assert bu.summary()["vrpo_incomplete"] == 2 and not ctl.events("vrpi_timeout")


def test_the_controller_says_two_bus_of_one_origin_apart_by_source():
    """Sim trial: two BUs of origin 0x0101 on two machines were one BU to the controller, their
    serials interleaved, and nothing was said. Now their VRPI alternating between two sources is
    logged `origin_shared` once, naming both; a BU restarted on a new port is no such pair."""
    ctl = Controller(ControllerConfig())
    stations = [Station(BaseUnit(), "10.0.0.10", C.INPUT_PORT), Station(BaseUnit(name="bu2"), "10.0.0.11", C.INPUT_PORT),
                Station(ctl, *CTL_STATION)]
    list(VirtualNetwork(stations).run(1.0))
    shared = ctl.events("origin_shared")
    assert [(e["origin"], {e["src"], e["other"]}) for e in shared] == [
        ("0x0101", {f"10.0.0.10:{C.INPUT_PORT}", f"10.0.0.11:{C.INPUT_PORT}"})]
    assert ctl.summary()["origin_shared"] == 1
    restarted = BaseUnit(config=BaseUnitConfig(restarts=(Restart(0.5, 0.1, 0, 0, 6000),)))
    ctl = Controller(ControllerConfig())
    run_virtual(1.5, restarted, ctl)
    assert ctl.bus[restarted.origin].src == (BU_STATION[0], 6000) and not ctl.events("origin_shared")
