"""The fuzz runner's bookkeeping, without a controller: which suspects a trigger keeps. A runner
is built on two free loopback ports; nothing is sent."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import pytest
from loopback import free_ports
from vm110 import constants as C
from vm110 import encode
from vm110.fuzz import cases as K
from vm110.fuzz import mutate as M
from vm110.fuzz.oracles import CRASH, MALFORMED_OUTPUT, MISSING_ACK, STALL, Limits, Monitor, Trigger
from vm110.fuzz.runner import TRIAL, Replay, RunConfig, Runner, _open_log, trial
from vm110.fuzz.session import Sent, Settings


@pytest.fixture
def runner(tmp_path: Path):
    rx, listen = free_ports(2)
    made = Runner(RunConfig(settings=Settings(("127.0.0.1", rx), ("127.0.0.1", listen)), out=tmp_path / "out"))
    yield made
    made.session.close()


def test_a_lost_controller_keeps_more_suspects_than_are_replayed(runner):
    """Trial: without --target-cmd the stall's culprit was the 13th suspect and was cut from
    suspect_cases, the only clue left."""
    for i in range(30):
        runner.records[i] = (K.generate(1, i), [])
    runner._unreproduced(Trigger(STALL, 0.0, "no VRPO", suspects=list(range(30))), list(range(30)), "gone")
    [entry] = runner.unreproduced
    assert entry["suspects"] == list(range(30))
    assert entry["suspect_cases"] == [K.generate(1, i).description for i in range(30)]


def test_a_kind_of_trigger_that_keeps_not_replaying_is_replayed_only_now_and_then(runner, monkeypatch):
    """Trial: a controller that acks at most 16 commands per scan cycle dropped acks at --coverage's
    5000 packets/s; each missing_ack was replayed alone (acked), and a 40 s run spent 90 s and more
    on 83 such replays. After 3 in a row, every 10th is replayed; the rest are listed."""
    trials: list[int] = []
    monkeypatch.setattr(runner, "_trial", lambda replay, trig: trials.append(trig.case_index))
    for i in range(30):
        runner.records[i] = (K.generate(1, i), [])
        runner._investigate(Trigger(MISSING_ACK, float(i), "no VRAO", i, [i], None, "no ack", i))
    assert trials == [0, 1, 2, 12, 22]
    assert len(runner.unreproduced) == 30 and runner.findings == []
    assert [u["suspects"] for u in runner.unreproduced if "not_replayed" in u] == \
        [[i] for i in range(30) if i not in trials]
    crash = Trigger(CRASH, 31.0, "crash", None, [3], None, "SIGSEGV")
    runner._investigate(crash)
    assert trials[-1:] == [None], "a crash is replayed all the same"


def test_each_run_appends_to_target_log_under_its_own_header(tmp_path):
    """A run that could not start leaves target.log; the next one must not mix into it unmarked."""
    (tmp_path / "target.log").write_bytes(b"the first run's controller output\n")
    with _open_log(tmp_path, "./ctl 5825 5827") as log:
        log.write(b"the second run's\n")
    lines = (tmp_path / "target.log").read_bytes().decode().splitlines()
    assert lines[0] == "the first run's controller output" and lines[2] == "the second run's"
    assert lines[1].startswith("== vm110 fuzz ") and lines[1].endswith(": ./ctl 5825 5827 ==")


def test_two_packets_left_by_minimising_are_the_reproducer(runner):
    """Trial: a case minimised to two of its three packets kept all three, minimised false (the
    reduction was dropped whenever more than one packet was left)."""
    vrci = [M.build(C.PacketType.VRCI, n, M.default_fields(C.PacketType.VRCI, 40 + n)) for n in range(2)]
    vrpi = M.build(C.PacketType.VRPI, 9, M.ARMED_VRPI)
    sent = [Sent(0.0, vrci[0], vrci[0], 0.0, True), Sent(0.0, vrpi, vrpi, 20.0, True),
            Sent(0.0, vrci[1], vrci[1], 20.0, True)]
    trig = Trigger(MISSING_ACK, 0.0, "no VRAO", case_index=1)
    runner._trial = lambda replay, t: t if set(vrci) <= {p.data for p in replay.packets} else None
    kept, shown, small, complete = runner._minimize(trig, K.Case(1, "sequence", "two commands"), sent)
    assert [p.data for p in kept] == vrci and complete and small is None and shown is not None


class _Echo:
    """A session whose controller answers every replay with the malformed output `kind`."""

    def __init__(self, kind: str) -> None:
        self.kind, self.supervisor, self.evidence_dir = kind, None, Path(".")
        self.settings = Settings(("127.0.0.1", 1), ("127.0.0.1", 2), limits=Limits(ack_timeout_ms=50.0))
        self.monitor = Monitor(self.settings.limits, 0.0)

    def run_steps(self, *args: object) -> list[Sent]:
        self.monitor.fire(Trigger(MALFORMED_OUTPUT, 0.0, self.kind, kind=self.kind))
        return []

    def pump(self, until: float) -> None:
        pass


def test_a_malformed_output_is_confirmed_only_by_its_own_kind():
    """Trial (BUGS=hang_any,bogus_any): 'VRPO serial 0 after 6' was confirmed by a replay whose
    VRAI drew a VRAO for a command never sent, another malformed output, and became a finding."""
    replay = Replay([Sent(0.0, b"VRAI", b"VRAI", 0.0, False)])
    assert trial(_Echo("VRAO unknown"), replay, MALFORMED_OUTPUT, "serial") is None    # type: ignore[arg-type]
    again = trial(_Echo("serial"), replay, MALFORMED_OUTPUT, "serial")                 # type: ignore[arg-type]
    assert again is not None and again.kind == "serial"


class _WrongAck:
    """A session whose controller acknowledges command ID 65535 as 1 (a signed 16-bit ID negated)."""

    def __init__(self, sent_before: bool) -> None:
        self.supervisor, self.evidence_dir = None, Path(".")
        self.settings = Settings(("127.0.0.1", 1), ("127.0.0.1", 2), limits=Limits(ack_timeout_ms=50.0))
        self.monitor = Monitor(self.settings.limits, 0.0)
        if sent_before:                 # the run had sent command ID 1 lately; a replay may not have
            one = M.build(C.PacketType.VRCI, 1, M.default_fields(C.PacketType.VRCI, 1))
            self.monitor.on_tx(time.time(), one, one, 1)

    def run_steps(self, *args: object) -> list[Sent]:
        now = time.time()
        vrci = M.build(C.PacketType.VRCI, 2, M.default_fields(C.PacketType.VRCI, 0xFFFF))
        self.monitor.on_tx(now, vrci, vrci, TRIAL)
        self.monitor.on_rx(now, encode.packet("VRAO", encode.ack_payload(1), origin=0, serial=0), ("127.0.0.1", 3))
        return []

    def pump(self, until: float) -> None:
        time.sleep(max(0.0, min(until, time.time() + 0.02) - time.time()))
        self.monitor.tick(time.time())


@pytest.mark.parametrize("sent_before", [True, False])
def test_a_missing_ack_whose_replay_draws_an_ack_with_a_wrong_id_still_triggers(sent_before):
    """Trial (a controller acknowledging 65535 as 1): the run, having sent command ID 1 lately, saw
    a missing ack; its --replay, which had not, saw a VRAO for a command never sent in its place
    and said "does not trigger any more", exit 0, of a bug still there."""
    replay = Replay([Sent(0.0, b"VRCI", b"VRCI", 0.0, True)])
    again = trial(_WrongAck(sent_before), replay, MISSING_ACK)    # type: ignore[arg-type]
    assert again is not None


class _SlowDeath:
    """A session whose controller falls silent at the replayed packets and dies `after` seconds
    later (a loop that ends in a signed overflow under UBSan), or, `after` None, goes on."""

    def __init__(self, after: Optional[float]) -> None:
        self.after, self.supervisor, self.evidence_dir = after, None, Path(".")
        self.settings = Settings(("127.0.0.1", 1), ("127.0.0.1", 2))
        self.monitor = Monitor(self.settings.limits, 0.0)
        self.start = time.time()

    def run_steps(self, *args: object) -> list[Sent]:
        self.start = time.time()
        return []

    def pump(self, until: float) -> None:
        time.sleep(max(0.0, min(until, time.time() + 0.02) - time.time()))
        now = time.time()
        if self.after is None:
            self.monitor.last_vrpo = now
        elif now >= self.start + self.after and not self.monitor.exited:
            self.monitor.on_exit(now, -6)


def test_a_crash_that_comes_a_while_after_its_packet_is_confirmed():
    """Trial (a controller of my own, built with UBSan, whose switch loop never ends on -1 until
    its counter overflows, some 1.5 s later): each crash was replayed, waited for 0.5 s, and left
    unreproduced; the run said 0 findings and exited 0."""
    replay = Replay([Sent(0.0, b"VRPI", b"VRPI", 0.0, True)])
    assert trial(_SlowDeath(1.5), replay, CRASH) is not None           # type: ignore[arg-type]
    start = time.time()
    assert trial(_SlowDeath(None), replay, CRASH) is None              # type: ignore[arg-type]
    assert time.time() - start < 1.0, "a controller that goes on sending VRPO is not waited for"


def test_a_valid_twin_that_triggers_too_is_said_and_no_field_is_blamed(runner):
    """Trial: a VRAO for a command never sent answered every VRAI, yet the finding was 'VRAI
    header origin=0x0' minimised to 5 differences: the minimiser took it that the twin does not
    trigger, and replaying valid_hex triggered too."""
    twin = M.build(C.PacketType.VRAI, 7, {"command_id": 40})
    mutated = M.build(C.PacketType.VRAI, 7, {"command_id": 40}, header={"origin": 0})
    case = K.Case(6, "vrai-fields", "VRAI header origin=0x0")
    sent = [Sent(0.0, mutated, twin, 0.0, False)]
    runner.records[6] = (case, sent)
    runner._trial = lambda replay, t: t                # every VRAI draws the bogus VRAO
    trig = Trigger("malformed_output", 0.0, "VRAO for command ID 40, never sent", suspects=[6],
                   kind="VRAO unknown")
    kept, shown, small, complete = runner._minimize(trig, case, sent)
    runner._write(trig, 6, 6, case.family, case.description, kept, shown, small, complete, case, [])
    finding = runner.findings[0]
    assert finding.valid_triggers and finding.differences == 0
    assert finding.packet_hex == finding.valid_hex == twin.hex() and finding.original_hex == mutated.hex()
    assert [step["hex"] for step in finding.steps] == [twin.hex()]


def test_a_valid_twin_that_does_not_trigger_leaves_the_fields_to_the_minimiser(runner):
    twin = M.build(C.PacketType.VRAI, 7, {"command_id": 40})
    mutated = M.build(C.PacketType.VRAI, 7, {"command_id": 40}, header={"origin": 0})
    case = K.Case(6, "vrai-fields", "VRAI header origin=0x0")
    sent = [Sent(0.0, mutated, twin, 0.0, False)]
    runner._trial = lambda replay, t: t if replay.packets[0].data[6] == 0 else None   # origin 0 does it
    trig = Trigger("malformed_output", 0.0, "VRAI origin", suspects=[6], kind="x")
    runner._write(trig, 6, 6, case.family, case.description, *runner._minimize(trig, case, sent), case, [])
    finding = runner.findings[0]
    assert not finding.valid_triggers and bytes.fromhex(finding.packet_hex)[6] == 0
    assert finding.differences == 5, "one origin byte and the CRC"


def test_a_stall_whose_culprit_is_past_the_replayed_suspects_is_bisected(runner):
    """Trial (a controller of my own that hangs on a VRPI one byte longer than its layout): at 100
    cases/s the VRPO cycles around the silence held some 40 cases, the VRPI was not among the 12
    replayed one by one, and the stall was left unreproduced."""
    for i in range(40):
        vrpi = M.build(C.PacketType.VRPI, i, M.ARMED_VRPI)
        runner.records[i] = (K.generate(1, i), [Sent(0.0, vrpi, vrpi, 0.0, True)])
    culprit = runner.records[25][1][0].data
    runner._trial = lambda replay, t: t if culprit in [p.data for p in replay.packets] else None
    nearest = [20, 19, 21, 18, 22, 17, 23, 16, 24, 15, 14, 13] + [25] + list(range(26, 40)) + list(range(13))
    runner._investigate(Trigger(STALL, 0.0, "no VRPO for 2003 ms", suspects=nearest))
    assert not runner.unreproduced
    [finding] = runner.findings
    assert finding.oracle == STALL and finding.case_index == 25


def test_cases_whose_acks_a_crash_cut_short_are_played_again_once(runner):
    """Trial: a VRCI my controller never acked was judged by no one: it crashed on a later case
    before the ack timeout, the ack was dropped with the crash, and the case was not sent again."""
    for i in (35, 46):
        runner.records[i] = (K.generate(1, i), [])
    played: list[int] = []
    runner.session.run_steps = lambda index, *args: played.append(index) or []
    runner.session.monitor.cut_short = [35, 7]           # 7: no longer kept
    runner._judge_again()
    runner.session.monitor.cut_short = [35]              # cut short again: not played a third time
    runner._judge_again()
    assert played == [35] and runner.session.monitor.cut_short == []


def test_a_crash_s_progress_line_says_crash_once(runner):
    """Trial: 'vm110 fuzz: crash: crash SIGABRT ABRT in on_vrpi (ctl.c:73); replaying 49 suspect case(s)'."""
    said: list[str] = []
    runner.cfg.progress = said.append
    runner._trial = lambda replay, t: None
    runner._investigate(Trigger(CRASH, 0.0, "crash SIGSEGV in execute (ctl.c:83)", kind="SIGSEGV execute"))
    assert said[0] == "crash SIGSEGV in execute (ctl.c:83); observing the controller again"


def test_a_minimised_missing_ack_names_the_command_its_packets_leave_unacknowledged(runner):
    """Trial: the command ID wrap case (65534, 65535, 0, 1) was minimised to 65535 then 1, yet the
    finding said 'no VRAO for command ID 0' and showed the VRCI of 1: 0 was no longer sent."""
    ids = (0xFFFE, 0xFFFF, 0, 1)
    vrci = {cid: M.build(C.PacketType.VRCI, n, M.default_fields(C.PacketType.VRCI, cid)) for n, cid in enumerate(ids)}
    sent = [Sent(0.0, vrci[cid], vrci[cid], 20.0, True) for cid in ids]

    def trial(replay: Replay, trig: Trigger) -> Optional[Trigger]:
        """My controller: an ID not above the last one is taken for a repeat and the last one acked."""
        played = [cid for cid in ids if vrci[cid] in {p.data for p in replay.packets}]
        owed = [cid for n, cid in enumerate(played) if n and cid <= played[n - 1]]
        return Trigger(MISSING_ACK, 0.0, f"no VRAO for command ID {owed[0]} within 1000 ms",
                       command_id=owed[0]) if owed else None
    runner._trial = trial
    trig = Trigger(MISSING_ACK, 0.0, "no VRAO for command ID 0 within 1000 ms", case_index=9, command_id=0)
    kept, shown, _, complete = runner._minimize(trig, K.Case(9, "sequence", "command ID wrap"), sent)
    assert [p.data for p in kept] == [vrci[0xFFFF], vrci[1]] and complete
    assert shown is not None and shown.data == vrci[1]
    assert (trig.command_id, trig.detail) == (1, "no VRAO for command ID 1 within 1000 ms")


def test_status_line_counts_as_the_summary_does_in_the_singular(capsys):
    """Trial: the status line read '1 bugs (1 hits)', the summary '1 findings (1 triggers)': two
    names for one count. Both now say findings and triggers."""
    from vm110.commands.fuzz import _StatusLine
    _StatusLine()({"cases": 1, "rate": 1.0, "rate_now": 1.0, "findings": 1, "triggers": 1, "left_s": None})
    assert "1 case, 1/s (average 1/s), 1 finding (1 trigger)" in capsys.readouterr().err
    _StatusLine()({"cases": 2, "rate": 1.0, "rate_now": 1.0, "findings": 2, "triggers": 0, "left_s": None})
    assert "2 cases, 1/s (average 1/s), 2 findings (0 triggers)" in capsys.readouterr().err


def _filtered_frames(display_filter: str) -> set[int]:
    """The frame numbers of `frame.number == n` or `frame.number in {a, b..c}`."""
    if display_filter.startswith("frame.number == "):
        return {int(display_filter.split("== ")[1])}
    frames: set[int] = set()
    for part in display_filter.removeprefix("frame.number in {").removesuffix("}").split(", "):
        first, _, last = part.partition("..")
        frames.update(range(int(first), int(last or first) + 1))
    return frames


def test_a_crash_made_by_a_case_s_stream_is_confirmed_among_several_suspects(runner):
    """Trial (a Python controller that divides by the battery): 'VRCI while the base unit is
    disarmed' streams VRPI with ru_battery 0; with 7 cases since the controller last spoke they were
    bisected as their packets alone, without that stream, and the crash was left unreproduced."""
    disarmed = next(i for i in range(len(K.sweep(1))) if K.generate(1, i).stream == M.DISARMED_VRPI)
    suspects = list(range(disarmed - 6, disarmed + 1))
    for i in suspects:
        case = K.generate(1, i)
        runner.records[i] = (case, [Sent(0.0, *step.build(n), step.delay_ms, step.expect_ack)
                                    for n, step in enumerate(case.steps)])

    def controller(replay: Replay, trig: Trigger) -> Optional[Trigger]:
        """Dies on a VRPI with ru_battery 0: what the base unit streams during the replay."""
        played = getattr(replay, "parts", None) or [replay]     # (cases played in turn)
        return trig if any(p.stream is not None and p.stream.get("ru_battery", 0) == 0 for p in played) else None
    runner._trial = controller
    runner._minimize = lambda trig, case, sent: (sent, sent[-1] if sent else None, None, True)
    runner.session.traffic = []
    runner._investigate(Trigger(CRASH, time.time(), "crash exit 1 ZeroDivisionError in on_vrpi (bugs.py:116)",
                                suspects=suspects, kind="exit 1 python:ZeroDivisionError on_vrpi"))
    assert not runner.unreproduced
    [finding] = runner.findings
    assert finding.case_index == disarmed and finding.stream == M.DISARMED_VRPI


def test_a_crash_that_needs_two_cases_keeps_each_case_s_stream_and_replays_it(runner, tmp_path):
    """Review: a crash bisected to two cases (the disarmed stream of one, then another's packet)
    was written with no case: its finding had no stream, and its replay sent the packets alone
    under the armed stream, which did not crash the controller."""
    from vm110.fuzz.findings import finding_from_json
    from vm110.fuzz.runner import finding_replay
    disarmed = next(i for i in range(len(K.sweep(1))) if K.generate(1, i).stream == M.DISARMED_VRPI)
    later = next(i for i in range(disarmed + 1, disarmed + 40) if len(K.generate(1, i).steps) >= 2)
    suspects = list(range(disarmed - 3, later + 3))
    for i in suspects:
        case = K.generate(1, i)
        runner.records[i] = (case, [Sent(0.0, *step.build(100 * i + n), step.delay_ms, step.expect_ack)
                                    for n, step in enumerate(case.steps)])
    fatal, arming = runner.records[later][1][-1].data, runner.records[disarmed][1][0].data

    def controller(replay: Replay, trig: Trigger) -> Optional[Trigger]:
        """Dies on `fatal` once a command came while the base unit was disarmed (the stream of an
        earlier case)."""
        played = replay.parts or [replay]
        primed = False
        for part in played:
            if primed and fatal in [p.data for p in part.packets]:
                return trig
            primed = primed or (part.stream == M.DISARMED_VRPI and arming in [p.data for p in part.packets])
        return None
    runner._trial = controller
    runner.session.traffic = [(time.time(), True, p.data, ("127.0.0.1", 1)) for i in suspects for p in runner.records[i][1]]
    trig = Trigger(CRASH, time.time(), "crash SIGSEGV in engage (ctl.c:9)", suspects=suspects, kind="SIGSEGV engage")
    runner._investigate(trig)
    [finding] = runner.findings
    assert finding.family == "sequence-of-cases"
    assert [(c["case_index"], c["stream"], c["packets"]) for c in finding.cases] == [
        (disarmed, M.DISARMED_VRPI, 1), (later, None, 1)], "each case with its stream and the packets it needs"
    assert [step["hex"] for step in finding.steps] == [arming.hex(), fatal.hex()] and finding.minimised
    path = runner.cfg.out / runner.files[0]
    read = finding_from_json(json.loads(path.read_text()), str(path))
    assert controller(finding_replay(read), trig) is trig, "the replay of the file crashes the controller again"
    frames = [p[2] for p in runner.session.traffic]
    both = {frames.index(p) + 1 for p in (arming, fatal)}
    assert _filtered_frames(read.display_filter) == both, "each case's packets"


def test_a_finding_whose_cases_do_not_add_up_to_its_steps_is_refused(tmp_path):
    from vm110.errors import CliError
    from vm110.fuzz.findings import Finding, finding_from_json
    step = {"hex": "00" * 20, "valid_hex": "00" * 20, "delay_ms": 0.0, "expect_ack": True}
    case = {"case_index": 1, "mutation": "x", "packets": 2, "pause_vrpi_ms": 0.0, "withhold_vrai_ms": 0.0,
            "stream": None, "settle_ms": 0.0}
    from dataclasses import asdict
    raw = asdict(Finding("crash", 1, 5, "sequence-of-cases", "x", "d", "00" * 20, "00" * 20, "00" * 20, 0, False,
                         [step], cases=[case]))
    with pytest.raises(CliError, match="add up to 2, not the 1 steps"):
        finding_from_json(raw, "f.json")
    raw["cases"][0]["stream"] = {"ru_battery": 1 << 40}
    with pytest.raises(CliError, match="does not fit"):
        finding_from_json(raw, "f.json")


def test_a_finding_made_by_a_case_s_stream_points_at_the_vrpi_streamed(runner):
    """Trial (a Python controller that divides by the battery): the finding of 'VRCI while the base
    unit is disarmed' pointed at its VRCI alone (frame.number == 192), a valid command; the VRPI with
    a battery of 0 that killed the controller was named nowhere."""
    from scapy.layers.inet import UDP
    from scapy.utils import PcapReader
    from vm110.decode import decode
    disarmed = next(i for i in range(len(K.sweep(1))) if K.generate(1, i).stream == M.DISARMED_VRPI)
    case = K.generate(1, disarmed)
    sent = [Sent(0.0, *step.build(30 + n), step.delay_ms, step.expect_ack) for n, step in enumerate(case.steps)]
    runner.records[disarmed] = (case, sent)
    peer = ("127.0.0.1", 1)
    now = time.time()
    streams = [M.build(C.PacketType.VRPI, 29, M.ARMED_VRPI), sent[0].data,
               M.build(C.PacketType.VRPI, 31, M.ARMED_VRPI), M.build(C.PacketType.VRPI, 32, M.DISARMED_VRPI),
               M.build(C.PacketType.VRPI, 33, M.DISARMED_VRPI)]
    runner.session.traffic = [(now, True, data, peer) for data in streams]
    runner._trial = lambda replay, t: t
    runner._investigate(Trigger(CRASH, now, "crash exit 1 ZeroDivisionError in on_vrpi (bugs.py:116)",
                                suspects=[disarmed], kind="exit 1 python:ZeroDivisionError on_vrpi@bugs.py:116"))
    [finding] = runner.findings
    assert finding.display_filter == "frame.number in {2, 4}"
    with PcapReader(str(runner.cfg.out / finding.pcap)) as reader:
        frames = [bytes(f[UDP].payload) for f in reader]
    assert decode(frames[3])["bu_state"] == M.DISARMED_VRPI["bu_state"] and frames[1] == sent[0].data


def test_the_status_line_shows_the_current_rate_beside_the_average(runner, monkeypatch, capsys):
    """Review: the status line's cases/s was the average since the start; a controller that slowed
    to 5 cases/s after a minute at 100 still showed 86/s. It shows the last 5 s' rate first."""
    import types

    from vm110.commands.fuzz import _StatusLine
    from vm110.fuzz import runner as R
    clock = [0.0]
    monkeypatch.setattr(R, "time", types.SimpleNamespace(time=lambda: clock[0]))
    lines: list[dict] = []
    runner.cfg.status = lines.append
    runner.started, runner.recent = 0.0, R.RecentRate(5.0, 0.0)
    for step in range(1, 141):       # a status every 0.5 s: 100 cases/s for 60 s, then 5/s for 10 s
        clock[0] = step * 0.5
        runner.cases_run += 50 if step <= 120 else 2 + step % 2
        runner._status()
    assert lines[-1]["rate_now"] == pytest.approx(5.0) and lines[-1]["rate"] == pytest.approx(6050 / 70)
    _StatusLine()(lines[-1])
    assert "6050 cases, 5/s (average 86/s)" in capsys.readouterr().err


def test_restarts_count_the_fuzzed_controller_s_not_the_replays(runner, monkeypatch):
    """Review: `restarts` was every start of the controller but the first, so a run whose controller
    never crashed said '3 restarts' (the starts of its replays). It now counts the restarts of the
    controller the run fuzzed (it died, hung or leaked), and `replay_starts` the others."""
    from types import SimpleNamespace

    from vm110.fuzz import runner as R
    supervisor = SimpleNamespace(starts=1, sanitizer_options={}, core_files=lambda: None)
    state = {"healthy": True}

    def restart() -> None:
        supervisor.starts += 1
        state["healthy"] = True

    runner.supervisor = supervisor
    monkeypatch.setattr(runner.session, "restart_target", restart)
    monkeypatch.setattr(runner.session, "healthy", lambda: state["healthy"])
    monkeypatch.setattr(R, "trial", lambda *args: None)
    replays = {MISSING_ACK: 2, CRASH: 1}
    monkeypatch.setattr(runner, "_investigate", lambda trig: [runner._trial(None, trig) for _ in
                                                               range(replays[trig.oracle])] != [])
    for oracle, healthy in ((MISSING_ACK, True), (CRASH, False)):   # a missing ack, then a crash
        state["healthy"] = healthy
        runner.session.monitor.triggers = [Trigger(oracle, 0.0, "x")]
        runner._investigate_all()
    summary = runner.summary()
    assert (summary["restarts"], summary["replay_starts"]) == (1, 4), "the crash; 3 replays and a clean start"
