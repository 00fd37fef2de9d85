"""captures/crane.pcapng: a crane's machine data over the EG-Link (captures/crane.py), decoded by
vm110.lua with dissector/examples/crane.lua on every tshark (4.0, 4.4, 4.6). Every crane field of
every VRPO burst (reassembled when split) and of every crane command equals what the generator put
in (crane.pcapng.machine.json, written from the controller's own record of what it sent). The
capture and its truths are what `make captures` writes (byte for byte); its analysis truth
(crane.pcapng.truth.json) is checked with the other bundled captures' (test_analysis_truth,
test_dissector_analysis)."""
from __future__ import annotations

import importlib.util
import json

import pytest
import tshark_runner as T

CAPTURES = T.REPO / "captures"
CAPTURE = CAPTURES / "crane.pcapng"
CRANE_LUA = T.REPO / "dissector" / "examples" / "crane.lua"
ALARM_BITS = {"crane.alarm_overload": 0x01, "crane.alarm_high_wind": 0x02, "crane.alarm_slack_rope": 0x04,
              "crane.alarm_limit_switch": 0x08}
FIELDS = ("frame.number", "vm110.type", "vm110.command_id", "crane.hoist_height", "crane.load", "crane.alarms",
          *ALARM_BITS, "crane.speed_limit", "crane.log_count", "crane.log.time", "crane.log.code", "crane.log.value",
          "crane.opcode", "crane.set_speed_limit", "crane.reset_alarms", "crane.horn", "crane.alarm_text")


def generator():
    spec = importlib.util.spec_from_file_location("crane_capture", CAPTURES / "crane.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_crane_capture_is_what_make_captures_writes(tmp_path):
    out = tmp_path / CAPTURE.name
    generator().generate(str(out))
    for suffix in ("", ".truth.json", ".machine.json"):
        fresh, committed = out.with_name(out.name + suffix), CAPTURE.with_name(CAPTURE.name + suffix)
        assert fresh.read_bytes() == committed.read_bytes(), f"run `make captures`: {committed.name} is stale"


def flag(text: str) -> bool:
    assert text in ("0", "1", "True", "False"), text
    return text in ("1", "True")


def numbers(text: str, base: int = 10) -> list[int]:
    return [int(x, base) for x in text.split("|")] if text else []


@pytest.mark.tshark
def test_crane_lua_decodes_every_machine_field_as_sent(ws):
    truth = json.loads((CAPTURES / "crane.pcapng.machine.json").read_text())
    pcap, lua = ws.dir / CAPTURE.name, ws.dir / CRANE_LUA.name
    pcap.write_bytes(CAPTURE.read_bytes())
    lua.write_bytes(CRANE_LUA.read_bytes())
    fields = ["-T", "fields", "-E", "aggregator=|", "-E", "occurrence=a", *(a for f in FIELDS for a in ("-e", f))]
    done = ws.run(["-X", f"lua_script:{ws.tshark.inner(lua)}", "-o", "vm110.machine:crane", "-2", "-r", str(pcap),
                   *fields])
    assert T.LUA_ERROR not in done.stdout + done.stderr
    rows = [dict(zip(FIELDS, line.split("\t"))) for line in done.stdout.splitlines()]
    periodic = [r for r in rows if r["crane.hoist_height"]]
    assert len(periodic) == len(truth["periodic"]) == 200
    split = 0
    for row, sent in zip(periodic, truth["periodic"]):
        where = f"frame {row['frame.number']}, cycle {sent['cycle']}"
        assert row["vm110.type"] == "VRPO", where
        assert [int(row[f"crane.{k}"]) for k in ("hoist_height", "load", "speed_limit", "log_count")] == \
            [sent["hoist_height"], sent["load"], sent["speed_limit"], len(sent["log"])], where
        assert int(row["crane.alarms"], 16) == sent["alarms"], where
        assert {f: flag(row[f]) for f in ALARM_BITS} == {f: bool(sent["alarms"] & bit) for f, bit in ALARM_BITS.items()}
        log = list(zip(numbers(row["crane.log.time"]), numbers(row["crane.log.code"], 16),
                       numbers(row["crane.log.value"])))
        assert log == [tuple(e) for e in sent["log"]], where
        split += sent["bytes"] > 488
    assert split == 20                          # the full log once a second: a burst of two VRPO
    assert {p["alarms"] for p in truth["periodic"]} >= {0, 0x01, 0x02, 0x03, 0x04, 0x08}   # each alarm, alone too
    # Commands, one transmission each (no loss): the operator's VRCI and the crane's VRCO in order.
    for kind in ("VRCI", "VRCO"):
        decoded = [r for r in rows if r["vm110.type"] == kind]
        sent = [c for c in truth["commands"] if c["type"] == kind]
        assert len(decoded) == len(sent) > 0
        for row, command in zip(decoded, sent):
            assert int(row["crane.opcode"], 16) == command["opcode"]
            if "set_speed_limit" in command:
                assert int(row["crane.set_speed_limit"]) == command["set_speed_limit"]
            if "reset_alarms" in command:
                assert int(row["crane.reset_alarms"], 16) == command["reset_alarms"]
            if "horn" in command:
                assert flag(row["crane.horn"]) == command["horn"]
            if "alarm_text" in command:
                assert row["crane.alarm_text"] == command["alarm_text"]
    # The acknowledgements and VRPI carry no crane data.
    assert not any(r["crane.opcode"] or r["crane.hoist_height"] for r in rows if r["vm110.type"] in ("VRPI", "VRAI", "VRAO"))
