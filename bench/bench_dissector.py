"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data), with
the stream analysis of issue 4 off (target: at most 1.3 x the plain-UDP time) and on (target: at
most 1.5 x).

The capture is `vm110 synth day` (normal operation with light loss, the simulators' timing of
TS-0006: VRPI every 125 ms, VRPO every 100 ms, an operator command every few seconds) cut to
about 100,000 packets. The headline runs extract the same frame/IP/UDP fields with and without the plugin: the figure is
what decoding EG-Link costs. The runs marked "+ vm110 fields" also extract vm110 (and analysis)
fields, so the dissector builds those items too; tshark then also prints twice as many columns.
Each command runs REPEAT times, interleaved; the best time of each is compared (wall time, the
figure of the issues; and CPU time, which other load disturbs less). Measured on the host's
tshark (4.0, Lua 5.2) and, when scripts/setup-tshark44.sh has built it, on tshark 4.4 (Lua 5.4)
in its chroot. Wireshark 4.0's tshark builds the full, visible tree for -T fields (4.4 builds it
invisible and only the referenced fields), so there every field of every packet is built.
"""
from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import tshark_runner as T  # noqa: E402
from vm110.synth import synthesize  # noqa: E402

DURATION_S = 5400     # about 100,000 packets of 'day'
REPEAT = 3
TARGET = 1.3
ANALYSIS_TARGET = 1.5
COMMON = ["-e", "frame.number", "-e", "ip.src", "-e", "udp.srcport", "-e", "udp.length"]
VM110_FIELDS = ["-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status", "-e", "vm110.command_id"]
ANALYSIS_FIELDS = ["-e", "vm110.analysis.serial_missing", "-e", "vm110.analysis.interval",
                   "-e", "vm110.analysis.retransmission_of", "-e", "vm110.analysis.ack_to"]


def timed(command: list[str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU (user + system) is less disturbed by other load."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(ws: T.Workspace, pcap: Path) -> dict[str, tuple[float, float]]:
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
    # The timed settings validate CRCs and analyse the streams.
    check = ws.run(["-n", "-r", str(pcap), "-c", "20", "-T", "fields", "-e", "vm110.crc.status", *on])
    if set(check.stdout.split()) != {"1"}:
        raise RuntimeError(f"the plugin did not find the first CRCs good: {check.stdout!r}")
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
    with tempfile.TemporaryDirectory() as tmp:
        for runner in T.RUNNERS:
            try:
                with runner.workspace(Path(tmp) / runner.name) as ws:
                    pcap = ws.dir / "day.pcap"
                    packets = synthesize("day", str(pcap), seed=1, duration_s=DURATION_S)["capture"]["packets"]
                    version = subprocess.run(runner.command(["--version"]), capture_output=True,
                                             text=True).stdout.split("\n")[0]
                    t = measure(ws, pcap)
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            plain = t["plain"]
            print(f"{version}: tshark -T fields, {packets} EG-Link packets ('day', {DURATION_S} s); "
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
