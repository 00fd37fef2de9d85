"""Option value types and options that several subcommands share, so that each is declared once."""
from __future__ import annotations

import argparse

from .. import constants as C
from ..analysis.report import SCOPES
from ..crc import BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, VARIANTS
from ..numbers import number, port
from ..sim.reading import Reading

# The input port; the output port is this + 2, so it must be a port too.
INPUT_PORT = port(room_above=C.OUTPUT_PORT_OFFSET)
INPUT_PORT_HELP = (f"input port (output port is +{C.OUTPUT_PORT_OFFSET}), {INPUT_PORT.range_text}; "
                   f"default {C.INPUT_PORT}")
SEED = number(0, 2**64 - 1, integer=True)
VRPO_START = number(0, 1, integer=True)
VRPO_START_HELP = f"first VRPO packet number, {VRPO_START.range_text}; default 0"
AUTO = "auto"


def add_reading_options(parser: argparse.ArgumentParser, found: bool) -> None:
    """--crc, --crc-order and --serial-scope: the readings of TS-0006 that interpretation.md leaves
    open. `found`: the analysis can find each from the capture (`auto`, the default); a simulator
    sends one, by default interpretation.md's."""
    auto = (AUTO,) if found else ()
    parser.add_argument("--crc", choices=(*auto, *VARIANTS), default=AUTO if found else DEFAULT_VARIANT,
                        help="CRC variant; auto picks the one that validates most packets" if found
                        else f"CRC variant; default {DEFAULT_VARIANT}")
    parser.add_argument("--crc-order", choices=(*auto, *BYTE_ORDERS), default=AUTO if found else DEFAULT_BYTE_ORDER,
                        help="byte order of the stored CRC; default " + (AUTO if found else DEFAULT_BYTE_ORDER))
    scopes = SCOPES if found else tuple(s for s in SCOPES if s != AUTO)
    parser.add_argument("--serial-scope", choices=scopes, default=scopes[0],
                        help="one serial counter per sender or per packet type; auto picks per sender" if found
                        else f"one serial counter per sender or per packet type; default {scopes[0]}")


def reading_of(args: argparse.Namespace) -> Reading:
    """The reading the options of `add_reading_options(found=False)` and --vrpo-start give."""
    return Reading(args.crc, args.crc_order, args.serial_scope, args.vrpo_start)
