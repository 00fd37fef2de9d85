"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data).

Both runs extract the same UDP-level fields; the plugin run also extracts vm110 fields, so the
dissector really builds them. Each side runs REPEAT times, interleaved; the best time of each is
compared. Target (issue 3): ratio at most 1.3.
"""
from __future__ import annotations

import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import tshark_runner as T  # noqa: E402
from vm110 import constants as C  # noqa: E402
from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO  # noqa: E402

PACKETS = 100_000
REPEAT = 3
TARGET = 1.3
COMMON = ["-e", "frame.number", "-e", "ip.src", "-e", "udp.srcport", "-e", "udp.length"]
VM110_FIELDS = ["-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status", "-e", "vm110.command_id"]


def traffic(count: int, seed: int = 110) -> list[bytes]:
    """A realistic mix: mostly VRPI (every 125 ms) and VRPO, with commands and their acks."""
    rng = random.Random(seed)
    vrpi = VRPI(bu_state=C.BuState.ARMED, vlaps=1, eg_link=1, ec_link=1, c_link=1, armed_ru=0x0C07,
                ru_state=C.RuState.ENABLED, ru_battery=88, ru_rssi=76, joystick1=250)
    templates = [
        (VM110(origin=0x0101) / vrpi, 50),
        (VM110() / VRPO(packet_number=0, periodic_data=bytes(range(120))), 35),
        (VM110(origin=0x0101) / VRCI(command_id=1, command_data=b"START".ljust(16, b"\0")), 4),
        (VM110() / VRAO(command_id=1), 4),
        (VM110() / VRCO(command_id=1, command_data=b"ALARM".ljust(16, b"\0")), 4),
        (VM110(origin=0x0101) / VRAI(command_id=1), 3),
    ]
    packets, weights = zip(*templates)
    out = []
    for serial, template in enumerate(rng.choices(packets, weights, k=count)):
        template.serial = serial & 0xFFFF
        out.append(bytes(template))
    return out


def best_time(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        pcap = Path(tmp) / "eglink-100k.pcap"
        T.write_pcap(pcap, traffic(PACKETS))
        base = ["tshark", "-n", "-r", str(pcap), "-T", "fields", *COMMON]
        plugin = ["tshark", "-n", "-X", f"lua_script:{T.PLUGIN}", "-r", str(pcap), "-T", "fields",
                  *COMMON, *VM110_FIELDS]
        check = subprocess.run(plugin[:-len(VM110_FIELDS) - len(COMMON)] + ["-c", "1", "-e", "vm110.crc.status"],
                               capture_output=True, text=True, check=True)
        if check.stdout.strip() != "1":
            print(f"the plugin did not validate the CRC of the first packet: {check.stdout!r}", file=sys.stderr)
            return 1
        without, with_plugin = [], []
        for _ in range(REPEAT):
            without.append(best_time(base))
            with_plugin.append(best_time(plugin))
    plain, dissected = min(without), min(with_plugin)
    ratio = dissected / plain
    print(f"tshark -T fields, {PACKETS} EG-Link packets: plain UDP {plain:.2f} s, "
          f"vm110 plugin (CRC on) {dissected:.2f} s, ratio {ratio:.2f} (target <= {TARGET})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
