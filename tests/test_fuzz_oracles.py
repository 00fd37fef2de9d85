"""The fuzzer's oracles on scripted traffic: each fires on its defect and stays quiet on correct
behaviour. Packets are made with vm110.encode (and corrupted by hand), times are given explicitly."""
from __future__ import annotations

import pytest

from vm110 import constants as C
from vm110 import encode
from vm110.fuzz.oracles import Limits, Monitor

CTL = ("127.0.0.1", 40000)
T0 = 1000.0


def vrci(command_id: int, serial: int = 1, origin: int = 0x0101) -> bytes:
    return encode.packet("VRCI", encode.command_payload(command_id), origin=origin, serial=serial)


def out(ptype: str, payload: bytes, serial: int, origin: int = 0) -> bytes:
    return encode.packet(ptype, payload, origin=origin, serial=serial)


def bad_crc(data: bytes) -> bytes:
    return data[:-1] + bytes([data[-1] ^ 0xFF])


class Link:
    """Feeds a Monitor the controller's packets with increasing serials."""

    def __init__(self) -> None:
        self.mon = Monitor(Limits(), T0)
        self.serial = 0

    def rx(self, t: float, ptype: str, payload: bytes = b"", origin: int = 0, corrupt: bool = False) -> None:
        data = out(ptype, payload, self.serial, origin)
        self.serial += 1
        self.mon.on_rx(t, bad_crc(data) if corrupt else data, CTL)

    def vrpo(self, t: float) -> None:
        self.rx(t, "VRPO", encode.vrpo_payload(0, b"x"))

    def oracles(self) -> list[str]:
        return [t.oracle for t in self.mon.triggers]


@pytest.fixture
def link() -> Link:
    return Link()


def test_acknowledged_commands_are_fine(link):
    for n, cid in enumerate((5, 5, 6)):          # a retransmission of 5, then 6
        link.mon.on_tx(T0 + n * 0.1, vrci(cid, n), vrci(cid, n), index=n)
    for n, cid in enumerate((5, 5, 6)):
        link.rx(T0 + 0.05 + n * 0.1, "VRAO", encode.ack_payload(cid))
    link.mon.tick(T0 + 5)
    assert link.oracles() == []


def test_missing_ack_for_a_retransmission(link):
    link.mon.on_tx(T0, vrci(9), vrci(9), index=3)
    link.mon.on_tx(T0 + 0.1, vrci(9, 2), vrci(9, 2), index=3)
    link.rx(T0 + 0.01, "VRAO", encode.ack_payload(9))
    link.mon.tick(T0 + 0.5)
    assert link.oracles() == []
    link.mon.tick(T0 + 0.1 + 1.01)
    assert link.oracles() == ["missing_ack"]
    assert link.mon.triggers[0].case_index == 3 and link.mon.triggers[0].command_id == 9


def test_one_ack_answers_a_burst_of_retransmissions_sent_before_it(link):
    """A PLC acks at the end of its 100 ms scan cycle: the storm case's 20 transmissions of one
    command ID, 5 ms apart, got one VRAO per cycle; the oracle took each VRAO as the ack of one
    transmission and reported a correct controller's missing_ack."""
    for n in range(5):
        link.mon.on_tx(T0 + n * 0.005, vrci(7, n), vrci(7, n), index=2)
    link.rx(T0 + 0.08, "VRAO", encode.ack_payload(7))
    link.mon.on_tx(T0 + 0.09, vrci(7, 5), vrci(7, 5), index=2)      # sent after the ack: owed one
    link.mon.tick(T0 + 1.05)            # the burst's deadlines passed, not the last one's
    assert link.oracles() == []
    link.mon.tick(T0 + 0.09 + 1.01)
    assert [(t.oracle, t.command_id) for t in link.mon.triggers] == [("missing_ack", 7)]


def test_a_command_of_a_base_unit_the_controller_hears_no_vrpi_of_needs_no_ack(link):
    """The fuzzer's VRPI come from origin 0x0101; a case's VRCI from another origin is a base unit
    whose RU state the controller cannot know (TS-0006 4.3): the reference controller leaves it
    unacknowledged until that unit's VRPI come: the oracle made that a missing_ack finding."""
    link.mon.on_tx(T0, vrci(4, origin=0x0202), vrci(4), index=1)
    link.mon.on_tx(T0 + 0.1, vrci(5), vrci(5), index=2)
    link.mon.tick(T0 + 5)
    assert [(t.oracle, t.command_id) for t in link.mon.triggers] == [("missing_ack", 5)]


def test_duplicate_frames_need_no_ack(link):
    link.mon.on_tx(T0, vrci(4), vrci(4), index=1, expect_ack=False)
    link.mon.tick(T0 + 3)
    assert link.oracles() == []


def test_illegal_command_acknowledged(link):
    link.mon.on_tx(T0, bad_crc(vrci(7)), vrci(7), index=11)
    link.mon.tick(T0 + 2)                          # no ack is right: nothing fires
    assert link.oracles() == []
    link.rx(T0 + 2.1, "VRAO", encode.ack_payload(7))
    assert link.oracles() == ["illegal_acked"] and link.mon.triggers[0].case_index == 11


def test_unknown_packet_id_from_a_command_is_judged_by_its_twin(link):
    mutated = b"VRXI" + vrci(8)[4:]
    link.mon.on_tx(T0, mutated, vrci(8), index=2)
    link.rx(T0 + 0.01, "VRAO", encode.ack_payload(8))
    assert link.oracles() == [], "an ack of a non-VRCI packet is not an illegal VRCI ack"


def test_ack_for_a_command_never_sent(link):
    link.rx(T0, "VRAO", encode.ack_payload(321))
    assert link.oracles() == ["malformed_output"]


@pytest.mark.parametrize("defect", ["crc", "origin", "direction", "repeat", "backwards"])
def test_malformed_output(link, defect):
    link.vrpo(T0)
    if defect == "crc":
        link.rx(T0 + 0.1, "VRPO", encode.vrpo_payload(0, b""), corrupt=True)
    elif defect == "origin":
        link.rx(T0 + 0.1, "VRPO", encode.vrpo_payload(0, b""), origin=0x0101)
    elif defect == "direction":
        link.rx(T0 + 0.1, "VRPI", encode.vrpi_payload({}))
    else:
        link.serial -= 1 if defect == "repeat" else 5
        link.vrpo(T0 + 0.1)
    assert link.oracles() == ["malformed_output"]


def test_serials_may_wrap(link):
    link.serial = C.SERIAL_MODULUS - 2
    for n in range(4):
        link.vrpo(T0 + n * 0.1)
    assert link.oracles() == []


def test_stall_blames_the_cases_right_after_the_last_vrpo(link):
    link.mon.note_case(T0 - 0.05, 1)
    link.vrpo(T0)
    link.mon.note_case(T0 + 0.02, 2)
    link.mon.note_case(T0 + 0.6, 3)
    link.mon.tick(T0 + 1.9)
    assert link.oracles() == []
    link.mon.tick(T0 + 2.01)
    assert link.oracles() == ["stall"]
    assert link.mon.triggers[0].suspects[:2] == [2, 1]
    link.mon.tick(T0 + 3)
    assert link.oracles() == ["stall"], "reported once per silence"


def test_stall_blames_the_cases_nearest_the_last_vrpo_on_either_side(link):
    """Trial: a controller that read its input after sending its VRPO (a PLC cycle) stopped on the
    case sent 5 ms before it; the cases after the VRPO were listed first and it was cut from the
    12 suspects kept."""
    for n in range(5):
        link.vrpo(T0 + n * 0.1)
    last = T0 + 0.4
    link.mon.note_case(last - 0.005, 99)                 # the culprit, read after the VRPO
    for n in range(20):
        link.mon.note_case(last + 0.01 * (n + 1), n)      # the cases it never read
    link.mon.tick(last + 2.01)
    assert link.mon.triggers[0].suspects[:3] == [99, 0, 1]


def test_vrco_resent_while_withheld_is_fine_until_it_stops(link):
    link.mon.withholding = True
    for n in range(4):
        link.rx(T0 + n * 0.1, "VRCO", encode.command_payload(2))
        link.mon.tick(T0 + n * 0.1 + 0.05)
    assert link.oracles() == []
    link.mon.tick(T0 + 0.3 + 0.26)
    assert link.oracles() == ["vrco_retransmit"]
    assert "not resent" in link.mon.triggers[0].detail


def test_vrco_after_its_vrai(link):
    link.rx(T0, "VRCO", encode.command_payload(2))
    vrai = encode.packet("VRAI", encode.ack_payload(2), origin=0x0101)
    link.mon.on_vrai(T0 + 0.001, 2, vrai)
    link.rx(T0 + 0.1, "VRCO", encode.command_payload(2))     # already in flight: fine
    assert link.oracles() == []
    link.rx(T0 + 0.4, "VRCO", encode.command_payload(2))
    assert link.oracles() == ["vrco_retransmit"] and link.mon.triggers[0].packet == vrai


def test_new_vrco_after_an_acked_one_is_fine(link):
    for cid in range(3):
        t = T0 + cid * 0.5
        link.rx(t, "VRCO", encode.command_payload(cid))
        link.mon.on_vrai(t + 0.001, cid, b"")
    link.mon.tick(T0 + 5)
    assert link.oracles() == []


def test_exit_is_a_crash_blaming_recent_cases(link):
    link.mon.note_case(T0 - 1, 1)
    link.vrpo(T0)
    link.mon.note_case(T0 + 0.01, 2)
    link.mon.note_case(T0 + 0.02, 3)
    link.mon.on_exit(T0 + 0.03, 3)
    # In the order sent: the runner bisects prefixes of them (the crash comes at the culprit).
    assert link.oracles() == ["crash"] and link.mon.triggers[0].suspects == [2, 3]
    assert link.mon.triggers[0].detail == "crash exit 3"


# --- several commands in flight (interpretation.md, "Commands") ---------------------------------
@pytest.mark.parametrize("order", [(5, 6), (6, 5)])
def test_two_outstanding_commands_acknowledged_in_either_order(link, order):
    link.mon.on_tx(T0, vrci(5, 1), vrci(5, 1), index=1)
    link.mon.on_tx(T0 + 0.05, vrci(6, 2), vrci(6, 2), index=2)        # a second key within 100 ms
    link.mon.on_tx(T0 + 0.1, vrci(5, 3), vrci(5, 3), index=1)         # 5 resent while 6 is open
    for n, cid in enumerate(order + (5,)):
        link.rx(T0 + 0.12 + n * 0.01, "VRAO", encode.ack_payload(cid))
    link.mon.tick(T0 + 5)
    assert link.oracles() == []


def test_missing_ack_names_the_command_left_out(link):
    link.mon.on_tx(T0, vrci(5, 1), vrci(5, 1), index=1)
    link.mon.on_tx(T0 + 0.05, vrci(6, 2), vrci(6, 2), index=2)
    link.rx(T0 + 0.06, "VRAO", encode.ack_payload(6))                   # only the later one
    link.mon.tick(T0 + 1.2)
    assert link.oracles() == ["missing_ack"]
    trigger = link.mon.triggers[0]
    assert (trigger.command_id, trigger.case_index) == (5, 1)


def test_an_illegal_and_a_legal_command_in_flight_together(link):
    link.mon.on_tx(T0, bad_crc(vrci(7, 1)), vrci(7, 1), index=11)
    link.mon.on_tx(T0 + 0.02, vrci(8, 2), vrci(8, 2), index=12)
    link.rx(T0 + 0.03, "VRAO", encode.ack_payload(8))
    link.mon.tick(T0 + 2)
    assert link.oracles() == []
    link.rx(T0 + 2.1, "VRAO", encode.ack_payload(7))
    assert link.oracles() == ["illegal_acked"] and link.mon.triggers[0].case_index == 11


def test_an_id_sent_legally_after_an_illegal_one_may_be_acked_again(link):
    link.mon.on_tx(T0, bad_crc(vrci(7, 1)), vrci(7, 1), index=11)
    link.mon.on_tx(T0 + 3, vrci(7, 2), vrci(7, 2), index=12)            # the ID reused, legally
    link.mon.on_tx(T0 + 3.001, vrci(7, 2), vrci(7, 2), index=12, expect_ack=False)   # its duplicate frame
    link.rx(T0 + 3.01, "VRAO", encode.ack_payload(7))
    link.rx(T0 + 3.02, "VRAO", encode.ack_payload(7))                   # the duplicate acknowledged too
    link.mon.tick(T0 + 5)
    assert link.oracles() == []


def test_ack_of_a_command_never_sent_while_others_are_open(link):
    link.mon.on_tx(T0, vrci(5, 1), vrci(5, 1), index=1)
    link.mon.on_tx(T0 + 0.05, vrci(6, 2), vrci(6, 2), index=2)
    for cid in (6, 9, 5):
        link.rx(T0 + 0.1, "VRAO", encode.ack_payload(cid))
    link.mon.tick(T0 + 5)
    assert link.oracles() == ["malformed_output"] and link.mon.triggers[0].command_id == 9


def test_vrco_in_flight_together_and_an_id_reused_after_a_pause(link):
    for n in range(3):                                                # 1 and 2 resent together
        link.rx(T0 + n * 0.1, "VRCO", encode.command_payload(1))
        link.rx(T0 + n * 0.1 + 0.05, "VRCO", encode.command_payload(2))
    link.mon.on_vrai(T0 + 0.26, 2, b"")
    link.mon.on_vrai(T0 + 0.27, 1, b"")
    link.rx(T0 + 0.25 + 2.5, "VRCO", encode.command_payload(1))        # a new command with ID 1
    link.mon.tick(T0 + 3)
    assert link.oracles() == []


# --- one command, one missing ack; a dead controller owes none ------------------------------------------
def test_a_command_resent_by_one_case_and_never_acked_is_one_trigger(link):
    """A case that sends one VRCI five times, none acknowledged: one trigger (five before, each
    replaying the same case)."""
    for n in range(5):
        link.mon.on_tx(T0 + n * 0.05, vrci(9, n), vrci(9, n), index=4)
    link.mon.tick(T0 + 1.5)
    assert link.oracles() == ["missing_ack"]
    assert (link.mon.triggers[0].command_id, link.mon.triggers[0].case_index) == (9, 4)
    assert not link.mon.pending


def test_the_same_command_id_from_two_cases_is_two_triggers(link):
    link.mon.on_tx(T0, vrci(9, 1), vrci(9, 1), index=4)
    link.mon.on_tx(T0 + 0.05, vrci(9, 2), vrci(9, 2), index=5)
    link.mon.tick(T0 + 1.5)
    assert [t.case_index for t in link.mon.triggers] == [4, 5]


def test_commands_sent_to_a_dead_controller_owe_no_ack(link):
    """The trial's run: the controller crashed in the middle of a case resending a command; the
    resends that went out after its exit raised missing_ack (one per resend, never reproduced).
    Nor is its silence a stall."""
    link.vrpo(T0)
    link.mon.on_tx(T0 + 0.01, vrci(9, 1), vrci(9, 1), index=7)
    link.mon.on_exit(T0 + 0.02, -6)
    for n in range(1, 4):
        link.mon.on_tx(T0 + 0.02 + n * 0.05, vrci(9, n + 1), vrci(9, n + 1), index=7)
    link.mon.tick(T0 + 3)
    assert link.oracles() == ["crash"]
    link.mon.reset_controller(T0 + 3)                                  # restarted: owed again
    link.mon.on_tx(T0 + 3.1, vrci(10, 5), vrci(10, 5), index=8)
    link.mon.tick(T0 + 4.2)
    assert link.oracles() == ["crash", "missing_ack"]


def test_a_controller_that_hangs_on_a_command_is_one_stall_led_by_that_command(link):
    """Trial (BUGS=hang_any): a hang gave a missing_ack finding and a stall finding."""
    for n in range(5):
        link.vrpo(T0 + n * 0.1)
    link.mon.note_case(T0 + 0.3, 6)
    link.mon.on_tx(T0 + 0.45, vrci(7, 1), vrci(7, 1), index=8)      # it hangs on this one
    link.mon.note_case(T0 + 0.45, 8)
    link.mon.tick(T0 + 1.5)
    assert link.oracles() == []
    link.mon.tick(T0 + 2.5)
    [stall] = link.mon.triggers
    assert stall.oracle == "stall" and stall.suspects == [8, 6] and stall.command_id == 7


def test_commands_sent_to_a_controller_already_hung_do_not_lead_the_stall(link):
    """Trial (a controller of my own, hung by a VRPI one byte longer than its layout): the VRCI
    cases sent during the 2 s after it had stopped led the suspects, the VRPI was cut from the 12
    replayed, and the stall was left unreproduced."""
    for n in range(5):
        link.vrpo(T0 + n * 0.1)
    last = T0 + 0.4
    link.mon.note_case(last + 0.02, 48)                  # the culprit, a VRPI
    for n in range(14):                                  # a VRCI case every 70 ms, unanswered
        t = last + 0.09 + 0.07 * n
        link.mon.note_case(t, 100 + n)
        link.mon.on_tx(t, vrci(200 + n, n), vrci(200 + n, n), index=100 + n)
        link.mon.tick(t)
    link.mon.tick(last + 2.01)
    [stall] = link.mon.triggers
    assert stall.oracle == "stall" and stall.suspects[:2] == [100, 48]
    assert 103 not in stall.suspects, "sent after it missed its next VRPO: not a suspect of the hang"
    assert stall.command_id == 200


def test_a_controller_back_on_a_new_port_restarted_on_its_own(link):
    """Trial: my controller, killed and started again 1 s later (as its service manager would
    after a crash), came back on a new ephemeral port with serial 0: no stall (1 s), and its serials
    were judged per port, so the run said nothing of it."""
    for n in range(5):
        link.vrpo(T0 + n * 0.1)
    link.mon.note_case(T0 + 0.42, 48)                   # it died on this one
    link.mon.on_rx(T0 + 1.5, out("VRPO", encode.vrpo_payload(0, b"x"), 0), ("127.0.0.1", 40001))
    [restart] = link.mon.triggers
    assert restart.oracle == "malformed_output" and restart.kind == "restart" and restart.suspects == [48]
    assert "port 40001 after port 40000" in restart.detail


def test_two_sockets_or_a_restart_by_the_fuzzer_are_no_restart(link):
    for n in range(5):
        link.vrpo(T0 + n * 0.1)
        link.mon.on_rx(T0 + n * 0.1 + 0.05, out("VRCO", encode.command_payload(n), n), ("127.0.0.1", 40001))
    link.mon.reset_controller(T0 + 1)                   # the fuzzer restarted it
    link.mon.on_rx(T0 + 1.5, out("VRPO", encode.vrpo_payload(0, b"x"), 0), ("127.0.0.1", 40002))
    assert link.oracles() == []


def test_a_controller_back_on_a_new_port_after_a_stall_is_that_stall(link):
    link.vrpo(T0)
    link.mon.tick(T0 + 2.1)
    link.mon.on_rx(T0 + 3, out("VRPO", encode.vrpo_payload(0, b"x"), 0), ("127.0.0.1", 40001))
    assert link.oracles() == ["stall"]


def test_acks_owed_from_before_the_controller_last_spoke_are_cut_short_by_a_crash_not_its(link):
    """Trial: my controller ignored a VRCI longer than its layout (a legal one) and went on acking
    the commands after it; it crashed on another case 0.5 s later, before that ack's timeout, and
    the missing ack was dropped as the crash's: the bug was never reported."""
    link.mon.on_tx(T0, vrci(35, 1), vrci(35, 1), index=35)              # never acked
    link.mon.on_tx(T0 + 0.1, vrci(46, 2), vrci(46, 2), index=46)
    link.rx(T0 + 0.12, "VRAO", encode.ack_payload(46))
    link.vrpo(T0 + 0.4)
    link.mon.on_tx(T0 + 0.45, vrci(81, 3), vrci(81, 3), index=81)        # it dies on this one
    link.mon.on_exit(T0 + 0.5, 1)
    [crash] = link.mon.triggers
    assert crash.suspects == [81] and link.mon.cut_short == [35]


def test_a_controller_silent_for_a_while_still_owes_its_ack(link):
    link.vrpo(T0)
    link.mon.on_tx(T0 + 0.01, vrci(7, 1), vrci(7, 1), index=8)
    link.mon.tick(T0 + 1.5)
    assert link.oracles() == []
    link.vrpo(T0 + 1.6)
    assert [(t.oracle, t.case_index, t.command_id) for t in link.mon.triggers] == [("missing_ack", 8, 7)]


def test_acks_missed_while_the_controller_was_dying_are_the_crash(link):
    """A sanitizer report that takes longer than the ack timeout: the command went out after the
    controller last spoke, so its missing ack is the crash's."""
    link.mon.note_case(T0 - 1, 1)
    link.mon.on_tx(T0 - 1, vrci(5, 1), vrci(5, 1), index=1)
    link.rx(T0 - 0.9, "VRAO", encode.ack_payload(5))
    link.mon.on_tx(T0 - 0.5, vrci(6, 2), vrci(6, 2), index=2)          # acked late: another bug
    link.vrpo(T0)
    link.mon.on_tx(T0 + 0.01, vrci(7, 3), vrci(7, 3), index=3)         # the controller is dying
    link.mon.tick(T0 + 1.2)
    assert [t.case_index for t in link.mon.triggers] == [2]     # 3: silent since it came, held
    link.mon.on_exit(T0 + 1.5, -6)
    assert [(t.oracle, t.case_index) for t in link.mon.triggers] == [("missing_ack", 2), ("crash", None)]


def test_an_ack_with_a_bad_crc_is_one_bug_not_a_missing_ack_too(link):
    """Trial (a controller that breaks the CRC of its VRAO for command ID 65535): two findings for
    one bug, `malformed_output: illegal VRAO ... bad_crc` and `missing_ack: no VRAO for command ID
    65535`, the second pointing at a VRCI the controller did answer."""
    link.mon.on_tx(T0, vrci(0xFFFF), vrci(0xFFFF), index=9)
    link.rx(T0 + 0.01, "VRAO", encode.ack_payload(0xFFFF), corrupt=True)
    for n in range(1, 16):                      # it goes on speaking past the ack timeout
        link.vrpo(T0 + 0.1 * n)
    link.mon.tick(T0 + 1.6)
    assert link.oracles() == ["malformed_output"]
    assert link.mon.triggers[0].command_id == 0xFFFF and link.mon.triggers[0].suspects[0] == 9



@pytest.mark.parametrize("sent_before", [False, True])
def test_an_ack_with_a_wrong_command_id_is_one_bug_not_a_missing_ack_too(link, sent_before):
    """Trial (a controller that acknowledges command ID 65534 as 2, a signed 16-bit ID negated):
    two findings for one bug, `malformed_output: VRAO for command ID 2, never sent` and
    `missing_ack: no VRAO for command ID 65534`, both replaying the same VRCI; and with command ID
    2 sent long before in a long run (every ID is, sooner or later), the missing ack alone."""
    if sent_before:
        link.mon.on_tx(T0 - 20, vrci(2), vrci(2), index=1)
        link.rx(T0 - 19.99, "VRAO", encode.ack_payload(2))
    link.mon.on_tx(T0, vrci(3), vrci(3), index=8)
    link.rx(T0 + 0.01, "VRAO", encode.ack_payload(3))
    link.mon.on_tx(T0 + 0.1, vrci(0xFFFE), vrci(0xFFFE), index=9)
    link.rx(T0 + 0.11, "VRAO", encode.ack_payload(2))
    for n in range(2, 17):                      # it goes on speaking past the ack timeout
        link.vrpo(T0 + 0.1 * n)
    link.mon.tick(T0 + 1.7)
    assert link.oracles() == ["malformed_output"]
    assert link.mon.triggers[0].command_id == 2 and link.mon.triggers[0].suspects[0] == 9


def test_another_ack_of_a_recent_command_answers_no_other(link):
    """Command 5 acknowledged twice (a controller sending each ack twice against loss) is no wrong
    ack: command 6, open, still owes its own."""
    link.mon.on_tx(T0, vrci(5), vrci(5), index=1)
    link.mon.on_tx(T0 + 0.02, vrci(6), vrci(6), index=2)
    for n in range(2):
        link.rx(T0 + 0.05 + n * 0.01, "VRAO", encode.ack_payload(5))
    for n in range(1, 16):
        link.vrpo(T0 + 0.1 * n)
    link.mon.tick(T0 + 1.6)
    assert link.oracles() == ["missing_ack"] and link.mon.triggers[0].command_id == 6


def test_a_wrong_ack_of_a_resend_is_the_same_finding_again(link):
    """The base unit goes on resending a command answered with a wrong ID (`resending`, until its
    ack is due): the controller's wrong ack of a resend blames the same command and case, not the
    cases of the moment, so it is the one finding again."""
    link.mon.on_tx(T0, vrci(0xFFFE), vrci(0xFFFE), index=9)
    link.rx(T0 + 0.01, "VRAO", encode.ack_payload(2))
    assert link.mon.resending(0xFFFE, T0 + 0.1)
    link.mon.note_case(T0 + 0.05, 10)
    link.mon.on_tx(T0 + 0.1, vrci(0xFFFE, 2), vrci(0xFFFE, 2), index=9, expect_ack=False)
    link.rx(T0 + 0.11, "VRAO", encode.ack_payload(2))
    assert [(t.answered, t.suspects[0], t.kind) for t in link.mon.triggers] == [(0xFFFE, 9, "VRAO unknown")] * 2
    assert not link.mon.resending(0xFFFE, T0 + 1.01), "given up when its ack was due"
