"""What the Wireshark GUI shows of the dissector, checked through tshark on every version: a
description (blurb) for every field, a glossary (`tshark -G fields`) in the same order on every
run, expert summaries that group (constant text: few distinct ones per capture), the analysis
findings in front of the Info column and in `vm110.analysis.flags`, the configuration profile
`dissector/profile/VM-110` (its colouring rules' and filter buttons' filters compile, its columns
load), and every Wireshark name the documentation mentions exists."""
from __future__ import annotations

import importlib
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

import tshark_runner as T
from longrun import runner_params

# The profile, the glossary and the expert summaries on 4.0 and 4.6; on 4.4 (the Lua 5.4 of 4.6) in
# the long run, for time.
pytestmark = [pytest.mark.tshark, pytest.mark.parametrize(
    "ws", runner_params(T.RUNNERS), indirect=True)]

CAPTURES = T.REPO / "captures"
PROFILE = T.REPO / "dissector" / "profile" / "VM-110"
DOCS = [T.REPO / "README.md", CAPTURES / "README.md", *sorted((T.REPO / "docs").glob("*.md"))]
ON = {"vm110.analysis": "TRUE"}
# The analysis findings' Info markers (FINDING in the dissector) and the experts they stand for.
MARKERS = {"Serial Gap", "Duplicate", "Out-Of-Order", "Restart", "Watchdog", "Silent Until End", "VRPO Interval",
           "Time Backwards",
           "VRCI Retransmission", "VRCO Retransmission", "VRCI Spurious Retransmission",
           "VRCO Spurious Retransmission", "Resend Interval", "Ack Without Command", "Duplicate Ack", "Late Ack",
           "Unacknowledged", "Interrupted", "Burst Packet Missing", "Incomplete Burst"}


def copy_in(ws: T.Workspace, capture: str):
    local = ws.dir / capture
    local.write_bytes((CAPTURES / capture).read_bytes())
    return local


def default_prefs(ws: T.Workspace) -> str:
    """`tshark -G defaultprefs` with the plugin: every preference, its description in comments."""
    return ws.run(["-G", "defaultprefs", "-X", f"lua_script:{ws.plugin()}"], plugin=False, shared=True).stdout


def expert_info(ws: T.Workspace, capture: str) -> str:
    """`tshark -2 -q -z expert` of the capture, the analysis on: Expert Information's lines."""
    return ws.run(["-r", str(copy_in(ws, capture)), "-2", "-q", "-z", "expert", *T.pref_args(ON)], shared=True).stdout


def test_every_field_has_a_description(ws):
    """The status bar shows a field's blurb; `tshark -G fields` lists it in the 8th column."""
    fields = [r for r in T.glossary(ws) if r[0] == "F" and not r[2].startswith("vm110.expert.")]
    assert len(fields) > 60 and "vm110.analysis.flags" in {r[2] for r in fields}
    missing = [r[2] for r in fields if len(r) < 8 or not r[7].strip()]
    assert not missing, f"fields without a description: {missing}"


# Preferences whose description names the severity of an expert they set, and a capture with it.
PREF_SEVERITY = {"vrpi_watchdog_ms": ("controller-watchdog.pcap", "VRPI interval above the controller watchdog"),
                 "vrpo_watchdog_ms": ("bu-watchdog.pcap", "VRPO interval above the base unit watchdog")}


def test_preference_descriptions_name_the_severity(ws):
    """The preferences dialog's tooltip (`tshark -G defaultprefs`) of a limit says what a packet
    beyond it gets, with the severity Expert Information shows. Trial: the watchdogs said "Warn
    above this" of what is an Error."""
    prefs = default_prefs(ws)
    for name, (capture, summary) in PREF_SEVERITY.items():
        description = re.search(rf"^# (.*)\n(?:# .*\n)*#vm110\.{name}:", prefs, re.M)[1]
        out = expert_info(ws, capture)
        section = re.search(rf"^(Error|Warn|Note)s \(\d+\)\n(?:(?!\n\n).)*{re.escape(summary)}", out, re.M | re.S)
        assert section and description.split()[0] == section[1], (name, description, section and section[1])


def test_glossary_order_is_deterministic(ws):
    """Fields and experts are registered in a fixed order (Lua 5.4's pairs() order changes from run to
    run), so `tshark -G fields` is the same every time."""
    first, second = T.glossary(ws, shared=False), T.glossary(ws, shared=False)
    assert first == second
    names = [r[2] for r in first if r[0] == "F"]
    assert names.index("vm110.analysis.ack_in") < names.index("vm110.type")  # (sorted by key)


def doc_names() -> dict[str, list[str]]:
    """Wireshark names (`vm110.x.y`) the documentation mentions -> the files mentioning them. Left
    out: `vm110.lua`, placeholders (`vm110.<name>`, `vm110.expert.<code>`) and Python names
    (`vm110.layers.bind_ports`), which must import."""
    out: dict[str, list[str]] = {}
    for doc in DOCS:
        text = doc.read_text()
        for m in re.finditer(r"vm110(?:\.[a-z0-9_]+)+", text):
            name = m.group(0)
            if name.endswith(".lua") or text[m.end():m.end() + 2] == ".<" or _python_name(name):
                continue
            out.setdefault(name, []).append(doc.name)
    return out


def _python_name(name: str) -> bool:
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return i > 1 or len(parts) == 1
    return False


def test_names_in_the_docs_exist(ws):
    """Every field, expert and preference name in README.md, captures/README.md and docs/*.md is
    one the dissector registers."""
    fields = {r[2] for r in T.glossary(ws) if r[0] == "F"}
    prefs = set(re.findall(r"^#?(vm110\.[a-z0-9_]+):", default_prefs(ws), re.M))
    assert "vm110.analysis" in prefs and "vm110.crc_variant" in prefs
    names = doc_names()
    assert len(names) > 40 and "vm110.analysis.flags" in names
    unknown = {n: docs for n, docs in names.items() if n not in fields and n not in prefs}
    assert not unknown, f"names in the docs that tshark does not know: {unknown}"
    experts = {n for n in names if n.startswith("vm110.expert.")}
    assert experts and experts <= fields


@pytest.mark.parametrize("capture", ["loss.pcapng", "overlap.pcapng", "restart.pcapng"])
def test_expert_summaries_group(ws, capture):
    """`tshark -z expert` groups by summary: a handful of constant lines (no numbers), not one per
    packet (255 on loss.pcapng when the numbers were in the text)."""
    rows = [line.split(None, 3) for line in expert_info(ws, capture).splitlines()]
    summaries = [r[3] for r in rows if len(r) == 4 and r[0].isdigit() and r[2] == "VM110"]
    assert summaries and len(summaries) == len(set(summaries)) <= 12, summaries
    assert not [s for s in summaries if re.search(r"\d", s)], summaries


@pytest.mark.parametrize("capture", ["illegal.pcap", "restart.pcapng"])
def test_expert_lines_read_as_the_gui_groups(ws, capture):
    """Analyze > Expert Information groups by expert, under its registered summary; `tshark -z
    expert` groups by the item's text. Each item carries its expert's summary, so the lines are the
    same groups in the same words; only a truncated datagram says why (the README's "Truncated: cut
    short by the capture (snaplen)": a line per reason, one "Truncated" group in the GUI). Trial:
    the GUI said "Unknown packet ID", "Unsupported revision", "ES-Link relays open" where tshark said
    "Unknown packet ID: the payload is not decoded", ..."""
    registered = {r[1] for r in T.glossary(ws) if r[0] == "F" and r[2].startswith("vm110.expert.")}
    rows = [line.split(None, 3) for line in expert_info(ws, capture).splitlines()]
    summaries = {r[3] for r in rows if len(r) == 4 and r[0].isdigit() and r[2] == "VM110"}
    assert len(summaries) >= 6
    assert not {s for s in summaries if s not in registered and not s.startswith("Truncated: ")}, registered


def test_expert_information_screenshot_is_current(ws):
    """docs/gui-expert-info.png shows Analyze > Expert Information on restart.pcapng, and
    docs/screenshots.md lists its lines: each expert's summary (the GUI's group line: the
    registered one) with its severity and count. They are what the dissector flags now (`tshark
    -z expert`, whose summary is the item's text: the registered one).
    Trial: the screenshot showed ES-Link relays open 2 times where the dissector flags 10."""
    doc = (T.REPO / "docs" / "screenshots.md").read_text()
    shown = sorted((sev, summary, int(n)) for sev, summary, n in
                   re.findall(r"^\| (Error|Warning|Note) \| (.+?) \| (\d+) \|$", doc, re.M))
    summaries = {summary for _, summary, _ in shown}
    out = expert_info(ws, "restart.pcapng")
    severity, flagged = "", {}
    for line in out.splitlines():
        heading = re.match(r"(Error|Warn|Note)s \(\d+\)$", line)
        row = line.split(None, 3)
        if heading:
            severity = {"Warn": "Warning"}.get(heading[1], heading[1])
        elif len(row) == 4 and row[0].isdigit() and row[2] == "VM110":
            [summary] = [s for s in summaries if row[3] == s]
            flagged[severity, summary] = flagged.get((severity, summary), 0) + int(row[0])
    assert shown and shown == sorted((sev, summary, n) for (sev, summary), n in flagged.items())


def _fields(ws, capture, *names, extra=()):
    proc = ws.run(["-r", str(copy_in(ws, capture)), "-2", *T.pref_args(ON), *extra, "-T", "fields",
                   "-E", "occurrence=a", *(a for n in names for a in ("-e", n))])
    assert T.LUA_ERROR not in proc.stdout + proc.stderr
    return [line.split("\t") for line in proc.stdout.splitlines()]


@pytest.mark.parametrize("capture", ["overlap.pcapng", "restart.pcapng", "retransmit.pcap"])
def test_findings_flags_and_info_markers(ws, capture):
    """vm110.analysis.flags is on exactly the packets with an analysis expert, lists the same
    findings the Info column shows in front ("[Serial Gap] [VRCI Retransmission] VRCI cmd 3, ...")."""
    codes = sorted(T.ANALYSIS_EXPERTS)
    rows = _fields(ws, capture, "frame.number", "vm110.analysis.flags", "_ws.col.Info",
                   *(f"vm110.expert.{c}" for c in codes))
    seen = set()
    for row in rows:
        number, flags, info, experts = row[0], row[1], row[2], row[3:]
        has_expert = any(experts)
        assert bool(flags) == has_expert, (number, flags, info)
        if not flags:
            assert not info.startswith("["), (number, info)
            continue
        names = flags.split(", ")
        assert set(names) <= MARKERS, (number, names)
        assert info.startswith("".join(f"[{n}] " for n in names)), (number, flags, info)
        seen.update(names)
    assert seen


def test_analysis_items_sit_in_one_subtree(ws):
    """Every analysis item is under "[VM-110 analysis]" (as TCP's "[SEQ/ACK analysis]") with the
    flags last."""
    out = ws.run(["-r", str(copy_in(ws, "overlap.pcapng")), "-2", *T.pref_args(ON), "-V", "-O", "vm110",
                  "-Y", "vm110.analysis.flags && vm110.analysis.retransmission_of"]).stdout
    block = out.split("    [VM-110 analysis]\n", 1)[1].split("\n\n", 1)[0]
    lines = [line for line in block.splitlines() if line.startswith("        [") and "Expert Info" not in line]
    assert any("Retransmission of frame" in line for line in lines)
    assert lines[-1].startswith("        [VM-110 analysis flags: ")


def profile_filters() -> list[tuple[str, str]]:
    """(source, filter) of every colouring rule and filter button of the profile."""
    out = []
    for line in (PROFILE / "colorfilters").read_text().splitlines():
        if line.startswith("@"):
            out.append(("colorfilters " + line.split("@")[1], line.split("@")[2]))
    for line in (PROFILE / "dfilter_buttons").read_text().splitlines():
        if line.startswith('"'):
            cells = re.findall(r'"((?:[^"\\]|\\.)*)"', line)
            assert len(cells) == 4 and cells[0] == "TRUE", line
            out.append(("button " + cells[1], cells[2].replace('\\"', '"')))
    return out


def test_profile_filters_compile(ws):
    """Every colouring rule and filter button compiles in this tshark (with the dissector), and the
    VM-110 ones each find something in a bundled capture."""
    filters = profile_filters()
    assert len(filters) >= 15
    # (the capture with the most kinds of findings first: most filters match there)
    pcaps = {c: copy_in(ws, c) for c in ("restart.pcapng", "overlap.pcapng", "illegal.pcap", "disarmed.pcap",
                                         "controller-watchdog.pcap")}

    def run(pcap: Path, expression: str, source: str) -> bool:
        proc = ws.run(["-r", str(pcap), "-2", *T.pref_args(ON), "-Y", expression], check=False)
        assert proc.returncode == 0 and T.LUA_ERROR not in proc.stdout + proc.stderr, \
            f"{source}: {expression!r}: {proc.stderr.strip()[-500:]}"
        return bool(proc.stdout.strip())

    # Wireshark's own rules only have to compile: all of them in one run (each alone if that fails).
    own = [(source, expression) for source, expression in filters if "vm110" not in expression]
    small = pcaps["controller-watchdog.pcap"]
    if ws.run(["-r", str(small), "-Y", " || ".join(f"({e})" for _, e in own)], check=False).returncode:
        for source, expression in own:
            run(small, expression, source)
    for source, expression in filters:
        if (source, expression) not in own:
            assert any(run(pcap, expression, source) for pcap in pcaps.values()), \
                f"{source}: {expression!r} matches nothing in {sorted(pcaps)}"


def with_profile(ws: T.Workspace, args: list[str], plugin: bool = True) -> subprocess.CompletedProcess:
    """tshark with `-C VM-110` (and the plugin), the profile in a personal configuration folder of
    its own."""
    config = ws.dir / "config"
    shutil.copytree(PROFILE, config / "profiles" / "VM-110")
    env = dict(os.environ, WIRESHARK_CONFIG_DIR=ws.tshark.inner(config))
    args = [*(["-X", f"lua_script:{ws.plugin()}"] if plugin else []), "-C", "VM-110",
            *(a.replace(str(ws.dir), ws.tshark.inner(ws.dir)) for a in args)]
    proc = subprocess.run(ws.tshark.command(args), capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0 and T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-1000:]
    return proc


def test_profile_illegal_filters_select_the_illegal_packets(ws):
    """The Illegal button, and the colouring rules for bad CRCs and illegal packets, select the
    packets `vm110 analyze` counts illegal, an empty datagram on an EG-Link port among them (the
    README's `truncated`; Wireshark calls no dissector for it, "UDP Len=0"). Trial: the button
    showed none of them, while analyze counted each one illegal. An ICMP error quoting an EG-Link
    datagram (a port unreachable) is coloured as Wireshark colours ICMP errors, and is not illegal
    (analyze reads no ICMP): trial: a whole quote was coloured as plain EG-Link input, hiding the
    error, and a quote of only the beginning as an illegal packet, and the Illegal button showed it."""
    from scapy.layers.inet import ICMP, IP
    from scapy.layers.l2 import Ether
    from scapy.utils import wrpcap
    from vm110 import encode
    from vm110.analysis import analyze
    vrpi = [encode.encode({"type": "VRPI", "serial": n, "origin": 0x0101}) for n in range(6)]
    bad_crc = encode.packet("VRPO", b"\0\0", serial=0, crc=0)
    quoted = IP(T.frame(T.Datagram(vrpi[4]))[14:])                # (the multicast VRPI, 66 bytes of UDP payload)
    unreachable = Ether() / IP(src=T.CONTROLLER_ADDR, dst=T.BU_ADDR) / ICMP(type=3, code=3)
    datagrams = [vrpi[0], T.Datagram(b""), vrpi[1], bad_crc, vrpi[2], T.Datagram(b"", sport=5827, dport=5827),
                 vrpi[3], T.Datagram(b"", sport=6000, dport=6000)]
    frames = [Ether(T.frame(d if isinstance(d, T.Datagram) else T.Datagram(d))) for d in datagrams]
    frames += [unreachable / bytes(quoted), unreachable / bytes(quoted)[:48], Ether(T.frame(T.Datagram(vrpi[5])))]
    for n, frame in enumerate(frames):
        frame.time = 1_700_000_000 + n / 8
    capture = ws.dir / "empty.pcap"
    wrpcap(str(capture), frames)
    [illegal] = [f for f in analyze(str(capture))["verdict"]["findings"] if f["rule"] == "illegal"]
    want = sorted(i["frame"] for i in illegal["items"])
    assert want == [2, 4, 6]
    filters = dict(profile_filters())
    proc = ws.run(["-r", str(capture), "-2", *T.pref_args(ON), "-Y", filters["button Illegal"], "-T", "fields",
                   "-e", "frame.number"])
    assert [int(n) for n in proc.stdout.split()] == want
    rows = with_profile(ws, ["-r", str(capture), "-2", "--color", "-T", "fields", "-e", "frame.number",
                             "-e", "frame.coloring_rule.name"]).stdout
    rules = dict(line.split("\t") for line in rows.splitlines())
    assert [int(n) for n, rule in rules.items() if rule in ("VM-110 bad CRC", "VM-110 illegal packet")] == want
    assert rules["9"] == rules["10"] == "ICMP errors"


def test_profile_colours_in_tshark_fields_output(ws):
    """`tshark --color -T fields -e frame.coloring_rule.name` with the profile names the rule the
    GUI uses: every EG-Link packet one of the VM-110 rules, the restarts (the truth's frames) the
    restart rule. Trial: tshark 4.0 coloured every EG-Link packet "UDP" (its -T fields builds only
    the vm110 fields the command line names, and the colouring rules name others)."""
    pcap = copy_in(ws, "restart.pcapng")
    truth = json.loads((CAPTURES / "restart.pcapng.truth.json").read_text())
    restarts = sorted(e["frame"] for s in truth["senders"] for e in s["serial"]["restart_events"])
    assert restarts == [187, 440, 517]
    rows = with_profile(ws, ["-r", str(pcap), "-2", "--color", "-T", "fields", "-e", "frame.number",
                             "-e", "frame.coloring_rule.name"]).stdout
    rules = [line.split("\t") for line in rows.splitlines()]
    assert len(rules) == 781 and all(rule.startswith("VM-110 ") for _, rule in rules), rules[:3]
    assert [int(n) for n, rule in rules if rule == "VM-110 restart"] == restarts


def test_profile_reads_cleanly_without_the_plugin(ws):
    """A Wireshark that has not loaded the plugin (not installed yet, or 4.4 and later as root)
    reads the profile without a warning. Trial: "No such preference vm110.analysis ... (save
    preferences to remove this warning)" on every start."""
    proc = with_profile(ws, ["-r", str(copy_in(ws, "normal.pcap")), "-c", "1"], plugin=False)
    assert proc.stdout and "WARNING" not in proc.stderr, proc.stderr


def test_profile_loads(ws):
    """`-C VM-110` with the profile in the personal configuration folder: the packet list has its
    columns (type, serial, command ID, interval) and the Info column its markers."""
    proc = with_profile(ws, ["-r", str(copy_in(ws, "retransmit.pcap")), "-2", "-T", "tabs"])
    # (tshark puts an arrow between consecutive source and destination columns)
    rows = [[c for c in line.split("\t") if c != "\u2192"] for line in proc.stdout.splitlines()]
    assert rows and all(len(r) == 11 for r in rows), rows[:3]
    by_type = {}
    for r in rows:
        by_type.setdefault(r[6].strip(), r)
    assert {"VRPI", "VRPO", "VRCI", "VRAO"} <= set(by_type)
    vrci = by_type["VRCI"]
    assert vrci[7].strip().isdigit() and vrci[8].strip().isdigit() and f"cmd {vrci[8].strip()}" in vrci[10]
    assert float(by_type["VRPI"][9] or "0") >= 0
    assert any(r[10].startswith("[VRCI Retransmission] ") for r in rows)


def test_profile_buttons_leave_out_icmp_quotes(ws):
    """No filter button selects an ICMP error that quotes an EG-Link datagram, and every such error
    (a parameter problem too) is coloured as an ICMP error: the quote carries the vm110 fields of a
    packet that was not received. The Relays open button selects the VRPI itself. Trial: Relays
    open listed the port unreachable quoting a VRPI with the relays open beside the VRPI, and a
    parameter problem quoting it was coloured "VM-110 ES-Link relays open"."""
    from scapy.layers.inet import ICMP, IP, UDP
    from scapy.layers.inet6 import ICMPv6DestUnreach, IPv6
    from scapy.layers.l2 import Ether
    from scapy.utils import wrpcap
    from vm110 import constants as C
    from vm110 import encode
    open_state = min(s for s in C.BU_STATE_NAMES if s < C.ES_RELAYS_CLOSED_FROM)
    vrpi = Ether(T.frame(T.Datagram(encode.encode({"type": "VRPI", "serial": 1, "bu_state": open_state}))))
    v6 = IPv6(src="fe80::1", dst="ff02::42") / UDP(sport=C.INPUT_PORT, dport=C.INPUT_PORT) / bytes(vrpi[UDP].payload)
    frames = [vrpi] + [Ether(src="02:00:0a:00:00:14", dst="02:00:0a:00:00:0a") / error / bytes(quoted) for error, quoted in (
        (IP(src=T.CONTROLLER_ADDR, dst=T.BU_ADDR) / ICMP(type=3, code=3), vrpi[IP]),     # port unreachable
        (IP(src=T.CONTROLLER_ADDR, dst=T.BU_ADDR) / ICMP(type=12, code=0), vrpi[IP]),    # parameter problem
        (IPv6(src="fe80::2", dst="fe80::1") / ICMPv6DestUnreach(code=4), v6))]
    for n, frame in enumerate(frames):
        frame.time = 1_700_000_000 + n / 8
    capture = ws.dir / "quoted.pcap"
    wrpcap(str(capture), frames)
    both = ws.run(["-r", str(capture), "-2", *T.pref_args(ON), "-Y", "vm110.es_relays_open == 1", "-T", "fields",
                   "-e", "frame.number"]).stdout.split()
    assert both == ["1", "2", "3", "4"]   # (each quote is dissected as VM-110)
    buttons = {source: expression for source, expression in profile_filters() if source.startswith("button ")}

    def matches(expression: str) -> list[str]:
        return ws.run(["-r", str(capture), "-2", *T.pref_args(ON), "-Y", expression, "-T", "fields",
                       "-e", "frame.number"]).stdout.split()
    assert matches(buttons["button Relays open"]) == ["1"]
    assert matches(" || ".join(f"({e})" for e in buttons.values())) == ["1"]
    rows = with_profile(ws, ["-r", str(capture), "-2", "--color", "-T", "fields", "-e", "frame.number",
                             "-e", "frame.coloring_rule.name"]).stdout
    assert [line.split("\t")[1] for line in rows.splitlines()] == ["VM-110 ES-Link relays open"] + ["ICMP errors"] * 3
