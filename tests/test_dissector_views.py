"""The dissector's fast path against its visible path: the same fields, experts, matches and Info.

With an invisible tree (tshark 4.4 `-T fields`, display filters over summary lines, the GUI's
packet list) the dissector builds only the referenced fields, flat; with a visible one (PDML,
-V) every field in its subtree. tshark 4.0 builds a visible tree for `-T fields`: there the
dissector builds the fields its command line names, flat and without bytes, as on an invisible
tree (tests/test_dissector_command_line.py), so those runs test that path on 4.0. The expectation is the visible
path (PDML, or `-V -P` for the Info column) of the same tshark, or an independent one (the
vectors, `vm110.decode` of the packet bytes, a capture's ground truth) for display filters.
"""
from __future__ import annotations

import contextlib
import functools
import json
from collections import defaultdict
from pathlib import Path
from typing import Callable, Iterator, Sequence

import pytest

import tshark_runner as T
from longrun import on_runner, runner_params
from vectorlib import load_vectors, packet_bytes
from vm110 import constants as C
from vm110.capture.reader import CaptureReader, address
from vm110.decode import decode
from vm110.layers import VM110, VRAO, VRCI, VRPI, VRPO

pytestmark = pytest.mark.tshark

CAPTURES = T.REPO / "captures"
# Commands, retransmissions and unacknowledged ones; serial loss, duplicates and reordering; VRPO
# bursts; illegal packets among other traffic. (bu-watchdog.pcap: display filters only.) Each with
# the version on which `make test` holds its fast path: 4.0 (its command-line fields) or 4.6 (Lua
# 5.4, invisible trees, as 4.4); the long run holds each on all three.
ANALYSED = {"retransmit.pcap": "4.0", "loss.pcapng": "4.6", "vrpo-split.pcapng": "4.6", "illegal.pcap": "4.0"}
VECTORS, CRAFTED = "vectors", "crafted"
SOURCES = (VECTORS, CRAFTED, *ANALYSED)
ON = {"vm110.analysis": "TRUE"}
PASSES = {"single": (), "two-pass": ("-2",)}
AGGREGATOR = "\x1f"          # between occurrences: in no value (numbers, hex, 4-character packet IDs)
PACKET_END = "@@vm110-end-of-packet@@"
MESSAGES = "_ws.expert.message"
# Sparse reference sets: on the first pass (one view for every frame) a header field, and a field
# derived from an unbuilt one with the VRPO data; on the second (a view per frame) a generated
# field of the analysis and one of the CRC's.
SPARSE = (("single", ("vm110.serial",)), ("single", ("vm110.es_relays_open", "vm110.periodic_data")),
          ("two-pass", ("vm110.analysis.ack_to", "vm110.crc.status")))
# Experts of the crafted capture (no capture of captures/ has the first two).
CRAFTED_EXPERTS = frozenset({"ack_late", "ack_without_command", "watchdog_vrpo", "watchdog_vrpi", "duplicate_ack",
                             "spurious_retransmission", "retransmission", "never_acked"})

Values = dict[str, list]     # field abbreviation -> its values in the frame, in tree order


# --- Running tshark --------------------------------------------------------------------------------
def _run(ws: T.Workspace, pcap: Path, prefs: dict, args: Sequence[str]) -> str:
    proc = ws.run(["-r", str(pcap), *T.pref_args(prefs), *args])
    assert T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-2000:]
    return proc.stdout


_CATALOGUES: dict = {}


def catalogue(ws: T.Workspace) -> dict[str, str]:
    """Every vm110 field but the experts, with its type, as `tshark -G fields` lists them with the
    plugin loaded."""
    if ws.tshark.name not in _CATALOGUES:
        fields = {r[2]: r[3] for r in T.glossary(ws)
                  if r[0] == "F" and r[2].startswith("vm110.") and not r[2].startswith("vm110.expert.")}
        assert len(fields) > 50 and "vm110.analysis.ack_to" in fields, sorted(fields)
        _CATALOGUES[ws.tshark.name] = fields
    return _CATALOGUES[ws.tshark.name]


def normal(ftype: str, text: str):
    """A value as PDML's `show` or `-T fields` writes it, in one form (they format bytes and
    booleans differently, and 4.0 and 4.4 booleans too)."""
    if ftype == "FT_BYTES":
        return "" if text == "<MISSING>" else text.replace(":", "").lower()   # (empty: 4.x writes <MISSING>)
    if ftype == "FT_BOOLEAN":
        return text in ("1", "True", "true")
    if ftype == "FT_DOUBLE":
        return float(text)
    if ftype.startswith(("FT_UINT", "FT_INT", "FT_FRAMENUM")):
        return int(text, 0)
    return text


def field_dump(ws: T.Workspace, pcap: Path, prefs: dict, fields: dict[str, str],
               extra: Sequence[str] = ()) -> dict[int, Values]:
    """frame number -> values of `fields` through `-T fields` (all occurrences)."""
    names = list(fields)
    out = _run(ws, pcap, prefs, [*extra, "-T", "fields", "-E", "occurrence=a", "-E", f"aggregator={AGGREGATOR}",
                                 "-e", "frame.number", *(a for n in names for a in ("-e", n))])
    dump = {}
    for line in out.splitlines():
        cells = line.split("\t")
        assert len(cells) == len(names) + 1, line
        dump[int(cells[0])] = {n: [normal(fields[n], v) for v in cell.split(AGGREGATOR)] if cell else []
                               for n, cell in zip(names, cells[1:])}
    return dump


def pdml_values(frames: list[T.Frame], fields: dict[str, str]) -> dict[int, Values]:
    out = {}
    for f in frames:
        values = {n: [] for n in fields}
        for item in f.items:
            if item.name in values:
                values[item.name].append(normal(fields[item.name], item.show))
        out[f.number] = values
    return out


def packet_list(ws: T.Workspace, pcap: Path, prefs: dict, expression: str, columns: Sequence[str] = (),
                extra: Sequence[str] = ()) -> dict[int, list[str]]:
    """frame -> its custom columns (one per field in `columns`), for the frames `-Y expression`
    keeps: summary lines (`-T tabs`), an invisible tree on tshark 4.0 too (its `-T fields` is not)."""
    spec = ",".join(['"No.","%m"', *(f'"{i}","%Cus:{field}"' for i, field in enumerate(columns))])
    out = _run(ws, pcap, prefs, [*extra, "-Y", expression, "-T", "tabs", "-o", f"gui.column.format:{spec}"])
    rows = {}
    for line in out.splitlines():
        cells = line.split("\t")
        assert len(cells) == len(columns) + 1, line
        rows[int(cells[0])] = cells[1:]
    return rows


def frames_matching(ws: T.Workspace, pcap: Path, prefs: dict, expression: str, extra: Sequence[str] = ()) -> list[int]:
    return sorted(packet_list(ws, pcap, prefs, expression, extra=extra))


def info_visible(ws: T.Workspace, pcap: Path, prefs: dict, extra: Sequence[str] = ()) -> list[str]:
    """The Info column with a visible tree: `-V -P` prints the summary line (here only Info)
    before each packet's details."""
    out = _run(ws, pcap, prefs, [*extra, "-V", "-P", "-O", "vm110", "-S", PACKET_END,
                                 "-o", 'gui.column.format:"Info","%i"'])
    infos, expect_summary = [], True
    for line in out.splitlines():
        if line == PACKET_END:
            expect_summary = True
        elif expect_summary:
            infos.append(line)
            expect_summary = False
    return infos


# --- What the tests read ---------------------------------------------------------------------------
def crafted(pcap: Path) -> None:
    """A few ms-timed packets with the experts no capture of captures/ has: a late acknowledgement,
    one without a command, and both watchdogs (with a retransmission, a spurious one, a duplicate
    acknowledgement and a command never acknowledged)."""
    bu = {"origin": 0x0101}
    vrpo = VRPO(packet_number=0, periodic_data=bytes(64))
    late = C.VRCI_FAIL_MS + 500
    timeline = [
        (0, VM110(serial=1, **bu) / VRPI()), (0, VM110(serial=1) / vrpo),
        (10, VM110(serial=2, **bu) / VRCI(command_id=1)),
        (10 + C.COMMAND_RESEND_MS, VM110(serial=3, **bu) / VRCI(command_id=1)),
        (C.VRPI_WATCHDOG_MS + 200, VM110(serial=4, **bu) / VRPI()),       # VRPI watchdog
        (1500, VM110(serial=5, **bu) / VRCI(command_id=1)),               # (within the reuse gap)
        (late - 100, VM110(serial=6, **bu) / VRCI(command_id=1)),
        (late, VM110(serial=2) / vrpo),                                   # VRPO watchdog
        (late + 10, VM110(serial=3) / VRAO(command_id=1)),                # late
        (late + 20, VM110(serial=4) / VRAO(command_id=7)),                # no such command
        (late + 30, VM110(serial=5) / VRAO(command_id=1)),                # duplicate
        (late + 40, VM110(serial=7, **bu) / VRCI(command_id=1)),          # after the ack
        (late + 100, VM110(serial=8, **bu) / VRCI(command_id=2)),         # never acknowledged
    ]
    T.write_pcap(pcap, [bytes(p) for _, p in timeline], [ms * 1000 for ms, _ in timeline])


def materialise(ws: T.Workspace, source: str) -> tuple[Path, dict]:
    """The capture inside the workspace and its preferences: a capture of captures/ or the crafted
    one with the analysis on, or every shared vector in one capture, decoding only. (The few
    vectors of other CRC settings then have a bad CRC: both paths see the same, and one capture
    instead of eight keeps the module fast; test_dissector_vectors checks each CRC setting.)"""
    pcap = ws.dir / (f"{source}.pcap" if source in (VECTORS, CRAFTED) else source)
    if source == VECTORS:
        T.write_pcap(pcap, (packet_bytes(v) for v in load_vectors()))
        return pcap, {}
    if source == CRAFTED:
        crafted(pcap)
    else:
        pcap.write_bytes((CAPTURES / source).read_bytes())
    return pcap, ON


_PDML: dict = {}


def visible(ws: T.Workspace, source: str, passes: str) -> list[T.Frame]:
    """The source's PDML (a visible tree), once per tshark, source and passes."""
    key = (ws.tshark.name, source, passes)
    if key not in _PDML:
        pcap, prefs = materialise(ws, source)
        frames, output = T.dissect_pdml(ws, pcap, prefs, [*PASSES[passes], "-J", "vm110"], shared=True)
        assert T.LUA_ERROR not in output
        _PDML[key] = frames
    return _PDML[key]


def expert_frames(frames: list[T.Frame]) -> dict[str, list[int]]:
    out = defaultdict(list)
    for f in frames:
        for code in sorted({e.abbrev[len("vm110.expert."):] for e in f.experts}):
            out[code].append(f.number)
    return out


def differences(want: dict[int, Values], got: dict[int, Values], limit: int = 12,
                names: tuple[str, str] = ("visible", "fast")) -> list[str]:
    errors = []
    for side, frames in zip(names, (set(want) - set(got), set(got) - set(want))):
        if frames:
            errors.append(f"frames only {side}: {sorted(frames)[:10]}")
    for number in sorted(set(want) & set(got)):
        for name in want[number]:
            if want[number][name] != got[number][name]:
                errors.append(f"frame {number} {name}: {names[0]} {want[number][name]!r}, "
                              f"{names[1]} {got[number][name]!r}")
    return errors[:limit] + ([f"... {len(errors) - limit} more"] if len(errors) > limit else [])


@contextlib.contextmanager
def workspace(runner: T.Tshark, base: Path) -> Iterator[T.Workspace]:
    try:
        runner.check()
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    with runner.workspace(base) as ws:
        yield ws


runner_ids = pytest.mark.parametrize("tshark", T.RUNNERS, ids=lambda r: r.name)
short_runners = pytest.mark.parametrize("tshark", runner_params(T.RUNNERS))


# --- Fields, experts and the Info column per source (one test each: its PDML is read once) ---------
def all_fields(ws: T.Workspace, source: str, pcap: Path, prefs: dict) -> list[str]:
    """`-T fields` with every vm110 field, single pass and -2, equals PDML frame by frame; so do
    the expert messages (in any order: the fast path attaches an expert to the protocol item when
    its field is not built)."""
    errors, fields = [], catalogue(ws)
    for passes, extra in PASSES.items():
        frames = visible(ws, source, passes)
        want = pdml_values(frames, fields)
        assert sum(bool(v) for values in want.values() for v in values.values()) > len(want)
        for f in frames:   # (vm110 frames: other protocols' experts are not in the vm110 PDML)
            if f.vm110:
                want[f.number][MESSAGES] = sorted(e.message for e in f.experts)
        got = field_dump(ws, pcap, prefs, {**fields, MESSAGES: "FT_STRING"}, extra)
        for values in got.values():
            values[MESSAGES] = sorted(values[MESSAGES])
        errors += [f"all fields, {passes}: {e}" for e in differences(want, got)]
    return errors


def experts(ws: T.Workspace, source: str, pcap: Path, prefs: dict) -> list[str]:
    """A display filter on experts alone (no vm110 field referenced: none is built) finds every
    expert where PDML has it, single pass and -2. One run per pass: `-Y "vm110.expert.a ||
    vm110.expert.b ..."` with a custom column per code (experts are no field of the dissector's,
    so it builds what it builds for `-Y vm110.expert.<code>` alone); the filter keeps exactly the
    frames with some expert. The experts the second pass adds (never_acked, burst_incomplete,
    ack_late on the command) also alone: `-2 -Y vm110.expert.<code>`."""
    errors, first = [], expert_frames(visible(ws, source, "single"))
    for passes, extra in PASSES.items():
        want = expert_frames(visible(ws, source, passes))
        codes = sorted(want)
        assert codes, f"no expert in {source}"
        rows = packet_list(ws, pcap, prefs, " || ".join(f"vm110.expert.{code}" for code in codes),
                           [f"vm110.expert.{code}" for code in codes], extra)
        every = sorted({n for frames in want.values() for n in frames})
        if sorted(rows) != every:
            errors.append(f"experts, {passes}: the filter keeps {sorted(set(rows) ^ set(every))[:10]} wrongly")
        for i, code in enumerate(codes):
            got = [n for n, cells in sorted(rows.items()) if cells[i]]
            if got != want[code]:
                errors.append(f"experts, {passes} {code}: PDML {want[code]}, fast {got}")
        if passes == "two-pass":
            for code in [c for c in codes if want[c] != first.get(c)]:
                got = frames_matching(ws, pcap, prefs, f"vm110.expert.{code}", extra)
                if got != want[code]:
                    errors.append(f"-2 -Y vm110.expert.{code}: PDML {want[code]}, fast {got}")
    return errors


def info_and_sparse(ws: T.Workspace, source: str, pcap: Path, prefs: dict) -> list[str]:
    """`-T fields` with one or two vm110 fields (only they are built) equals their values in PDML;
    with `-e _ws.col.Info` added to the first such run of a pass, the Info column equals that of
    `-V -P`, single pass and -2. The vm110 tree's text starts with the same summary."""
    errors, catalog, with_info = [], catalogue(ws), set()
    for passes, names in SPARSE:
        extra, frames = PASSES[passes], visible(ws, source, passes)
        fields = {n: catalog[n] for n in names}
        column = {} if passes in with_info else {"_ws.col.Info": "FT_STRING"}
        got = field_dump(ws, pcap, prefs, {**column, **fields}, extra)
        want = pdml_values(frames, fields)
        assert any(v for values in want.values() for v in values.values()), names
        errors += [f"sparse {names}, {passes}: {e}" for e in
                   differences(want, {n: {f: v[f] for f in fields} for n, v in got.items()})]
        if not column:
            continue
        with_info.add(passes)
        want = info_visible(ws, pcap, prefs, extra)
        assert len(want) == len(frames) == len(got), passes
        errors += [f"Info, {passes} frame {n}: visible {w!r}, fast {got[n]['_ws.col.Info']!r}"
                   for n, w in enumerate(want, start=1) if got[n]["_ws.col.Info"] != [w]][:10]
        errors += [f"Info, {passes} frame {f.number}: tree {f.text!r}, Info {info!r}" for f, info in zip(frames, want)
                   if f.vm110 and not f"VM-110 EG-Link, {info}".startswith(f.text)][:10]
    return errors


def _views() -> list:
    """(tshark, source) pairs: the vectors and the crafted capture on every version."""
    every = [r.version for r in T.RUNNERS]
    return [on_runner(r, s, id=f"{s}-{r.name}", short=[ANALYSED[s]] if s in ANALYSED else every)
            for s in SOURCES for r in T.RUNNERS]


@pytest.mark.parametrize("tshark, source", _views())
def test_fast_path_equals_visible_path(tshark, source, tmp_path):
    """Every field, the experts, a sparse reference set and the Info column: fast path = PDML."""
    with workspace(tshark, tmp_path) as ws:
        pcap, prefs = materialise(ws, source)
        errors = all_fields(ws, source, pcap, prefs) + experts(ws, source, pcap, prefs) \
            + info_and_sparse(ws, source, pcap, prefs)
        checked = {(code, passes) for passes in PASSES for code in expert_frames(visible(ws, source, passes))}
    assert not errors, "\n".join(errors)
    if source == "retransmit.pcap":
        assert ("never_acked", "two-pass") in checked and ("never_acked", "single") not in checked
    if source == "vrpo-split.pcapng":
        assert ("burst_incomplete", "two-pass") in checked and ("burst_incomplete", "single") not in checked
    if source == CRAFTED:
        assert CRAFTED_EXPERTS <= {code for code, _ in checked}


# --- Display filters against independent expectations ------------------------------------------------
@functools.lru_cache(maxsize=None)
def _datagrams(capture: str) -> dict[int, tuple[str, float, dict]]:
    """frame -> (source "ip:port", time, vm110.decode() of the UDP payload), for every UDP frame to
    or from an EG-Link port (read by the project's capture reader, not by tshark)."""
    out = {}
    for ts, src, sport, dport, payload, frame in CaptureReader(str(CAPTURES / capture)):
        if {sport, dport} & {C.INPUT_PORT, C.OUTPUT_PORT}:
            out[frame] = (address(src, sport), ts, decode(payload))
    return out


def _truth(capture: str) -> dict:
    return json.loads(Path(f"{CAPTURES / capture}.truth.json").read_text())


def _gap_frames(capture: str) -> set[int]:
    """Frames that reveal a serial gap: the truth's gap times per sender, found in the capture."""
    at = {}
    for frame, (source, ts, d) in _datagrams(capture).items():
        direction = "Input" if d["type"].endswith("I") else "Output"
        at[(f"{direction} {source} origin 0x{d['origin']:04x}", round(ts, 6))] = frame
    return {at[(s["id"], g["time"])] for s in _truth(capture)["senders"] for g in s["serial"]["gaps"]}


def _where(capture: str, keep: Callable[[dict], bool]) -> set[int]:
    return {n for n, (_, _, d) in _datagrams(capture).items() if keep(d)}


def _retransmissions(capture: str) -> set[int]:
    commands = _truth(capture)["commands"]
    return {f for kind in ("VRCI", "VRCO") for cmd in commands[kind]["list"] for f in cmd["frames"][1:]}


def _command_frames(capture: str, kind: str, command_id: int) -> set[int]:
    return {f for cmd in _truth(capture)["commands"][kind]["list"] if cmd["command_id"] == command_id
            for f in cmd["frames"]}


# (capture, passes, filter, expected frames, or an expected count)
CAPTURE_FILTERS = (
    ("bu-watchdog.pcap", "single", f"vm110.bu_state == 0x{C.BuState.EXTERNAL_LINK_ERROR:02x}",
     lambda c: _where(c, lambda d: d.get("bu_state") == C.BuState.EXTERNAL_LINK_ERROR)),
    ("bu-watchdog.pcap", "single", "vm110.es_relays_open == 1", lambda c: _where(c, lambda d: d.get("es_relays_open"))),
    ("illegal.pcap", "single", "vm110.crc.status == 0", lambda c: _where(c, lambda d: "bad_crc" in d["problems"])),
    ("illegal.pcap", "single", "_ws.expert.severity >= error", lambda c: _where(c, lambda d: d["problems"])),
    ("retransmit.pcap", "single", 'vm110.type == "VRCI" && vm110.command_id == 5',
     lambda c: _command_frames(c, "VRCI", 5)),
    ("retransmit.pcap", "single", "vm110.analysis.retransmission_number >= 1", _retransmissions),
    ("loss.pcapng", "single", "vm110.analysis.serial_missing > 0", _gap_frames),
    ("vrpo-split.pcapng", "two-pass", "vm110.burst.complete == 0", lambda c: _truth(c)["vrpo_bursts"]["incomplete"]),
)
# On the vectors, one per frame: (filter, which decode the filter matches, by vm110.decode with
# the default CRC setting, as the capture is dissected)
VECTOR_FILTERS = (
    (f"vm110.bu_state == 0x{C.BuState.FAILED:02x}", lambda d: d.get("bu_state") == C.BuState.FAILED),
    ("vm110.crc.status == 0", lambda d: "bad_crc" in d["problems"]),
    ("vm110.command_id == 17", lambda d: d.get("command_id") == 17),
    ("vm110.es_relays_open == 1", lambda d: bool(d.get("es_relays_open"))),
    ('vm110.type == "VRPO" && vm110.packet_number >= 1', lambda d: d.get("packet_number", 0) >= 1),
    ("vm110.unarmed_rus == 2 || vm110.armed_ru == 0x0c07",
     lambda d: d.get("unarmed_rus") == 2 or d.get("armed_ru") == 0x0C07),
)


@short_runners
def test_display_filters_match_independent_expectations(tshark, tmp_path):
    """`-Y` on vm110 fields (only they are built) keeps the frames the decoder or the truth names."""
    errors = []
    with workspace(tshark, tmp_path) as ws:
        for capture, passes, expression, expected in CAPTURE_FILTERS:
            local = ws.dir / capture
            if not local.exists():
                local.write_bytes((CAPTURES / capture).read_bytes())
            got, want = frames_matching(ws, local, ON, expression, PASSES[passes]), expected(capture)
            if isinstance(want, int):
                ok = len(got) == want
            else:
                ok = got == sorted(want)
            assert want, f"{capture}: {expression!r} is expected to match nothing"
            if not ok:
                errors.append(f"{capture} {passes} {expression!r}: tshark {got}, expected {want}")
        pcap, prefs = materialise(ws, VECTORS)
        decoded = [decode(packet_bytes(v)) for v in load_vectors()]
        for expression, keep in VECTOR_FILTERS:
            want = [n for n, d in enumerate(decoded, start=1) if keep(d)]
            got = frames_matching(ws, pcap, prefs, expression)
            assert want, expression
            if got != want:
                errors.append(f"vectors {expression!r}: tshark {got}, expected {want}")
    assert not errors, "\n".join(errors)


# --- Different fields referenced on each pass ---------------------------------------------------------
# (capture, -R, -Y, the field written, read filter and display filter as Python predicates on
# the single pass's field values)
SWITCHES = {
    "all-frames-kept": ("retransmit.pcap", "vm110.serial", "vm110.analysis.retransmission_number >= 1",
                        "vm110.analysis.since_first",
                        lambda v: bool(v["vm110.serial"]),
                        lambda v: (v["vm110.analysis.retransmission_number"] or [0])[0] >= 1),
    # Frames the read filter drops are still dissected on the first pass, under the number of the
    # next frame kept (tshark numbers only the kept ones): the analysis must see every frame and
    # show each kept frame its own results.
    "frames-dropped": ("loss.pcapng", 'vm110.type == "VRPI"', "vm110.analysis.interval > 200",
                       "vm110.analysis.serial_missing",
                       lambda v: v["vm110.type"] == ["VRPI"],
                       lambda v: (v["vm110.analysis.interval"] or [0])[0] > 200),
}


@short_runners
@pytest.mark.parametrize("case", SWITCHES)
def test_pass_switching(tshark, case, tmp_path):
    """`-2 -R <one field> -Y <another> -e <a third>` (a different reference set on each pass)
    equals the single pass's field dump filtered in Python, frames numbered as tshark numbers the
    ones the read filter keeps."""
    capture, read, display, shown, keep, match = SWITCHES[case]
    with workspace(tshark, tmp_path) as ws:
        catalog = catalogue(ws)
        pcap, prefs = materialise(ws, capture)
        fields = {n: catalog[n] for n in ("vm110.type", "vm110.serial", "vm110.analysis.retransmission_number",
                                          "vm110.analysis.interval", shown)}
        full = field_dump(ws, pcap, prefs, fields)
        got = field_dump(ws, pcap, prefs, {shown: catalog[shown]}, ["-2", "-R", read, "-Y", display])
    kept = [values for _, values in sorted(full.items()) if keep(values)]
    want = {number: {shown: values[shown]} for number, values in enumerate(kept, start=1) if match(values)}
    assert want and any(v[shown] for v in want.values())
    if got != want:
        pytest.fail(f"tshark -2 -R '{read}' -Y '{display}' -e {shown}:\n"
                    + "\n".join(differences(want, got, names=("expected", "tshark"))), pytrace=False)


@runner_ids
@pytest.mark.parametrize("passes", sorted(PASSES))
def test_crc_on_every_pass_matches_the_decoder(tshark, passes, tmp_path):
    """The calculated CRC and its status on each pass equal vm110.decode's, with the analysis on
    (on the second pass an analysed packet's CRC is not recalculated: it matched on the first)."""
    capture = "illegal.pcap"   # good and bad CRCs, every illegal reason, other traffic
    with workspace(tshark, tmp_path) as ws:
        local = ws.dir / capture
        local.write_bytes((CAPTURES / capture).read_bytes())
        fields = {"vm110.crc.calculated": "FT_UINT32", "vm110.crc.status": "FT_UINT8"}
        dump = field_dump(ws, local, ON, fields, PASSES[passes])
    expected = {}
    for _, _, _, dport, payload, number in CaptureReader(str(CAPTURES / capture)):
        d = decode(payload)
        if dport in (C.INPUT_PORT, C.OUTPUT_PORT) and d.get("crc.status"):
            expected[number] = {"vm110.crc.calculated": [d["crc.calculated"]],
                                "vm110.crc.status": [1 if d["crc.status"] == "Good" else 0]}
    got = {n: v for n, v in dump.items() if v["vm110.crc.status"]}
    assert expected and got == expected
