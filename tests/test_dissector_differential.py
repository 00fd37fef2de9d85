"""Differential test: random valid packets of every type, crafted with the scapy layers from a fixed
seed, decode field for field the same in tshark (the Lua dissector) and in Python (`vm110.decode`),
with the same problems and warnings, the warnings on the field they name, the same display names
of every enumerated value, and a tree that covers every byte. One tshark run per CRC setting."""
from __future__ import annotations

import pytest

import dissector_packets as P
import tshark_runner as T
from longrun import runner_params
from vm110.protocol import ENUM_FIELDS
from vm110 import decode

pytestmark = pytest.mark.tshark

SEED = 20_261_121
COUNT = 2000                       # default CRC settings
PER_SETTING = 60                   # every other CRC variant and byte order
SETTINGS = [(v, o) for v in ("mpeg2", "iso-hdlc", "bzip2", "jamcrc") for o in ("little", "big")]


def _check_frame(frame: T.Frame, data: bytes, variant: str, order: str) -> list[str]:
    """Differences between tshark's frame and Python's decode() of the same bytes."""
    expected = decode(data, variant, order)
    errors = []
    if not frame.vm110:
        return ["no vm110 tree"]
    got = T.canonical_fields(frame)
    want = T.python_expectation(expected)
    if got != want:
        keys = sorted(set(got) | set(want))
        errors.append("fields: " + ", ".join(f"{k}: tshark {got.get(k)!r} python {want.get(k)!r}"
                                             for k in keys if got.get(k) != want.get(k)))
    problems, warnings, odd = T.problems_and_warnings(frame)
    if problems != sorted(expected["problems"]) or warnings != sorted(expected["warnings"]):
        errors.append(f"experts: tshark {problems} {warnings}, python {expected['problems']} {expected['warnings']}")
    errors += odd
    for name, names in ENUM_FIELDS.items():
        item = frame.first(f"vm110.{name}")
        if item is not None:
            value = want[name]
            shown = f"{names[value]} (0x{value:02x})" if value in names else f"Unknown (0x{value:02x})"
            if T.showname_value(item) != shown:
                errors.append(f"{name} shown as {T.showname_value(item)!r}, expected {shown!r}")
    if T.uncovered_bytes(frame):
        errors.append(f"bytes outside every field: {T.uncovered_bytes(frame)}")
    if not frame.text.startswith(f"VM-110 EG-Link, {want['type']} "):
        errors.append(f"tree text {frame.text!r}")
    return errors


@pytest.mark.parametrize("tshark", runner_params(T.RUNNERS))
@pytest.mark.parametrize("variant,order", SETTINGS)
def test_random_valid_packets_match_python(tshark, variant, order, tmp_path):
    count = COUNT if (variant, order) == ("mpeg2", "little") else PER_SETTING
    packets = P.valid_packets(count, SEED + SETTINGS.index((variant, order)), variant, order)
    assert all(not decode(p, variant, order)["problems"] for p in packets)
    try:
        with tshark.workspace(tmp_path) as ws:
            pcap = ws.dir / "valid.pcap"
            T.write_pcap(pcap, packets)
            frames, output = T.dissect_pdml(ws, pcap, {"vm110.crc_variant": variant, "vm110.crc_byte_order": order})
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert T.LUA_ERROR not in output
    assert len(frames) == len(packets)
    failures = {f.number: e for f, p in zip(frames, packets) if (e := _check_frame(f, p, variant, order))}
    assert not failures, f"{len(failures)} of {len(packets)} frames differ, e.g. {list(failures.items())[:3]}"
