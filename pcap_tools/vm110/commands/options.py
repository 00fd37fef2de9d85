"""Option value types that several subcommands share, so that each is declared once."""
from __future__ import annotations

from .. import constants as C
from ..numbers import number, port

# The input port; the output port is this + 2, so it must be a port too.
INPUT_PORT = port(room_above=C.OUTPUT_PORT_OFFSET)
INPUT_PORT_HELP = (f"input port (output port is +{C.OUTPUT_PORT_OFFSET}), {INPUT_PORT.range_text}; "
                   f"default {C.INPUT_PORT}")
SEED = number(0, 2**64 - 1, integer=True)
