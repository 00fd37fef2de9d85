"""Every shared vector through the Lua dissector in real tshark, read back through pyshark.

For each tshark (host 4.0 / Lua 5.2, chroot 4.4 / Lua 5.4) the vectors are written to one capture
per CRC setting, dissected once, and every field, display name, problem and warning compared with
the vector; a failure lists every vector that differs and how. A second read of the same capture as PDML checks what pyshark flattens away: which
field each expert is attached to, and that the tree covers every byte.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import pytest

import tshark_runner as T
from vm110.analysis.tshark_packets import packets
from vectorlib import load_vectors, packet_bytes

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
    """The vm110 layer of each packet, read through pyshark as the tshark engine reads it."""
    # Preferences after -X: tshark 4.4 rejects a plugin's -o given before the plugin is loaded.
    read = packets(str(pcap), ["-X", f"lua_script:{ws.plugin_file()}", *T.pref_args(prefs)],
                   tshark_path=ws.pyshark_tshark_path())
    return [pkt.vm110 if "vm110" in pkt else None for pkt in read]


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


def _dissect_all(runner: T.Tshark, base) -> dict[str, Seen]:
    """Every vector through tshark: one capture and two runs (pyshark, PDML) per CRC setting."""
    groups = defaultdict(list)
    for vector in VECTORS:
        groups[(vector["crc_variant"], vector["crc_byte_order"])].append(vector)
    out = {}
    with runner.workspace(base) as ws:
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
    return out


def _fields_and_experts(s: Seen, vector: dict) -> list[str]:
    if not vector["hex"]:
        # UDP hands no empty payload to any dissector: there is nothing for vm110 to show.
        return [] if s.layer is None and not s.frame.vm110 else ["a tree for an empty datagram"]
    if s.layer is None:
        return ["no vm110 tree"]
    errors = []
    if s.fields != vector["fields"]:
        keys = sorted(set(s.fields) | set(vector["fields"]))
        errors += [f"{k}: tshark {s.fields.get(k)!r}, vector {vector['fields'].get(k)!r}"
                   for k in keys if s.fields.get(k) != vector["fields"].get(k)]
    problems, warnings = [], []
    for abbrev, message in s.experts:
        code = abbrev[len("vm110.expert."):]
        if code in T.PROBLEM_CODES:
            problems.append(code)
        elif code in T.FIELD_WARNING_CODES:
            match = T._FIELD_IN_MESSAGE.match(message)
            warnings.append(f"{code}:{match.group(1) if match else message}")
        elif code != "es_relays_open":
            warnings.append(code)
    if (sorted(problems), sorted(warnings)) != (vector["problems"], vector["warnings"]):
        errors.append(f"experts {sorted(problems)} {sorted(warnings)}")
    relays_experts = [m for a, m in s.experts if a == "vm110.expert.es_relays_open"]
    if bool(relays_experts) != bool(vector["fields"].get("es_relays_open")):
        errors.append(f"es_relays_open experts {relays_experts}")
    return errors


def _display_names(s: Seen, vector: dict) -> list[str]:
    if s.layer is None:
        return [] if not vector["names"] else ["no tree to show names"]
    names, errors = vector["names"], []
    type_item = s.layer.get_field("vm110.type")
    if "type" in names:
        expected = f"Packet ID: {vector['fields']['type']} ({names['type']})"
        if type_item.showname != expected:
            errors.append(f"type shown as {type_item.showname!r}, expected {expected!r}")
    elif type_item is not None and not type_item.showname.endswith("(Unknown)"):
        errors.append(f"unknown type shown as {type_item.showname!r}")
    for name in ENUM_FIELDS:
        if name not in vector["fields"]:
            continue
        shown = s.layer.get_field(f"vm110.{name}").showname.split(": ", 1)[1]
        value = vector["fields"][name]
        expected = names[name] if names[name].startswith("Unknown") else f"{names[name]} (0x{value:02x})"
        if shown != expected:
            errors.append(f"{name} shown as {shown!r}, expected {expected!r}")
    return errors


def _tree_structure(s: Seen, vector: dict) -> list[str]:
    """Experts sit on the field they name, and every byte of the packet is in some field."""
    frame = s.frame
    if not frame.vm110:
        return []
    problems, warnings, odd = T.problems_and_warnings(frame)
    errors = odd[:]
    if (problems, warnings) != (vector["problems"], vector["warnings"]):
        errors.append(f"PDML experts {problems} {warnings}")
    if frame.size != len(packet_bytes(vector)):
        errors.append(f"tree spans {frame.size} bytes")
    if T.uncovered_bytes(frame):
        errors.append(f"bytes in no field: {T.uncovered_bytes(frame)}")
    return errors


# One test per tshark (not per vector): each tshark reads the vectors once, on one xdist worker.
@pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
def test_vectors_through_tshark(tshark, tmp_path):
    try:
        seen = _dissect_all(tshark, tmp_path)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    failures = {}
    for vector in VECTORS:
        s = seen[vector["name"]]
        errors = _fields_and_experts(s, vector) + _display_names(s, vector) + _tree_structure(s, vector)
        if errors:
            failures[vector["name"]] = errors
    assert not failures, "\n".join(f"{name}: {errors}" for name, errors in failures.items())
