"""Lua dissector speed, measured the way a user runs it (issue 13): `tshark -T fields` over a
100,000-packet EG-Link capture with the plugin at its default preferences (CRC validation and
stream analysis on) and vm110 fields referenced, against tshark without the plugin (the packets
then decode as plain UDP data) printing as many columns.

The capture is `vm110 synth day` (normal operation with light loss, the simulators' timing of
TS-0006: VRPI every 125 ms, VRPO every 100 ms, an operator command every few seconds) cut to
about 100,000 packets. Every run prints the same four frame/IP/UDP fields, and then:
- "vm110": 4 vm110 fields (type, serial, CRC status, command ID), against "plain 8": 4 more
  frame/IP/UDP fields. Nothing in that output reads the stream analysis, so the plugin does not
  run it (a single pass prints each frame before it reads the next): the CRC is validated;
- "vm110 + analysis": those and 4 stream-analysis fields (serial_missing, interval,
  retransmission_of, ack_to), against "plain 12": 8 more frame/IP/UDP fields. The analysis runs,
  as it does for every output that reads it (the GUI, columns, expert infos, filters);
- "vm110, -2": the first run with two passes (tshark -2, as the GUI dissects a frame again each
  time it is looked at), against "plain 8, -2".
A field referenced is what any column, display filter or -T fields -e vm110.* does; with none,
Wireshark may skip building the tree, which is not how the plugin is used.

For scale, "Lua floor" is the least any Lua dissector pays for that output: a plugin of a few
lines that registers the same four fields, reads the packet ID and serial and adds the protocol
item and three values (no CRC, no checks, no analysis). What the plugin costs above it is its own.
"vm110, CRC + analysis off" is the plugin with both switched off (-o vm110.check_crc:FALSE -o
vm110.analysis:FALSE): its decode, value checks and fields alone. The last line gives both ratios
of each version against its target: the one without the analysis, and the one with it.

Each command runs REPEAT times, interleaved over the commands and the tshark versions (4.0 with Lua
5.2; 4.4 and 4.6 with Lua 5.4: the host's tshark for its own version, Debian chroots for the others,
as the tests run them, tests/tshark_runner.py); the best time of each is compared: wall time, the figure of
the issue, and CPU time (user + system), which other load on the machine disturbs less. Beside
it, the median over the rounds of each round's ratio: on a shared machine whose speed drifts for
minutes at a time, one lucky plain run can move a ratio of best times by a fifth.

Options: --baseline FILE also times another copy of the plugin (say, the previous commit's) in the
same interleaved runs, so that before and after come from one measurement; --tune-gc also times
the plugin with the preference vm110.tune_gc on (the collector settings it offers, off by
default); --repeat N; --packets-duration S (seconds of 'day', 5400 = about 100,000 packets).
"""
from __future__ import annotations

import argparse
import contextlib
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import tshark_runner as T
from vm110.synth import synthesize

DURATION_S = 5400     # about 100,000 packets of 'day'
REPEAT = 3
TARGETS = {"4.0": 2.0, "4.4": 1.25, "4.6": 1.25}
COMMON = ["-e", "frame.number", "-e", "ip.src", "-e", "udp.srcport", "-e", "udp.length"]
VM110_FIELDS = ["-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status", "-e", "vm110.command_id"]
ANALYSIS_FIELDS = ["-e", "vm110.analysis.serial_missing", "-e", "vm110.analysis.interval",
                   "-e", "vm110.analysis.retransmission_of", "-e", "vm110.analysis.ack_to"]
BARE = "vm110, CRC + analysis off"
PLAIN_EXTRA = ["-e", "ip.dst", "-e", "udp.dstport", "-e", "ip.ttl", "-e", "udp.checksum",
               "-e", "frame.len", "-e", "eth.src", "-e", "eth.dst", "-e", "ip.id"]


# The "Lua floor" plugin: the same fields, values only, nothing computed.
FLOOR_PLUGIN = """\
local p = Proto("vm110", "VM-110 EG-Link (Lua floor)")
local f_type = ProtoField.string("vm110.type", "Type")
local f_serial = ProtoField.uint16("vm110.serial", "Serial")
local f_crc = ProtoField.uint8("vm110.crc.status", "CRC status")
local f_cid = ProtoField.uint16("vm110.command_id", "Command ID")
p.fields = { f_type, f_serial, f_crc, f_cid }
function p.dissector(tvb, pinfo, tree)
    local s = tvb:raw(0, 10)
    local root = tree:add(p)
    root:add(f_type, s:sub(1, 4))
    root:add(f_serial, s:byte(9) + s:byte(10) * 256)
    root:add(f_crc, 2)
    return tvb:len()
end
local udp = DissectorTable.get("udp.port")
udp:add(5825, p)
udp:add(5827, p)
"""


def timed(command: list[str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU (user + system) is less disturbed by other load."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def commands(ws: T.Workspace, pcap: Path, baseline: Path | None, tune_gc: bool) -> dict[str, list[str]]:
    capture = ws.tshark.inner(pcap)
    plugins = {"": ws.plugin()}
    if baseline:
        copy = ws.dir / "baseline.lua"
        shutil.copyfile(baseline, copy)
        plugins["before: "] = ws.tshark.inner(copy)
    floor = ws.dir / "floor.lua"
    floor.write_text(FLOOR_PLUGIN)
    out = {
        "plain 8": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON, *PLAIN_EXTRA[:8]]),
        "Lua floor": ws.tshark.command(["-n", "-X", f"lua_script:{ws.tshark.inner(floor)}", "-r", capture,
                                        "-T", "fields", *COMMON, *VM110_FIELDS]),
        "plain 12": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON, *PLAIN_EXTRA]),
        "plain 8, -2": ws.tshark.command(["-n", "-2", "-r", capture, "-T", "fields", *COMMON, *PLAIN_EXTRA[:8]]),
    }
    for label, plugin in plugins.items():
        base = ["-n", "-X", f"lua_script:{plugin}", "-r", capture, "-T", "fields", *COMMON, *VM110_FIELDS]
        out[f"{label}vm110"] = ws.tshark.command(base)
        out[f"{label}vm110 + analysis"] = ws.tshark.command([*base, *ANALYSIS_FIELDS])
        out[f"{label}vm110, -2"] = ws.tshark.command(["-2", *base])
    out[BARE] = ws.tshark.command(["-n", "-X", f"lua_script:{ws.plugin()}", "-o", "vm110.check_crc:FALSE",
                                   "-o", "vm110.analysis:FALSE", "-r", capture, "-T", "fields", *COMMON,
                                   *VM110_FIELDS])
    if tune_gc:
        base = ["-n", "-X", f"lua_script:{ws.plugin()}", "-r", capture, "-o", "vm110.tune_gc:TRUE",
                "-T", "fields", *COMMON, *VM110_FIELDS]
        out["vm110, tune_gc on"] = ws.tshark.command(base)
    return out


def round_ratio(runs: dict[tuple[str, str], list], runner: str, name: str, plain: str) -> float:
    """The median over the rounds of a round's wall time / its plain run's: a slow spell of the
    machine, which can put one command's best run far from another's, slows both alike."""
    return statistics.median(a[0] / b[0] for a, b in zip(runs[(runner, name)], runs[(runner, plain)]))


def check(ws: T.Workspace, pcap: Path) -> None:
    """The timed settings (the defaults) validate CRCs and analyse the streams."""
    proc = ws.run(["-n", "-r", str(pcap), "-c", "20", "-T", "fields", "-e", "vm110.crc.status"])
    if set(proc.stdout.split()) != {"1"}:
        raise RuntimeError(f"the plugin did not find the first CRCs good: {proc.stdout!r}")
    proc = ws.run(["-n", "-r", str(pcap), "-c", "20", "-T", "fields", "-e", "vm110.analysis.interval"])
    if not proc.stdout.strip():
        raise RuntimeError("the stream analysis produced no interval")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, help="another copy of vm110.lua to time alongside")
    parser.add_argument("--tune-gc", action="store_true", help="also time with vm110.tune_gc on")
    parser.add_argument("--repeat", type=int, default=REPEAT)
    parser.add_argument("--duration", type=int, default=DURATION_S, help="seconds of 'day' (5400: ~100k packets)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        setups = []
        for runner in T.RUNNERS:
            try:
                ws = stack.enter_context(runner.workspace(Path(tmp) / runner.name))
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            pcap = ws.dir / "day.pcap"
            packets = synthesize("day", str(pcap), seed=1, duration_s=args.duration)["capture"]["packets"]
            version = subprocess.run(runner.command(["--version"]), capture_output=True,
                                     text=True).stdout.split("\n")[0]
            check(ws, pcap)
            setups.append((runner, version, packets, commands(ws, pcap, args.baseline, args.tune_gc)))
        runs: dict[tuple[str, str], list] = {}
        for _ in range(args.repeat):  # interleaved: every command of every version, then again
            for runner, _, _, cmds in setups:
                for name, command in cmds.items():
                    runs.setdefault((runner.name, name), []).append(timed(command))
        best = {key: tuple(map(min, zip(*values))) for key, values in runs.items()}
        headline = []
        for runner, version, packets, cmds in setups:
            t = {name: best[(runner.name, name)] for name in cmds}
            print(f"{version}: tshark -T fields, {packets} EG-Link packets ('day', {args.duration} s), default "
                  f"preferences (CRC validation and stream analysis on), best of {args.repeat} interleaved")
            for name in cmds:
                if name.startswith("plain"):
                    continue
                plain_name = "plain 12" if name.endswith("analysis") else "plain 8, -2" if name.endswith("-2") \
                    else "plain 8"
                plain = t[plain_name]
                print(f"  {name:26s} {t[name][0]:6.2f} s  ratio {t[name][0] / plain[0]:.2f} "
                      f"(median of rounds {round_ratio(runs, runner.name, name, plain_name):.2f})   "
                      f"CPU {t[name][1]:6.2f} s  ratio {t[name][1] / plain[1]:.2f}")
            print(f"  {'plain 8 / 12 columns':26s} {t['plain 8'][0]:6.2f} / {t['plain 12'][0]:.2f} s   "
                  f"CPU {t['plain 8'][1]:.2f} / {t['plain 12'][1]:.2f} s; two passes (-2) "
                  f"{t['plain 8, -2'][0]:.2f} s")
            ratio = t["vm110"][0] / t["plain 8"][0]
            ratio_a = t["vm110 + analysis"][0] / t["plain 12"][0]
            medians = (round_ratio(runs, runner.name, "vm110", "plain 8"),
                       round_ratio(runs, runner.name, "vm110 + analysis", "plain 12"))
            headline.append(f"{runner.version} {ratio:.2f}x, {ratio_a:.2f}x with the analysis (medians of rounds "
                            f"{medians[0]:.2f}x, {medians[1]:.2f}x; target <= {TARGETS.get(runner.version, '?')})")
        print("vm110 / plain UDP, wall time, best runs, 4 vm110 fields (the analysis read by nothing: not run), "
              "and with 4 analysis fields more (the analysis runs): " + "; ".join(headline))
    return 0


if __name__ == "__main__":
    sys.exit(main())
