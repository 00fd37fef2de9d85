"""The fuzzer's case schedule: reproducible, covering what issue 7 lists, legal where it must be.

Expectations come from the specification through independent means: the bit-by-bit reference CRC
(tests/reference_crc.py) and plain struct unpacking, besides vm110.decode for the illegal reasons.
"""
from __future__ import annotations

import struct

import pytest

from reference_crc import reference_crc
from vm110 import constants as C
from vm110.decode import decode
from vm110.fuzz import cases as K
from vm110.fuzz import mutate as M

SEED = 1
SWEEP = len(K.sweep(SEED))
SERIAL = 4242


def packets(case: K.Case, serial: int = SERIAL) -> list[tuple[bytes, bytes]]:
    return [step.build(serial + n) for n, step in enumerate(case.steps)]


def all_sweep() -> list[K.Case]:
    return [K.generate(SEED, i) for i in range(SWEEP)]


def crc_ok(data: bytes, variant: str = "mpeg2", order: str = "little") -> bool:
    size = struct.unpack_from("<H", data, 10)[0]
    end = C.PREFIX_LEN + size
    return len(data) == end + 4 and int.from_bytes(data[end:end + 4], order) == reference_crc(data[:end], variant)


def test_same_seed_and_index_give_the_same_case():
    for index in list(range(0, SWEEP, 7)) + list(range(SWEEP, SWEEP + 120)):
        a, b = K.generate(SEED, index), K.generate(SEED, index)
        assert (a.family, a.description) == (b.family, b.description)
        assert packets(a) == packets(b)


def test_seeds_differ_after_the_sweep():
    a = [K.generate(1, i).description for i in range(SWEEP, SWEEP + 50)]
    b = [K.generate(2, i).description for i in range(SWEEP, SWEEP + 50)]
    assert a != b


def test_command_ids_are_fresh_across_nearby_cases():
    seen: set[int] = set()
    for index in range(5000):
        ids = set(K.command_ids(index))
        assert len(ids) == K.IDS_PER_CASE and not ids & seen
        seen |= ids


def test_field_cases_are_legal_and_change_one_field():
    checked = 0
    for case in all_sweep():
        if not case.family.endswith("-fields") or "header" in case.description or "beyond" in case.description:
            continue
        (data, twin), = packets(case)
        assert crc_ok(data), case.description
        assert decode(data)["problems"] == [], case.description
        name = case.description.split()[1].split("=")[0]
        mine, base = decode(data), decode(twin)
        changed = {k for k in mine if k not in ("crc", "crc.calculated", "warnings", "es_relays_open")
                   and mine[k] != base.get(k)}
        assert changed == {name}, case.description
        checked += 1
    assert checked > 100


def test_structure_cases_are_illegal():
    checked = 0
    for case in all_sweep():
        if not case.family.endswith("-structure"):
            continue
        (data, twin), = packets(case)
        assert decode(data)["problems"], case.description
        assert crc_ok(twin)
        checked += 1
    assert checked > 60


@pytest.mark.parametrize("variant,order", [(v, o) for v in ("mpeg2", "iso-hdlc", "bzip2", "jamcrc")
                                           for o in ("little", "big") if (v, o) != ("mpeg2", "little")])
def test_other_crc_variants_are_those_variants(variant, order):
    found = [c for c in all_sweep() if c.description.endswith(f"crc variant {variant} {order}-endian")]
    assert {c.family for c in found} == {"vrpi-structure", "vrci-structure", "vrai-structure"}
    for case in found:
        (data, _), = packets(case)
        assert crc_ok(data, variant, order) and not crc_ok(data)


def _values(field: str) -> set[int]:
    out = set()
    for case in all_sweep():
        if case.family == "vrpi-fields" and case.description.startswith(f"VRPI {field}="):
            out.add(decode(packets(case)[0][0])[field])
    return out


def test_boundary_values_are_covered():
    for i in range(1, C.JOYSTICKS + 1):
        assert {-1001, -1000, 1000, 1001, -32768, 32767, 0} <= _values(f"joystick{i}") | {0}
    assert {101, 255} <= _values("ru_battery")
    assert {4, 255} <= _values("vlaps")
    assert _values("bu_state") - {int(v) for v in C.BuState}, "BU states outside the set"
    assert _values("ru_state") - {int(v) for v in C.RuState}
    assert -250 in _values("joystick1"), "sign flip of the sweep's joystick1 = 250"


def test_structure_and_sequence_kinds_are_covered():
    texts = [c.description for c in all_sweep()]
    lengths = [len(p[0]) for c in all_sweep() if c.family.endswith("structure") for p in packets(c)]
    assert max(lengths) > C.MAX_PACKET and C.MAX_PACKET + 1 in lengths
    for needle in ("truncated", "trailing byte", "size field", "unknown packet ID", "revision=0x1",
                   "origin=0x0", "origin=0xffff", "retransmitted", "storm", "command ID wrap",
                   "repeated serial", "serial going back", "serial wrap", "VRAI for a command never sent",
                   "withhold VRAI", "sent to the controller"):
        assert any(needle in t for t in texts), needle
    gaps = [c.pause_vrpi_ms for c in all_sweep() if c.pause_vrpi_ms]
    assert min(gaps) < C.VRPI_WATCHDOG_MS < max(gaps)


def test_wrap_case_sends_65535_then_0():
    case = next(c for c in all_sweep() if "command ID wrap" in c.description)
    ids = [struct.unpack_from("<H", p, C.PREFIX_LEN)[0] for p, _ in packets(case)]
    assert ids[ids.index(65535) + 1] == 0
    assert all(crc_ok(p) for p, _ in packets(case))


def test_random_cases_mutate_valid_packets():
    kinds = set()
    for index in range(SWEEP, SWEEP + 300):
        case = K.generate(SEED, index)
        kinds.add(case.family)
        for data, twin in packets(case):
            assert crc_ok(twin), case.description
            if case.family != "random-sequence":    # sequences send valid packets, in odd order or timing
                assert data != twin, case.description
    assert kinds == {"random-bytes", "random-fields", "random-structure", "random-sequence"}


def test_a_bug_s_signature_names_the_packet_type_not_how_it_was_mutated():
    """Trial: a stall on a VRPI field and one on a VRCI field shared the signature `stall no VRPO
    (fields)`, the second replacing the first's reproducer; one missing CRC check was two findings,
    `(structure)` and `(bytes)`. README: the oracle, what it judged and the packet type."""
    from vm110.fuzz.runner import case_kind
    kinds = [case_kind(K.Case(i, family, description)) for i, (family, description) in enumerate([
        ("vrpi-fields", "VRPI joystick1=-32768"), ("vrci-fields", "VRCI command_spare=2147483647"),
        ("vrci-structure", "VRCI CRC of another variant"), ("random-bytes", "VRCI byte 7 = 0xff"),
        ("wrong-direction", "VRAI sent to the controller"), ("sequence", "four new commands back to back")])]
    assert kinds == ["VRPI", "VRCI", "VRCI", "VRCI", "VRAI", "sequence"]
    assert case_kind(None) == "none"


def test_a_sequence_s_signature_names_the_packet_type_it_sent():
    """Trial: a controller whose serial went back on command ID 65535 gave `malformed_output serial
    (sequence)` for the command ID wrap and `(VRCI)` for a VRCI case: one bug, two findings."""
    from vm110.fuzz.runner import case_kind
    from vm110.fuzz.session import Sent
    vrci = M.build(C.PacketType.VRCI, 3, M.default_fields(C.PacketType.VRCI, 0xFFFF))
    wrap = K.Case(9, "sequence", "command ID wrap 65534, 65535, 0, 1")
    assert case_kind(wrap, Sent(0.0, b"XXXX" + vrci[4:], vrci, 0.0, True)) == "VRCI"
    assert case_kind(wrap, Sent(0.0, b"XXXX", b"XXXX", 0.0, True)) == "sequence"


def test_legal_packets_with_payload_beyond_the_layout_are_sent():
    """Trial: blind mode never sent a legal packet longer than its layout (interpretation.md: a
    warning), so a controller that copies `size` bytes into a buffer of the layout's length was never
    caught. They are field cases: legal, acknowledged, the layout's fields unchanged."""
    found = [c for c in all_sweep() if "beyond its layout" in c.description]
    assert {c.description.split()[0] for c in found} == {"VRPI", "VRCI", "VRAI"} and len(found) == 9
    for case in found:
        (data, twin), = packets(case)
        mine, base = decode(data), decode(twin)
        assert mine["problems"] == [] and "extra_payload" in str(mine["warnings"]), case.description
        assert len(data) - len(twin) in (1, 64) or len(data) == C.MAX_PACKET, case.description
        assert {k: mine[k] for k in base if k not in ("size", "crc", "crc.calculated", "warnings")} == \
            {k: base[k] for k in base if k not in ("size", "crc", "crc.calculated", "warnings")}


def test_extra_payload_cases_say_byte_for_one_and_old_findings_with_the_old_text_still_read(tmp_path):
    """Trial: a case was described as 'VRPI payload: 1 bytes beyond its layout (legal)'."""
    import json
    from dataclasses import asdict
    from vm110.fuzz.findings import Finding, finding_from_json
    shown = sorted({c.description.split(": ", 1)[1] for c in all_sweep() if "beyond its layout" in c.description})
    assert shown == ["1 byte beyond its layout (legal)", "64 bytes beyond its layout (legal)",
                     "up to 492 bytes beyond its layout (legal)"]
    vrpi = M.build(C.PacketType.VRPI, 1, M.ARMED_VRPI).hex()
    old = Finding("missing_ack", 1, 7, "vrpi-fields", "VRPI payload: 1 bytes beyond its layout (legal)", "no VRAO",
                  vrpi, vrpi, vrpi, 0, True, [{"hex": vrpi, "valid_hex": vrpi, "delay_ms": 0.0, "expect_ack": True}])
    path = tmp_path / "finding-001-missing_ack.json"
    path.write_text(json.dumps(asdict(old)))
    assert finding_from_json(json.loads(path.read_text()), str(path)).mutation == old.mutation
