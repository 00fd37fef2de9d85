"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data), with
the stream analysis of issue 4 off (target: at most 1.3 x the plain-UDP time) and on (target: at
most 1.5 x).

The headline runs extract the same frame/IP/UDP fields with and without the plugin: the figure is
what decoding EG-Link costs. The runs marked "+ vm110 fields" also extract vm110 (and analysis)
fields, so the dissector builds those items too; tshark then also prints twice as many columns.
Each command runs REPEAT times, interleaved; the best time of each is compared (wall time, the
figure of the issues; and CPU time, which other load disturbs less). Measured on the host's
tshark (4.0, Lua 5.2) and, when scripts/setup-tshark44.sh has built it, on tshark 4.4 (Lua 5.4)
in its chroot. Wireshark 4.0's tshark builds the full, visible tree for -T fields (4.4 builds it
invisible and only the referenced fields), so there every field of every packet is built.
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


def measure(ws: T.Workspace, pcap: Path, bad: list[int]) -> dict[str, tuple[float, float]]:
    """Best (wall, CPU) of REPEAT interleaved runs of each command."""
    capture = ws.tshark.inner(pcap)
    plugin = ["-n", "-X", f"lua_script:{ws.plugin()}", "-r", capture, "-T", "fields", *COMMON]
    off, on = ["-o", "vm110.analysis:FALSE"], ["-o", "vm110.analysis:TRUE"]
    commands = {
        "plain": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON]),
        "decode": ws.tshark.command([*plugin, *off]),
        "decode_fields": ws.tshark.command([*plugin, *VM110_FIELDS, *off]),
        "analysis": ws.tshark.command([*plugin, *on]),
        "analysis_fields": ws.tshark.command([*plugin, *VM110_FIELDS, *ANALYSIS_FIELDS, *on]),
    }
    # The timed settings validate CRCs (the corrupted frames are flagged) and analyse the streams.
    check = ws.run(["-n", "-r", str(pcap), "-T", "fields", "-e", "frame.number", "-Y", "vm110.expert.bad_crc", *on])
    if [int(n) for n in check.stdout.split()] != bad:
        raise RuntimeError(f"the plugin did not flag exactly the {len(bad)} frames with a bad CRC")
    check = ws.run(["-n", "-r", str(pcap), "-c", "20", "-T", "fields", "-e", "vm110.analysis.interval", *on])
    if not check.stdout.strip():
        raise RuntimeError("the stream analysis produced no interval")
    runs: dict[str, list] = {name: [] for name in commands}
    for _ in range(REPEAT):
        for name, command in commands.items():
            runs[name].append(timed(command))
    return {name: tuple(map(min, zip(*values))) for name, values in runs.items()}


def ratio_line(label: str, run: tuple[float, float], plain: tuple[float, float], target: str = "") -> str:
    return (f"  {label}: {run[0]:.2f} s, wall-time ratio {run[0] / plain[0]:.2f}{target}; "
            f"CPU {run[1]:.2f} s, ratio {run[1] / plain[1]:.2f}")


def main() -> int:
    packets = traffic(PACKETS)
    bad = sorted(random.Random(7).sample(range(1, PACKETS + 1), PACKETS // 1000))   # frame numbers
    for number in bad:
        packets[number - 1] = packets[number - 1][:-1] + bytes([packets[number - 1][-1] ^ 0xFF])
    with tempfile.TemporaryDirectory() as tmp:
        for runner in T.RUNNERS:
            try:
                with runner.workspace(Path(tmp) / runner.name) as ws:
                    pcap = ws.dir / "eglink-100k.pcap"
                    T.write_pcap(pcap, packets, [i * SPACING_US for i in range(len(packets))])
                    version = subprocess.run(runner.command(["--version"]), capture_output=True,
                                             text=True).stdout.split("\n")[0]
                    t = measure(ws, pcap, bad)
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            plain = t["plain"]
            print(f"{version}: tshark -T fields, {PACKETS} EG-Link packets ({len(bad)} with a bad CRC); "
                  f"plain UDP {plain[0]:.2f} s (CPU {plain[1]:.2f} s)")
            print(ratio_line("vm110 plugin, CRC on, analysis off", t["decode"], plain, f" (target <= {TARGET})"))
            print(ratio_line("  + vm110 fields", t["decode_fields"], plain))
            print(ratio_line("vm110 plugin, CRC on, analysis on", t["analysis"], plain,
                             f" (target <= {ANALYSIS_TARGET})"))
            print(ratio_line("  + vm110 and analysis fields", t["analysis_fields"], plain))
            print(f"  analysis cost on/off: wall {t['analysis'][0] / t['decode'][0]:.2f}, "
                  f"CPU {t['analysis'][1] / t['decode'][1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
