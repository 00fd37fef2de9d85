"""Minimisation: the smallest difference from the valid twin that still triggers."""
from __future__ import annotations

import struct

from reference_crc import reference_crc
from vm110 import constants as C
from vm110 import encode
from vm110.decode import decode
from vm110.fuzz.minimize import ddmin, difference, minimize

VRPI_FIELDS = dict(bu_state=0x11, armed_ru=0x0C07, ru_state=3, ru_battery=80, joystick1=250)


def vrpi(**changes: int) -> bytes:
    return encode.packet("VRPI", encode.vrpi_payload(dict(VRPI_FIELDS, **changes)), origin=0x0101, serial=9)


def crc_ok(data: bytes) -> bool:
    end = C.PREFIX_LEN + struct.unpack_from("<H", data, 10)[0]
    return int.from_bytes(data[end:end + 4], "little") == reference_crc(data[:end])


def joystick1(data: bytes) -> int:
    return struct.unpack_from("<h", data, C.PREFIX_LEN + 14)[0]


def test_ddmin_finds_a_one_minimal_subset():
    assert sorted(ddmin(list(range(20)), lambda s: {3, 17} <= set(s))) == [3, 17]
    assert ddmin([1], lambda s: True) == [1]


def test_field_change_keeps_only_the_culprit_and_a_valid_crc():
    twin = vrpi()
    packet = vrpi(joystick1=-32768, ru_battery=200, switch3=7)
    result = minimize(packet, twin, lambda b: crc_ok(b) and joystick1(b) == -32768)
    assert result.complete and crc_ok(result.packet) and joystick1(result.packet) == -32768
    assert result.packet[:C.PREFIX_LEN] == twin[:C.PREFIX_LEN]
    body = result.packet[:-4]      # 250 = fa 00 -> -32768 = 00 80: both bytes of joystick1, nothing else
    assert [i for i in range(len(body)) if body[i] != twin[i]] == [C.PREFIX_LEN + 14, C.PREFIX_LEN + 15]


def test_oversize_is_cut_to_the_first_length_that_triggers():
    twin = vrpi()
    result = minimize(twin + bytes(700), twin, lambda b: len(b) > C.MAX_PACKET)
    assert len(result.packet) == C.MAX_PACKET + 1
    assert result.differences == C.MAX_PACKET + 1 - len(twin)


def test_bad_crc_shrinks_to_one_byte():
    twin = encode.packet("VRCI", encode.command_payload(5), origin=0x0101, serial=3)
    packet = twin[:-4] + b"\0\0\0\0"
    result = minimize(packet, twin, lambda b: not crc_ok(b))
    assert result.complete and difference(result.packet, twin) == 1


def test_budget_keeps_a_packet_that_triggers():
    twin = vrpi()
    packet = vrpi(joystick1=-32768, ru_battery=200)
    result = minimize(packet, twin, lambda b: crc_ok(b) and joystick1(b) == -32768, max_trials=1)
    assert not result.complete and joystick1(result.packet) == -32768 and crc_ok(result.packet)


def test_a_legal_extra_payload_shrinks_with_its_size_field():
    """Trial: every shorter tail kept the original `size` (a size mismatch, illegal): a legal VRCI
    of 512 bytes stayed 512 bytes, 476 differences, and was marked minimised."""
    twin = encode.packet("VRCI", encode.command_payload(5), origin=0x0101, serial=3)
    body = twin[:-4] + bytes(range(256)) + bytes(214)
    packet = body[:10] + struct.pack("<H", len(body) - C.PREFIX_LEN) + body[12:]
    packet += reference_crc(packet).to_bytes(4, "little")
    assert len(packet) == C.MAX_PACKET and decode(packet)["problems"] == []

    def legal_and_longer(b: bytes) -> bool:
        fields = decode(b)
        return not fields["problems"] and fields["type"] == "VRCI" and fields["size"] > 22
    result = minimize(packet, twin, legal_and_longer, max_trials=100)
    assert result.complete and legal_and_longer(result.packet) and len(result.packet) == len(twin) + 1
