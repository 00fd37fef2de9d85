"""The readings of TS-0006 that interpretation.md leaves open, as a simulated device speaks them."""
from __future__ import annotations

from dataclasses import dataclass

from ..crc import DEFAULT_BYTE_ORDER, DEFAULT_VARIANT


@dataclass(frozen=True)
class Reading:
    """The CRC variant and its byte order, one serial counter per sender or per packet type, the
    number of the first VRPO packet (`analyze`, `simulate` and `synth` take the same options);
    the defaults are interpretation.md's."""

    crc: str = DEFAULT_VARIANT
    crc_order: str = DEFAULT_BYTE_ORDER
    serial_scope: str = "sender"
    vrpo_start: int = 0

    def node_options(self) -> dict[str, str]:
        """The `Node` arguments of a device that speaks it (the controller's VRPO numbering aside)."""
        return {"crc": self.crc, "crc_order": self.crc_order, "serial_scope": self.serial_scope}
