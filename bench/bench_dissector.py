"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data), with
the stream analysis of issue 4 off and on (its target: at most 1.5 x the plain-UDP time; the
analysis's own cost is the on/off ratio).

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
ANALYSIS_TARGET = 1.5
SPACING_US = 25_000   # VRPO packets then come >= 25 ms apart: each one is a burst, as in normal traffic
COMMON = ["-e", "frame.number", "-e", "ip.src", "-e", "udp.srcport", "-e", "udp.length"]
VM110_FIELDS = ["-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status", "-e", "vm110.command_id"]
ANALYSIS_FIELDS = ["-e", "vm110.analysis.serial_missing", "-e", "vm110.analysis.interval",
                   "-e", "vm110.analysis.retransmission_of", "-e", "vm110.analysis.ack_to"]


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
    serials = {b"I": 0, b"O": 0}          # one counter per sender (direction), as senders number
    for index, template in enumerate(rng.choices(packets, weights, k=count)):
        direction = bytes(template)[3:4]
        template.serial = serials[direction] & 0xFFFF
        serials[direction] += 1
        if hasattr(template.payload, "command_id"):
            template.payload.command_id = (index // 8) & 0xFFFF   # some retransmissions, some acked
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


def measure(ws: T.Workspace, pcap: Path) -> dict[str, tuple[float, float]]:
    """Best (wall, CPU) of REPEAT interleaved runs: plain UDP, the plugin without and with the analysis."""
    capture = ws.tshark.inner(pcap)
    plugin = ["-n", "-X", f"lua_script:{ws.plugin()}", "-r", capture, "-T", "fields", *COMMON, *VM110_FIELDS]
    commands = {
        "plain": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON]),
        "decode": ws.tshark.command([*plugin, "-o", "vm110.analysis:FALSE"]),
        "analysis": ws.tshark.command([*plugin, *ANALYSIS_FIELDS, "-o", "vm110.analysis:TRUE"]),
    }
    check = ws.run(["-n", "-r", str(pcap), "-c", "1", "-T", "fields", "-e", "vm110.crc.status"])
    if check.stdout.strip() != "1":
        raise RuntimeError(f"the plugin did not validate the first packet's CRC: {check.stdout!r}")
    check = ws.run(["-n", "-r", str(pcap), "-c", "20", "-T", "fields", "-e", "vm110.analysis.interval"])
    if not check.stdout.strip():
        raise RuntimeError("the stream analysis produced no interval")
    runs: dict[str, list] = {name: [] for name in commands}
    for _ in range(REPEAT):
        for name, command in commands.items():
            runs[name].append(timed(command))
    return {name: tuple(map(min, zip(*values))) for name, values in runs.items()}


def main() -> int:
    packets = traffic(PACKETS)
    with tempfile.TemporaryDirectory() as tmp:
        for runner in T.RUNNERS:
            try:
                with runner.workspace(Path(tmp) / runner.name) as ws:
                    pcap = ws.dir / "eglink-100k.pcap"
                    T.write_pcap(pcap, packets, [i * SPACING_US for i in range(len(packets))])
                    version = subprocess.run(runner.command(["--version"]), capture_output=True,
                                             text=True).stdout.split("\n")[0]
                    t = measure(ws, pcap)
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            plain, decode, analysis = t["plain"], t["decode"], t["analysis"]
            print(f"{version}: tshark -T fields, {PACKETS} EG-Link packets: plain UDP {plain[0]:.2f} s, "
                  f"vm110 plugin (CRC on, analysis off) {decode[0]:.2f} s, wall-time ratio {decode[0] / plain[0]:.2f} "
                  f"(target <= {TARGET}); CPU {plain[1]:.2f} s vs {decode[1]:.2f} s, "
                  f"ratio {decode[1] / plain[1]:.2f}")
            print(f"{version}: with the stream analysis on {analysis[0]:.2f} s, wall-time ratio "
                  f"{analysis[0] / plain[0]:.2f} (target <= {ANALYSIS_TARGET}), CPU ratio {analysis[1] / plain[1]:.2f}; "
                  f"analysis cost on/off: wall {analysis[0] / decode[0]:.2f}, CPU {analysis[1] / decode[1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
