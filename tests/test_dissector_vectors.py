"""Every shared vector through the Lua dissector in real tshark, read back through pyshark.

For each tshark (host 4.0 / Lua 5.2, chroot 4.4 / Lua 5.4) the vectors are written to one capture
per CRC setting, dissected once, and every field, display name, problem and warning compared with
the vector. A second read of the same capture as PDML checks what pyshark flattens away: which
field each expert is attached to, and that the tree covers every byte.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import pyshark
import pytest

import tshark_runner as T
from vectorlib import load_vectors, packet_bytes, vector_ids

pytestmark = pytest.mark.tshark

VECTORS = load_vectors()
ENUM_FIELDS = ("bu_state", "eg_link", "ec_link", "c_link", "ru_state", "ru_disabled", "ru_cable",
               "ru_docked", "encoder_switch")


@dataclass
class Seen:
    """What tshark made of one vector: through pyshark, and through PDML."""

    layer: object = None                  # pyshark layer, None when there is no vm110 tree
    frame: T.Frame = None
    fields: dict = field(default_factory=dict)
    experts: list = field(default_factory=list)   # (abbrev, message)


def _pyshark_read(ws: T.Workspace, pcap, prefs: dict) -> list:
    # Preferences after -X: tshark 4.4 rejects a plugin's -o given before the plugin is loaded.
    capture = pyshark.FileCapture(str(pcap), tshark_path=ws.pyshark_tshark_path(), keep_packets=False,
                                  custom_parameters=["-X", f"lua_script:{ws.plugin_file()}", *T.pref_args(prefs)])
    try:
        return [pkt.vm110 if "vm110" in pkt else None for pkt in capture]
    finally:
        capture.close()


def _from_layer(layer) -> tuple[dict, list]:
    fields, experts = {}, []
    for name, container in layer._all_fields.items():
        if name.startswith("vm110.expert."):
            experts += [(name, f.showname) for f in container.all_fields]
        elif name.startswith("vm110."):
            short = name[len("vm110."):]
            if short in T.NOT_CANONICAL:
                continue
            main = container.main_field
            item = T.Item(name, main.show or "", main.showname or "", 0, 0, "")
            fields[short] = T.item_value(short, item)
    return fields, experts


@pytest.fixture(scope="module", params=T.RUNNERS, ids=lambda r: r.name)
def seen(request, tmp_path_factory) -> dict[str, Seen]:
    runner = request.param
    groups = defaultdict(list)
    for vector in VECTORS:
        groups[(vector["crc_variant"], vector["crc_byte_order"])].append(vector)
    out = {}
    try:
        with runner.workspace(tmp_path_factory.mktemp(f"vectors-{runner.name}")) as ws:
            for (variant, order), vectors in groups.items():
                pcap = ws.dir / f"vectors-{variant}-{order}.pcap"
                T.write_pcap(pcap, (packet_bytes(v) for v in vectors))
                prefs = {"vm110.crc_variant": variant, "vm110.crc_byte_order": order}
                layers = _pyshark_read(ws, pcap, prefs)
                frames, output = T.dissect_pdml(ws, pcap, prefs)
                assert T.LUA_ERROR not in output
                assert len(layers) == len(frames) == len(vectors)
                for vector, layer, frame in zip(vectors, layers, frames):
                    s = Seen(layer, frame)
                    if layer is not None:
                        s.fields, s.experts = _from_layer(layer)
                    out[vector["name"]] = s
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    return out


@pytest.mark.parametrize("vector", VECTORS, ids=vector_ids(VECTORS))
def test_vector_through_tshark(seen, vector):
    s = seen[vector["name"]]
    if not vector["hex"]:
        # UDP hands no empty payload to any dissector: there is nothing for vm110 to show.
        assert s.layer is None and s.frame.vm110 is False
        return
    assert s.layer is not None, "no vm110 tree"
    assert s.fields == vector["fields"]
    problems, warnings = [], []
    for abbrev, message in s.experts:
        code = abbrev[len("vm110.expert."):]
        if code in T.PROBLEM_CODES:
            problems.append(code)
        elif code in T.FIELD_WARNING_CODES:
            warnings.append(f"{code}:{T._FIELD_IN_MESSAGE.match(message).group(1)}")
        elif code != "es_relays_open":
            warnings.append(code)
    assert sorted(problems) == vector["problems"]
    assert sorted(warnings) == vector["warnings"]
    relays_experts = [m for a, m in s.experts if a == "vm110.expert.es_relays_open"]
    assert bool(relays_experts) == bool(vector["fields"].get("es_relays_open"))


@pytest.mark.parametrize("vector", VECTORS, ids=vector_ids(VECTORS))
def test_vector_display_names(seen, vector):
    s = seen[vector["name"]]
    if s.layer is None:
        assert not vector["names"]
        return
    names = vector["names"]
    type_item = s.layer.get_field("vm110.type")
    if "type" in names:
        assert type_item.showname == f"Packet ID: {vector['fields']['type']} ({names['type']})"
    elif type_item is not None:
        assert type_item.showname.endswith("(Unknown)")
    for name in ENUM_FIELDS:
        if name not in vector["fields"]:
            assert name not in names
            continue
        shown = s.layer.get_field(f"vm110.{name}").showname.split(": ", 1)[1]
        value = vector["fields"][name]
        expected = names[name] if names[name].startswith("Unknown") else f"{names[name]} (0x{value:02x})"
        assert shown == expected


@pytest.mark.parametrize("vector", VECTORS, ids=vector_ids(VECTORS))
def test_vector_tree_structure(seen, vector):
    """Experts sit on the field they name, and every byte of the packet is in some field."""
    frame = seen[vector["name"]].frame
    if not frame.vm110:
        return
    problems, warnings, odd = T.problems_and_warnings(frame)
    assert odd == []
    assert (problems, warnings) == (vector["problems"], vector["warnings"])
    assert frame.size == len(packet_bytes(vector))
    assert T.uncovered_bytes(frame) == []
