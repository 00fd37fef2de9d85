"""Seeded packet generators for the dissector tests: random valid packets of every type crafted with
the scapy layers, and random or mutated malformed ones (random bytes behind a valid packet ID,
scapy `fuzz()`, truncations, wrong sizes, bit flips, other revisions and IDs)."""
from __future__ import annotations

import random
import struct
from typing import Callable

from scapy.packet import fuzz

from vm110 import constants as C
from vm110.layers import VM110, VRAI, VRAO, VRCI, VRCO, VRPI, VRPO, crc_settings

PAYLOAD_CLASSES = {"VRPI": VRPI, "VRPO": VRPO, "VRCI": VRCI, "VRCO": VRCO, "VRAI": VRAI, "VRAO": VRAO}
TYPE_IDS = [t.value.encode() for t in C.PacketType]


def _enum(rng: random.Random, names: dict) -> int:
    """Mostly a defined value, sometimes any byte (an unknown value)."""
    return rng.randrange(256) if rng.random() < 0.08 else int(rng.choice(list(names)))


def _often(rng: random.Random, usual: int, other: Callable[[], int], p_other: float = 0.1) -> int:
    return other() if rng.random() < p_other else usual


def _vrpi(rng: random.Random) -> VRPI:
    armed = rng.random() < 0.7
    ru_data = armed or rng.random() < 0.15      # RU data while disarmed: warnings
    fields = dict(
        bu_state=_enum(rng, C.BU_STATE_NAMES),
        vlaps=_often(rng, rng.randrange(C.VLAPS_MAX + 1), lambda: rng.randrange(256)),
        unarmed_rus=rng.randrange(8),
        eg_link=_enum(rng, C.LINK_STATUS_NAMES), ec_link=_enum(rng, C.LINK_STATUS_NAMES),
        c_link=_enum(rng, C.LINK_STATUS_NAMES),
        armed_ru=rng.randrange(1, 1 << 16) if armed else 0,
        vrpi_spare=_often(rng, 0, lambda: rng.randrange(1, 1 << 48), 0.05).to_bytes(C.VRPI_SPARE_LEN, "little"),
    )
    if ru_data:
        joystick = lambda: _often(rng, rng.randint(-1000, 1000), lambda: rng.randint(-32768, 32767))  # noqa: E731
        switch = lambda: _often(rng, rng.choice([-1, 0, 1, 2, 3, rng.randint(0, 1000)]),  # noqa: E731
                                lambda: rng.randint(-32768, 32767))
        fields.update(
            ru_state=_enum(rng, C.RU_STATE_NAMES),
            ru_battery=_often(rng, rng.randrange(101), lambda: rng.randrange(256)),
            ru_rssi=_often(rng, rng.randrange(101), lambda: rng.randrange(256)),
            ru_cable=_enum(rng, C.RU_CABLE_NAMES), ru_docked=_enum(rng, C.RU_DOCKED_NAMES),
            ru_disabled=_enum(rng, C.RU_DISABLED_NAMES),
            encoder=rng.randrange(256), encoder_switch=_enum(rng, C.ENCODER_SWITCH_NAMES),
            **{f"joystick{i}": joystick() for i in range(1, C.JOYSTICKS + 1)},
            **{f"switch{i}": switch() for i in range(1, C.SWITCHES + 1)},
        )
    return VRPI(**fields)


def _command(cls, rng: random.Random):
    return cls(command_id=rng.randrange(1 << 16),
               command_spare=_often(rng, 0, lambda: rng.randrange(1, 1 << 32), 0.05),
               command_data=bytes(rng.randrange(256) for _ in range(C.COMMAND_DATA_LEN)))


def _payload(kind: str, rng: random.Random):
    if kind == "VRPI":
        return _vrpi(rng)
    if kind == "VRPO":
        size = rng.choice([0, 1, C.VRPO_MAX_DATA, rng.randrange(C.VRPO_MAX_DATA + 1)])
        return VRPO(packet_number=rng.randrange(1 << 16), periodic_data=bytes(rng.randrange(256) for _ in range(size)))
    if kind in ("VRCI", "VRCO"):
        return _command(PAYLOAD_CLASSES[kind], rng)
    return PAYLOAD_CLASSES[kind](command_id=rng.randrange(1 << 16))


def valid_packets(count: int, seed: int, variant: str = "mpeg2", order: str = "little") -> list[bytes]:
    """Legal packets (right size, good CRC, revision 0) of every type, round robin; field values
    mostly in range, sometimes not (warnings are legal)."""
    rng = random.Random(seed)
    kinds = list(PAYLOAD_CLASSES)
    out = []
    with crc_settings(variant, order):
        for i in range(count):
            kind = kinds[i % len(kinds)]
            origin = rng.randrange(1 << 16) if kind.endswith("I") else _often(rng, 0, lambda: rng.randrange(1, 1 << 16), 0.05)
            header = VM110(origin=origin, serial=rng.randrange(1 << 16),
                           spare=_often(rng, 0, lambda: rng.randrange(1, 1 << 32), 0.05))
            out.append(bytes(header / _payload(kind, rng)))
    return out


def _set_size(data: bytes, size: int) -> bytes:
    return data[:10] + struct.pack("<H", size & 0xFFFF) + data[12:]


def malformed_packets(seed: int) -> list[bytes]:
    """At least 20,000 packets that stress the framing rules."""
    rng = random.Random(seed)
    base = valid_packets(1500, seed + 1)
    out: list[bytes] = []
    for _ in range(4000):                                   # random bytes behind a valid packet ID
        out.append(rng.choice(TYPE_IDS) + bytes(rng.randrange(256) for _ in range(rng.randrange(0, 530))))
    random.seed(seed)                                       # scapy's fuzz() draws from `random`
    for i in range(2400):
        kind = list(PAYLOAD_CLASSES)[i % 6]
        header = fuzz(VM110(type=kind.encode())) if i % 2 else VM110(serial=rng.randrange(1 << 16))
        out.append(bytes(header / fuzz(PAYLOAD_CLASSES[kind]())))
    for _ in range(4000):                                   # truncations and extensions
        data = rng.choice(base)
        cut = rng.randrange(len(data))
        out.append(data[:cut] if rng.random() < 0.75 else data + bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40))))
    for _ in range(4000):                                   # wrong sizes
        data = rng.choice(base)
        size = rng.choice([0, 1, 2, 45, 47, C.MAX_PAYLOAD, C.MAX_PAYLOAD + 1, 0xFFFF, rng.randrange(1 << 16),
                           len(data) - C.OVERHEAD + rng.choice([-3, -1, 1, 3])])
        out.append(_set_size(data, size))
    for _ in range(3000):                                   # bit flips: bad CRC, odd values
        data = bytearray(rng.choice(base))
        for _ in range(rng.randrange(1, 4)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        out.append(bytes(data))
    for _ in range(2600):                                   # other revisions, unknown or near-miss IDs
        data = bytearray(rng.choice(base))
        if rng.random() < 0.5:
            data[4:6] = struct.pack("<H", rng.randrange(1, 1 << 16))
        else:
            data[:4] = rng.choice([b"VRXI", b"vrpi", b"VRP\0", b"\0\0\0\0", bytes(rng.randrange(32, 127) for _ in range(4))])
        out.append(bytes(data))
    return out
