"""Write a capture with one crafted packet of each EG-Link type (a sampler for Wireshark).

The packets go from a base unit (10.0.0.10) and a controller (10.0.0.20) to the default multicast
group, as a network tap would see them: well-formed traffic, each command followed by its
acknowledgement. Nothing is sent anywhere.
"""
from __future__ import annotations

import argparse
import sys

from scapy.layers.inet import IP, UDP
from scapy.layers.l2 import Ether

from .. import constants as C
from ..capture.writer import format_of, open_writer
from ..fileio import atomic_writer
from ..layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO

BU_ADDR, CONTROLLER_ADDR = "10.0.0.10", "10.0.0.20"
GROUP_MAC = "01:00:5e:7f:2a:14"  # 239.255.42.20 mapped to Ethernet multicast


# Each acknowledgement this long after its command: well inside the 100 ms resend interval, so
# the sampler is well-formed traffic that `vm110 analyze` passes (the 100 ms steps keep it readable).
ACK_AFTER_S = 0.02


def sample_packets() -> list:
    """One packet of each type, with typical values, spaced out in time; each command before its
    acknowledgement (Wireshark pairs them: no [Ack Without Command])."""
    bu = (BU_ADDR, C.INPUT_PORT, 0x0101)
    controller = (CONTROLLER_ADDR, C.OUTPUT_PORT, 0)
    step = C.COMMAND_RESEND_MS / 1000
    timeline = [
        (0.0, bu, VRPI(bu_state=C.BuState.ARMED, vlaps=1, eg_link=1, ec_link=1, c_link=1, armed_ru=0x0C07,
                       ru_state=C.RuState.ENABLED, ru_battery=88, ru_rssi=76, joystick1=250, joystick2=-400,
                       switch1=1, switch3=-1, encoder=200)),
        (step, controller, VRPO(packet_number=0, periodic_data=bytes(range(64)))),
        (2 * step, bu, VRCI(command_id=17, command_data=b"START PUMP".ljust(C.COMMAND_DATA_LEN, b"\0"))),
        (2 * step + ACK_AFTER_S, controller, VRAO(command_id=17)),
        (3 * step, controller, VRCO(command_id=3, command_data=b"ALARM HIGH LOAD".ljust(C.COMMAND_DATA_LEN, b"\0"))),
        (3 * step + ACK_AFTER_S, bu, VRAI(command_id=3)),
    ]
    serials: dict[str, int] = {}      # one counter per sender
    frames = []
    for offset, (addr, port, origin), payload in timeline:
        serial = serials[addr] = serials.get(addr, -1) + 1
        frame = _frame(addr, port, VM110(origin=origin, serial=serial) / payload)
        frame.time = 1_700_000_000 + offset
        frames.append(frame)
    return frames


def _frame(src: str, port: int, packet):
    return (Ether(dst=GROUP_MAC) / IP(src=src, dst=C.MULTICAST_GROUP, ttl=C.MULTICAST_TTL)
            / UDP(sport=port, dport=port) / packet)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True,
                        help="capture file to write (pcapng when it ends in .pcapng, else pcap), through a "
                             "temporary file renamed into place; - writes pcap to standard output "
                             "(vm110 craft --out - | vm110 dissect -)")


def run(args: argparse.Namespace) -> int:
    frames = sample_packets()
    records = ((round(frame.time * 1_000_000), bytes(frame)) for frame in frames)
    if args.out == "-":     # (as `-` everywhere else: a file named "-" is a surprise in the current folder)
        with open_writer(sys.stdout.buffer, "pcap") as writer:
            writer.write_many(records)
        print(f"wrote {len(frames)} packets to standard output", file=sys.stderr)
        return 0
    with atomic_writer(args.out) as stream, open_writer(stream, format_of(args.out)) as writer:
        writer.write_many(records)
    print(f"wrote {len(frames)} packets to {args.out}")
    return 0
