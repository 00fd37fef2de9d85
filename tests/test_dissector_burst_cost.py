"""The dissector's VRPO burst tracking is linear in the burst's length (issue 17, part 5): a
controller that sends back-to-back VRPO without end (exactly the capture one needs to look at) once
cost a rescan of the whole burst per packet. One burst of 8,192 VRPO packets must cost at most a
small multiple of the same packets in bursts of 16, both measured in this run on the host's tshark
(CPU time, best of two interleaved runs): a complexity check, not a speed figure. Before the fix
the ratio was about 20 at 16,384 packets (36 s against 2.6 s on Wireshark 4.0); the rescan being
quadratic, about 7 at this length (8.5 s against 1.25 s)."""
from __future__ import annotations

import resource
import subprocess

import pytest

import tshark_runner as T
from vm110 import constants as C

pytestmark = pytest.mark.tshark

PACKETS = 8_192
SHORT = 16
MAX_RATIO = 3.0


def cpu_seconds(command: list[str]) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def test_one_long_burst_costs_as_much_as_short_bursts(tmp_path):
    from vm110.layers import VM110, VRPO
    packets = [bytes(VM110(serial=i) / VRPO(packet_number=i, periodic_data=bytes(C.VRPO_MAX_DATA)))
               for i in range(PACKETS)]
    with T.HOST.workspace(tmp_path) as ws:
        long_pcap, short_pcap = ws.dir / "one-burst.pcap", ws.dir / "short-bursts.pcap"
        T.write_pcap(long_pcap, packets, [i * 1000 for i in range(PACKETS)])  # 1 ms apart: one burst
        T.write_pcap(short_pcap, packets, [i * 1000 + i // SHORT * 100_000 for i in range(PACKETS)])
        fields = ["-T", "fields", "-e", "vm110.serial", "-e", "vm110.burst.packets", "-e", "vm110.burst.complete"]
        probe = ws.run(["-r", str(long_pcap), "-2", *fields])
        assert probe.stdout.splitlines()[-1].split("\t")[1] == str(PACKETS)  # one burst indeed
        cost = {"long": [], "short": []}
        for _ in range(2):
            for name, pcap in (("long", long_pcap), ("short", short_pcap)):
                command = ws.tshark.command(["-n", "-X", f"lua_script:{ws.plugin()}", "-r", str(pcap), *fields])
                cost[name].append(cpu_seconds(command))
    long_s, short_s = min(cost["long"]), min(cost["short"])
    print(f"one burst of {PACKETS}: {long_s:.2f} s CPU; bursts of {SHORT}: {short_s:.2f} s CPU; "
          f"ratio {long_s / short_s:.2f}")
    assert long_s <= MAX_RATIO * short_s, cost
