"""The case schedule: case index -> Case, reproducible from (seed, case index).

The first cases are a fixed sweep, families interleaved so that the cheap, high-yield cases of
every family come first (one bad CRC, one oversize packet, one retransmission ...); after the
sweep, each case is drawn from its own random generator seeded with (seed, index).

Serial numbers and the base-unit stream are the session's: a step is built when it is sent,
from the base unit's next serial. Command IDs are a function of the case index alone.
"""
from __future__ import annotations

import functools
import itertools
import random
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from .. import constants as C
from . import mutate as M

IDS_PER_CASE = 4
ID_BASE = 16
WRAP_IDS = (C.SERIAL_MODULUS - 2, C.SERIAL_MODULUS - 1, 0, 1)   # command IDs across the wrap

# Builds one packet from the base unit's next serial: (packet, its valid twin).
Builder = Callable[[int], tuple[bytes, bytes]]


@dataclass
class Step:
    build: Builder
    delay_ms: float = 0.0          # wait before sending
    expect_ack: bool = True        # False for an exact duplicate frame (same serial)


@dataclass
class Case:
    index: int
    family: str
    description: str
    steps: list[Step] = field(default_factory=list)
    pause_vrpi_ms: float = 0.0      # base unit holds its VRPI stream back after the steps
    withhold_vrai_ms: float = 0.0   # base unit does not acknowledge the next VRCO for this long
    stream: Optional[dict[str, Any]] = None   # VRPI fields of the stream during the case
    settle_ms: float = 0.0          # quiet time after the steps


def command_ids(index: int) -> list[int]:
    """The command IDs case `index` may use: fresh within any window shorter than ~16000 cases."""
    return [(ID_BASE + IDS_PER_CASE * index + j) % C.SERIAL_MODULUS for j in range(IDS_PER_CASE)]


def _valid(ptype: C.PacketType, fields: dict[str, Any], header: Optional[dict[str, Any]] = None,
           twin_fields: Optional[dict[str, Any]] = None) -> Builder:
    """A packet with `fields` and `header` (legal unless the header makes it not); its valid twin
    has `twin_fields` (default: `fields`) and the default header."""
    def build(serial: int) -> tuple[bytes, bytes]:
        twin = M.build(ptype, serial, fields if twin_fields is None else twin_fields)
        if header is None and twin_fields is None:
            return twin, twin
        return M.build(ptype, serial, fields, header), twin
    return build


def _mutated(ptype: C.PacketType, fields: dict[str, Any], change: Callable[[bytes], bytes]) -> Builder:
    def build(serial: int) -> tuple[bytes, bytes]:
        twin = M.build(ptype, serial, fields)
        return change(twin), twin
    return build


def _fields_for(ptype: C.PacketType, index: int, sweep: bool = False) -> dict[str, Any]:
    if ptype is C.PacketType.VRPI:
        return dict(M.SWEEP_VRPI if sweep else M.ARMED_VRPI)
    return M.default_fields(ptype, command_ids(index)[0])


def _nth_structural(valid: bytes, seed: int, position: int) -> bytes:
    return next(itertools.islice(M.structural(valid, random.Random(seed)), position, None))[1]


# --- sweep families ---------------------------------------------------------------------------
def _structural_family(ptype: C.PacketType, rng: random.Random) -> list[Callable[[int], Case]]:
    family = f"{ptype.value.lower()}-structure"
    out: list[Callable[[int], Case]] = []
    for position, name in enumerate(_structural_names(ptype)):
        seed = rng.randrange(1 << 32)

        def make(index: int, position: int = position, name: str = name, seed: int = seed) -> Case:
            def change(valid: bytes) -> bytes:
                return _nth_structural(valid, seed, position)
            return Case(index, family, f"{ptype.value} {name}",
                        [Step(_mutated(ptype, _fields_for(ptype, index), change))])
        out.append(make)
    for name, value, legal in M.header_mutations():
        if not legal:
            def header(index: int, n: str = name, v: int = value) -> Case:
                return Case(index, family, f"{ptype.value} header {n}={v:#x}",
                            [Step(_valid(ptype, _fields_for(ptype, index), {n: v}))])
            out.insert(min(len(out), 2), header)
    return out


def _field_family(ptype: C.PacketType, rng: random.Random) -> list[Callable[[int], Case]]:
    family = f"{ptype.value.lower()}-fields"
    out: list[Callable[[int], Case]] = []
    skip = ("command_id",)   # command IDs are the session's bookkeeping; sequences cover their edges
    for name, value in M.field_mutations(ptype, _fields_for(ptype, 0, sweep=True), rng, skip):
        def make(index: int, name: str = name, value: Any = value) -> Case:
            base = _fields_for(ptype, index, sweep=True)
            shown = value.hex() if isinstance(value, bytes) else value
            return Case(index, family, f"{ptype.value} {name}={shown}",
                        [Step(_valid(ptype, dict(base, **{name: value}), twin_fields=base))])
        out.append(make)
    for name, value, legal in M.header_mutations():
        if legal:
            def header(index: int, n: str = name, v: int = value) -> Case:
                return Case(index, family, f"{ptype.value} header {n}={v:#x}",
                            [Step(_valid(ptype, _fields_for(ptype, index, sweep=True), {n: v}))])
            out.insert(min(len(out), 3), header)
    for extra in _EXTRA_PAYLOAD:
        def longer(index: int, extra: Optional[int] = extra) -> Case:
            shown = "up to 492 bytes" if extra is None else f"{extra} byte{'s' if extra != 1 else ''}"
            return Case(index, family, f"{ptype.value} payload: {shown} beyond its layout (legal)",
                        [Step(_extra_payload(ptype, _fields_for(ptype, index, sweep=True), extra))])
        out.insert(min(len(out), 4), longer)
    return out


# A legal packet may carry payload beyond its type's layout (interpretation.md: a warning, not
# illegal): a controller that trusts `size` to fill a buffer of the layout's length overflows it.
_EXTRA_PAYLOAD = (1, 64, None)        # None: up to the largest payload (492 bytes)


def _extra_payload(ptype: C.PacketType, fields: dict[str, Any], extra: Optional[int]) -> Builder:
    def build(serial: int) -> tuple[bytes, bytes]:
        twin = M.build(ptype, serial, fields)
        body = twin[:-C.CRC_LEN]
        size = len(body) - C.PREFIX_LEN
        more = C.MAX_PAYLOAD - size if extra is None else extra
        return M.recrc(M.set_u16(body + bytes([0x41]) * more, M.SIZE_OFFSET, size + more)), twin
    return build


def _vrci(command_id: int) -> Builder:
    fields = dict(command_id=command_id, command_data=b"FUZZ".ljust(C.COMMAND_DATA_LEN, b"\0"))
    return lambda serial: (M.build(C.PacketType.VRCI, serial, fields),) * 2


def _duplicate_frame(command_id: int) -> list[Step]:
    """A VRCI and then the very same frame again (same serial): a duplicate, not a retransmission."""
    first = _vrci(command_id)
    frame: list[tuple[bytes, bytes]] = []

    def original(serial: int) -> tuple[bytes, bytes]:
        frame[:] = [first(serial)]
        return frame[0]
    return [Step(original), Step(lambda serial: frame[0], 10.0, expect_ack=False)]


def _vrpi_serial(offset: int, absolute: Optional[int] = None) -> Builder:
    def build(serial: int) -> tuple[bytes, bytes]:
        s = absolute if absolute is not None else serial + offset
        return M.build(C.PacketType.VRPI, s, M.ARMED_VRPI), M.build(C.PacketType.VRPI, serial, M.ARMED_VRPI)
    return build


def _sequence_family() -> list[Callable[[int], Case]]:
    F = "sequence"
    VRAI = C.PacketType.VRAI
    resend = C.COMMAND_RESEND_MS
    wd = C.VRPI_WATCHDOG_MS
    return [
        lambda i: Case(i, F, "VRCI retransmitted after 100 ms (same command ID, new serial)",
                       [Step(_vrci(command_ids(i)[0])), Step(_vrci(command_ids(i)[0]), resend)]),
        lambda i: Case(i, F, "command ID wrap 65534, 65535, 0, 1",
                       [Step(_vrci(c), 20.0) for c in WRAP_IDS]),
        lambda i: Case(i, F, f"VRPI gap of {wd + 100} ms (controller watchdog {wd} ms)", pause_vrpi_ms=wd + 100),
        lambda i: Case(i, F, "VRCI retransmission storm: 20 transmissions",
                       [Step(_vrci(command_ids(i)[0]))] + [Step(_vrci(command_ids(i)[0]), 5.0) for _ in range(19)]),
        lambda i: Case(i, F, "VRAI for a command never sent",
                       [Step(_valid(VRAI, dict(command_id=command_ids(i)[0])))]),
        lambda i: Case(i, F, "VRPI with a repeated serial", [Step(_vrpi_serial(-1))]),
        lambda i: Case(i, F, "VRCI frame received twice (same serial: a duplicate)",
                       _duplicate_frame(command_ids(i)[0])),
        lambda i: Case(i, F, "withhold VRAI for 800 ms: the VRCO must be resent every 100 ms",
                       withhold_vrai_ms=800.0),
        lambda i: Case(i, F, "VRPI serial going back by 5", [Step(_vrpi_serial(-5))]),
        lambda i: Case(i, F, "VRCI while the base unit is disarmed", [Step(_vrci(command_ids(i)[0]), 130.0)],
                       stream=dict(M.DISARMED_VRPI), settle_ms=130.0),
        lambda i: Case(i, F, "VRPI serial jump by 1000", [Step(_vrpi_serial(1000))]),
        lambda i: Case(i, F, "VRPI serial wrap 65535 -> 0",
                       [Step(_vrpi_serial(0, C.SERIAL_MODULUS - 1)), Step(_vrpi_serial(0, 0), 10.0)]),
        lambda i: Case(i, F, f"VRPI gap of {wd - 100} ms (below the watchdog)", pause_vrpi_ms=wd - 100),
        lambda i: Case(i, F, "four new commands back to back",
                       [Step(_vrci(c)) for c in command_ids(i)]),
        lambda i: Case(i, F, "VRCI command ID going back by 1 (new command with an old ID)",
                       [Step(_vrci(command_ids(i)[1])), Step(_vrci(command_ids(i)[0]), resend)]),
        lambda i: Case(i, F, f"VRPI gap of {wd + 10} ms", pause_vrpi_ms=wd + 10),
        lambda i: Case(i, F, "VRPI gap of 1000 ms", pause_vrpi_ms=1000.0),
        lambda i: Case(i, F, "VRAI for command IDs 0 and 65535",
                       [Step(_valid(VRAI, dict(command_id=0))), Step(_valid(VRAI, dict(command_id=0xFFFF)))]),
        lambda i: Case(i, F, "VRCI command IDs 0 and 65535 as new commands",
                       [Step(_vrci(0xFFFF), 20.0), Step(_vrci(0), 20.0)]),
    ]


def _direction_family() -> list[Callable[[int], Case]]:
    """Output packets sent to the controller: legal packets it must not choke on."""
    def make(i: int, p: C.PacketType) -> Case:
        return Case(i, "wrong-direction", f"{p.value} sent to the controller",
                    [Step(_valid(p, M.default_fields(p, command_ids(i)[0])))])
    return [functools.partial(_index_first, make, ptype) for ptype in M.OUTPUT_TYPES]


def _index_first(make: Callable[[int, Any], Case], arg: Any, index: int) -> Case:
    return make(index, arg)


@functools.lru_cache(maxsize=4)
def sweep(seed: int) -> tuple[Callable[[int], Case], ...]:
    """The deterministic first part of the schedule, families interleaved round-robin."""
    rng = random.Random(f"vm110-fuzz-sweep/{seed}")
    VRPI, VRCI, VRAI = C.PacketType.VRPI, C.PacketType.VRCI, C.PacketType.VRAI
    families = [
        _structural_family(VRCI, rng),
        _sequence_family(),
        _structural_family(VRPI, rng),
        _field_family(VRPI, rng),
        _field_family(VRCI, rng),
        _structural_family(VRAI, rng),
        _field_family(VRAI, rng),
        _direction_family(),
    ]
    longest = max(len(f) for f in families)
    return tuple(f[k] for k in range(longest) for f in families if k < len(f))


@functools.lru_cache(maxsize=None)
def _structural_names(ptype: C.PacketType) -> tuple[str, ...]:
    return tuple(name for name, _ in M.structural(M.build(ptype, 0, _fields_for(ptype, 0)), random.Random(0)))


def _random_sequence(rng: random.Random, index: int) -> Case:
    F, ids = "random-sequence", command_ids(index)
    kind = rng.choices(range(5), weights=(30, 15, 15, 20, 20))[0]   # the slow ones (gaps, withholding) rarer
    if kind == 0:
        count, delay = rng.randint(2, 6), rng.choice((0.0, 5.0, 20.0, 50.0, C.COMMAND_RESEND_MS, 150.0))
        return Case(index, F, f"VRCI sent {count} times, {delay:.0f} ms apart",
                    [Step(_vrci(ids[0]), delay if n else 0.0) for n in range(count)])
    if kind == 1:
        gap = rng.randrange(C.VRPI_PERIOD_MS * 2, C.VRPI_WATCHDOG_MS * 2 + 200, 10)
        return Case(index, F, f"VRPI gap of {gap} ms", pause_vrpi_ms=float(gap))
    if kind == 2:
        hold = rng.randrange(2 * C.COMMAND_RESEND_MS, 15 * C.COMMAND_RESEND_MS, 50)
        return Case(index, F, f"withhold VRAI for {hold} ms", withhold_vrai_ms=float(hold))
    if kind == 3:
        offset = rng.choice((-100, -2, 0, 2, 100, C.SERIAL_HALF))
        return Case(index, F, f"VRPI serial off by {offset:+d}", [Step(_vrpi_serial(offset - 1))])
    command_id = rng.randrange(C.SERIAL_MODULUS)
    return Case(index, F, f"VRAI for command ID {command_id}",
                [Step(_valid(C.PacketType.VRAI, dict(command_id=command_id)))])


def _random_case(seed: int, index: int) -> Case:
    rng = random.Random(f"vm110-fuzz/{seed}/{index}")
    ptype = rng.choice(M.INPUT_TYPES)
    fields = _fields_for(ptype, index)
    kind = rng.random()
    if kind < 0.48:
        def change(valid: bytes) -> bytes:
            return M.random_bytes(valid, random.Random(f"{seed}/{index}/bytes"))[1]
        text = M.random_bytes(M.build(ptype, 0, fields), random.Random(f"{seed}/{index}/bytes"))[0]
        return Case(index, "random-bytes", f"{ptype.value} {text}", [Step(_mutated(ptype, fields, change))])
    if kind < 0.78:
        skip = ("command_id",) if ptype is C.PacketType.VRCI else ()
        base = dict(fields)
        name, value = rng.choice(M.field_mutations(ptype, fields, rng, skip))
        fields[name] = value
        if ptype is C.PacketType.VRPI and rng.random() < 0.5:   # and a second field
            name2, value2 = rng.choice(M.field_mutations(ptype, fields, rng, skip + (name,)))
            fields[name2] = value2
            name, value = f"{name}={value!r} {name2}", value2
        shown = value.hex() if isinstance(value, bytes) else value
        return Case(index, "random-fields", f"{ptype.value} {name}={shown}",
                    [Step(_valid(ptype, fields, twin_fields=base))])
    if kind < 0.96:    # the rest: timing-heavy sequences, few so that the rate stays up
        names = _structural_names(ptype)
        position = rng.randrange(len(names))
        sub_seed = rng.randrange(1 << 32)

        def change(valid: bytes) -> bytes:
            return _nth_structural(valid, sub_seed, position)
        return Case(index, "random-structure", f"{ptype.value} {names[position]}",
                    [Step(_mutated(ptype, fields, change))])
    return _random_sequence(rng, index)


def generate(seed: int, index: int) -> Case:
    """Case `index` of the schedule for `seed`."""
    cases = sweep(seed)
    if index < len(cases):
        return cases[index](index)
    return _random_case(seed, index)
