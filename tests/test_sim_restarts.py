"""The reference controller across base-unit reboots, held to interpretation.md ("Sender restarts",
"Commands"): a BU that rebooted starts a new command stream, so a command ID it reuses after the
reboot is a new command, even within the 2000 ms reuse gap; without a reboot it is a repeat.

The BU's packets are written by hand here (serials, times, source ports as the rule's examples
give them), not by our simulated BU, and fed straight to the controller. After a restart of the
controller itself, or a silence of VRPI, a command waits for a VRPI to tell the RU's state (TS-0006
4.3); the last test runs that end to end with the simulated BU on the virtual clock.
"""
from __future__ import annotations

from vm110 import constants as C
from vm110 import encode
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.lifecycle import Restart

ORIGIN, BU = 0x0101, ("10.0.0.10", C.INPUT_PORT)
ARMED = {"bu_state": int(C.BuState.ARMED), "armed_ru": 0x0C07, "ru_state": int(C.RuState.ENABLED),
         "ru_battery": 90}


class Bu:
    """A base unit written by hand: each packet with the serial and source given."""

    def __init__(self, ctl: Controller, serial: int = 1000, src: tuple[str, int] = BU, origin: int = ORIGIN,
                 state: dict | None = None) -> None:
        self.ctl, self.serial, self.src, self.origin, self.state = ctl, serial, src, origin, state or ARMED

    def send(self, ptype: C.PacketType, payload: bytes, t: float, serial: int | None = None) -> None:
        if serial is not None:
            self.serial = serial
        data = encode.packet(ptype, payload, origin=self.origin, serial=self.serial)
        self.serial = (self.serial + 1) & 0xFFFF
        self.ctl.receive(data, round(t * 1e6), self.src)

    def vrpi(self, t: float, serial: int | None = None) -> None:
        self.send(C.PacketType.VRPI, encode.vrpi_payload(self.state), t, serial)

    def vrci(self, t: float, command_id: int, serial: int | None = None) -> None:
        self.send(C.PacketType.VRCI, encode.command_payload(command_id, b"GO"), t, serial)

    def running(self, start: float, end: float) -> None:
        """VRPI every 125 ms from `start` until before `end`."""
        t = start
        while t < end - 1e-9:
            self.vrpi(t)
            t += 0.125


def controller() -> Controller:
    ctl = Controller()
    ctl.attach(lambda data, now, meta: None)
    ctl.start(0)
    return ctl


def executed(ctl: Controller) -> list[int]:
    return [e["command_id"] for e in ctl.events("executed")]


def test_an_id_reused_without_a_reboot_within_the_reuse_gap_is_a_repeat():
    ctl = controller()
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.0, 5)
    bu.running(1.05, 1.6)
    bu.vrci(1.6, 5)                              # 600 ms later, the counter going on: a retransmission
    assert executed(ctl) == [5] and [e["command_id"] for e in ctl.events("repeat")] == [5]


def test_an_id_reused_after_a_reboot_is_a_new_command():
    """Before: the second ID 5, 600 ms after the first but after the BU rebooted (its counter back
    at 0), was a "repeat" and never executed."""
    ctl = controller()
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.0, 5)
    bu.vrpi(1.05)                                # ... the BU reboots: silent until 1.5 s
    bu.vrpi(1.5, serial=0)                       # a restart: not in order, nor a copy, nor a plausible gap
    bu.vrpi(1.55)                                # serial 1 confirms it
    bu.vrci(1.6, 5)
    assert executed(ctl) == [5, 5] and not ctl.events("repeat")
    assert [(e["at"], e["serial"]) for e in ctl.events("bu_restart")] == [(1.5, 0)]


def test_the_restarting_packet_itself_may_carry_the_reused_id():
    """The reboot's first packet is the command (serial 0): it is a new command once the next packet
    (serial 1) confirms the restart, and it is acknowledged at once either way."""
    ctl = controller()
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.0, 5)
    bu.vrpi(1.05)                                # (the last VRPI before the reboot: 450 ms, within the VRPI timeout)
    bu.vrci(1.5, 5, serial=0)
    assert executed(ctl) == [5] and ctl.sent["VRAO"] == 2       # not decided yet, but acknowledged
    bu.vrpi(1.55)
    assert executed(ctl) == [5, 5] and not ctl.events("repeat")


def test_a_stray_packet_that_no_next_packet_confirms_restarts_nothing():
    """An unconfirmed jump is out of order and nothing else: the command in it is a repeat."""
    ctl = controller()
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.0, 5)
    bu.vrpi(1.05)
    end = bu.serial
    bu.vrci(1.5, 5, serial=30000)                # far from the counter, and not followed by 30001…30004
    bu.vrpi(1.55, serial=end)                    # the counter goes on where it was
    bu.vrci(1.6, 5)
    assert executed(ctl) == [5] and [e["command_id"] for e in ctl.events("repeat")] == [5, 5]
    assert not ctl.events("bu_restart")


def test_a_copy_of_the_command_is_not_a_new_command_after_a_reboot():
    ctl = controller()
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.0, 5)
    bu.vrpi(1.5, serial=0)
    bu.vrpi(1.55)
    bu.vrci(1.6, 5)
    bu.vrci(1.6005, 5, serial=2)                 # a copy (same serial, 0.5 ms later: a mirror port)
    bu.vrci(1.7, 5)                              # and a retransmission of the new command
    assert executed(ctl) == [5, 5] and len(ctl.events("repeat")) == 2


def test_a_bu_back_on_a_new_source_port_is_a_new_sender():
    """A command is (sender, command ID), the sender including its source port: the same ID from a
    new port is a new command. After 250 ms of silence of the old port that is the BU restarted
    (logged as such); before, another sender (nothing restarted)."""
    for silence, restarted in ((0.3, True), (0.2, False)):
        ctl = controller()
        bu = Bu(ctl)
        bu.running(0.0, 1.0)
        bu.vrci(1.0, 5)
        Bu(ctl, serial=bu.serial, src=(BU[0], 40000)).vrci(1.0 + silence, 5)
        assert executed(ctl) == [5, 5] and not ctl.events("repeat")
        # (logged with the source it came back on: the log said nothing of the new port)
        assert [e["src"] for e in ctl.events("bu_restart")] == ([f"{BU[0]}:40000"] if restarted else [])


def test_the_base_unit_delivers_an_id_a_restarted_controller_reuses():
    """The same rule the other way: a controller program restarted (its counter back at 0) sends a
    VRCO with an ID it used 500 ms before; the BU hands it to the RU application again."""
    from vm110.sim.bu import BaseUnit

    bu = BaseUnit()
    bu.attach(lambda data, now, meta: None)
    bu.start(0)
    ctl = ("10.0.0.20", C.OUTPUT_PORT)

    def send(ptype: C.PacketType, payload: bytes, t: float, serial: int) -> None:
        bu.receive(encode.packet(ptype, payload, serial=serial), round(t * 1e6), ctl)

    for n in range(10):
        send(C.PacketType.VRPO, encode.vrpo_payload(0, b"x" * 8), n * 0.1, 500 + n)
    send(C.PacketType.VRCO, encode.command_payload(3, b"SET"), 1.0, 510)
    send(C.PacketType.VRCO, encode.command_payload(3, b"SET"), 1.1, 511)          # a retransmission
    send(C.PacketType.VRPO, encode.vrpo_payload(0, b"x" * 8), 1.4, 0)            # restarted
    send(C.PacketType.VRCO, encode.command_payload(3, b"SET"), 1.5, 1)
    assert [e["command_id"] for e in bu.events("vrco_delivered")] == [3, 3]
    assert [(e["src"], e["serial"]) for e in bu.events("controller_restart")] == [(f"{ctl[0]}:{ctl[1]}", 0)]


def acks(sent: list) -> list[int]:
    return [meta.key for meta in sent if meta.ptype is C.PacketType.VRAO]


def test_a_command_heard_after_the_controller_restarted_waits_for_a_vrpi():
    """TS-0006 4.3: the controller checks that the RU is armed before executing a command; 4.4: it
    acknowledges a command it has processed; 5.1.3: the BU resends it every 100 ms until then.
    Before: the controller back from a restart refused (and acknowledged) the first VRCI it heard
    when it came before the first VRPI, though the RU was armed all along: the command was lost
    and the operator told it went through. Now it is left unacknowledged, and the BU's
    retransmission after the VRPI is executed."""
    sent: list = []
    ctl = Controller(ControllerConfig(restarts=(Restart(1.0, 0.5),)))
    ctl.attach(lambda data, now, meta: sent.append(meta))
    ctl.start(0)
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.vrci(1.55, 7)                   # the controller is back at 1.5: no VRPI heard since
    assert not ctl.events("refused") and not executed(ctl) and acks(sent) == []
    assert [(e["command_id"], e["last_vrpi"]) for e in ctl.events("deferred")] == [(7, None)]
    bu.vrpi(1.6)
    bu.vrci(1.65, 7)                   # the BU's retransmission
    assert executed(ctl) == [7] and acks(sent) == [7] and not ctl.events("repeat")


def test_a_command_after_a_vrpi_silence_waits_for_a_vrpi():
    """The same after 800 ms without VRPI (the input path down, the VRCI through first): the RU's
    state of 800 ms ago is no longer known (5.1.1, watchdog 500 ms). Before: executed on it."""
    sent: list = []
    ctl = controller()
    ctl.attach(lambda data, now, meta: sent.append(meta))
    bu = Bu(ctl)
    bu.running(0.0, 1.0)
    bu.serial += 6                     # (6 packets lost in the silence)
    bu.vrci(1.675, 3)
    assert not executed(ctl) and acks(sent) == [] and len(ctl.events("deferred")) == 1
    bu.vrpi(1.68)
    bu.vrci(1.775, 3)
    assert executed(ctl) == [3] and acks(sent) == [3]


def test_every_command_acknowledged_across_a_controller_restart_was_executed():
    """End to end on the virtual clock: the simulated BU presses keys before, during and just after
    the controller's restart (RU armed throughout); every command the BU saw acknowledged was
    executed, once. Before: those whose first copy after the restart beat the first VRPI were
    refused, yet acknowledged."""
    from vm110.sim.bu import BaseUnit
    from vm110.sim.remote import Remote
    from vm110.sim.virtual import Station, VirtualNetwork

    keys = [{"at": t, "data": f"KEY {i}"} for i, t in enumerate((1.0, 2.2, 3.0, 3.45, 3.5, 3.52, 4.0))]
    bu = BaseUnit(Remote.from_script({"steps": [{"at": 0, "state": "armed"}], "commands": keys}))
    ctl = Controller(ControllerConfig(restarts=(Restart(2.0, 1.5),)))
    for _ in VirtualNetwork([Station(bu, "10.0.0.10", C.INPUT_PORT), Station(ctl, "10.0.0.20", C.OUTPUT_PORT)]).run(6.0):
        pass
    acked = sorted(e["command_id"] for e in bu.events("command_acked"))
    assert acked == list(range(len(keys))) and not bu.events("command_failed")
    assert sorted(executed(ctl)) == acked and not ctl.events("refused")


def test_a_rebooted_base_unit_is_initial_then_disarmed_until_the_ru_is_armed_again():
    """TS-0006 4.1.1 and 4.3 across a BU reboot (down at 1 s, back at 1.5 s): its VRPI say "Initial,
    not fully operative yet" for boot_ms, then "Disarmed" with the RU among the unarmed RUs, until
    the operator arms it again rearm_ms after the BU came back; meanwhile the controller refuses the
    operator's keys (still acknowledged) and executes those after. Before: back armed at once."""
    from vm110.decode import decode
    from vm110.sim.bu import BaseUnit, BaseUnitConfig
    from vm110.sim.remote import Remote
    from vm110.sim.virtual import Station, VirtualNetwork

    keys = [{"at": t, "data": f"KEY {i}"} for i, t in enumerate((0.5, 4.0, 6.0))]
    bu = BaseUnit(Remote.from_script({"steps": [{"at": 0, "state": "armed", "unarmed_rus": 1}], "commands": keys}),
                  BaseUnitConfig(restarts=(Restart(1.0, 0.5),), boot_ms=800, rearm_ms=3000))
    ctl = Controller()
    states = []
    for batch in VirtualNetwork([Station(bu, "10.0.0.10", C.INPUT_PORT), Station(ctl, "10.0.0.20", C.OUTPUT_PORT)]).run(7.0):
        for t, _, index, data, *_ in batch:
            p = decode(data)
            if index == 0 and p["type"] == "VRPI":
                states.append((t / 1e6, p["bu_state"], p["armed_ru"], p["unarmed_rus"], p["es_relays_open"]))
    INITIAL, DISARMED, ARMED = int(C.BuState.INITIAL), int(C.BuState.DISARMED), int(C.BuState.ARMED)

    def state_at(t):
        return [s[1:] for s in states if s[0] <= t][-1]
    assert state_at(0.9) == (ARMED, 0x0C07, 1, False)
    assert [s[0] for s in states if 0.9 < s[0] < 1.5] == []                  # down
    # (a VRPI every 125 ms from 1.5 s: the last before 2.3 s at 2.25 s, the last before 4.5 s at 4.375 s)
    assert state_at(1.5) == state_at(2.25) == (INITIAL, 0, 0, True)          # back at 1.5 s
    assert state_at(2.375) == state_at(4.375) == (DISARMED, 0, 2, False)     # the RU on, unarmed
    assert state_at(4.5) == (ARMED, 0x0C07, 1, False)                        # armed again
    assert [e["data"] for e in ctl.events("executed")] == ["KEY 0", "KEY 2"]
    assert [e["data"] for e in ctl.events("refused")] == ["KEY 1"]
    assert sorted(e["command_id"] for e in bu.events("command_acked")) == [0, 0, 1]


def test_a_command_is_judged_by_the_ru_of_the_bu_that_sent_it():
    """Two BUs on the group (each its own origin, TS-0006 3.2), one armed, one disarmed: each
    command is checked against the RU of its own BU (4.3). Trial: the disarmed BU's VRPI, sent just
    before the armed one's command, had that command refused; and a BU heard from for the first
    time had its command decided on the other BU's VRPI, not deferred."""
    ctl = controller()
    armed = Bu(ctl)
    disarmed = Bu(ctl, serial=7, src=("10.0.0.11", C.INPUT_PORT), origin=0x0202,
                  state={"bu_state": int(C.BuState.DISARMED), "unarmed_rus": 1})
    for n in range(8):
        armed.vrpi(n * 0.125)
        disarmed.vrpi(n * 0.125 + 0.01)          # always the last VRPI before a command
        armed.vrci(n * 0.125 + 0.02, n)
        disarmed.vrci(n * 0.125 + 0.03, 100 + n)
    assert executed(ctl) == list(range(8))
    assert [e["command_id"] for e in ctl.events("refused")] == [100 + n for n in range(8)]
    silent = Bu(ctl, serial=50, src=("10.0.0.12", C.INPUT_PORT), origin=0x0303)
    silent.vrci(1.01, 200)                        # no VRPI of its own yet: its RU's state is unknown
    assert [e["command_id"] for e in ctl.events("deferred")] == [200] and 200 not in executed(ctl)
