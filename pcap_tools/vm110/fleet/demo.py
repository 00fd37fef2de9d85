"""A synthetic fleet for `make fleet-demo` and the tests: 10 machines at 4 sites, 4 captures each
a week apart (`vm110 synth` scenarios and seeds), laid out as `sites/<site>/<machine>/*.pcap`
with a sidecar giving the base unit firmware. Planted: two machines with lossy links, one
whose base unit stalls (controller watchdog), one whose commands fail; one capture cut short.

    python -m vm110.fleet.demo OUT_FOLDER
"""
from __future__ import annotations

import json
import os
import shutil
import struct
import sys

from ..fileio import write_bytes, write_text
from ..jsonin import loads
from ..synth import synthesize
from .dataset import FORMAT, FORMAT_VERSION, MANIFEST

# site, machine, scenario, duration (s; None: the scenario's), base unit firmware
MACHINES = (
    ("north", "crane-01", "normal", 8.0, "3.2"),
    ("north", "crane-02", "disarmed", 8.0, "3.2"),
    ("north", "crane-03", "loss", 10.0, "3.4"),
    ("south", "crane-04", "normal", 8.0, "3.2"),
    ("south", "crane-05", "controller-watchdog", None, "3.4"),
    ("south", "crane-06", "normal", 8.0, "3.4"),
    ("east", "crane-07", "disarmed", 8.0, "3.2"),
    ("east", "crane-08", "retransmit", None, "3.2"),
    ("west", "crane-09", "normal", 8.0, "3.2"),
    ("west", "crane-10", "loss", 10.0, "3.4"),
)
BAD_LINKS = ("crane-03", "crane-05", "crane-10")
FAILING_COMMANDS = ("crane-08",)
WATCHDOG = ("crane-05",)
DAMAGED = ("east", "crane-07", 3)       # its 4th capture is cut in the middle of a record
WEEKS = 4
WEEK_S = 7 * 86400
SYNTH_START = 1_750_000_000                       # where `vm110 synth` captures begin
FIRST_DAY = 1_748_822_400                         # 2025-06-02 00:00 UTC, a Monday
_PCAP_LE = (0xA1B2C3D4, 0xA1B23C4D)


def shift_pcap(data: bytes, seconds: int) -> bytes:
    """The little-endian pcap `data` with every record `seconds` later."""
    if struct.unpack_from("<I", data)[0] not in _PCAP_LE:
        raise ValueError("not a little-endian pcap")
    out = bytearray(data)
    pos = 24
    while pos + 16 <= len(out):
        sec, _, incl, _ = struct.unpack_from("<IIII", out, pos)
        struct.pack_into("<I", out, pos, sec + seconds)
        pos += 16 + incl
    return bytes(out)


def captures(root: str) -> list[str]:
    """Write the fleet under `root`; returns the capture paths."""
    written = []
    for index, (site, machine, scenario, duration, firmware) in enumerate(MACHINES):
        folder = os.path.join(root, "sites", site, machine)
        os.makedirs(folder, exist_ok=True)
        for week in range(WEEKS):
            start = FIRST_DAY + week * WEEK_S + index * 3600 + 8 * 3600
            path = os.path.join(folder, f"{machine}-w{week + 1}.pcap")
            synthesize(scenario, path, seed=100 * index + week + 1, duration_s=duration, fmt="pcap")
            os.remove(path + ".truth.json")      # the demo's captures come without their truth
            with open(path, "rb") as f:
                data = shift_pcap(f.read(), start - SYNTH_START)
            if (site, machine, week) == DAMAGED:
                data = data[:len(data) * 2 // 3 + 7]
            write_bytes(path, data)
            write_text(path + ".meta.json", json.dumps({"bu_firmware": firmware, "scenario": scenario}) + "\n")
            written.append(path)
    return written


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m vm110.fleet.demo OUT_FOLDER", file=sys.stderr)
        return 2
    paths = captures(argv[0])
    print(f"wrote {len(paths)} captures of {len(MACHINES)} machines under {argv[0]}/sites")
    _drop_older_dataset(os.path.join(argv[0], "dataset"))
    return 0


def _drop_older_dataset(path: str) -> None:
    """The demo's own dataset of an older format (a vm110 before) cannot take the new build: the
    demo builds it afresh. Only a folder whose manifest says it is a fleet dataset goes."""
    try:
        with open(os.path.join(path, MANIFEST), "rb") as f:
            doc = loads(f.read())
    except (OSError, ValueError):
        return
    if isinstance(doc, dict) and doc.get("format") == FORMAT and doc.get("format_version") != FORMAT_VERSION:
        shutil.rmtree(path)
        print(f"removed the demo's dataset of format version {doc.get('format_version')!r} at {path}: built afresh")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
