"""What the dissector asks Wireshark on a visited frame with an invisible tree (tshark -2's second
pass under a display filter or -T fields on 4.4 and later): which vm110 fields are referenced,
about 90 TreeItem.referenced() calls, some 8 us a packet. tshark primes every frame of its second
pass alike, so one answer serves the pass; before, every packet asked again (26,562 calls for the
382 packets of normal.pcap on 4.0). Counted by a Lua script loaded first that wraps
TreeItem.referenced: a count of calls, not a timing."""
from __future__ import annotations

import pytest

import tshark_runner as T

pytestmark = pytest.mark.tshark

COUNTER = """\
local real, calls = TreeItem.referenced, 0
TreeItem.referenced = function(...) calls = calls + 1 return real(...) end
local tap = Listener.new("frame")
function tap.draw() io.stderr:write("referenced calls: " .. calls .. "\\n") end
"""


def referenced_calls(ws: T.Workspace, args: list[str]) -> tuple[int, str]:
    counter = ws.dir / "counter.lua"
    counter.write_text(COUNTER)
    proc = ws.run(["-n", "-X", f"lua_script:{ws.tshark.inner(counter)}", "-X", f"lua_script:{ws.plugin()}", *args],
                  plugin=False)
    assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-1000:]
    [line] = [x for x in proc.stderr.splitlines() if x.startswith("referenced calls: ")]
    return int(line.split(": ")[1]), proc.stdout


def test_the_second_pass_asks_which_fields_are_referenced_once(ws):
    capture = ws.dir / "normal.pcap"
    capture.write_bytes((T.REPO / "captures" / "normal.pcap").read_bytes())
    packets = 382
    single, shown = referenced_calls(ws, ["-r", str(capture), "-Y", "vm110.serial >= 0"])
    double, shown_2 = referenced_calls(ws, ["-r", str(capture), "-2", "-Y", "vm110.serial >= 0"])
    assert len(shown.splitlines()) == len(shown_2.splitlines()) == packets
    # (the first pass asks once, as before; the second pass once more: some 90 calls each, not 90 a packet)
    assert 0 < single < packets and 0 < double < 3 * single, (single, double)
