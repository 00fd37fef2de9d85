"""vm110: tools for the VM-110 EG-Link (TS-0006): scapy layers, fast decoding, CRC variants."""
from __future__ import annotations

from .crc import crc32, crc_bytes
from .decode import decode

__all__ = ["__version__", "crc32", "crc_bytes", "decode"]
__version__ = "0.1.0"
