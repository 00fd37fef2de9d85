"""How the dissector is found and set up in tshark: default ports, the input-port preference,
Decode As, the heuristic and its switch, CRC validation off, the Info column, display filters;
and the `vm110 dissect` command. Every check runs on both tshark versions."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

import tshark_runner as T
from vm110 import constants as C
from vm110.cli import main
from vm110.layers import VM110, VRAO, VRCI, VRPI, VRPO

pytestmark = pytest.mark.tshark

VRPI_ARMED = bytes(VM110(origin=0x0101, serial=12) / VRPI(
    bu_state=C.BuState.ARMED, armed_ru=0x0C07, ru_state=C.RuState.ENABLED, ru_battery=88))
VRPI_STOPPED = bytes(VM110(origin=0x0101, serial=13) / VRPI(bu_state=C.BuState.STOPPED, unarmed_rus=2))
VRCI_17 = bytes(VM110(origin=0x0101, serial=14) / VRCI(command_id=17))
VRAO_17 = bytes(VM110(serial=3) / VRAO(command_id=17))
VRPO_0 = bytes(VM110(serial=4) / VRPO(packet_number=0, periodic_data=bytes(64)))
OTHER_PORT = 40000


def _fields(ws: T.Workspace, datagrams, *fields: str, prefs=None, extra=()) -> list[list[str]]:
    pcap = ws.dir / "capture.pcap"
    T.write_pcap(pcap, datagrams)
    args = ["-r", str(pcap), *T.pref_args(prefs), *extra, "-T", "fields", *(a for f in fields for a in ("-e", f))]
    proc = ws.run(args)
    assert T.LUA_ERROR not in proc.stdout + proc.stderr
    return [line.split("\t") for line in proc.stdout.splitlines()]


def test_info_column(ws):
    rows = _fields(ws, [VRPI_ARMED, VRPI_STOPPED, VRCI_17, VRAO_17, VRPO_0], "_ws.col.Protocol", "_ws.col.Info")
    assert rows == [
        ["VM110", "VRPI Armed RU 0x0C07 Enabled bat 88%, serial 12"],
        ["VM110", "VRPI Stopped unarmed RUs 2, serial 13"],
        ["VM110", "VRCI cmd 17, serial 14"],
        ["VM110", "VRAO ack 17, serial 3"],
        ["VM110", "VRPO #0 64 bytes, serial 4"],
    ]


def test_info_column_names_the_illegal_reasons(ws):
    bad_crc = VRAO_17[:-1] + bytes([VRAO_17[-1] ^ 1])
    rows = _fields(ws, [bad_crc, VRPI_ARMED[:30]], "_ws.col.Info")
    assert rows == [["VRAO ack 17, serial 3 [Illegal: bad CRC]"],
                    ["VRPI Armed RU 0x0C07 Enabled bat 88%, serial 12 [Illegal: bad CRC, size mismatch, truncated]"]]


def test_command_id_filter_pairs_commands_and_acks(ws):
    rows = _fields(ws, [VRPI_ARMED, VRCI_17, VRAO_17, VRPO_0], "vm110.type", extra=["-Y", "vm110.command_id == 17"])
    assert rows == [["VRCI"], ["VRAO"]]


def test_filters_on_names_and_generated_fields(ws):
    packets = [VRPI_ARMED, VRPI_STOPPED, VRCI_17, VRAO_17]
    assert _fields(ws, packets, "vm110.serial", extra=["-Y", 'vm110.bu_state == "Stopped"']) == [["13"]]
    assert _fields(ws, packets, "vm110.serial", extra=["-Y", "vm110.es_relays_open == 1"]) == [["13"]]
    assert _fields(ws, packets, "vm110.serial", extra=["-Y", 'vm110.direction == "Output"']) == [["3"]]
    assert _fields(ws, packets, "vm110.serial", extra=["-Y", "vm110.crc.status == 1"]) == [["12"], ["13"], ["14"], ["3"]]


def test_default_ports_and_heuristic(ws):
    elsewhere = [T.Datagram(VRPI_ARMED, OTHER_PORT, OTHER_PORT), T.Datagram(VRCI_17, OTHER_PORT + 1, 33333)]
    # A payload whose size does not match the UDP length is not claimed on other ports.
    inconsistent = T.Datagram(VRPI_ARMED + b"\0", OTHER_PORT, OTHER_PORT)
    packets = [VRPI_ARMED, VRAO_17, *elsewhere, inconsistent]
    assert [r[0] for r in _fields(ws, packets, "frame.protocols")] == [
        "eth:ethertype:ip:udp:vm110"] * 4 + ["eth:ethertype:ip:udp:data"]
    off = _fields(ws, packets, "frame.protocols", prefs={"vm110.heuristic": "FALSE"})
    assert [r[0].endswith(":vm110") for r in off] == [True, True, False, False, False]


def test_input_port_preference(ws):
    port = 6000
    packets = [T.Datagram(VRPI_ARMED, port, port), T.Datagram(VRAO_17, port + C.OUTPUT_PORT_OFFSET, 1234),
               T.Datagram(VRPI_ARMED, C.INPUT_PORT, C.INPUT_PORT)]
    rows = _fields(ws, packets, "frame.protocols", prefs={"vm110.heuristic": "FALSE", "vm110.input_port": str(port)})
    assert [r[0].endswith(":vm110") for r in rows] == [True, True, False]


def test_decode_as(ws):
    packets = [T.Datagram(VRPI_ARMED, 7000, 7001)]
    prefs = {"vm110.heuristic": "FALSE"}
    assert _fields(ws, packets, "frame.protocols", prefs=prefs) == [["eth:ethertype:ip:udp:data"]]
    rows = _fields(ws, packets, "frame.protocols", "vm110.serial", prefs=prefs, extra=["-d", "udp.port==7000,vm110"])
    assert rows == [["eth:ethertype:ip:udp:vm110", "12"]]


def test_crc_validation_off(ws):
    bad_crc = VRAO_17[:-1] + bytes([VRAO_17[-1] ^ 1])
    rows = _fields(ws, [bad_crc], "vm110.crc.status", "vm110.crc.calculated", "vm110.expert.bad_crc", "vm110.crc",
                   prefs={"vm110.check_crc": "FALSE"})
    assert rows[0][:3] == ["2", "", ""]
    assert int(rows[0][3], 16) == int.from_bytes(bad_crc[-4:], "little")


def test_ethernet_trailer_does_not_move_the_crc(ws):
    """Bytes after the UDP datagram (padding, trailers) are not EG-Link: the CRC comes from `size`."""
    rows = _fields(ws, [T.Datagram(VRAO_17, trailer=bytes(8))], "frame.len", "udp.length", "vm110.crc.status")
    assert rows == [["72", "30", "1"]]


@pytest.fixture
def sample_capture(tmp_path):
    pcap = tmp_path / "sample.pcap"
    T.write_pcap(pcap, [VRPI_ARMED, VRCI_17, VRAO_17])
    return pcap


def _vm110(*args: str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, env=env)


def test_a_second_copy_stands_aside(ws):
    """An installed plugin and `-X lua_script:` with the repository's copy: the first loaded
    dissects, the second says in one line that it was not loaded and why (no Lua stack trace)."""
    second = ws.dir / "second" / "vm110.lua"
    second.parent.mkdir()
    second.write_bytes(T.PLUGIN.read_bytes())
    pcap = ws.dir / "capture.pcap"
    T.write_pcap(pcap, [VRPI_ARMED, VRCI_17])
    proc = ws.run(["-X", f"lua_script:{second}", "-r", str(pcap), "-T", "fields", "-e", "vm110.type"])
    assert proc.stdout.split() == ["VRPI", "VRCI"]
    said = [line for line in proc.stderr.splitlines() if "vm110" in line]
    assert len(said) == 1 and "stack traceback" not in proc.stderr, proc.stderr
    assert said[0].endswith(f"vm110: {ws.tshark.inner(second)} not loaded: the VM-110 dissector is loaded already "
                            f"from {ws.plugin()} (version 0.1.0); remove one of the two")


def test_dissect_command(sample_capture):
    T.HOST.check()
    done = _vm110("dissect", str(sample_capture), "-T", "fields", "-e", "vm110.type", "-e", "vm110.command_id")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["VRPI\t", "VRCI\t17", "VRAO\t17"]
    done = _vm110("dissect", str(sample_capture), "--", "-Y", "vm110.command_id == 17")
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 2
    piped = subprocess.run([sys.executable, "-m", "vm110", "dissect", "-", "-T", "fields", "-e", "vm110.type"],
                           input=sample_capture.read_bytes(), capture_output=True)  # `-`: from a pipe
    assert piped.returncode == 0, piped.stderr
    assert piped.stdout.decode().splitlines() == ["VRPI", "VRCI", "VRAO"]


def test_dissect_command_errors(sample_capture, tmp_path):
    done = _vm110("dissect", str(tmp_path / "missing.pcap"))
    assert done.returncode == 2 and done.stderr.startswith("vm110 dissect: cannot read")
    no_tshark = dict(os.environ, PATH=str(tmp_path))
    done = _vm110("dissect", str(sample_capture), env=no_tshark)
    assert done.returncode == 2 and "tshark not found" in done.stderr
    elsewhere = dict(os.environ, VM110_DISSECTOR=str(tmp_path / "none.lua"))
    done = _vm110("dissect", str(sample_capture), env=elsewhere)
    assert done.returncode == 2 and "dissector is not at" in done.stderr


def test_dissect_command_refuses_an_empty_capture_and_reads_a_named_pipe(sample_capture, tmp_path, capfd):
    """README, "Exit codes": an empty input is exit 2 with one line. tshark passes over an empty file
    or pipe with status 0 and no word, as over a capture without packets (Wireshark 4.0 to 4.6);
    and a named pipe (`vm110 dissect <(tcpdump -w - ...)`), which tshark reads, was refused as
    "cannot read"."""
    T.HOST.check()
    empty = tmp_path / "empty.pcap"
    empty.write_bytes(b"")
    assert main(["dissect", str(empty)]) == 2
    assert capfd.readouterr().err.splitlines() == [f"vm110 dissect: {empty}: empty, not a capture"]
    piped = subprocess.run([sys.executable, "-m", "vm110", "dissect", "-"], input="", capture_output=True, text=True)
    assert (piped.returncode, piped.stderr.splitlines()) == (2, ["vm110 dissect: standard input: empty, not a capture"])
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    writer = subprocess.Popen(["sh", "-c", f"cat '{sample_capture}' > '{fifo}'"])
    assert main(["dissect", str(fifo), "-T", "fields", "-e", "vm110.type"]) == 0
    writer.wait(timeout=60)
    assert capfd.readouterr().out.splitlines() == ["VRPI", "VRCI", "VRAO"]


def test_readme_filters_are_valid(ws):
    """The display filters the README shows compile in this tshark and match the golden capture."""
    readme = (T.REPO / "README.md").read_text()
    block = readme.split("**Filters.**", 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
    filters = [line.split("  ")[0].strip() for line in block.splitlines() if line.strip()]
    assert len(filters) >= 5
    pcap = ws.dir / "golden.pcap"
    pcap.write_bytes((T.REPO / "tests" / "golden" / "vm110-sample.pcap").read_bytes())
    for expression in filters:
        proc = ws.run(["-r", str(pcap), "-Y", expression], check=False)
        assert proc.returncode == 0, f"{expression!r}: {proc.stderr.strip()}"
        assert proc.stdout.strip(), f"{expression!r} matches nothing in the golden capture"


def test_documented_preferences_path_names_the_protocol(ws):
    """Wireshark's Preferences > Protocols tree lists a protocol by its short name, the one `tshark
    -G protocols` gives (TCP, UDP, ...): every such path in the documents names it so. Trial: the
    README sent the user to Protocols > VM-110 EG-Link (the full name), captures/README.md to VM110."""
    proc = ws.run(["-G", "protocols", "-X", f"lua_script:{ws.plugin()}"], plugin=False)
    short = next(row[1] for row in (line.split("\t") for line in proc.stdout.splitlines()) if row[2:3] == ["vm110"])
    docs = [T.REPO / "README.md", T.REPO / "captures" / "README.md", *(T.REPO / "docs").glob("*.md")]
    named = [name for doc in docs
             for name in re.findall(r"Preferences [\u203a\u2192] Protocols [\u203a\u2192] ([^,\u203a\u2192)]+?)(?: [\u203a\u2192]|,|\)|$)",
                                    " ".join(doc.read_text().split()))]
    assert len(named) >= 3 and set(named) == {short}


def test_documented_plugin_type_is_the_one_listed(ws):
    """The README tells the user to find vm110.lua in About > Plugins by its type, which is the one
    `tshark -G plugins` lists (trial: it said "lua"; Wireshark lists "lua script", 4.6 "Lua script")."""
    proc = ws.run(["-G", "plugins", "-X", f"lua_script:{ws.plugin()}"], plugin=False)
    listed = {row[2].lower() for row in (line.split("\t") for line in proc.stdout.splitlines()) if row[0].endswith("vm110.lua")}
    documented = re.findall(r"lists `vm110\.lua` \(type \"([^\"]+)\"\)", (T.REPO / "README.md").read_text())
    assert len(documented) == 1 and listed == set(documented)


def _documented_filters() -> list[str]:
    """The display filters the documents give a user to type: the README's filter blocks and the
    filters in captures/README.md's table (backquoted, with a comparison or naming a vm110 or crane
    field)."""
    readme = (T.REPO / "README.md").read_text()
    filters = []
    for title in ("**Filters.**", "**Stream analysis filters**"):
        block = readme.split(title, 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
        filters += [line.split("  ")[0].strip() for line in block.splitlines() if line.strip()]
    table = (T.REPO / "captures" / "README.md").read_text().split("## The captures", 1)[1]
    filters += [f.replace("\\|", "|") for f in re.findall(r"`((?:vm110|crane|udp|_ws)\.[^`]*? (?:==|>=|<=|>|<) [^`]+)`", table)]
    return filters


def test_documented_filters_compile(ws):
    """Every display filter the README and captures/README.md show compiles in this tshark (with the
    crane example for its fields): one run, the filters joined by ||, since tshark refuses the whole
    filter for one bad part (trial: the stream analysis block and the captures' table were checked
    by hand only)."""
    filters = _documented_filters()
    assert len(filters) >= 25 and "crane.load > 15000" in filters and "vm110.reassembled" in filters
    crane = ws.dir / "crane.lua"
    crane.write_bytes((T.REPO / "dissector" / "examples" / "crane.lua").read_bytes())
    pcap = ws.dir / "golden.pcap"
    pcap.write_bytes((T.REPO / "tests" / "golden" / "vm110-sample.pcap").read_bytes())
    proc = ws.run(["-X", f"lua_script:{ws.tshark.inner(crane)}", "-r", str(pcap), "-2",
                   "-Y", " || ".join(f"({f})" for f in filters)], check=False)
    assert proc.returncode == 0 and T.LUA_ERROR not in proc.stdout + proc.stderr, proc.stderr[-2000:]


def test_make_install_wireshark(tmp_path):
    """`make install-wireshark` puts the plugin where tshark finds it without -X."""
    T.HOST.check()
    env = dict(os.environ, HOME=str(tmp_path), XDG_CONFIG_HOME=str(tmp_path / ".config"))
    done = subprocess.run(["make", "-s", "-C", str(T.REPO), "install-wireshark"], env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    installed = tmp_path / ".local" / "lib" / "wireshark" / "plugins" / "vm110.lua"
    assert installed.read_bytes() == T.PLUGIN.read_bytes()
    plugins = subprocess.run(["tshark", "-G", "plugins"], env=env, capture_output=True, text=True).stdout
    assert any(line.startswith("vm110.lua") and str(installed) in line for line in plugins.splitlines())


@pytest.mark.parametrize("target", ["install-wireshark", "install-profile"])
def test_make_install_needs_no_system_packages(target):
    """`make install-wireshark` ran setup first: apt-get (through sudo) of the test tools (afl++,
    clang, gdb, debootstrap, chromium...) to copy one file; on a machine without apt it failed.
    It needs only the virtual environment with the command."""
    done = subprocess.run(["make", "-n", "-C", str(T.REPO), "-o", ".venv/.installed", target],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "setup-system" not in done.stdout and "apt-get" not in done.stdout, done.stdout
    assert "wireshark install" in done.stdout


@pytest.mark.parametrize("lua", ["lua5.2", "lua5.4"])
def test_plugin_compiles_on_lua_52_and_54(lua):
    """Lua 5.2 rejects 5.3 operators (& | ~ << >> //) at compile time; bit32 is not in Wireshark 4.4."""
    source = T.PLUGIN.read_text()
    assert "bit32." not in source and "module(" not in source
    done = subprocess.run([lua, "-e", f"assert(loadfile({str(T.PLUGIN)!r}))"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_two_pass_reuses_the_crc_and_agrees(ws):
    """`tshark -2` dissects every frame twice; the second pass takes the CRC from the per-frame memo."""
    pcap = ws.dir / "golden.pcap"
    pcap.write_bytes((T.REPO / "tests" / "golden" / "vm110-sample.pcap").read_bytes())
    fields = ["-T", "fields", "-e", "vm110.crc.calculated", "-e", "vm110.crc.status", "-e", "_ws.col.Info"]
    one = ws.run(["-r", str(pcap), *fields]).stdout
    two = ws.run(["-2", "-r", str(pcap), *fields]).stdout
    assert one == two and "0x" in one
