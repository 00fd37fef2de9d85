"""Decode the EG-Link packets of a capture (pcap or pcapng), one line or JSON object each.

Datagrams on the configured ports, and on any UDP port when they start with a known packet ID,
are decoded with the fast path (`vm110.decode`); illegal ones are shown with their reasons.
Other traffic is skipped. Enumerations show their names beside the numbers, as in the dissector
("Armed (0x11)"); times are ISO 8601 UTC and seconds from the capture's first packet.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import string
import sys
from typing import Any, Iterator, Optional

from .. import constants as C
from .. import protocol as P
from ..capture import linktypes as L
from ..capture.linktypes import unread
from ..capture.reader import CaptureError, CaptureReader, address
from ..capture.spool import as_given, stdin_spool
from ..crc import BYTE_ORDERS, VARIANTS
from ..decode import decode
from ..errors import CliError
from ..printable import escaped
from ..timefmt import since, utc_iso
from ..words import plural
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
    parser.add_argument("--hex", action="store_true",
                        help="CAPTURE is one UDP payload in hex instead (Wireshark's Copy as Hex Stream; spaces "
                             "and colons between bytes allowed); - reads one payload a line from standard input")
    parser.add_argument("--port", type=INPUT_PORT, default=C.INPUT_PORT, help=INPUT_PORT_HELP)
    parser.add_argument("--crc", choices=VARIANTS, default=VARIANTS[0], help="CRC variant")
    parser.add_argument("--crc-order", choices=BYTE_ORDERS, default=BYTE_ORDERS[0],
                        help="byte order of the stored CRC")
    parser.add_argument("--json", action="store_true", help="one JSON object per packet")


def eglink_datagrams(reader: CaptureReader, port: int) -> Iterator[tuple[int, float, str, bytes]]:
    """(frame number, time, source "ip:port", UDP payload) of each EG-Link datagram; UDP tunnels
    are counted in the reader's `tunnelled`, as the analysis counts them."""
    ports = {port, port + C.OUTPUT_PORT_OFFSET}
    for ts, src, sport, dport, payload, frame in reader:
        if payload is not None and (sport in ports or dport in ports or payload[:C.ID_LEN] in _IDS):
            yield frame, ts, address(src, sport), payload
        else:
            reader.tunnelled += dport in L.TUNNEL_PORTS


def unread_notes(reader: CaptureReader) -> list[str]:
    """What the reader passed over that may carry EG-Link packets, which `vm110 dissect` reads: frames
    of link types it does not read, IP fragments of datagrams never whole (the others are
    reassembled, as Wireshark does) and tunnels (not unwrapped)."""
    instead = "`vm110 dissect` reads what Wireshark reads"
    notes = [unread(reader.unknown_link, reader.link_types, instead)] if reader.unknown_link else []
    if reader.fragments:
        notes.append(f"{plural(reader.fragments, 'IP fragment')} of datagrams never whole: EG-Link packets in them are "
                     f"not decoded ({instead})")
    if reader.tunnelled:
        notes.append(f"{plural(reader.tunnelled, 'frame')} of tunnels not unwrapped (IP in IP, GRE with ERSPAN, "
                     f"VXLAN, GENEVE): EG-Link packets in them are not decoded ({instead})")
    return notes


def enum_name(name: str, value: int) -> str:
    """The name of an enumerated field's value, "Unknown" beyond the enumeration (as the dissector)."""
    names = P.ENUM_FIELDS[name]
    return names.get(value, "Unknown")


def enum_text(name: str, value: int) -> str:
    """The dissector's form of an enumerated value: "Armed (0x11)", "Unknown (0x07)"."""
    return f"{enum_name(name, value)} (0x{value:02x})"


def _value(name: str, value: Any) -> str:
    if name in P.ENUM_FIELDS:
        return enum_text(name, value)
    return f"0x{value:04X}" if name == "armed_ru" else str(value)


def _text(fields: dict[str, Any]) -> str:
    """A decoded datagram in words: type, serial, the type's main fields, why it is illegal, warnings."""
    names = _SUMMARY_FIELDS.get(fields.get("type", ""), ())
    ptype = escaped(fields.get("type", "?"))   # off the network: ESC [ 2 J cleared the screen, a CR LF forged a line
    parts = [f"{ptype:<4} serial={fields.get('serial', '?')}"]
    parts += [f"{name}={_value(name, fields[name])}" for name in names if name in fields]
    if fields["problems"]:
        parts.append("ILLEGAL(" + ",".join(fields["problems"]) + ")")
    if fields["warnings"]:
        parts.append("warn(" + ",".join(fields["warnings"]) + ")")
    return " ".join(parts)


def _line(number: int, when: float, start: float, src: str, fields: dict[str, Any]) -> str:
    return f"{number:>6} {utc_iso(when)} {since(when, start):>12} {src:<21} {_text(fields)}"


def _jsonable(value: Any) -> Any:
    return value.hex() if isinstance(value, bytes) else value


def _decoded(fields: dict[str, Any]) -> dict[str, Any]:
    """The decoded fields as JSON takes them, and each enum's name (`names`)."""
    names = {k: enum_name(k, v) for k, v in fields.items() if k in P.ENUM_FIELDS}
    return {**{k: _jsonable(v) for k, v in fields.items()}, "names": names}


def _json(number: int, when: float, start: float, src: str, fields: dict[str, Any]) -> str:
    """The decoded fields, plus the time in both readable forms and each enum's name (`names`)."""
    return json.dumps({"frame": number, "time": when, "time_utc": utc_iso(when),
                       "time_relative": round(when - start, 6), "src": src, **_decoded(fields)})


def datagram_of(text: str, where: str) -> bytes:
    """The bytes a line of hex gives (Wireshark's Copy as Hex Stream, or bytes apart by spaces or
    colons); CliError naming `where` for anything else, since a datagram is never guessed at (the
    texts are shown through repr: a control character in them reaches no terminal)."""
    digits = "".join(text.replace(":", " ").split())
    shown = repr(text.strip() if len(text.strip()) <= 40 else text.strip()[:40] + "...")
    bad = next((c for c in digits if c not in string.hexdigits), None)
    if bad is not None:
        raise CliError(f"{where}: {shown} is not hex ({bad!r} is no hex digit)")
    if len(digits) % 2:
        raise CliError(f"{where}: {shown} is not hex (an odd number of digits, {len(digits)}: half a byte)")
    if not digits:
        raise CliError(f"{where}: no bytes given")
    return bytes.fromhex(digits)


def _hex_lines(given: str) -> Iterator[tuple[str, str]]:
    """(where, text) of each datagram given in hex: the argument, or each line of standard input
    that is not blank (bytes that are no text are no hex digits: said, not a traceback)."""
    if given != "-":
        yield "--hex", given
        return
    lines = 0
    for number, raw in enumerate(sys.stdin.buffer, 1):
        text = raw.decode("latin-1")
        if text.strip():
            lines += 1
            yield f"standard input, line {number}", text
    if not lines:
        raise CliError("standard input: empty, no datagram in hex")


def run_hex(args: argparse.Namespace) -> int:
    """`--hex`: each datagram given in hex, decoded and printed as a capture's are, numbered."""
    count = 0
    for where, text in _hex_lines(args.capture):
        fields = decode(datagram_of(text, where), args.crc, args.crc_order)
        count += 1
        print(json.dumps({"datagram": count, **_decoded(fields)}) if args.json else f"{count:>6} {_text(fields)}")
    if not args.json:
        print(plural(count, "EG-Link packet"))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.hex:
        return run_hex(args)
    count = 0
    start: Optional[float] = None
    with contextlib.ExitStack() as stack:
        path = stdin_spool(stack) if args.capture == "-" else args.capture
        try:
            reader = stack.enter_context(CaptureReader(path))
        except CaptureError as exc:
            raise CliError(as_given(str(exc), path, args.capture)) from None
        for number, when, src, data in eglink_datagrams(reader, args.port):
            if start is None:     # the capture's first packet, EG-Link or not
                start = reader.first_ts if reader.first_ts is not None else when
            fields = decode(data, args.crc, args.crc_order)
            if fields["problems"] and number in reader.snap_truncated:
                fields["problems"] = [C.Problem.TRUNCATED.value]    # the capture cut it: nothing else is judged
            count += 1
            print((_json if args.json else _line)(number, when, start, src, fields))
    if not args.json:
        print(plural(count, "EG-Link packet"))
    for note in unread_notes(reader):    # (else "0 EG-Link packets" would read as a capture without any)
        print(f"vm110 decode: {note}", file=sys.stderr)
    if reader.problem is not None:
        # Everything before the damage was printed; the damage is never passed over in silence.
        raise CliError(as_given(f"{path}: damaged, read up to byte {reader.damage}: {reader.problem}", path,
                                args.capture))
    return 0
