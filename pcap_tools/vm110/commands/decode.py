"""Decode the EG-Link packets of a capture (pcap or pcapng), one line or JSON object each.

Datagrams on the configured ports, and on any UDP port when they start with a known packet ID,
are decoded with the fast path (`vm110.decode`); illegal ones are shown with their reasons.
Other traffic is skipped.
"""
from __future__ import annotations

import argparse
import contextlib
import json
from typing import Any, Iterator

from .. import constants as C
from ..capture.reader import CaptureReader, address
from ..capture.spool import stdin_spool
from ..crc import BYTE_ORDERS, VARIANTS
from ..decode import decode
from ..errors import CliError
from .options import INPUT_PORT, INPUT_PORT_HELP

_IDS = frozenset(t.value.encode() for t in C.PacketType)
_SUMMARY_FIELDS = {
    "VRPI": ("bu_state", "armed_ru", "ru_state", "ru_battery"),
    "VRPO": ("packet_number",),
    "VRCI": ("command_id",), "VRCO": ("command_id",),
    "VRAI": ("command_id",), "VRAO": ("command_id",),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="pcap or pcapng file; - reads standard input")
    parser.add_argument("--port", type=INPUT_PORT, default=C.INPUT_PORT, help=INPUT_PORT_HELP)
    parser.add_argument("--crc", choices=VARIANTS, default=VARIANTS[0], help="CRC variant")
    parser.add_argument("--crc-order", choices=BYTE_ORDERS, default=BYTE_ORDERS[0],
                        help="byte order of the stored CRC")
    parser.add_argument("--json", action="store_true", help="one JSON object per packet")


def eglink_datagrams(reader: CaptureReader, port: int) -> Iterator[tuple[int, float, str, bytes]]:
    """(frame number, time, source "ip:port", UDP payload) of each EG-Link datagram."""
    ports = {port, port + C.OUTPUT_PORT_OFFSET}
    for ts, src, sport, dport, payload, frame in reader:
        if sport in ports or dport in ports or payload[:C.ID_LEN] in _IDS:
            yield frame, ts, address(src, sport), payload


def _line(number: int, when: float, src: str, fields: dict[str, Any]) -> str:
    names = _SUMMARY_FIELDS.get(fields.get("type", ""), ())
    parts = [f"{number:>6} {when:.6f} {src:<21} {fields.get('type', '?'):<4} serial={fields.get('serial', '?')}"]
    parts += [f"{name}={fields[name]}" for name in names if name in fields]
    if fields["problems"]:
        parts.append("ILLEGAL(" + ",".join(fields["problems"]) + ")")
    if fields["warnings"]:
        parts.append("warn(" + ",".join(fields["warnings"]) + ")")
    return " ".join(parts)


def _jsonable(value: Any) -> Any:
    return value.hex() if isinstance(value, bytes) else value


def run(args: argparse.Namespace) -> int:
    count = 0
    with contextlib.ExitStack() as stack:
        reader = stack.enter_context(CaptureReader(stdin_spool(stack) if args.capture == "-" else args.capture))
        for number, when, src, data in eglink_datagrams(reader, args.port):
            fields = decode(data, args.crc, args.crc_order)
            count += 1
            if args.json:
                print(json.dumps({"frame": number, "time": when, "src": src,
                                  **{k: _jsonable(v) for k, v in fields.items()}}))
            else:
                print(_line(number, when, src, fields))
    if not args.json:
        print(f"{count} EG-Link packets")
    if reader.problem is not None:
        # Everything before the damage was printed; the damage is never passed over in silence.
        raise CliError(f"{args.capture}: damaged, read up to byte {reader.damage}: {reader.problem}")
    return 0
