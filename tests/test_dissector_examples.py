"""dissector/examples/crane.lua: a machine-specific sub-dissector plugged into vm110.lua's
vm110.periodic_data / vm110.command_data tables. A crane capture is crafted here with the scapy
layers (a split VRPO burst carrying 808 bytes of crane data, a small unsplit one, crane commands
both ways) and read back through real tshark on both versions: every crane field equals what was
put in; the example is not loaded by the main plugin alone."""
from __future__ import annotations

import struct

import pytest

import tshark_runner as T
from vm110 import constants as C
from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPO

pytestmark = pytest.mark.tshark

CRANE = T.REPO / "dissector" / "examples" / "crane.lua"
HEIGHT, LOAD, ALARMS, SPEED = 1234, 5678, 0x05, 80     # alarms: overload + slack rope
LOG = [(1000 + i, 0x100 + i % 7, i * 3) for i in range(100)]   # 8 + 800 bytes: split in two VRPO
SMALL = (321, 45, 0x02, 60)


def crane_data(height: int, load: int, alarms: int, speed: int, log=()) -> bytes:
    return struct.pack("<HHBBH", height, load, alarms, speed, len(log)) + b"".join(
        struct.pack("<IHH", *entry) for entry in log)


def capture_packets() -> tuple[list[bytes], list[int]]:
    big = crane_data(HEIGHT, LOAD, ALARMS, SPEED, LOG)
    parts = [big[:C.VRPO_MAX_DATA], big[C.VRPO_MAX_DATA:]]
    packets = [bytes(VM110(serial=1 + i) / VRPO(packet_number=i, periodic_data=p)) for i, p in enumerate(parts)]
    packets.append(bytes(VM110(serial=3) / VRPO(packet_number=0, periodic_data=crane_data(*SMALL))))
    packets.append(bytes(VM110(origin=0x0101, serial=1) / VRCI(command_id=7, command_data=b"\x01\x32".ljust(16, b"\0"))))
    packets.append(bytes(VM110(serial=4) / VRAO(command_id=7)))
    packets.append(bytes(VM110(serial=5) / VRCO(command_id=9, command_data=b"\x81HIGH WIND".ljust(16, b"\0"))))
    packets.append(bytes(VM110(origin=0x0101, serial=2) / VRAI(command_id=9)))
    times = [0, 50, 100_000, 150_000, 160_000, 200_000, 210_000]   # µs: the burst, then 100 ms later the rest
    return packets, times


FIELDS = ("frame.number", "crane.hoist_height", "crane.load", "crane.alarms", "crane.alarm_overload",
          "crane.alarm_slack_rope", "crane.alarm_high_wind", "crane.speed_limit", "crane.log_count",
          "crane.log.time", "crane.log.code", "crane.log.value", "crane.opcode", "crane.set_speed_limit",
          "crane.alarm_text", "vm110.reassembled", "_ws.lua.error")


def with_crane(ws: T.Workspace, *runs: list[str]) -> list:
    """tshark with the crane example on the capture of `capture_packets` (crane.pcap in the
    workspace), FIELDS printed, once per argument list."""
    packets, times = capture_packets()
    pcap = ws.dir / "crane.pcap"
    T.write_pcap(pcap, packets, times)
    crane = ws.dir / CRANE.name
    crane.write_bytes(CRANE.read_bytes())
    fields = ["-T", "fields", "-E", "aggregator=|", "-E", "occurrence=a", *(a for f in FIELDS for a in ("-e", f))]
    return [ws.run(["-X", f"lua_script:{ws.tshark.inner(crane)}", "-r", str(pcap), *args, *fields]) for args in runs]


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_crane_example_decodes_the_capture(tshark, tmp_path):
    try:
        with tshark.workspace(tmp_path) as ws:
            on, off = with_crane(ws, ["-2", "-o", "vm110.machine:crane"], ["-2"])
            alone = ws.run(["-r", str(ws.dir / "crane.pcap"), "-2", "-o", "vm110.machine:crane", "-V"])
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in on.stdout + on.stderr + off.stderr
    rows = [dict(zip(FIELDS, line.split("\t"))) for line in on.stdout.splitlines()]
    big, small = rows[1], rows[2]
    # The split burst: decoded once, from the reassembled data, on its last packet.
    assert not rows[0]["crane.hoist_height"]
    assert [big["crane.hoist_height"], big["crane.load"], big["crane.speed_limit"], big["crane.log_count"]] == \
        [str(HEIGHT), str(LOAD), str(SPEED), str(len(LOG))]
    assert int(big["crane.alarms"], 16) == ALARMS
    assert [big[f] in ("1", "True") for f in ("crane.alarm_overload", "crane.alarm_slack_rope", "crane.alarm_high_wind")] \
        == [True, True, False]
    assert [int(x) for x in big["crane.log.time"].split("|")] == [e[0] for e in LOG]
    assert [int(x, 16) for x in big["crane.log.code"].split("|")] == [e[1] for e in LOG]
    assert [int(x) for x in big["crane.log.value"].split("|")] == [e[2] for e in LOG]
    assert bytes.fromhex(big["vm110.reassembled"].replace(":", "")) == crane_data(HEIGHT, LOAD, ALARMS, SPEED, LOG)
    # A small unsplit VRPO: its own periodic data.
    assert [small["crane.hoist_height"], small["crane.load"], small["crane.speed_limit"], small["crane.log_count"]] == \
        [str(SMALL[0]), str(SMALL[1]), str(SMALL[3]), "0"]
    # Commands both ways.
    assert int(rows[3]["crane.opcode"], 16) == 0x01 and rows[3]["crane.set_speed_limit"] == "50"
    assert int(rows[5]["crane.opcode"], 16) == 0x81 and rows[5]["crane.alarm_text"] == "HIGH WIND"
    assert not rows[4]["crane.opcode"] and not rows[6]["crane.opcode"]
    # Without the Machine preference the crane dissector is not called.
    assert not any(line.split("\t")[1] for line in off.stdout.splitlines())
    # The main plugin alone does not load the example.
    assert "VM-110 EG-Link" in alone.stdout and "Crane" not in alone.stdout and "Hoist" not in alone.stdout


@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_crane_example_without_the_stream_analysis(tshark, tmp_path):
    """With the stream analysis off (vm110.analysis) the machine's dissectors still get what needs
    no other packet: the command data, and an unsplit VRPO's periodic data; a split burst is not
    reassembled. Trial: nothing at all was decoded for the crane, though the README gives the
    command table every command's data."""
    try:
        with tshark.workspace(tmp_path) as ws:
            runs = with_crane(ws, *([*passes, "-o", "vm110.machine:crane", "-o", "vm110.analysis:FALSE"]
                                    for passes in ([], ["-2"])))
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    for run in runs:
        assert T.LUA_ERROR not in run.stdout + run.stderr
        rows = [dict(zip(FIELDS, line.split("\t"))) for line in run.stdout.splitlines()]
        assert [r["crane.hoist_height"] for r in rows] == ["", "", str(SMALL[0]), "", "", "", ""]
        assert not any(r["vm110.reassembled"] for r in rows)
        assert int(rows[3]["crane.opcode"], 16) == 0x01 and rows[3]["crane.set_speed_limit"] == "50"
        assert int(rows[5]["crane.opcode"], 16) == 0x81 and rows[5]["crane.alarm_text"] == "HIGH WIND"
