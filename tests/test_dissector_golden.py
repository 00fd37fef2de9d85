"""Golden `tshark -V -O vm110` output of a small capture with one packet of each kind, on both tshark
versions. Only the vm110 part of each frame is compared (with the frame number), so that changes in
how Wireshark prints Ethernet, IP or UDP between versions do not matter.

Regenerate after an intended change: `make golden` (runs this file as a script).
"""
from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

import pytest

import tshark_runner as T
from vm110 import constants as C
from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
CAPTURE = GOLDEN_DIR / "vm110-sample.pcap"
EXPECTED = GOLDEN_DIR / "vm110-sample.txt"


def sample_packets() -> list[bytes]:
    """One packet of each type, then warnings and every kind of illegal packet."""
    armed = VRPI(bu_state=C.BuState.ARMED, vlaps=1, eg_link=1, ec_link=1, c_link=1, armed_ru=0x0C07,
                 ru_state=C.RuState.ENABLED, ru_battery=88, ru_rssi=76, joystick1=250, joystick2=-400,
                 switch1=1, switch3=-1, encoder=200)
    vrpi = bytes(VM110(origin=0x0101, serial=1) / armed)
    revision = bytearray(vrpi)
    revision[4:6] = struct.pack("<H", 1)
    return [
        vrpi,
        bytes(VM110(origin=0x0101, serial=2, spare=1) / VRPI(
            bu_state=C.BuState.STOPPED, unarmed_rus=2, ru_cable=5, joystick1=1200, vrpi_spare=b"\x01" + bytes(5))),
        bytes(VM110(serial=3) / VRPO(packet_number=0, periodic_data=bytes(range(64)))),
        bytes(VM110(origin=0x0101, serial=4) / VRCI(command_id=17, command_data=b"START PUMP".ljust(16, b"\0"))),
        bytes(VM110(serial=5) / VRAO(command_id=17)),
        bytes(VM110(origin=7, serial=6) / VRCO(command_id=3, command_data=b"ALARM".ljust(16, b"\0"))),
        bytes(VM110(origin=0x0101, serial=7) / VRAI(command_id=3)),
        vrpi[:-1] + bytes([vrpi[-1] ^ 0xFF]),                                       # bad CRC
        b"VRXI" + vrpi[4:],                                                         # unknown packet ID
        bytes(revision),                                                            # revision 1
        bytes(VM110(origin=0x0101, serial=8) / VRCI(command_id=18))[:30],           # truncated
        bytes(VM110(serial=9) / VRPO(packet_number=1, periodic_data=bytes(C.VRPO_MAX_DATA + 3))),  # too large
        vrpi[:12],                                                                  # shorter than a header
    ]


# Long byte fields: 4.0 shows 36 bytes and "…", 4.4 up to the label limit ("Name […]: ...").
_LONG_BYTES = re.compile(r"^(\s*[^:\[]+?)(?: \[…\])?: ([0-9a-f]{72})[0-9a-f]*…?")

def _same_bytes_display(line: str) -> str:
    return _LONG_BYTES.sub(lambda m: f"{m.group(1)}: {m.group(2)}…", line)


def vm110_text(verbose: str) -> str:
    """Frame numbers and the vm110 subtree of `tshark -V -O vm110` output."""
    out = []
    for line in verbose.splitlines():
        if line.startswith("Frame "):
            out.append(line.split(":")[0])
            inside = False
        elif line.startswith("VM-110 EG-Link"):
            inside = True
        elif line and not line.startswith(" "):
            inside = False
        if inside:
            out.append(_same_bytes_display(line))
    return "\n".join(out) + "\n"


def render(ws: T.Workspace, capture: Path) -> str:
    local = ws.dir / capture.name
    if local != capture:
        local.write_bytes(capture.read_bytes())
    proc = ws.run(["-r", str(local), "-V", "-O", "vm110"])
    assert T.LUA_ERROR not in proc.stdout + proc.stderr
    return vm110_text(proc.stdout)


@pytest.mark.tshark
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_golden(tshark, tmp_path):
    try:
        with tshark.workspace(tmp_path) as ws:
            got = render(ws, CAPTURE)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert got == EXPECTED.read_text(), "dissector output changed: check it, then `make golden`"


def test_golden_capture_is_current(tmp_path):
    """The stored capture is what sample_packets() builds (so `make golden` is reproducible)."""
    rebuilt = tmp_path / "rebuilt.pcap"
    T.write_pcap(rebuilt, sample_packets())
    assert rebuilt.read_bytes() == CAPTURE.read_bytes()


def main() -> int:
    """Rebuild the capture and the expected text with the first tshark (4.0); check the others agree."""
    GOLDEN_DIR.mkdir(exist_ok=True)
    T.write_pcap(CAPTURE, sample_packets())
    first, *others = T.RUNNERS
    with first.workspace(GOLDEN_DIR) as ws:
        EXPECTED.write_text(render(ws, CAPTURE))
    print(f"wrote {CAPTURE.relative_to(Path.cwd())} and {EXPECTED.relative_to(Path.cwd())}")
    status = 0
    for runner in others:
        try:
            with runner.workspace(GOLDEN_DIR) as ws:
                if render(ws, CAPTURE) != EXPECTED.read_text():
                    print(f"warning: tshark {runner.version} prints it differently: see "
                          "`pytest tests/test_dissector_golden.py`")
                    status = 1
        except T.TsharkUnavailable as exc:
            print(f"not checked on tshark {runner.version}: {exc}")
    return status


if __name__ == "__main__":
    sys.exit(main())
