"""The protocol declaration (vm110/protocol.py) and what is derived from it: the Lua tables stay
in step with it, the hand-fused fast paths of the analysis agree with the plain derived code, and a
field added to the declaration reaches decode, the layers, the analysis record and the Lua
dissector with no other edit."""
from __future__ import annotations

import random
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from vectorlib import load_vectors, packet_bytes
from vm110 import constants as C
from vm110 import protocol as P
from vm110.analysis import collect, engine
from vm110.capture import linktypes as L
from vm110.capture.writer import PcapngWriter, PcapWriter, UdpFlow
from vm110.decode import decode
from vm110.encode import encode
from vm110.fuzz.mutate import default_fields, structural
from vm110.layers import PAYLOAD_CLASSES, VM110

ROOT = Path(__file__).resolve().parents[1]
LUA_TABLES = ROOT / "scripts" / "lua-tables"


def test_the_lua_tables_are_up_to_date():
    run = subprocess.run([sys.executable, str(LUA_TABLES), "--check"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr


def test_an_edited_lua_section_is_found_out_of_date(tmp_path):
    lua = tmp_path / "vm110.lua"
    text = (ROOT / "dissector" / "vm110.lua").read_text()
    lua.write_text(text.replace('label = "Joystick 1"', 'label = "Stick 1"', 1))
    run = subprocess.run([sys.executable, str(LUA_TABLES), "--check", str(lua)], capture_output=True, text=True)
    assert run.returncode == 1 and "make lua-tables" in run.stderr
    subprocess.run([sys.executable, str(LUA_TABLES), str(lua)], check=True, capture_output=True)
    assert lua.read_text() == text


def test_the_declaration_gives_the_sizes_of_ts_0006():
    # TS-0006 section 4: payload sizes, and the header of section 3.
    assert P.PAYLOAD_BOUNDS == {
        C.PacketType.VRPI: (46, 46), C.PacketType.VRPO: (2, 490), C.PacketType.VRCI: (22, 22),
        C.PacketType.VRCO: (22, 22), C.PacketType.VRAI: (2, 2), C.PacketType.VRAO: (2, 2)}
    assert P.HEADER.format == "<4sHHHHI" and P.SIZE_OFFSET == 10
    assert [f.name for f in P.HEADER_FIELDS] == ["revision", "origin", "serial", "size", "spare"]


def test_the_scapy_layers_are_the_declaration():
    for ptype, cls in PAYLOAD_CLASSES.items():
        packet = P.PACKETS[ptype]
        names = [f.name for f in packet.fields] + ([packet.tail.name] if packet.tail else [])
        assert [f.name for f in cls.fields_desc] == names
        assert sum(f.sz for f in cls.fields_desc[:len(packet.fields)]) == packet.min_size
    assert [f.name for f in VM110.fields_desc] == ["type", *(f.name for f in P.HEADER_FIELDS), "crc"]


# --- The analysis engine's hand-fused reads against the declaration and decode() -------------------
def test_the_fused_header_reads_are_the_declared_header():
    data = encode({"type": "VRCI", "revision": 3, "origin": 0x0102, "serial": 77, "command_id": 9})
    pid, revision, size = engine._HDR.unpack_from(data)
    fields = decode(data)
    assert (pid.decode(), revision, size) == (fields["type"], fields["revision"], fields["size"])
    # _FUSED / _HEAD_FIELDS read the packet ID, revision and size at fixed places of the frame.
    udp = L.ETH_HEADER_LEN + L.IPV4_MIN_HEADER + L.UDP_HEADER_LEN + 16        # after the pcap record header
    at = {name: off - udp for name, _, off in engine._HEAD_FIELDS if off >= udp}
    assert at == {"pid": 0, "rev": P.HEADER_OFFSETS["revision"], "size": P.SIZE_OFFSET}


def _packets() -> list[bytes]:
    """The shared vectors and structural damage to one valid packet of each type."""
    rng = random.Random(15)
    out = [packet_bytes(v) for v in load_vectors()]
    for ptype in C.PacketType:
        valid = encode(dict(default_fields(ptype, 5), type=ptype.value, serial=3))
        out.append(valid)
        out.extend(data for _, data in structural(valid, rng))
    return [p for p in out if len(p) <= 1400]


class _Records:
    """Stands in for the Analysis: keeps the legal packets' frame numbers."""

    def __init__(self) -> None:
        self.frames: list[int] = []

    def feed(self, rec: np.ndarray, sources: dict) -> None:
        self.frames.extend(rec["frame"].tolist())


@pytest.mark.parametrize("form", ["pcap", "pcapng", "raw-ip"])
def test_the_fast_paths_judge_every_packet_as_decode_does(form, tmp_path):
    """Each walk of the fast engine (fused pcap, fused pcapng, datagrams) records exactly the
    packets that decode() finds legal, and counts the rest illegal."""
    packets = _packets()
    flow = UdpFlow("10.0.0.10", C.INPUT_PORT, "239.255.42.20", C.INPUT_PORT)
    path = tmp_path / f"mixed.{form}"
    with open(path, "wb") as out:
        if form == "raw-ip":
            writer = PcapWriter(out, linktype=L.LINKTYPE_RAW)
            frames = [flow.frame(p)[L.ETH_HEADER_LEN:] for p in packets]
        else:
            writer = (PcapWriter if form == "pcap" else PcapngWriter)(out)
            frames = [flow.frame(p) for p in packets]
        writer.write_many((1_000 * i, frame) for i, frame in enumerate(frames))
        writer.close()
    records = _Records()
    got = engine.FastEngine()._read(str(path), "mpeg2", "little", records)
    legal = [i + 1 for i, p in enumerate(packets) if not decode(p)["problems"]]
    assert records.frames == legal
    assert got.illegal == len(packets) - len(legal) > 0


def test_the_record_keeps_the_declared_state_bytes():
    fields = {"type": "VRPI", "bu_state": 0x11, "armed_ru": 0x0C07, "ru_state": 3, "ru_battery": 88,
              "ru_disabled": 2, "joystick1": -5}
    data = encode(fields)
    rec = np.frombuffer(collect.RECORD.pack(1.0, 1, 0, C.INPUT_PORT, data), dtype=collect.RECORD_DTYPE)[0]
    state = dict(zip(collect.STATE_FIELDS, collect.STATE.unpack(rec["state"].tobytes())))
    decoded = decode(data)
    assert state == {name: decoded[name] for name in collect.STATE_FIELDS}
    assert (rec["origin"], rec["serial"], rec["size"]) == (decoded["origin"], decoded["serial"], decoded["size"])
    assert collect.STATE_FIELDS[-1] == "ru_disabled" and "joystick1" not in collect.STATE_FIELDS


# --- One edit: a field added to the declaration of a copy ---------------------------------------
NEW_FIELD = ('    Field("ru_mood", "u8", "RU mood", "How the remote unit feels", enum=RU_CABLE, range=(0, 1), '
             'ru=True, state=True),\n')
ANCHOR = '    *(Field(f"joystick{i}", "s16"'

CHECK_COPY = textwrap.dedent("""
    import json, sys
    import vm110
    assert vm110.__file__.startswith(sys.argv[1]), vm110.__file__
    from vm110.decode import decode
    from vm110.encode import encode
    from vm110.layers import VM110, VRPI
    from vm110.analysis import collect
    data = encode({"type": "VRPI", "armed_ru": 0, "ru_mood": 7, "joystick1": 12})
    fields = decode(data)
    layer = VM110(data)
    print(json.dumps({
        "size": fields["size"], "ru_mood": fields["ru_mood"], "joystick1": fields["joystick1"],
        "warnings": fields["warnings"],
        "layer": layer[VRPI].ru_mood, "layer_bytes": bytes(VM110() / VRPI(ru_mood=7, joystick1=12)) == data,
        "state": list(collect.STATE_FIELDS),
        "hex": data.hex(),
    }))
""")


def test_a_field_added_to_the_declaration_reaches_everything(tmp_path):
    for part in ("pcap_tools/vm110", "scripts/lua-tables", "dissector/vm110.lua"):
        src, dst = ROOT / part, tmp_path / part
        dst.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__")) if src.is_dir()
         else shutil.copy(src, dst))
    declaration = tmp_path / "pcap_tools/vm110/protocol.py"
    text = declaration.read_text()
    assert text.count(ANCHOR) == 1
    declaration.write_text(text.replace(ANCHOR, NEW_FIELD + ANCHOR))

    lua_tables = tmp_path / "scripts/lua-tables"
    assert subprocess.run([sys.executable, str(lua_tables), "--check"], capture_output=True).returncode == 1
    subprocess.run([sys.executable, str(lua_tables)], check=True, capture_output=True)
    assert subprocess.run([sys.executable, str(lua_tables), "--check"], capture_output=True).returncode == 0

    run = subprocess.run([sys.executable, "-c", CHECK_COPY, str(tmp_path)], capture_output=True, text=True,
                         env={"PYTHONPATH": str(tmp_path / "pcap_tools"), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    import json
    got = json.loads(run.stdout)
    assert got["size"] == 47 and got["ru_mood"] == 7 and got["joystick1"] == 12
    # the field's declared rules: value names (0, 1), range 0..1, zero while no RU is armed
    assert {"unknown_enum:ru_mood", "out_of_range:ru_mood", "disarmed_ru_data:ru_mood"} <= set(got["warnings"])
    assert got["layer"] == 7 and got["layer_bytes"]
    assert got["state"][-1] == "ru_mood"

    # The regenerated dissector decodes it too (host tshark 4.0, Lua 5.2).
    if shutil.which("tshark") is None:
        pytest.skip("no host tshark")
    data = bytes.fromhex(got["hex"])
    flow = UdpFlow("10.0.0.10", C.INPUT_PORT, "239.255.42.20", C.INPUT_PORT)
    capture = tmp_path / "one.pcap"
    with open(capture, "wb") as stream, PcapWriter(stream) as writer:
        writer.write_many([(0, flow.frame(data))])
    out = subprocess.run(["tshark", "-n", "-X", f"lua_script:{tmp_path / 'dissector/vm110.lua'}", "-r", str(capture),
                          "-T", "fields", "-e", "vm110.ru_mood", "-e", "vm110.joystick1", "-e", "vm110.size"],
                         capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["0x07", "12", "47"], out.stderr      # value-named fields show in hex
    tree = subprocess.run(["tshark", "-n", "-X", f"lua_script:{tmp_path / 'dissector/vm110.lua'}", "-r",
                           str(capture), "-V", "-O", "vm110"], capture_output=True, text=True, timeout=60).stdout
    assert "RU mood: Unknown (0x07)" in tree or "RU mood: 0x07" in tree
    assert "vm110.ru_mood is outside 0..1" in tree


def test_packet_spans_are_the_layout():
    vrci = P.PACKETS[C.PacketType.VRCI]
    data = encode({"type": "VRCI", "command_id": 0x0203, "command_data": b"ABC".ljust(16, b"\0")})
    payload = data[C.PREFIX_LEN:-C.CRC_LEN]
    assert payload[vrci.span("command_data")] == b"ABC".ljust(16, b"\0")
    assert struct.unpack("<H", payload[vrci.span("command_id")]) == (0x0203,)
