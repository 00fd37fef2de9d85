"""Writes the shared vectors (tests/vectors/*.json) from the specification.

Independent of the package under test: packets are packed here with `struct` from the layouts of
TS-0006 chapter 4, the CRC is the bit-by-bit reference, and every expected problem and warning is
written down by hand per case. Run it again only to add cases: `python tests/vectors/make_vectors.py`.
"""
from __future__ import annotations

import json
import pathlib
import struct
import sys

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from reference_crc import reference_crc  # noqa: E402

# TS-0006 chapter 4, field by field: (name, struct code)
VRPI = [("bu_state", "B"), ("vlaps", "B"), ("unarmed_rus", "B"), ("eg_link", "B"), ("ec_link", "B"),
        ("c_link", "B"), ("armed_ru", "H"), ("ru_state", "B"), ("ru_battery", "B"), ("ru_rssi", "B"),
        ("ru_cable", "B"), ("ru_docked", "B"), ("ru_disabled", "B"),
        ("joystick1", "h"), ("joystick2", "h"), ("joystick3", "h"), ("joystick4", "h"),
        ("switch1", "h"), ("switch2", "h"), ("switch3", "h"), ("switch4", "h"),
        ("switch5", "h"), ("switch6", "h"), ("switch7", "h"), ("switch8", "h"),
        ("encoder", "B"), ("encoder_switch", "B"), ("vrpi_spare", "6s")]
COMMAND = [("command_id", "H"), ("command_spare", "I"), ("command_data", "16s")]
ACK = [("command_id", "H")]
VRPO = [("packet_number", "H")]
LAYOUT = {"VRPI": VRPI, "VRCI": COMMAND, "VRCO": COMMAND, "VRAI": ACK, "VRAO": ACK, "VRPO": VRPO}
BYTE_FIELDS = {"vrpi_spare", "command_data", "periodic_data"}

BU_STATE = {0x00: "Initial", 0x01: "Stopped", 0x02: "External link error", 0x03: "Blocked",
            0x04: "Failed", 0x10: "Disarmed", 0x11: "Armed"}
LINK = {0: "Unused", 1: "Operational", 2: "No link", 3: "Link error", 4: "Interface error",
        5: "Data error", 6: "Passive"}
RU_STATE = {0: "Initial", 1: "Disarmed", 2: "Armed", 3: "Enabled", 4: "Stopped"}
RU_DISABLED = {0: "Enabled", 1: "Disabled (tilt)", 2: "Disabled (inactivity)"}
CABLE = {0: "Wireless", 1: "Cable"}
DOCKED = {0: "Not docked", 1: "Docked"}
ENC_SWITCH = {0: "Released", 1: "Pushed"}
ENUMS = {"bu_state": BU_STATE, "eg_link": LINK, "ec_link": LINK, "c_link": LINK, "ru_state": RU_STATE,
         "ru_disabled": RU_DISABLED, "ru_cable": CABLE, "ru_docked": DOCKED, "encoder_switch": ENC_SWITCH}
TYPE_NAMES = {"VRPI": "VisionRemote Periodic Input", "VRPO": "VisionRemote Periodic Output",
              "VRCI": "VisionRemote Command Input", "VRCO": "VisionRemote Command Output",
              "VRAI": "VisionRemote Acknowledge Input", "VRAO": "VisionRemote Acknowledge Output"}

ARMED = dict(bu_state=0x11, vlaps=1, unarmed_rus=0, eg_link=1, ec_link=1, c_link=1, armed_ru=0x0C07,
             ru_state=3, ru_battery=88, ru_rssi=76, ru_cable=0, ru_docked=0, ru_disabled=0,
             joystick1=250, joystick2=-400, joystick3=0, joystick4=1000,
             switch1=1, switch2=0, switch3=-1, switch4=1000, switch5=3, switch6=2, switch7=0, switch8=0,
             encoder=200, encoder_switch=1, vrpi_spare=bytes(6))
ZERO_VRPI = {name: (bytes(6) if name == "vrpi_spare" else 0) for name, _ in VRPI}
DISARMED = {**ZERO_VRPI, "bu_state": 0x10, "vlaps": 1, "unarmed_rus": 2, "eg_link": 1, "ec_link": 1,
            "c_link": 6}
DATA16 = bytes(range(0x41, 0x51))


def pack_payload(ptype: str, fields: dict) -> bytes:
    out = b"".join(struct.pack("<" + code, fields[name]) for name, code in LAYOUT[ptype])
    return out + fields.get("periodic_data", b"")


def vector(name: str, description: str, ptype: str, payload_fields: dict | None = None, *,
           revision: int = 0, origin: int = 0, serial: int = 1, spare: int = 0, size: int | None = None,
           raw_payload: bytes | None = None, crc: int | None = None, crc_xor: int = 0, cut: int | None = None,
           trailing: bytes = b"", variant: str = "mpeg2", order: str = "little",
           problems: tuple = (), warnings: tuple = (), fields: dict | None = None) -> dict:
    """One vector. `fields` (when given) replaces the expected fields computed from the inputs."""
    payload = raw_payload if raw_payload is not None else pack_payload(ptype, payload_fields or {})
    size = len(payload) if size is None else size
    head = ptype.encode("latin-1") + struct.pack("<HHHHI", revision, origin, serial, size, spare)
    body = head + payload
    stored = (reference_crc(body, variant) if crc is None else crc) ^ crc_xor
    packet = body + stored.to_bytes(4, order) + trailing
    if cut is not None:
        packet = packet[:cut]
    if fields is None:
        fields = dict(type=ptype, revision=revision, origin=origin, serial=serial, size=size, spare=spare)
        if ptype in LAYOUT:
            fields["direction"] = "Input" if ptype[3] == "I" else "Output"
        fields["crc"] = stored
        fields["crc.calculated"] = reference_crc(body, variant)
        fields["crc.status"] = "Good" if stored == fields["crc.calculated"] else "Bad"
        if ptype in LAYOUT and revision == 0:
            fields.update(payload_fields or {})
            if ptype == "VRPO" and len(payload) >= 2:
                fields["periodic_data"] = payload[2:490]
            if ptype == "VRPI":
                fields["es_relays_open"] = payload_fields["bu_state"] < 0x10
    return {
        "name": name, "description": description, "hex": packet.hex(),
        "crc_variant": variant, "crc_byte_order": order,
        "fields": {k: (v.hex() if isinstance(v, bytes) else v) for k, v in fields.items()},
        "names": names_of(fields),
        "problems": sorted(problems), "warnings": sorted(warnings),
    }


def names_of(fields: dict) -> dict:
    names = {}
    if fields.get("type") in TYPE_NAMES:
        names["type"] = TYPE_NAMES[fields["type"]]
    for name, table in ENUMS.items():
        if name in fields:
            names[name] = table.get(fields[name], f"Unknown (0x{fields[name]:02x})")
    return names


def header_vectors() -> list[dict]:
    return [
        vector("header_serial_0", "serial 0", "VRAO", dict(command_id=1), serial=0),
        vector("header_serial_65535", "serial at its maximum, before the wrap", "VRAO", dict(command_id=1),
               serial=65535),
        vector("header_origin_max_input", "origin 0xFFFF on an input packet is fine", "VRAI",
               dict(command_id=2), origin=0xFFFF),
        vector("header_origin_output", "origin must be 0 on output packets", "VRAO", dict(command_id=2),
               origin=0x0101, warnings=("origin_nonzero:origin",)),
        vector("header_spare_nonzero", "header spare not zero", "VRPI", ARMED, spare=0xDEADBEEF,
               warnings=("spare_nonzero:spare",)),
    ]


def vrpi_vectors() -> list[dict]:
    out = [
        vector("vrpi_armed_typical", "armed remote in normal operation, switches of every kind", "VRPI",
               ARMED, origin=0x0101, serial=1234),
        vector("vrpi_all_zero", "every payload byte zero: BU Initial, relays open", "VRPI", ZERO_VRPI),
        vector("vrpi_disarmed", "disarmed base, two unarmed remotes, C-Link passive", "VRPI", DISARMED,
               origin=0x0101),
        vector("vrpi_joystick_limits", "joysticks at +/-1000", "VRPI",
               {**ARMED, "joystick1": 1000, "joystick2": -1000, "joystick3": 999, "joystick4": -999}),
        vector("vrpi_joystick_beyond", "joysticks beyond +/-1000", "VRPI",
               {**ARMED, "joystick1": 1001, "joystick2": -1001, "joystick3": 32767, "joystick4": -32768},
               warnings=("out_of_range:joystick1", "out_of_range:joystick2", "out_of_range:joystick3",
                         "out_of_range:joystick4")),
        vector("vrpi_switch_limits", "switches at -1 and 1000", "VRPI",
               {**ARMED, "switch1": -1, "switch8": 1000}),
        vector("vrpi_switch_beyond", "switches at -2 and 1001", "VRPI",
               {**ARMED, "switch1": -2, "switch8": 1001},
               warnings=("out_of_range:switch1", "out_of_range:switch8")),
        vector("vrpi_battery_rssi_100", "battery and RSSI at 100 %", "VRPI",
               {**ARMED, "ru_battery": 100, "ru_rssi": 100}),
        vector("vrpi_battery_rssi_101", "battery and RSSI at 101 %", "VRPI",
               {**ARMED, "ru_battery": 101, "ru_rssi": 255},
               warnings=("out_of_range:ru_battery", "out_of_range:ru_rssi")),
        vector("vrpi_vlaps_3", "three VLAPs", "VRPI", {**ARMED, "vlaps": 3}),
        vector("vrpi_vlaps_4", "four VLAPs is beyond the range", "VRPI", {**ARMED, "vlaps": 4},
               warnings=("out_of_range:vlaps",)),
        vector("vrpi_encoder_255", "encoder wraps freely: 255 is fine", "VRPI", {**ARMED, "encoder": 255}),
        vector("vrpi_spare_nonzero", "VRPI spare bytes not zero", "VRPI",
               {**ARMED, "vrpi_spare": b"\x00\x01\x00\x00\x00\xff"}, warnings=("spare_nonzero:vrpi_spare",)),
        vector("vrpi_disarmed_with_ru_data", "armed_ru 0 but RU fields set", "VRPI",
               {**DISARMED, "ru_state": 3, "ru_battery": 50, "joystick1": 10, "switch2": -1},
               warnings=("disarmed_ru_data:joystick1", "disarmed_ru_data:ru_battery",
                         "disarmed_ru_data:ru_state", "disarmed_ru_data:switch2")),
        vector("vrpi_armed_ru_ffff", "RU ID 0xFFFF", "VRPI", {**ARMED, "armed_ru": 0xFFFF}),
    ]
    for value, label in BU_STATE.items():
        ru = ARMED if value == 0x11 else {**ARMED, "bu_state": value}
        out.append(vector(f"vrpi_bu_state_{value:02x}", f"BU state {label}", "VRPI", ru))
    for value in (0x05, 0x12, 0xFF):
        out.append(vector(f"vrpi_bu_state_unknown_{value:02x}", "BU state not in the set", "VRPI",
                          {**ARMED, "bu_state": value}, warnings=("unknown_enum:bu_state",)))
    for value, label in LINK.items():
        out.append(vector(f"vrpi_link_{value}", f"every link {label}", "VRPI",
                          {**ARMED, "eg_link": value, "ec_link": value, "c_link": value}))
    out.append(vector("vrpi_link_unknown", "link statuses 7, 0x80, 0xFF", "VRPI",
                      {**ARMED, "eg_link": 7, "ec_link": 0x80, "c_link": 0xFF},
                      warnings=("unknown_enum:c_link", "unknown_enum:ec_link", "unknown_enum:eg_link")))
    for value, label in RU_STATE.items():
        out.append(vector(f"vrpi_ru_state_{value}", f"RU state {label}", "VRPI", {**ARMED, "ru_state": value}))
    out.append(vector("vrpi_ru_state_unknown", "RU state 5", "VRPI", {**ARMED, "ru_state": 5},
                      warnings=("unknown_enum:ru_state",)))
    for value, label in RU_DISABLED.items():
        out.append(vector(f"vrpi_ru_disabled_{value}", f"RU {label}", "VRPI", {**ARMED, "ru_disabled": value}))
    out.append(vector("vrpi_flags_set", "cable, docked, encoder pushed", "VRPI",
                      {**ARMED, "ru_cable": 1, "ru_docked": 1, "encoder_switch": 1}))
    out.append(vector("vrpi_flags_unknown", "flags outside their sets", "VRPI",
                      {**ARMED, "ru_disabled": 3, "ru_cable": 2, "ru_docked": 7, "encoder_switch": 2},
                      warnings=("unknown_enum:encoder_switch", "unknown_enum:ru_cable",
                                "unknown_enum:ru_disabled", "unknown_enum:ru_docked")))
    out.append(vector("vrpi_extra_payload", "VRPI with two bytes beyond its layout (size 48)", "VRPI",
                      raw_payload=pack_payload("VRPI", ARMED) + b"\x01\x02",
                      fields=_with(ARMED, "VRPI", size=48, extra=b"\x01\x02"),
                      warnings=("extra_payload",)))
    return out


def _with(payload_fields: dict, ptype: str, *, size: int, extra: bytes, serial: int = 1) -> dict:
    """Expected fields of a packet whose payload is the layout plus `extra` bytes."""
    body = ptype.encode() + struct.pack("<HHHHI", 0, 0, serial, size, 0) + pack_payload(ptype, payload_fields) + extra
    crc = reference_crc(body)
    fields = dict(type=ptype, revision=0, origin=0, serial=serial, size=size, spare=0,
                  direction="Input" if ptype[3] == "I" else "Output", crc=crc, **{"crc.calculated": crc},
                  **{"crc.status": "Good"}, **payload_fields)
    if ptype == "VRPI":
        fields["es_relays_open"] = payload_fields["bu_state"] < 0x10
    return fields


def vrpo_vectors() -> list[dict]:
    data64 = bytes(range(64))
    data488 = bytes((i * 7) & 0xFF for i in range(488))
    return [
        vector("vrpo_empty", "packet number 0 and no periodic data", "VRPO",
               dict(packet_number=0, periodic_data=b"")),
        vector("vrpo_64", "64 bytes of periodic data", "VRPO", dict(packet_number=0, periodic_data=data64),
               serial=77),
        vector("vrpo_488", "a full VRPO: 488 bytes of data", "VRPO", dict(packet_number=1, periodic_data=data488)),
        vector("vrpo_packet_number_max", "packet number 65535", "VRPO",
               dict(packet_number=65535, periodic_data=b"\x01")),
        vector("vrpo_origin_nonzero", "VRPO with origin set", "VRPO", dict(packet_number=0, periodic_data=b"x"),
               origin=7, warnings=("origin_nonzero:origin",)),
        vector("vrpo_extra_payload", "VRPO with 490 bytes of data (size 492): 2 beyond the layout", "VRPO",
               raw_payload=struct.pack("<H", 0) + bytes(490),
               fields=_with(dict(packet_number=0, periodic_data=bytes(488)), "VRPO", size=492, extra=bytes(2)),
               warnings=("extra_payload",)),
    ]


def command_vectors() -> list[dict]:
    out = []
    for ptype, origin in (("VRCI", 0x0101), ("VRCO", 0)):
        low = ptype.lower()
        out += [
            vector(f"{low}_typical", f"{ptype} command 17", ptype,
                   dict(command_id=17, command_spare=0, command_data=DATA16), origin=origin, serial=300),
            vector(f"{low}_id_0", f"{ptype} command ID 0", ptype,
                   dict(command_id=0, command_spare=0, command_data=bytes(16)), origin=origin),
            vector(f"{low}_id_65535", f"{ptype} command ID 65535, before the wrap", ptype,
                   dict(command_id=65535, command_spare=0, command_data=b"\xff" * 16), origin=origin),
            vector(f"{low}_spare_nonzero", f"{ptype} with its spare set", ptype,
                   dict(command_id=5, command_spare=1, command_data=DATA16), origin=origin,
                   warnings=("spare_nonzero:command_spare",)),
        ]
    out.append(vector("vrco_origin_nonzero", "VRCO with origin set", "VRCO",
                      dict(command_id=9, command_spare=0, command_data=DATA16), origin=0x0101,
                      warnings=("origin_nonzero:origin",)))
    for ptype, origin in (("VRAO", 0), ("VRAI", 0x0101)):
        low = ptype.lower()
        for cid in (0, 17, 65535):
            out.append(vector(f"{low}_id_{cid}", f"{ptype} acknowledging command {cid}", ptype,
                              dict(command_id=cid), origin=origin))
    return out


def illegal_vectors() -> list[dict]:
    ack = dict(command_id=17)
    head = dict(revision=0, origin=0, serial=1, spare=0)
    return [
        vector("illegal_unknown_id", "packet ID VRXX: header only", "VRXX", raw_payload=b"\x01\x02",
               problems=("unknown_id",)),
        vector("illegal_unknown_id_lowercase", "packet ID vrpi is not VRPI", "vrpi",
               raw_payload=pack_payload("VRPI", ARMED), problems=("unknown_id",)),
        vector("illegal_bad_crc", "VRPI with one bit of its CRC flipped", "VRPI", ARMED, crc_xor=1,
               problems=("bad_crc",)),
        vector("illegal_revision_1", "revision 1: header only, payload not decoded", "VRPI", ARMED,
               revision=1, problems=("revision",)),
        vector("illegal_size_too_small", "size says 40, the UDP payload carries 46: trailing bytes", "VRPI",
               raw_payload=pack_payload("VRPI", ARMED)[:40], trailing=b"\x00" * 6,
               problems=("size_mismatch", "truncated"), fields=_truncated_vrpi(40)),
        vector("illegal_size_too_big", "size says 46, only 40 payload bytes: the CRC is the last 4 bytes",
               "VRPI", raw_payload=pack_payload("VRPI", ARMED)[:40], size=46,
               problems=("size_mismatch", "truncated"), fields=_truncated_vrpi(40, size=46)),
        vector("illegal_size_too_large", "size 493 with a matching UDP length", "VRPO",
               raw_payload=struct.pack("<H", 3) + bytes(491), problems=("size_too_large",),
               warnings=("extra_payload",),
               fields=_with(dict(packet_number=3, periodic_data=bytes(488)), "VRPO", size=493, extra=bytes(3))),
        vector("illegal_size_600_short", "size 600 in a 22-byte packet", "VRAO", raw_payload=b"\x11\x00",
               size=600, problems=("size_mismatch", "size_too_large"),
               fields={"type": "VRAO", **head, "size": 600, "direction": "Output", "command_id": 17,
                       **_crc_fields(b"VRAO" + struct.pack("<HHHHI", 0, 0, 1, 600, 0) + b"\x11\x00", None)}),
        vector("illegal_truncated_vrpi", "VRPI with size 10 (consistent UDP length)", "VRPI",
               raw_payload=pack_payload("VRPI", ARMED)[:10], problems=("truncated",),
               fields=_truncated_vrpi(10)),
        vector("illegal_truncated_ack", "VRAO with size 0", "VRAO", raw_payload=b"", problems=("truncated",)),
        vector("illegal_truncated_vrpo_0", "VRPO with size 0", "VRPO", raw_payload=b"", problems=("truncated",)),
        vector("illegal_truncated_vrpo_1", "VRPO with size 1", "VRPO", raw_payload=b"\x05",
               problems=("truncated",)),
        vector("illegal_truncated_command", "VRCI with size 8: command ID and spare only", "VRCI",
               raw_payload=struct.pack("<HI", 4, 0) + b"\x00\x00", problems=("truncated",),
               fields=_partial("VRCI", struct.pack("<HI", 4, 0) + b"\x00\x00",
                               dict(command_id=4, command_spare=0))),
        vector("illegal_short_12", "12 bytes: ID and part of the header, no CRC", "VRPI", ARMED, cut=12,
               problems=("truncated",),
               fields=dict(type="VRPI", direction="Input", revision=0, origin=0, serial=1, size=46)),
        vector("illegal_short_18", "18 bytes: header and half a CRC", "VRAO", ack, cut=18,
               problems=("size_mismatch", "truncated"),
               fields=dict(type="VRAO", direction="Output", **head, size=2)),
        vector("illegal_short_2", "2 bytes", "VRAO", ack, cut=2, problems=("truncated",), fields={}),
        vector("illegal_empty", "no bytes at all", "VRAO", ack, cut=0, problems=("truncated",), fields={}),
        vector("illegal_many", "unknown ID, revision 2, size mismatch and a bad CRC at once", "ABCD",
               raw_payload=b"\x00" * 4, revision=2, trailing=b"\x99", crc=0x12345678,
               problems=("bad_crc", "revision", "size_mismatch", "unknown_id")),
    ]


def _crc_fields(body: bytes, stored: int | None) -> dict:
    calc = reference_crc(body)
    stored = calc if stored is None else stored
    return {"crc": stored, "crc.calculated": calc, "crc.status": "Good" if stored == calc else "Bad"}


def _partial(ptype: str, payload: bytes, decoded: dict, size: int | None = None) -> dict:
    """Expected fields of a packet carrying `payload` whole, with a good CRC after it."""
    size = len(payload) if size is None else size
    body = ptype.encode() + struct.pack("<HHHHI", 0, 0, 1, size, 0) + payload
    return {"type": ptype, "revision": 0, "origin": 0, "serial": 1, "size": size, "spare": 0,
            "direction": "Input" if ptype[3] == "I" else "Output", **_crc_fields(body, None), **decoded}


def _truncated_vrpi(n: int, *, size: int | None = None) -> dict:
    """Fields of a VRPI whose payload holds only the first n bytes: the fields that fit whole.
    With `size` beyond them the CRC sits in the last 4 bytes and covers what precedes them."""
    payload = pack_payload("VRPI", ARMED)[:n]
    decoded, offset = {}, 0
    for name, code in VRPI:
        width = struct.calcsize("<" + code)
        if offset + width > n:
            break
        decoded[name] = ARMED[name]
        offset += width
    decoded["es_relays_open"] = False
    return _partial("VRPI", payload, decoded, size)


def crc_vectors() -> list[dict]:
    out = []
    for variant in ("mpeg2", "iso-hdlc", "bzip2", "jamcrc"):
        for order in ("little", "big"):
            out.append(vector(f"crc_{variant}_{order}", f"VRAO with a {variant} CRC stored {order}-endian",
                              "VRAO", dict(command_id=42), variant=variant, order=order))
    out.append(vector("crc_bzip2_read_as_mpeg2", "a bzip2 CRC checked as mpeg2 is bad", "VRAO",
                      dict(command_id=42), crc=reference_crc(
                          b"VRAO" + struct.pack("<HHHHI", 0, 0, 1, 2, 0) + b"\x2a\x00", "bzip2"),
                      problems=("bad_crc",)))
    out.append(vector("crc_big_read_as_little", "a big-endian CRC read as little-endian is bad", "VRAO",
                      dict(command_id=42), crc=int.from_bytes(reference_crc(
                          b"VRAO" + struct.pack("<HHHHI", 0, 0, 1, 2, 0) + b"\x2a\x00").to_bytes(4, "big"),
                          "little"), problems=("bad_crc",)))
    return out


GROUPS = {
    "header": ("Header fields: serial and origin limits, spare", header_vectors),
    "vrpi": ("VRPI: typical, all zeros, disarmed, every boundary and every enum value", vrpi_vectors),
    "vrpo": ("VRPO: 0, 64 and 488 bytes of data, packet number limits", vrpo_vectors),
    "commands": ("VRCI, VRCO, VRAO, VRAI: command IDs 0, 17 and 65535", command_vectors),
    "illegal": ("Illegal packets of every reason of interpretation.md", illegal_vectors),
    "crc": ("Every CRC variant and stored byte order", crc_vectors),
}


def main() -> None:
    names = set()
    for group, (description, make) in GROUPS.items():
        vectors = make()
        for v in vectors:
            assert v["name"] not in names, v["name"]
            names.add(v["name"])
        path = HERE / f"{group}.json"
        path.write_text(json.dumps({"description": description, "vectors": vectors}, indent=1) + "\n")
        print(f"{path.name}: {len(vectors)} vectors")


if __name__ == "__main__":
    main()
