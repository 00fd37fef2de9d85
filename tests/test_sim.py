"""The simulated base unit and the reference controller over real UDP sockets on loopback.

Loopback unicast only (127.0.0.1, ephemeral ports): nothing leaves the machine. Each test runs a
few seconds of wall-clock time.
"""
from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter

from loopback import LOOPBACK, free_ports
from vm110 import constants as C
from vm110.decode import decode
from vm110.sim.bu import BaseUnit, BaseUnitConfig
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.impair import Impairer, Impairment
from vm110.sim.realtime import RealtimeRunner
from vm110.sim.remote import Remote
from vm110.sim.transport import UdpConfig, UdpTransport


class RecordingBU(BaseUnit):
    """Keeps what it sends, to look at its VRPI."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.wire = []

    def transmit(self, data, now, meta):
        self.wire.append((now, data))
        super().transmit(data, now, meta)


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
    # Every VRCI that reached the controller, first or repeated, got its own VRAO.
    assert ctl.received["VRCI"] == ctl.sent["VRAO"] == len(executed) + len(repeats)
    assert bu.sent["VRCI"] > len(sent)                          # the BU did resend
    # The controller's own commands: resent until the VRAI, each delivered to the RU once.
    vrco = ids(ctl, "vrco_sent")
    assert len(vrco) >= 4 and sorted(ids(ctl, "vrco_acked")) == vrco
    delivered = ids(bu, "vrco_delivered")
    assert sorted(delivered) == vrco
    assert bu.sent["VRAI"] == bu.received["VRCO"] >= len(vrco)
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
    common = ["--source", f"{LOOPBACK}:0", "--duration", "2.5", "--json"]
    vm110 = [sys.executable, "-m", "vm110", "simulate"]
    ctl = subprocess.Popen(vm110 + ["controller", "--listen", f"{LOOPBACK}:{ctl_rx}", "--peer", f"{LOOPBACK}:{bu_rx}",
                                    "--command-every", "0.5", *common], stdout=subprocess.PIPE, text=True)
    bu = subprocess.run(vm110 + ["bu", "--listen", f"{LOOPBACK}:{bu_rx}", "--peer", f"{LOOPBACK}:{ctl_rx}",
                                 "--command-every", "0.3", "--loss", "10", "--seed", "5", *common],
                        capture_output=True, text=True, timeout=20)
    ctl_out, _ = ctl.communicate(timeout=20)
    assert bu.returncode == 0 and ctl.returncode == 0, bu.stderr
    bu_log = [json.loads(line) for line in bu.stdout.splitlines() if line.startswith("{")]
    ctl_log = [json.loads(line) for line in ctl_out.splitlines() if line.startswith("{")]
    bu_sum, ctl_sum = bu_log[-1]["summary"], ctl_log[-1]["summary"]
    assert bu_sum["received"]["VRPO"] >= 15 and ctl_sum["received"]["VRPI"] >= 12
    executed = [e["command_id"] for e in ctl_log if e.get("event") == "executed"]
    assert executed and len(executed) == len(set(executed))
    assert {e["command_id"] for e in bu_log if e.get("event") == "command_acked"} <= set(executed)
    assert ctl_sum["sent"]["VRAO"] == ctl_sum["received"]["VRCI"]


def test_cli_usage_errors_are_one_line_with_exit_code_2(tmp_path):
    vm110 = [sys.executable, "-m", "vm110", "simulate"]
    bad_script = tmp_path / "remote.json"
    bad_script.write_text('{"steps": [{"at": 0, "state": "flying"}]}')
    for args in (["bu", "--peer", "not-an-address"],
                 ["controller", "--listen", "127.0.0.1:99999"],
                 ["bu", "--stall", "5:3"],
                 ["controller", "--port", "65535"],
                 ["bu", "--duration", "0"],
                 ["bu", "--script", str(tmp_path / "missing.json")],
                 ["bu", "--script", str(bad_script), "--listen", f"{LOOPBACK}:0", "--peer", f"{LOOPBACK}:9"]):
        done = subprocess.run(vm110 + args, capture_output=True, text=True, timeout=20)
        assert done.returncode == 2, (args, done.stderr)
        assert "Traceback" not in done.stderr and done.stderr.strip(), args
