"""Crafting captures with known impairments for the analysis tests (and checks of the crafting).

`Traffic` collects frames (time, source, ports, EG-Link bytes built with the scapy layers) and
writes them with the project's fast capture writer; the tests know exactly what they put in.
"""
from __future__ import annotations

import struct

from scapy.layers.inet import UDP
from scapy.layers.l2 import Ether
from scapy.utils import rdpcap

from vm110 import constants as C
from vm110.capture.writer import UdpFlow, open_writer
from vm110.layers import VM110, VRAI, VRAO, VRCO, VRPI, VRPO, crc_settings

BU, CTRL, GROUP = "10.0.0.10", "10.0.0.20", C.MULTICAST_GROUP
BU_ORIGIN = 0x0101
T0 = 1_700_000_000.0


def payload(cls, serial: int, origin: int = 0, variant: str = "mpeg2", order: str = "little", **fields) -> bytes:
    """EG-Link bytes from the scapy layers; header fields (revision, size, crc, spare) may be forced."""
    head = {k: fields.pop(k) for k in ("revision", "size", "crc", "spare") if k in fields}
    with crc_settings(variant, order):
        return bytes(VM110(origin=origin, serial=serial, **head) / cls(**fields))


def vrpi(serial: int, origin: int = BU_ORIGIN, **fields) -> bytes:
    fields.setdefault("bu_state", C.BuState.ARMED)
    return payload(VRPI, serial, origin, **fields)


class Traffic:
    """Frames to write; times in seconds after T0."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, str, int, int, bytes]] = []

    def add(self, t: float, data: bytes, src: str = BU, sport: int = C.INPUT_PORT,
            dport: int | None = None) -> int:
        """Add one datagram; returns its frame number (1-based, after sorting by time)."""
        self.frames.append((T0 + t, src, sport, sport if dport is None else dport, data))
        return len(self.frames)

    def write(self, path, fmt: str = "pcap") -> list[tuple]:
        """Write in the order added (so frames may go back in time on purpose)."""
        flows: dict = {}
        with open(path, "wb") as out, open_writer(out, fmt) as writer:
            for t, src, sport, dport, data in self.frames:
                flow = flows.setdefault((src, sport, dport), UdpFlow(src, sport, GROUP, dport))
                writer.write(round(t * 1_000_000), flow.frame(data))
        return self.frames


def test_crafted_frames_read_back_with_scapy(tmp_path):
    traffic = Traffic()
    traffic.add(0.0, vrpi(7, joystick1=-5))
    traffic.add(0.1, payload(VRCO, 3, command_id=9), src=CTRL, sport=C.OUTPUT_PORT)
    traffic.add(0.2, payload(VRPO, 4, packet_number=0, periodic_data=b"x" * 10), src=CTRL, sport=C.OUTPUT_PORT)
    traffic.add(0.3, payload(VRAO, 5, command_id=1, crc=0), src=CTRL, sport=C.OUTPUT_PORT)
    traffic.add(0.4, payload(VRAI, 8, BU_ORIGIN, command_id=9))
    traffic.write(tmp_path / "c.pcap")
    frames = rdpcap(str(tmp_path / "c.pcap"))
    assert [round(float(f.time) - T0, 6) for f in frames] == [0.0, 0.1, 0.2, 0.3, 0.4]
    first = frames[0][VM110]
    assert (first.serial, first.origin, first[VRPI].joystick1, first.crc_ok()) == (7, BU_ORIGIN, -5, True)
    assert frames[1][VRCO].command_id == 9 and frames[1][UDP].sport == C.OUTPUT_PORT
    assert len(frames[2][VRPO].periodic_data) == 10
    assert frames[3][VM110].crc == 0 and not frames[3][VM110].crc_ok()
    # Ethernet padding follows short datagrams; the UDP length still bounds the payload.
    assert len(bytes(frames[4][Ether])) >= 60
    assert struct.unpack("!H", bytes(frames[4][UDP])[4:6])[0] == 8 + len(payload(VRAI, 8, BU_ORIGIN, command_id=9))
