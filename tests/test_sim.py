"""The simulated base unit and the reference controller over real UDP sockets on loopback.

Loopback unicast only (127.0.0.1, ephemeral ports): nothing leaves the machine. Each test runs a
few seconds of wall-clock time.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import re
import socket
import subprocess
import sys
from collections import Counter

import pytest

from loopback import LOOPBACK, free_ports
from vm110 import cli
from vm110 import constants as C
from vm110.decode import decode
from vm110.errors import CliError
from vm110.sim.bu import BaseUnit, BaseUnitConfig
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.impair import Impairer, Impairment
from vm110.sim.lifecycle import Restart
from vm110.sim.realtime import RealtimeRunner
from vm110.sim.remote import Remote
from vm110.sim.transport import UdpConfig, UdpTransport
from vm110.sim.virtual import Station, VirtualNetwork


class RecordingBU(BaseUnit):
    """Keeps what it sends, to look at its VRPI, and where what it receives comes from."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.wire = []
        self.heard = []

    def transmit(self, data, now, meta):
        self.wire.append((now, data))
        super().transmit(data, now, meta)

    def receive(self, data, now, src=None):
        self.heard.append((now, src, data))
        super().receive(data, now, src)


def run_pair(bu: BaseUnit, ctl: Controller, seconds: float, bu_imp: Impairment = None,
             ctl_imp: Impairment = None) -> None:
    def transport(imp, name):
        cfg = UdpConfig(listen=(LOOPBACK, 0), dest=(LOOPBACK, 0), source=(LOOPBACK, 0))
        return UdpTransport(cfg, Impairer(imp, name) if imp else None).open()
    tb, tc = transport(bu_imp, "bu"), transport(ctl_imp, "controller")
    tb.set_dest(tc.rx_address)
    tc.set_dest(tb.rx_address)
    RealtimeRunner([(bu, tb), (ctl, tc)]).run(seconds)


def ids(node, event):
    return [e["command_id"] for e in node.events(event)]


def test_commands_are_acknowledged_and_executed_once_despite_loss():
    bu = BaseUnit(Remote.simple(armed=True, command_every=0.25, command_until=2.0))
    ctl = Controller(ControllerConfig(command_every_s=0.4, command_until_s=2.0))
    run_pair(bu, ctl, 3.5,
             bu_imp=Impairment(loss=30.0, only=("VRCI", "VRAI"), seed=3),
             ctl_imp=Impairment(loss=30.0, only=("VRAO",), seed=4))
    sent, acked = ids(bu, "command_sent"), ids(bu, "command_acked")
    assert len(sent) >= 6 and sorted(acked) == sent             # every operator command acknowledged
    executed = ids(ctl, "executed")
    assert sorted(executed) == sorted(set(executed)) == sorted(sent)   # each executed exactly once
    repeats = ids(ctl, "repeat")
    assert repeats, "30 % loss should have caused retransmissions"
    # Every VRCI that reached the controller, first or repeated, got its own VRAO (sent, or dropped by the loss).
    assert ctl.received["VRCI"] == ctl.sent["VRAO"] + ctl.impaired_dropped["VRAO"] == len(executed) + len(repeats)
    assert bu.sent["VRCI"] > len(sent)                          # the BU did resend
    # The controller's own commands: resent until the VRAI, each delivered to the RU once.
    vrco = ids(ctl, "vrco_sent")
    assert len(vrco) >= 4 and sorted(ids(ctl, "vrco_acked")) == vrco
    # The summary says so, as the base unit's does (it had no command outcomes).
    assert (ctl.summary()["commands_acked"], ctl.summary()["commands_gave_up"]) == (len(vrco), 0)
    assert (bu.summary()["commands_acked"], bu.summary()["commands_failed"]) == (len(sent), 0)
    delivered = ids(bu, "vrco_delivered")
    assert sorted(delivered) == vrco
    assert bu.sent["VRAI"] + bu.impaired_dropped["VRAI"] == bu.received["VRCO"] >= len(vrco)
    assert ctl.illegal_packets == bu.illegal_packets == 0


def test_both_watchdogs_react_when_the_other_side_stops():
    bu = RecordingBU(Remote.simple(armed=True), BaseUnitConfig(stalls=((0.2, 0.9),)))
    ctl = Controller(ControllerConfig(stalls=((1.0, 3.4),)))
    run_pair(bu, ctl, 3.8)
    # BU silent for 0.7 s: the controller flags the VRPI timeout 500 ms after the last VRPI.
    timeouts, restored = ctl.events("vrpi_timeout"), ctl.events("vrpi_restored")
    assert len(timeouts) == 1 and len(restored) == 1
    assert 0.6 <= timeouts[0]["t"] <= 0.95 and restored[0]["t"] >= 0.9
    # Controller hung 2.4 s: the BU's VRPO watchdog trips 2000 ms after the last VRPO and the VRPI
    # shows EG-Link "No link" and an open ES-Link ("External link error") until VRPO is back.
    trips, back = bu.events("vrpo_watchdog"), bu.events("vrpo_restored")
    assert len(trips) == 1 and len(back) == 1
    assert 2.85 <= trips[0]["t"] <= 3.3 and trips[0]["es_relays_open"]
    states = [(now / 1e6, decode(data)) for now, data in bu.wire if data[:4] == b"VRPI"]
    tripped = [f for t, f in states if trips[0]["t"] < t < back[0]["t"]]
    assert tripped and all(f["bu_state"] == C.BuState.EXTERNAL_LINK_ERROR and f["es_relays_open"]
                           and f["eg_link"] == C.LinkStatus.NO_LINK for f in tripped)
    assert all(f["bu_state"] == C.BuState.ARMED for t, f in states if t < trips[0]["t"] or t > back[0]["t"] + 0.2)


def test_a_remote_disarmed_after_being_armed_sends_no_ru_data():
    # Spec 4.1, Armed RU: "When 0, all the following fields are set to 0" (the RU's state, battery
    # and RSSI of the armed step stayed, warned as disarmed_ru_data by decode and the dissector).
    bu = RecordingBU(Remote.from_script({"steps": [{"at": 0, "state": "armed", "battery": 90, "rssi": 80},
                                                  {"at": 0.5, "state": "disarmed", "unarmed_rus": 2}]}))
    run_pair(bu, Controller(), 1.0)
    states = [(now / 1e6, decode(data)) for now, data in bu.wire if data[:4] == b"VRPI"]
    armed = [f for t, f in states if t < 0.45]
    disarmed = [f for t, f in states if t > 0.55]
    assert armed and all(f["armed_ru"] and f["ru_battery"] for f in armed)
    assert disarmed and all(f["armed_ru"] == 0 and not f["warnings"] for f in disarmed), disarmed[0]
    assert all((f["ru_state"], f["ru_battery"], f["ru_rssi"]) == (0, 0, 0) for f in disarmed)


def test_illegal_packets_are_ignored_and_counted():
    reasons = ("bad_crc", "revision", "unknown_id", "size_mismatch", "size_too_large", "truncated",
               "revision+bad_crc")
    bu_mangles = tuple((0.1 + 0.2 * i, r, "VRPI") for i, r in enumerate(reasons)) + ((1.0, "truncated", "VRCI"),)
    ctl_mangles = tuple((0.15 + 0.2 * i, r, "VRPO") for i, r in enumerate(reasons))
    bu = BaseUnit(Remote.from_script({"steps": [{"at": 0, "state": "armed"}],
                                      "commands": [{"at": 1.05, "data": "GO"}]}))
    ctl = Controller()
    run_pair(bu, ctl, 2.0, bu_imp=Impairment(mangles=bu_mangles, seed=1),
             ctl_imp=Impairment(mangles=ctl_mangles, seed=1))
    expected = Counter(r for _, rs, _ in bu_mangles for r in rs.split("+"))
    assert ctl.illegal == expected and ctl.illegal_packets == len(bu_mangles)
    assert bu.illegal == Counter(r for _, rs, _ in ctl_mangles for r in rs.split("+"))
    # The truncated VRCI was not acknowledged: the BU had to send the command again.
    acked = bu.events("command_acked")
    assert len(acked) == 1 and acked[0]["transmissions"] == 2
    assert ids(ctl, "executed") == [acked[0]["command_id"]] and ctl.sent["VRAO"] == 1
    assert not ctl.events("vrpi_timeout") and not bu.events("vrpo_watchdog")


def test_cli_simulators_talk_over_loopback():
    ctl_rx, bu_rx = free_ports(2)
    common = ["--source", f"{LOOPBACK}:0", "--json"]
    vm110 = [sys.executable, "-m", "vm110", "simulate"]
    # The controller outlives the BU (however long the BU's start takes): the BU hears it all its 2.5 s.
    with subprocess.Popen(vm110 + ["controller", "--listen", f"{LOOPBACK}:{ctl_rx}", "--peer", f"{LOOPBACK}:{bu_rx}",
                                   "--command-every", "0.5", "--duration", "6", *common], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as ctl:
        assert "receiving on" in ctl.stderr.readline()      # listening before the BU speaks
        bu = subprocess.run(vm110 + ["bu", "--listen", f"{LOOPBACK}:{bu_rx}", "--peer", f"{LOOPBACK}:{ctl_rx}",
                                     "--command-every", "0.3", "--loss", "10", "--seed", "5", "--duration", "2.5",
                                     *common],
                            capture_output=True, text=True, timeout=20)
        ctl_out, _ = ctl.communicate(timeout=20)
    assert bu.returncode == 0 and ctl.returncode == 0, bu.stderr
    bu_log = [json.loads(line) for line in bu.stdout.splitlines() if line.startswith("{")]
    ctl_log = [json.loads(line) for line in ctl_out.splitlines() if line.startswith("{")]
    bu_sum, ctl_sum = bu_log[-1]["summary"], ctl_log[-1]["summary"]
    assert bu_sum["received"]["VRPO"] >= 15 and ctl_sum["received"]["VRPI"] >= 12
    executed = [e["command_id"] for e in ctl_log if e.get("event") == "executed"]
    # Refused: heard before a VRPI with an armed RU got through (the BU drops 10 %); acknowledged all the same.
    handled = executed + [e["command_id"] for e in ctl_log if e.get("event") == "refused"]
    assert executed and len(handled) == len(set(handled))
    assert {e["command_id"] for e in bu_log if e.get("event") == "command_acked"} <= set(handled)
    assert ctl_sum["sent"]["VRAO"] == ctl_sum["received"]["VRCI"]


def test_cli_usage_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    bad_script = tmp_path / "remote.json"
    bad_script.write_text('{"steps": [{"at": 0, "state": "flying"}]}')
    good_script = tmp_path / "good.json"
    good_script.write_text('{"steps": [{"at": 0, "state": "armed"}]}')
    for args in (["bu", "--peer", "not-an-address"],
                 ["controller", "--listen", "127.0.0.1:99999"],
                 ["bu", "--stall", "5:3"],
                 ["controller", "--port", "65535"],
                 ["bu", "--duration", "0"],
                 ["bu", "--script", str(tmp_path / "missing.json")],
                 ["bu", "--restart", "soon"],
                 ["controller", "--restart", "3:70000"],
                 ["controller", "--restart", "3", "--restart-silence", "0", "--duration", "1"],
                 # (the restart's options without a restart: taken without a word, and nothing restarted)
                 ["controller", "--restart-silence", "3", "--duration", "1", "--listen", f"{LOOPBACK}:0", "--peer",
                  f"{LOOPBACK}:9"],
                 ["bu", "--restart-serial", "40000", "--duration", "1", "--listen", f"{LOOPBACK}:0", "--peer",
                  f"{LOOPBACK}:9"],
                 ["bu", "--script", str(bad_script), "--listen", f"{LOOPBACK}:0", "--peer", f"{LOOPBACK}:9"],
                 # (a script and the flags it replaces: the flags were ignored without a word)
                 ["bu", "--script", str(good_script), "--no-motion", "--listen", f"{LOOPBACK}:0", "--peer",
                  f"{LOOPBACK}:9"],
                 ["bu", "--script", str(good_script), "--command-every", "1", "--listen", f"{LOOPBACK}:0"],
                 # (below the clock's 1 µs: 0, which means none (BU), or a command every tick (controller))
                 ["bu", "--command-every", "1e-9"],
                 ["controller", "--command-every", "0.0000005"]):
        try:                         # (in this process: refused before any socket is opened)
            code = cli.main(["simulate", *args])
        except SystemExit as exc:
            code = exc.code
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("vm110 simulate: ") and err.count("\n") == 1, (args, err)


def virtual_pair(bu: BaseUnit, ctl: Controller, seconds: float, bu_imp: Impairment = None,
                 ctl_imp: Impairment = None) -> list:
    stations = [Station(bu, "10.0.0.10", C.INPUT_PORT, bu_imp or Impairment()),
                Station(ctl, "10.0.0.20", C.OUTPUT_PORT, ctl_imp or Impairment())]
    return [a for batch in VirtualNetwork(stations).run(seconds) for a in batch]


def test_several_commands_in_flight_each_resent_acked_and_executed_once():
    # Two keys 50 ms apart, and a third ID reused after a pause; every VRAO lost until 0.45 s.
    script = {"steps": [{"at": 0, "state": "armed"}],
              "commands": [{"at": 0.1, "data": "A"}, {"at": 0.15, "data": "B"}, {"at": 3.0, "data": "C", "id": 0}]}
    bu = BaseUnit(Remote.from_script(script))
    ctl = Controller(ControllerConfig(commands=((0.2, b"X"), (0.25, b"Y"))))
    arrivals = virtual_pair(bu, ctl, 4.0, ctl_imp=Impairment(drops=((0.0, 0.45, ("VRAO",)),)))
    assert ids(bu, "command_sent") == [0, 1, 0] and sorted(ids(bu, "command_acked")) == [0, 0, 1]
    vrci = [(a[0], a[5].key) for a in arrivals if a[5].ptype is C.PacketType.VRCI]
    first = [t for t, cid in vrci if cid == 0 and t < 1_000_000]
    assert len(first) == 5 and all(b - a == 100_000 for a, b in itertools.pairwise(first))   # resent on its own
    assert sorted(ids(ctl, "executed")) == [0, 0, 1]              # the reused ID is a new command
    assert len(ids(ctl, "repeat")) == ctl.received["VRCI"] - 3
    assert sorted(ids(ctl, "vrco_acked")) == [0, 1] and ids(bu, "vrco_delivered") == [0, 1]


def test_mirror_copies_reach_the_tap_only():
    bu, ctl = BaseUnit(Remote.simple(armed=True)), Controller()
    arrivals = virtual_pair(bu, ctl, 5.0, bu_imp=Impairment(mirror=50.0, seed=2))
    copies = [a for a in arrivals if not a[6]]
    assert 10 < len(copies) and all(a[2] == 0 for a in copies)
    originals = {(a[5].serial): a[0] for a in arrivals if a[6] and a[2] == 0}
    assert all(50 <= a[0] - originals[a[5].serial] <= 3000 for a in copies)      # 0.05-3 ms later
    assert ctl.received["VRPI"] == bu.sent["VRPI"]                                 # delivered once


def test_restart_and_stop_on_the_virtual_clock():
    bu = BaseUnit(Remote.simple(armed=True, command_every=0.5), BaseUnitConfig(stop_at_s=3.0),
                  serial_start=40000)
    ctl = Controller(ControllerConfig(restarts=(Restart(1.0, 0.5, serial=7, command_id=100),
                                                Restart(2.0, 0.3, port=50000)), command_every_s=0.4,
                                      commands=((0.93, b"LATE"),)))
    arrivals = virtual_pair(bu, ctl, 4.0, bu_imp=Impairment(drops=((0.9, 1.0, ("VRAI",)),)))
    mine = [(a[0], a[2], a[5]) for a in arrivals if a[5].sender == "controller"]
    assert not [t for t, _, _ in mine if 1_000_000 <= t < 1_500_000 or 2_000_000 <= t < 2_300_000]
    after = [m.serial for t, _, m in mine if t >= 1_500_000]
    assert after[0] == 7 and {e for t, e, _ in mine} == {1, 2}    # endpoint 2: the new port
    assert next(meta.serial for _, e, meta in mine if e == 2) == 0
    restarts = ctl.events("restart")
    assert [(e["t"], e["serial"], e["port"], e.get("port_from")) for e in restarts] == [
        (1.5, 7, C.OUTPUT_PORT, None), (2.3, 0, 50000, C.OUTPUT_PORT)]        # the port it sends from, and before
    assert [e["command_id"] for e in ctl.events("vrco_dropped")] == [2]     # the VRCO of 0.93 s
    assert ids(ctl, "vrco_sent")[3] == 100                        # IDs afresh from the restart's
    assert max(a[0] for a in arrivals if a[5].sender == "bu") < 3_000_000 and bu.events("stopped")
    assert next(a[5].serial for a in arrivals if a[5].sender == "bu") == 40000


def test_restart_on_a_new_port_over_sockets():
    bu = RecordingBU(Remote.simple(armed=True))
    ctl = Controller(ControllerConfig(restarts=(Restart(0.6, 0.3, port=0),)))
    run_pair(bu, ctl, 1.5)
    ports = [src[1] for _, src, data in bu.heard if data[:4] == b"VRPO"]
    switch = next(i for i, p in enumerate(ports) if p != ports[0])
    assert len(set(ports)) == 2 and set(ports[switch:]) == {ports[switch]}
    serials = [decode(data)["serial"] for _, _, data in bu.heard if data[:4] == b"VRPO"]
    assert serials[switch] == 0 and serials[switch - 1] > 0
    assert not bu.illegal_packets and len(ctl.events("restart")) == 1


def test_cli_restart_stop_and_mirror_options():
    ctl_rx, bu_rx = free_ports(2)
    vm110 = [sys.executable, "-m", "vm110", "simulate"]
    common = ["--source", f"{LOOPBACK}:0", "--duration", "2.0", "--json"]
    with subprocess.Popen(vm110 + ["controller", "--listen", f"{LOOPBACK}:{ctl_rx}", "--peer", f"{LOOPBACK}:{bu_rx}",
                                   "--restart", "0.5:0", "--restart-silence", "0.3", "--restart-serial", "9",
                                   "--mirror", "20", *common], stdout=subprocess.PIPE, text=True) as ctl:
        bu = subprocess.run(vm110 + ["bu", "--listen", f"{LOOPBACK}:{bu_rx}", "--peer", f"{LOOPBACK}:{ctl_rx}",
                                     "--stop-at", "1.2", "--serial-start", "40000", *common],
                            capture_output=True, text=True, timeout=20)
        ctl_out, _ = ctl.communicate(timeout=20)
    assert bu.returncode == 0 and ctl.returncode == 0, bu.stderr
    ctl_log = [json.loads(line) for line in ctl_out.splitlines() if line.startswith("{")]
    bu_log = [json.loads(line) for line in bu.stdout.splitlines() if line.startswith("{")]
    [(serial, port)] = [(e["serial"], e["port"]) for e in ctl_log if e.get("event") == "restart"]
    assert serial == 9 and 0 < port != ctl_rx          # 0 asked: the free port it took is logged
    assert [round(e["t"], 1) for e in bu_log if e.get("event") == "stopped"] == [1.2]
    assert ctl_log[-1]["summary"]["received"]["VRPI"] < 12           # nothing after 1.2 s
    assert bu_log[-1]["summary"]["received"]["VRPO"] > ctl_log[-1]["summary"]["sent"]["VRPO"] * 0.9 * 0.6 / 1.7


@pytest.mark.parametrize("script, message", [
    ({"command_every": -1}, "command_every is '-1': must be a number from 0 to"),     # sent 33,216 VRCI in 1.5 s
    ({"steps": [{"at": 0, "set": {"joystick1": 70000}}]}, "steps[0].set.joystick1 is '70000': must be an integer"),
    ({"steps": [{"at": 1e308}]}, "steps[0].at is '1e+308'"),
    ([1, 2], "the script must be a JSON object"),
    ({"commands": [{"at": 1, "id": 70000}]}, "commands[0].id is '70000'"),                # was sent as ID 4464
    ({"steps": [{"at": 0, "set": {"no_such_field": 1}}]}, "'no_such_field' is not a VRPI field"),
    ({"steps": [{"at": 0, "colour": "red"}]}, "steps[0] has unknown key 'colour'"),
    ({"steps": [{"at": float("nan")}]}, "steps[0].at is 'nan'"),
    ({"commands": [{"at": 1, "data": 5}]}, "commands[0].data must be a string"),
    ({"command_every": 1e-9}, "command_every is 1e-09: must be 0 (none) or at least 1e-06 s"),   # was none
    ({"steps": [{"at": 0}] * 100_001}, "steps has 100001 entries (at most 100000)"),
    # Keys of a state, given without it, were checked and then did nothing (a trial):
    ({"steps": [{"at": 5, "battery": 20}]}, ('steps[0].battery goes with "state": "armed" (to change only the field: '
                                             '"set": {"ru_battery": ...})')),
    ({"steps": [{"at": 0, "state": "disarmed", "ru": 5}]}, 'steps[0].ru goes with "state": "armed"'),
    ({"steps": [{"at": 7, "unarmed_rus": 3}]}, 'steps[0].unarmed_rus goes with "state": "armed" or "state": "disarmed"'),
    # Command data beyond the 16 bytes of the field, or characters of no byte (cut, sent as "?", silently):
    ({"commands": [{"at": 1, "data": "\u20ac 5"}]}, "commands[0].data '€ 5': at most 16 characters, each one byte"),
    ({"commands": [{"at": 1, "data": "A" * 17}]}, "at most 16 characters, each one byte (U+0000 to U+00FF)"),
])
def test_a_script_is_checked_before_anything_is_sent(tmp_path, script, message):
    path = tmp_path / "remote.json"
    path.write_text(json.dumps(script))
    with pytest.raises(CliError, match=re.escape(message)):
        Remote.load(str(path))


def test_a_restart_onto_the_port_it_receives_on_is_refused_before_the_run(capsys):
    """It failed at the restart ("Address already in use"), after running until then (a trial)."""
    code = cli.main(["simulate", "bu", "--listen", "127.0.0.10:15827", "--peer", "127.0.0.20:15825",
                     "--source", "127.0.0.10:15825", "--restart", "0.2:15827", "--duration", "1"])
    assert code == 2 and capsys.readouterr().err == (
        "vm110 simulate: --restart 0.2:15827: the node receives on port 15827 (127.0.0.10); it must send from "
        "another\n")


UNICAST = {"bu": ["--listen", "127.0.0.10:40007", "--peer", "127.0.0.20:5825"],
           "controller": ["--listen", "127.0.0.20:40007", "--peer", "127.0.0.10:5827"]}


@pytest.mark.parametrize("role, args, message", [
    ("bu", ["--source", "127.0.0.10:5827"], ("--source 127.0.0.10:5827: port 5827 is the controller's (--port 5825); "
                                             "a base unit sends from its own, 5825, or a port that is neither")),
    ("controller", ["--source", "127.0.0.20:5825"], ("--source 127.0.0.20:5825: port 5825 is the base unit's "
                                                     "(--port 5825); a controller sends from its own, 5827, or a port "
                                                     "that is neither")),
    ("bu", ["--port", "6000", "--source", "127.0.0.10:6002"], "port 6002 is the controller's (--port 6000)"),
    ("bu", ["--source", "127.0.0.10:0", "--restart", "0.5:5827"], "--restart 0.5:5827: port 5827 is the controller's"),
    ("controller", ["--restart", "0.5:5825"], "--restart 0.5:5825: port 5825 is the base unit's"),
    ("bu", ["--source", "127.0.0.10:40007"], ("--source 127.0.0.10:40007: the node receives on port 40007 "
                                             "(127.0.0.10); it must send from another")),
])
def test_a_node_cannot_send_from_the_other_sides_port_or_its_own_receiving_one(capsys, role, args, message):
    """Before: a BU given the controller's port (--source, --restart AT:NEW_PORT; by --port) sent
    its inputs from the output port, passing for the controller to a reader that goes by ports
    (TS-0006 2.2), and a --source on its own receiving port failed blaming "another program".
    Now each is refused before anything is sent, exit 2, naming the option and the ports."""
    code = cli.main(["simulate", role, *UNICAST[role], *args, "--duration", "0.1"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("vm110 simulate: ") and message in err and err.count("\n") == 1, err


def test_a_key_given_twice_is_refused(tmp_path):
    """The last one counted, silently (a trial: "steps" twice)."""
    path = tmp_path / "remote.json"
    path.write_text('{"steps": [{"at": 0, "state": "armed"}], "steps": []}')
    with pytest.raises(CliError, match="not JSON: the key 'steps' is given twice in one object"):
        Remote.load(str(path))


def test_arming_another_ru_starts_its_own_battery_and_a_set_level_stays():
    """Re-arming without `battery` kept draining the previous RU's battery (80 % on RU 4000, a
    trial); a level `set` is the field's value, not a level the old drain overrides."""
    remote = Remote.from_script({"steps": [{"at": 0, "state": "armed", "battery": 80},
                                           {"at": 600, "state": "armed", "ru": 4000, "unarmed_rus": 2},
                                           {"at": 1200, "set": {"ru_battery": 50}}]})
    at = {t: remote.fields(t * 1_000_000) for t in (0, 599, 601, 1199, 1201, 1800)}
    assert [at[t]["ru_battery"] for t in at] == [80, 71, 90, 90, 50, 50]      # 1 % a minute from 80
    assert (at[601]["armed_ru"], at[601]["unarmed_rus"]) == (4000, 2)        # unarmed_rus beside it was dropped


def test_a_unicast_address_is_one_simulators_alone():
    # Two on one address shared its packets (SO_REUSEADDR): a simulator left running took half.
    cfg = UdpConfig(listen=(LOOPBACK, free_ports(1)[0]), dest=(LOOPBACK, 9), source=(LOOPBACK, 0))
    with contextlib.closing(UdpTransport(cfg).open()), pytest.raises(CliError, match="Address already in use"):
        UdpTransport(cfg).open()


def test_windows_that_touch_do_not_spin():
    """A stall beginning where another ends (or a restart, a stop, one within another) spun the
    virtual clock at that instant for ever (and `vm110 simulate` at 100 % CPU): the VRPI due in
    the first window was looked up in it again and again. Run in a child with a timeout."""
    code = """if True:
        from vm110.sim.bu import BaseUnit, BaseUnitConfig
        from vm110.sim.lifecycle import Restart
        from vm110.sim.virtual import Station, VirtualNetwork
        for life in ({"stalls": ((1.0, 2.0), (2.0, 3.0))}, {"stalls": ((1.0, 3.0),), "restarts": (Restart(2.0, 1.5),)},
                     {"stalls": ((1.0, 3.0),), "stop_at_s": 2.0}):
            bu = BaseUnit(config=BaseUnitConfig(**life))
            sent = [a[0] for batch in VirtualNetwork([Station(bu, "10.0.0.10", 5825)]).run(5.0) for a in batch]
            print(next((t for t in sent if t > 0.9e6), None), len(sent))
    """
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    # back at 3 s; back from the restart at 3.5 s; stopped for good
    assert done.stdout.split() == ["3000000", "24", "3500000", "20", "None", "8"]


def test_a_port_in_use_is_named_with_the_socket_that_needs_it():
    """The source port in use was said as "cannot open UDP sockets (LISTEN -> PEER): Address already
    in use": it named the listening address, which was free (a trial). Both simulators on one
    address meet that way, so the message says how the README runs them."""
    listen, source = free_ports(2)
    cfg = UdpConfig(listen=(LOOPBACK, listen), dest=(LOOPBACK, 9), source=(LOOPBACK, source))
    hint = (" (held by another program; on one machine each simulator needs an address of its own, as in the "
            "README's \"Simulators and synthesis\": 127.0.0.10 and 127.0.0.20)")
    for taken, message in ((source, f"cannot send from {LOOPBACK}:{source} to {LOOPBACK}:9: Address already in use"),
                           (listen, f"cannot receive on {LOOPBACK}:{listen}: Address already in use")):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
            holder.bind((LOOPBACK, taken))
            with pytest.raises(CliError) as info:
                UdpTransport(cfg).open()
        assert str(info.value) == message + hint


def test_a_script_nested_too_deeply_is_one_line(tmp_path):
    path = tmp_path / "remote.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    done = subprocess.run([sys.executable, "-m", "vm110", "simulate", "bu", "--script", str(path), "--listen",
                           f"{LOOPBACK}:0", "--peer", f"{LOOPBACK}:9"], capture_output=True, text=True, timeout=20)
    assert done.returncode == 2 and "nested too deeply" in done.stderr and done.stderr.count("\n") == 1


def test_the_summary_says_sent_apart_from_what_the_impairment_dropped(capsys):
    """Sim trial: `sent` counted the packets --loss dropped on purpose, so the peer's received
    count fell short of it with no way to tell the network from the option. Now `sent` is what
    went on the wire (once each), `impaired_dropped` what the option dropped and `impaired_copies`
    its extra copies: checked against the datagrams a socket of the test received, and against
    the serials (one counter from 0: every packet made has one)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.bind((LOOPBACK, 0))
        peer.setblocking(False)
        code = cli.main(["simulate", "bu", "--listen", f"{LOOPBACK}:0", "--source", f"{LOOPBACK}:0",
                         "--peer", f"{LOOPBACK}:{peer.getsockname()[1]}", "--loss", "40", "--duplicate", "30",
                         "--seed", "3", "--command-every", "0.05", "--duration", "0.6", "--quiet"])
        wire = []
        with contextlib.suppress(BlockingIOError):
            while True:
                wire.append(peer.recv(65535))
    assert code == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])["summary"]
    on_wire = Counter(decode(d)["type"] for d in wire)
    copies, dropped = Counter(summary["impaired_copies"]), Counter(summary["impaired_dropped"])
    assert dropped["VRPI"] and dropped["VRCI"] and copies["VRPI"]
    assert Counter(summary["sent"]) + copies == on_wire and not summary["impaired_held"]
    serials = {decode(d)["serial"] for d in wire}
    assert len(serials) == sum(summary["sent"].values())          # each sent once, its copies beside
    # (the packets made are at least those up to the last serial on the wire: the last ones may be dropped)
    assert sum(summary["sent"].values()) + sum(dropped.values()) >= max(serials) + 1 > len(serials)


def _out_of_order(reorder: float, period_us: int = 125_000, count: int = 4000) -> float:
    """Share of a periodic stream that arrives after a packet sent after it, under `--reorder`."""
    impairer = Impairer(Impairment(reorder=reorder, seed=2), "bu")
    late, latest = 0, -1
    for i in range(count):
        arrival = impairer.apply(b"x", i * period_us, "VRPI")[0][0]
        late += arrival < latest
        latest = max(latest, arrival)
    return late / count


def test_reorder_is_refused_where_more_would_reorder_less(capsys):
    """Sim trial: `--reorder 100` (help: "PCT held back") held every packet back alike, a delay:
    about 1.5 % of VRPI came out of order, as few as with --reorder 2. Packets held back overtake
    each other less the more are held, so the option stops at 50, where reordering is greatest."""
    shares = [_out_of_order(p) for p in (2, 10, 25, 50)]
    assert shares == sorted(shares) and _out_of_order(100) < shares[1] < _out_of_order(60) < shares[-1]
    for value in ("51", "100"):
        with pytest.raises(SystemExit) as info:
            cli.main(["simulate", "bu", "--reorder", value, "--listen", f"{LOOPBACK}:0", "--peer", f"{LOOPBACK}:9",
                      "--duration", "0.1"])
        assert info.value.code == 2
        assert f"argument --reorder: '{value}' is out of range: must be 0 to 50 percent" in capsys.readouterr().err


def test_a_second_bu_of_one_origin_from_one_address_is_refused(capsys):
    """Sim trial: two `simulate bu` of one origin to one group shared its port and ran without a
    word; the controller took them for one BU whose serials interleaved. The second now ends before
    it starts (exit 2, one line saying why); another origin runs beside it, and the claim goes with
    the process that held it (killed: nothing left behind)."""
    peer, source = (f"{LOOPBACK}:{port}" for port in free_ports(2))
    bu = ["simulate", "bu", "--listen", f"{LOOPBACK}:0", "--source", source, "--peer", peer, "--quiet"]
    with subprocess.Popen([sys.executable, "-m", "vm110", *bu, "--duration", "30"], stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True) as first:
        assert "receiving on" in first.stderr.readline()
        assert cli.main([*bu, "--duration", "0.1"]) == 2
        out, err = capsys.readouterr()
        assert not out and err == (f"vm110 simulate: another simulated base unit on this machine already sends as "
                                   f"origin 0x0101 from {source} to {peer}: the controller cannot tell two BUs of one "
                                   "origin from one address apart (their serials interleave); give each its own "
                                   "--origin\n")
        assert cli.main([*bu, "--origin", "0x0102", "--duration", "0.1"]) == 0
        first.kill()
    assert cli.main([*bu, "--duration", "0.1"]) == 0


def test_copies_delayed_past_the_end_are_said_not_sent(capsys):
    """Sim trial: with --delay 500, a 1 s run's summary said 8 VRPI sent; 4 reached the peer, the
    rest still waiting out their delay when the run ended. Those are now `impaired_held`."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.bind((LOOPBACK, 0))
        peer.setblocking(False)
        code = cli.main(["simulate", "bu", "--listen", f"{LOOPBACK}:0", "--source", f"{LOOPBACK}:0",
                         "--peer", f"{LOOPBACK}:{peer.getsockname()[1]}", "--delay", "300", "--duration", "0.5",
                         "--quiet"])
        wire = []
        with contextlib.suppress(BlockingIOError):
            while True:
                wire.append(peer.recv(65535))
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])["summary"]
    assert code == 0 and wire and summary["impaired_held"]["VRPI"] >= 2
    assert summary["sent"]["VRPI"] - summary["impaired_held"]["VRPI"] == len(wire)
