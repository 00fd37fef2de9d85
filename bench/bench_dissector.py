"""Lua dissector speed: `tshark -T fields` over a 100,000-packet EG-Link capture, with the plugin
(CRC validation on) against tshark without it (the packets then decode as plain UDP data), with
the stream analysis of issue 4 off (target: at most 1.3 x the plain-UDP time) and on (target: at
most 1.5 x).

The capture is `vm110 synth day` (normal operation with light loss, the simulators' timing of
TS-0006: VRPI every 125 ms, VRPO every 100 ms, an operator command every few seconds) cut to
about 100,000 packets. The headline runs extract the same frame/IP/UDP fields with and without
the plugin: the figure is what decoding EG-Link costs. The runs marked "+ vm110 fields" also extract vm110 (and analysis)
fields, so the dissector builds those items too; tshark then also prints twice as many columns.
Each command runs REPEAT times, interleaved; the best time of each is compared (wall time, the
figure of the issues; and CPU time, which other load disturbs less). Measured on the host's
tshark (4.0, Lua 5.2) and, when scripts/setup-tshark44.sh has built it, on tshark 4.4 (Lua 5.4)
in its chroot. Wireshark 4.0's tshark builds the full, visible tree for -T fields (4.4 builds it
invisible and only the referenced fields), so there every field of every packet is built.

Two references measured in the same run put the ratios in context:
- "plain, 8 / 12 columns": plain UDP printing four / eight more frame/Ethernet/IP/UDP fields, so
  that the "+ vm110 fields" runs are also compared with a run that writes as many columns;
- "Lua tree floor": a Lua dissector that adds, per packet, as many tree items as vm110's visible
  tree has for that packet type (counted from vm110's own PDML of the capture), each over its own
  TvbRange, and does nothing else: no CRC, no checks, no labels. It is what any Lua dissector
  that shows every field pays for its items where the tree is visible (all of tshark 4.0's
  -T fields); vm110 / floor is then the cost of everything vm110 does besides its items.
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
from lxml import etree  # noqa: E402
from vm110 import constants as C  # noqa: E402
from vm110.synth import synthesize  # noqa: E402

DURATION_S = 5400     # about 100,000 packets of 'day'
REPEAT = 3
TARGET = 1.3
ANALYSIS_TARGET = 1.5
COMMON = ["-e", "frame.number", "-e", "ip.src", "-e", "udp.srcport", "-e", "udp.length"]
VM110_FIELDS = ["-e", "vm110.type", "-e", "vm110.serial", "-e", "vm110.crc.status", "-e", "vm110.command_id"]
ANALYSIS_FIELDS = ["-e", "vm110.analysis.serial_missing", "-e", "vm110.analysis.interval",
                   "-e", "vm110.analysis.retransmission_of", "-e", "vm110.analysis.ack_to"]
# Plain fields printed instead of the vm110 ones: the first four for VM110_FIELDS, all for both lists.
PLAIN_EXTRA = ["-e", "ip.dst", "-e", "udp.dstport", "-e", "ip.ttl", "-e", "udp.checksum",
               "-e", "frame.len", "-e", "eth.src", "-e", "eth.dst", "-e", "ip.id"]
COUNT_PACKETS = 2000  # packets whose visible vm110 tree is counted for the floor

FLOOR_LUA = """-- Written by bench/bench_dissector.py: items only, as many per packet type as vm110's visible tree.
{gc}
local p = Proto("vm110floor", "Lua tree floor")
local f = ProtoField.uint8("vm110floor.byte", "Byte", base.DEC)
p.fields = {{ f }}
local ITEMS = {{ {items} }}
function p.dissector(tvb, pinfo, tree)
    local n = tvb:len()
    local root = tree:add(p, tvb(0, n))
    for i = 2, ITEMS[tvb:raw(0, 4)] or 1 do root:add(f, tvb(i % n, 1)) end
    return n
end
local udp = DissectorTable.get("udp.port")
udp:add({input}, p)
udp:add({output}, p)
"""


def visible_items(ws: T.Workspace, capture: str) -> dict[str, int]:
    """Packet type -> the most tree items vm110's visible tree has for it (its protocol item,
    fields, text items and subtrees; expert items not counted), from its PDML."""
    proc = ws.run(["-n", "-r", capture, "-c", str(COUNT_PACKETS), "-T", "pdml", "-o", "vm110.analysis:FALSE"])
    items: dict[str, int] = {}
    for proto in etree.fromstring(proc.stdout.encode(), parser=etree.XMLParser(huge_tree=True)).iter("proto"):
        if proto.get("name") != "vm110":
            continue
        kind = next((f.get("show") for f in proto.iter("field") if f.get("name") == "vm110.type"), None)
        count = 1 + sum(1 for f in proto.iter("field") if not (f.get("name") or "").startswith("_ws.expert"))
        if kind:
            items[kind] = max(items.get(kind, 0), count)
    return items


def collector_settings() -> str:
    """vm110.lua's tuning of the Lua collector (it applies to every Lua plugin): the floor runs with it too."""
    text = T.PLUGIN.read_text()
    start = text.index('if _VERSION == "Lua 5.4" then')
    return text[start:text.index("\nend\n", start) + 4]


def floor_plugin(ws: T.Workspace, capture: str) -> tuple[str, str]:
    """The floor dissector, written where tshark sees it: its path as tshark sees it, and its
    items per packet type."""
    counts = sorted(visible_items(ws, capture).items())
    path = ws.dir / "floor.lua"
    path.write_text(FLOOR_LUA.format(gc=collector_settings(), items=", ".join(f"{k} = {n}" for k, n in counts),
                                     input=C.INPUT_PORT, output=C.OUTPUT_PORT))
    return ws.tshark.inner(path), ", ".join(f"{k} {n}" for k, n in counts)


def timed(command: list[str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU (user + system) is less disturbed by other load."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(ws: T.Workspace, pcap: Path) -> tuple[dict[str, tuple[float, float]], str]:
    """Best (wall, CPU) of REPEAT interleaved runs of each command; the floor's items per type."""
    capture = ws.tshark.inner(pcap)
    floor, floor_items = floor_plugin(ws, capture)
    plugin = ["-n", "-X", f"lua_script:{ws.plugin()}", "-r", capture, "-T", "fields", *COMMON]
    off, on = ["-o", "vm110.analysis:FALSE"], ["-o", "vm110.analysis:TRUE"]
    commands = {
        "plain": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON]),
        "plain_8": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON, *PLAIN_EXTRA[:8]]),
        "plain_12": ws.tshark.command(["-n", "-r", capture, "-T", "fields", *COMMON, *PLAIN_EXTRA]),
        "floor": ws.tshark.command(["-n", "-X", f"lua_script:{floor}", "-r", capture, "-T", "fields", *COMMON]),
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
    return {name: tuple(map(min, zip(*values))) for name, values in runs.items()}, floor_items


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
                    t, floor_items = measure(ws, pcap)
            except T.TsharkUnavailable as exc:
                print(f"{runner.name}: not measured ({exc})")
                continue
            plain, floor = t["plain"], t["floor"]
            print(f"{version}: tshark -T fields, {packets} EG-Link packets ('day', {DURATION_S} s); "
                  f"plain UDP {plain[0]:.2f} s (CPU {plain[1]:.2f} s)")
            print(ratio_line("vm110 plugin, CRC on, analysis off", t["decode"], plain, f" (target <= {TARGET})"))
            print(ratio_line("  + vm110 fields", t["decode_fields"], plain)
                  + f"; against plain with as many columns {t['decode_fields'][0] / t['plain_8'][0]:.2f}")
            print(ratio_line("vm110 plugin, CRC on, analysis on", t["analysis"], plain,
                             f" (target <= {ANALYSIS_TARGET})"))
            print(ratio_line("  + vm110 and analysis fields", t["analysis_fields"], plain)
                  + f"; against plain with as many columns {t['analysis_fields'][0] / t['plain_12'][0]:.2f}")
            print(f"  analysis cost on/off: wall {t['analysis'][0] / t['decode'][0]:.2f}, "
                  f"CPU {t['analysis'][1] / t['decode'][1]:.2f}")
            print(ratio_line("reference: plain, 8 columns", t["plain_8"], plain))
            print(ratio_line("reference: plain, 12 columns", t["plain_12"], plain))
            print(ratio_line("reference: Lua tree floor (items only)", floor, plain)
                  + f"; vm110 (analysis off) / floor {t['decode'][0] / floor[0]:.2f}")
            print(f"    (floor items per packet, as vm110's visible tree: {floor_items})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
