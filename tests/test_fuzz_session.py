"""The base-unit role in-process against the reference controller on loopback: a VRPI stream that
keeps the controller in normal operation, one serial counter, only the target as destination,
multicast TTL 1 and the rate limit."""
from __future__ import annotations

import itertools
import sys
import socket
import struct
import time

import pytest

from vm110 import constants as C
from vm110.decode import decode
from vm110.fuzz import cases
from vm110.fuzz.runner import start_target
from vm110.fuzz.session import Session, Settings
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.realtime import RealtimeRunner
from vm110.sim.transport import UdpConfig, UdpTransport

RATE = 40.0


class Recorder:
    """Stands in for the fuzzer's socket and writes down every sendto."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.sent = sock, []

    def sendto(self, data: bytes, address: tuple[str, int]) -> int:
        self.sent.append((time.monotonic(), data, address))
        return self.sock.sendto(data, address)

    def __getattr__(self, name: str):
        return getattr(self.sock, name)


@pytest.fixture
def reference():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    listen = probe.getsockname()
    probe.close()
    ctl = Controller(ControllerConfig(command_every_s=0.5))
    transport = UdpTransport(UdpConfig(listen=("127.0.0.1", 0), dest=listen, source=("127.0.0.1", 0))).open()
    runner = RealtimeRunner([(ctl, transport)])
    runner.start_thread()
    yield ctl, transport.rx_address, listen
    runner.stop()


def test_base_unit_role(reference):
    ctl, target, listen = reference
    session = Session(Settings(target=target, listen=listen, rate=RATE))
    recorder = session.link.sock = Recorder(session.link.sock)
    assert session.link.sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == C.MULTICAST_TTL
    try:
        start_target(session)
        start = time.monotonic()
        case_packets = []
        for index in range(12):    # the sweep's first cases: no VRPI gaps among them
            case = cases.generate(1, index)
            assert not case.pause_vrpi_ms
            sent = session.run_steps(index, [(s.build, s.delay_ms, s.expect_ack) for s in case.steps],
                                     0.0, case.withhold_vrai_ms, case.stream, case.settle_ms)
            case_packets += [p.data for p in sent]
        session.pump(time.time() + 0.6)
        elapsed = time.monotonic() - start
    finally:
        session.close()
    assert {address for _, _, address in recorder.sent} == {target}
    serials = [struct.unpack_from("<H", data, 8)[0] for _, data, _ in recorder.sent]
    assert serials == list(range(serials[0], serials[0] + len(serials))), "one counter for all it sends"
    stream = [t for t, data, _ in recorder.sent if data not in case_packets and data[:4] == b"VRPI"]
    assert len(stream) >= elapsed * 1000 / C.VRPI_PERIOD_MS - 2
    gaps = [b - a for a, b in itertools.pairwise(stream)]
    assert max(gaps) < C.VRPI_WATCHDOG_MS / 1000, "no VRPI gap reaches the controller's watchdog"
    case_sends = [t for t, data, _ in recorder.sent if data in case_packets]
    assert len(case_sends) >= 12
    assert min(b - a for a, b in itertools.pairwise(case_sends)) >= 1 / RATE - 0.002, "rate limit"
    assert not ctl.events("vrpi_timeout"), "the stream kept the controller in normal operation"
    assert ctl.events("vrco_acked"), "VRCO answered with VRAI"
    legal_vrci = {struct.unpack_from("<H", d, C.PREFIX_LEN)[0] for d in case_packets
                  if d[:4] == b"VRCI" and not decode(d)["problems"]}
    handled = {e["command_id"] for e in ctl.events("executed") + ctl.events("refused") + ctl.events("repeat")}
    assert legal_vrci and legal_vrci <= handled


# A controller that says a last word when stopped: SIGTERM lands while a VRPO is due, and its loop
# sends it before it looks at the flag (the trial's ctl.py on a loaded machine).
_LAST_WORD = """
import signal, socket, sys, time
from vm110 import encode
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(("127.0.0.1", int(sys.argv[1])))
peer, serial, stop = ("127.0.0.1", int(sys.argv[2])), 0, []
signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
def vrpo():
    global serial
    sock.sendto(encode.packet("VRPO", encode.vrpo_payload(serial, b"x"), serial=serial), peer)
    serial += 1
while not stop:
    vrpo()
    time.sleep(0.05)
vrpo()
"""


def test_a_restart_by_the_fuzzer_starts_the_serials_afresh(tmp_path):
    """Trial (BUGS=hang_any,bogus_any): the last VRPO of the controller the fuzzer stopped was read
    after the monitor's reset, and the new process's first serial was 'VRPO serial 0 after 6', a
    malformed_output finding of the fuzzer's own restart."""
    from loopback import free_ports
    from vm110.fuzz.supervisor import Supervisor

    (tmp_path / "ctl.py").write_text(_LAST_WORD)
    rx, listen = free_ports(2)
    supervisor = Supervisor(f"{sys.executable} ctl.py {rx} {listen}", cwd=tmp_path)
    session = Session(Settings(("127.0.0.1", rx), ("127.0.0.1", listen), startup_s=10.0), supervisor, tmp_path)
    try:
        start_target(session)
        session.pump(time.time() + 0.3)
        session.restart_target()
        session.pump(time.time() + 0.2)
    finally:
        session.close()
    assert session.monitor.triggers == []
    assert sorted(session.monitor.serials.values()) and max(session.monitor.serials.values()) < 10, \
        "the new process's serials"


@pytest.mark.parametrize("ack", ["wrong_id", "bad_crc"])
def test_a_wrong_or_illegal_ack_does_not_stop_the_resends(ack):
    """Review: a VRAO with a wrong command ID (or a bad CRC) counted as the command's ack for the
    session, which stopped resending the VRCI; a base unit ignores such an ack and resends until
    its own VRAO comes (TS-0006 5.1.3, 5.1.5). Still one finding: the ack, not a missing ack too."""
    from loopback import free_ports
    from vm110 import encode

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    listen, = free_ports(1)
    session = Session(Settings(target=sink.getsockname(), listen=("127.0.0.1", listen)))
    recorder = session.link.sock = Recorder(session.link.sock)
    command = lambda serial: encode.packet("VRCI", encode.command_payload(0xFFFE), origin=0x0101, serial=serial)  # noqa: E731
    resends = lambda: sum(data[:4] == b"VRCI" for _, data, _ in recorder.sent) - 1   # noqa: E731
    ctl = ("127.0.0.1", 40000)
    try:
        t0 = session.send_case_packet(7, lambda serial: (command(serial), command(serial)), 0.0, True).time
        vrao = encode.packet("VRAO", encode.ack_payload(2 if ack == "wrong_id" else 0xFFFE), serial=1)
        session._on_rx(time.time(), vrao if ack == "wrong_id" else vrao[:-1] + bytes([vrao[-1] ^ 0xFF]), ctl)
        session.pump(t0 + 0.35)
        before = resends()
        session._on_rx(time.time(), encode.packet("VRAO", encode.ack_payload(0xFFFE), serial=2), ctl)
        session.pump(time.time() + 0.25)
        session.monitor.tick(t0 + 2 * session.settings.limits.ack_timeout_ms / 1000)
    finally:
        session.close()
        sink.close()
    assert before >= 2, "resent after the wrong ack"
    assert resends() == before, "not resent after its own ack"
    assert [t.oracle for t in session.monitor.triggers] == ["malformed_output"]
