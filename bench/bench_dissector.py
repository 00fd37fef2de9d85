"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data).

Both runs extract the same UDP-level fields; the plugin run also extracts vm110 fields, so the
dissector really builds them. Each side runs REPEAT times, interleaved; the best time of each is
compared (wall time, the figure of issue 3, whose target is at most 1.3; and CPU time, which other
load on the machine disturbs less). Measured on the host's tshark (4.0, Lua 5.2) and,
when scripts/setup-tshark44.sh has built it, on tshark 4.4 (Lua 5.4) in its chroot.
"""
from __future__ import annotations

import random
import resource
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


def timed(command: list[str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU (user + system) is less disturbed by other load."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(ws: T.Workspace, pcap: Path) -> tuple[tuple[float, float], tuple[float, float]]:
    """Best (wall, CPU) of REPEAT interleaved runs: plain UDP, then with the plugin."""
    capture = ws.tshark.inner(pcap)
    base = ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON])
    plugin = ws.tshark.command(["-n", "-X", f"lua_script:{ws.plugin()}", "-r", capture, "-T", "fields",
                                *COMMON, *VM110_FIELDS])
    check = ws.run(["-n", "-r", str(pcap), "-c", "1", "-T", "fields", "-e", "vm110.crc.status"])
    if check.stdout.strip() != "1":
        raise RuntimeError(f"the plugin did not validate the first packet's CRC: {check.stdout!r}")
    without, with_plugin = [], []
    for _ in range(REPEAT):
        without.append(timed(base))
        with_plugin.append(timed(plugin))
    return tuple(map(min, zip(*without))), tuple(map(min, zip(*with_plugin)))


def main() -> int:
    packets = traffic(PACKETS)
    with tempfile.TemporaryDirectory() as tmp:
        for runner in T.RUNNERS:
            try:
                with runner.workspace(Path(tmp) / runner.name) as ws:
                    pcap = ws.dir / "eglink-100k.pcap"
                    T.write_pcap(pcap, packets)
                    version = subprocess.run(runner.command(["--version"]), capture_output=True,
                                             text=True).stdout.split("\n")[0]
                    plain, dissected = measure(ws, pcap)
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            print(f"{version}: tshark -T fields, {PACKETS} EG-Link packets: plain UDP {plain[0]:.2f} s, "
                  f"vm110 plugin (CRC on) {dissected[0]:.2f} s, wall-time ratio {dissected[0] / plain[0]:.2f} "
                  f"(target <= {TARGET}); CPU {plain[1]:.2f} s vs {dissected[1]:.2f} s, "
                  f"ratio {dissected[1] / plain[1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
