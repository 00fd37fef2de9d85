"""One simulated base unit per origin and source address on an EG-Link, on this machine.

Two `simulate bu` of one origin sending from one address and port (the specification's set-up:
the interface's port 5825, shared with the controller's group socket on one machine) to one group
or peer start without a word, but to the controller they are one BU whose serials interleave and
whose state flips between the two: a misconfiguration it cannot even see (BUs of one origin from
two sources it tells apart: `origin_shared`). Each BU sending from a fixed port claims its
(destination, source, origin) with a Linux abstract Unix socket, which the kernel frees when the
process ends however it ends (no lock file left behind), and which is private to the network
namespace, as the EG-Link's sockets are.
"""
from __future__ import annotations

import errno
import hashlib
import socket
from typing import Optional

from ..errors import CliError
from .transport import Address


def claim_origin(dest: Address, source: Address, origin: int) -> Optional[socket.socket]:
    """The claim to send as `origin` from `source` to `dest`, held until the socket is closed;
    CliError when another simulated BU holds it. None where abstract sockets do not exist (not Linux):
    nothing is checked there."""
    # (hashed: an abstract name has at most 107 bytes, two IPv6 addresses may not fit)
    what = f"from {source[0]}:{source[1]} to {dest[0]}:{dest[1]} as origin 0x{origin:04x}"
    name = "\0vm110 simulate bu " + hashlib.sha256(what.encode()).hexdigest()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(name)
    except OSError as exc:
        sock.close()
        if exc.errno != errno.EADDRINUSE:
            return None
        raise CliError(f"another simulated base unit on this machine already sends as origin 0x{origin:04x} from "
                       f"{source[0]}:{source[1]} to {dest[0]}:{dest[1]}: the controller cannot tell two BUs of one "
                       "origin from one address apart (their serials interleave); give each its own --origin") from None
    return sock
