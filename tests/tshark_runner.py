"""Runs dissector/vm110.lua through real tshark, once per Wireshark version the dissector supports:
4.0 (Lua 5.2, Debian 12), 4.4 (Lua 5.4, Debian 13) and 4.6 (Lua 5.4, Debian testing). The host's
tshark stands for its own version when it loads a Lua plugin for this user (4.4 and later load none
when run as root); every other version runs in a cached Debian chroot that scripts/tshark-chroot.sh
builds (`make tsharks`: `python tests/tshark_runner.py --setup` builds the ones this host needs).

Also writes EG-Link payloads into a pcap (Ethernet/IPv4/UDP, padded to 60 bytes like a real wire) and
reads tshark's PDML back into plain Python objects, with the field an expert is attached to.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import shlex
import shutil
import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Optional, Sequence

from lxml import etree

import sessionwide
from vm110 import constants as C

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "dissector" / "vm110.lua"
CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "vm110"
LUA_ERROR = "Lua Error"
BU_ADDR, CONTROLLER_ADDR = "10.0.0.10", "10.0.0.20"
GROUP_ADDR = C.MULTICAST_GROUP


class TsharkUnavailable(RuntimeError):
    """The tshark of a runner cannot be used on this machine."""


@dataclass(frozen=True)
class Tshark:
    """One tshark installation: the host's, or the one in a Debian chroot (`root`)."""

    root: Optional[Path] = None
    version: str = ""              # major.minor; the host's: as `tshark --version` says
    suite: str = ""                # the chroot's Debian suite
    script: str = ""               # the debootstrap script for it, when debootstrap may not know the suite

    @property
    def name(self) -> str:
        """"host", or the chroot's suite (the tests' ids)."""
        return self.suite if self.root is not None else "host"

    def check(self) -> None:
        if self.root is None:
            found = facts(shutil.which("tshark"))
            if found.version is None:
                raise TsharkUnavailable("tshark is not installed: run `make setup`")
            if not found.loads_lua:
                raise TsharkUnavailable(f"the host's tshark {found.version} loads no Lua plugin for this user "
                                        "(4.4 and later skip them as root)")
            return
        if not (self.root / ".vm110-ready").exists():
            raise TsharkUnavailable(f"no tshark {self.version} chroot at {self.root}: run `make tsharks` "
                                    "(needs root)")
        if os.geteuid() != 0:
            raise TsharkUnavailable(f"running tshark inside the {self.version} chroot needs root")

    def setup(self) -> None:
        """Build this runner's chroot (cached: at once when it is there)."""
        if self.root is None:
            return
        env = dict(os.environ, **{f"VM110_{self.suite.upper()}_ROOT": str(self.root)})
        subprocess.run(["bash", str(REPO / "scripts" / "tshark-chroot.sh"), self.suite, self.suite,
                        *([self.script] if self.script else [])], env=env, check=True, stdout=subprocess.DEVNULL)

    @contextlib.contextmanager
    def workspace(self, base: Path) -> Iterator["Workspace"]:
        """A directory that tshark sees too (inside the chroot for the chroot's tshark)."""
        self.check()
        if self.root is None:
            base.mkdir(parents=True, exist_ok=True)
            yield Workspace(self, base)
            return
        path = Path(tempfile.mkdtemp(prefix="vm110-", dir=self.root / "tmp"))
        try:
            yield Workspace(self, path)
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def inner(self, path: Path) -> str:
        """`path` as tshark sees it."""
        if self.root is None:
            return str(path)
        return "/" + str(Path(path).resolve().relative_to(self.root.resolve()))

    def command(self, args: Sequence[str], user: Optional[str] = None) -> list[str]:
        """tshark with `args`; in a chroot, as `user` when given (the host's tshark: the caller's)."""
        if self.root is None:
            return ["tshark", *args]
        # In a mount namespace of its own with /proc mounted in the chroot, as on a real system:
        # the dissector reads tshark's command line from /proc/self/cmdline.
        spec = [f"--userspec={user}:{user}"] if user else []
        return ["unshare", "--mount", "--fork", "sh", "-c", 'mount -t proc proc "$0/proc" && exec chroot "$@"',
                str(self.root), *spec, str(self.root), "tshark", *args]


@dataclass(frozen=True)
class Facts:
    """What a tshark executable is: its version (major.minor) and whether it loads a Lua script
    given with -X lua_script for this user."""

    version: Optional[str]
    loads_lua: bool


_facts: dict[str, Facts] = {}


def facts(tshark: Optional[str]) -> Facts:
    """The facts of the executable `tshark` (a path; None: no tshark), asked once."""
    if tshark is None:
        return Facts(None, False)
    if tshark not in _facts:
        version, loads = None, False
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            first = subprocess.run([tshark, "--version"], capture_output=True, text=True,
                                   timeout=120).stdout.split("\n")[0]
            match = re.search(r"\b(\d+)\.(\d+)\.\d+", first)
            version = match and f"{match[1]}.{match[2]}"
            with tempfile.TemporaryDirectory() as tmp:
                probe = Path(tmp) / "probe.lua"
                probe.write_text('Proto("vm110probe", "probe")\n')
                out = subprocess.run([tshark, "-G", "protocols", "-X", f"lua_script:{probe}"],
                                     capture_output=True, text=True, timeout=120).stdout
                loads = any(line.split("\t")[2:3] == ["vm110probe"] for line in out.splitlines())
        _facts[tshark] = Facts(version, loads)
    return _facts[tshark]


def host_tshark() -> Optional[str]:
    """The host's own tshark: the PATH's, past any overlay_bin() folder (below) a parent put there."""
    path = [d for d in os.environ.get("PATH", "").split(os.pathsep)
            if not (Path(d).parent == CACHE and d.endswith("-bin"))]
    return shutil.which("tshark", path=os.pathsep.join(path))


# The versions the dissector is tested on: (version, Debian suite, debootstrap script).
VERSIONS = (("4.0", "bookworm", ""), ("4.4", "trixie", ""),
            ("4.6", "forky", "/usr/share/debootstrap/scripts/sid"))   # (debootstrap may not know forky yet)


def _runner(version: str, suite: str, script: str) -> Tshark:
    host = facts(host_tshark())
    if host.version == version and host.loads_lua:
        return Tshark(None, version)
    root = Path(os.environ.get(f"VM110_{suite.upper()}_ROOT") or CACHE / suite)
    return Tshark(root, version, suite, script)


RUNNERS = tuple(_runner(*v) for v in VERSIONS)


def overlay_bin(runner: Tshark) -> Path:
    """A folder with a `tshark` that runs the runner's chroot tshark on this machine's own files:
    the chroot's /usr and /etc (4.0's global init.lua is /etc/wireshark's) mounted over the host's
    in a mount namespace of its own (needs root)."""
    assert runner.root is not None
    folder = CACHE / f"{runner.suite}-bin"
    script = folder / "tshark"
    text = (f"#!/bin/sh\n# vm110 tests: tshark {runner.version} of the {runner.suite} chroot, on this machine's files\n"
            "exec unshare --mount sh -c 'mount --bind \"$0/usr\" /usr && mount --bind \"$0/etc\" /etc "
            "&& exec /usr/bin/tshark \"$@\"' "
            f"{shlex.quote(str(runner.root))} \"$@\"\n")
    if not script.exists() or script.read_text() != text:
        folder.mkdir(parents=True, exist_ok=True)
        fresh = folder / f".tshark.{os.getpid()}"
        fresh.write_text(text)
        fresh.chmod(0o755)
        os.replace(fresh, script)
    return folder


# The tshark that the package's own commands find on the PATH (vm110 dissect, analyze --engine
# tshark, wireshark check) is the host's. Where that one loads no Lua plugin (run as root, 4.4 and
# later), it is the first runner's through overlay_bin(), so that those tests run here too.
_first = RUNNERS[0]
if (not facts(host_tshark()).loads_lua and os.geteuid() == 0 and _first.root is not None
        and (_first.root / ".vm110-ready").exists()):
    _overlay = str(overlay_bin(_first))
    if shutil.which("tshark") != os.path.join(_overlay, "tshark"):
        os.environ["PATH"] = f"{_overlay}{os.pathsep}{os.environ.get('PATH', '')}"
HOST = Tshark(None, facts(shutil.which("tshark")).version or "")


@dataclass
class Workspace:
    tshark: Tshark
    dir: Path

    def plugin_file(self) -> Path:
        """The plugin file on the host (a copy inside the chroot for the chroot's tshark)."""
        if self.tshark.root is None:
            return PLUGIN
        target = self.dir / PLUGIN.name
        if not target.exists():
            shutil.copyfile(PLUGIN, target)
        return target

    def plugin(self) -> str:
        """The plugin as tshark sees it."""
        return self.tshark.inner(self.plugin_file())

    def run(self, args: Sequence[str], plugin: bool = True, check: bool = True,
            timeout: float = 600, shared: bool = False) -> subprocess.CompletedProcess:
        """Run tshark (with the plugin) and return its output; paths in `args` are host paths.
        `shared`: the output of the same run (same tshark, arguments, files and personal folders)
        made in this session by any test of any worker, for the runs several tests read alike."""
        inner_args = [self._translate(a) for a in args]
        if plugin:
            inner_args = ["-X", f"lua_script:{self.plugin()}"] + inner_args
        command = self.tshark.command(inner_args)
        if shared:
            proc = self._shared(command, timeout)
        else:
            proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout, errors="replace")
        if check and proc.returncode != 0:
            raise AssertionError(f"tshark ({self.tshark.name}) exited {proc.returncode}: {proc.stderr[-2000:]}")
        return proc

    def _shared(self, command: list[str], timeout: float) -> subprocess.CompletedProcess:
        here = self.tshark.inner(self.dir)
        key = [self.tshark.name, self.tshark.version, shutil.which(command[0]) or command[0],
               *(os.environ.get(v, "") for v in ("HOME", "XDG_CONFIG_HOME", "WIRESHARK_CONFIG_DIR"))]
        for arg in command:
            key.append(arg.replace(here, "<workspace>"))
            for candidate in (arg, arg.split(":", 1)[-1]):   # (a file, or lua_script:file)
                host = Path(candidate.replace(here, str(self.dir), 1))
                with contextlib.suppress(OSError, ValueError):
                    if host.is_file():
                        key.append(hashlib.sha256(host.read_bytes()).hexdigest())

        def run() -> bytes:
            proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout, errors="replace")
            return json.dumps([proc.returncode, proc.stdout.replace(here, "<workspace>"),
                               proc.stderr.replace(here, "<workspace>")]).encode()

        code, out, err = json.loads(sessionwide.value(json.dumps(key), run))
        return subprocess.CompletedProcess(command, code, out.replace("<workspace>", here),
                                           err.replace("<workspace>", here))

    def _translate(self, arg: str) -> str:
        if self.tshark.root is None:
            return arg
        return arg.replace(str(self.dir), self.tshark.inner(self.dir))

    def pyshark_tshark_path(self) -> str:
        """An executable named `tshark` for pyshark's `tshark_path`: the chroot's, behind a wrapper."""
        if self.tshark.root is None:
            return shutil.which("tshark") or "tshark"
        wrapper_dir = self.dir / "bin"
        wrapper_dir.mkdir(exist_ok=True)
        wrapper = wrapper_dir / "tshark"
        root = str(self.tshark.root.resolve())
        wrapper.write_text(
            "#!/bin/bash\n"
            "# pyshark passes host paths: strip the chroot prefix from every argument.\n"
            f"root='{root}'\n"
            'exec chroot "$root" tshark "${@//"$root"/}"\n')
        wrapper.chmod(0o755)
        return str(wrapper)


# --- Captures ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Datagram:
    payload: bytes
    sport: Optional[int] = None   # default: by the packet ID's direction (input 5825, output 5827)
    dport: Optional[int] = None
    trailer: bytes = b""          # after the IP packet, inside the Ethernet frame


def ip_checksum(header: bytes) -> int:
    total = sum(struct.unpack(f"!{len(header) // 2}H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def _addr(text: str) -> bytes:
    return bytes(int(x) for x in text.split("."))


def default_port(payload: bytes) -> int:
    return C.OUTPUT_PORT if payload[3:4] == b"O" else C.INPUT_PORT


def frame(d: Datagram) -> bytes:
    """Ethernet + IPv4 + UDP (no UDP checksum) around the payload, padded to the 60-byte minimum
    (after the trailer, if any)."""
    port = default_port(d.payload)
    sport, dport = d.sport or port, d.dport or port
    src = CONTROLLER_ADDR if d.payload[3:4] == b"O" else BU_ADDR
    udp = struct.pack("!HHHH", sport, dport, 8 + len(d.payload), 0) + d.payload
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, C.MULTICAST_TTL, 17, 0,
                     _addr(src), _addr(GROUP_ADDR))
    ip = ip[:10] + struct.pack("!H", ip_checksum(ip)) + ip[12:]
    eth = bytes.fromhex("01005e7f2a14 02fc00000001 0800")   # destination, source, IPv4
    return (eth + ip + udp + d.trailer).ljust(60, b"\0")


def write_pcap(path: Path, datagrams: Iterable[Datagram | bytes], times_us: Optional[Sequence[int]] = None) -> int:
    """Write one frame per datagram, 1 ms apart or at `times_us` (µs from the start); returns the
    number of frames."""
    count = 0
    with open(path, "wb") as out:
        out.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1))
        for count, d in enumerate(datagrams, start=1):
            data = frame(d if isinstance(d, Datagram) else Datagram(d))
            offset = count * 1000 if times_us is None else times_us[count - 1]
            seconds, micros = divmod(1_700_000_000_000_000 + offset, 1_000_000)
            out.write(struct.pack("<IIII", seconds, micros, len(data), len(data)) + data)
    return count


# --- PDML ----------------------------------------------------------------------------------------
@dataclass
class Item:
    name: str
    show: str
    showname: str
    pos: int
    size: int
    parent: str            # name of the enclosing field ("" for the vm110 protocol item itself)


@dataclass
class Expert:
    abbrev: str
    message: str
    parent: str            # name of the field the expert is attached to


@dataclass
class Frame:
    number: int
    vm110: bool = False
    pos: int = 0            # where the vm110 protocol starts in the frame
    size: int = 0
    items: list[Item] = field(default_factory=list)
    experts: list[Expert] = field(default_factory=list)
    text: str = ""          # the protocol item's text

    def first(self, name: str) -> Optional[Item]:
        return next((i for i in self.items if i.name == name), None)


_PLAIN_PARENTS = {"_ws.lua.text", None}


def _parent_name(element: etree._Element) -> str:
    parent = element.getparent()
    while parent is not None and parent.tag == "field" and parent.get("name") in _PLAIN_PARENTS:
        parent = parent.getparent()
    if parent is None or parent.tag != "field":
        return ""
    return parent.get("name") or ""


def parse_pdml(text: str) -> list[Frame]:
    frames = []
    root = etree.fromstring(text.encode(), parser=etree.XMLParser(huge_tree=True))
    for number, packet in enumerate(root.iter("packet"), start=1):
        frame_ = Frame(number)
        proto = packet.find("proto[@name='vm110']")
        if proto is not None:
            frame_.vm110 = True
            frame_.pos, frame_.size = int(proto.get("pos")), int(proto.get("size"))
            frame_.text = proto.get("showname") or ""
            for el in proto.iter("field"):
                name = el.get("name") or ""
                if name == "_ws.expert":
                    abbrev = next((c.get("name") for c in el if (c.get("name") or "").startswith("vm110.expert.")), "")
                    message = next((c.get("show") for c in el if c.get("name") == "_ws.expert.message"), "")
                    frame_.experts.append(Expert(abbrev, message, _parent_name(el)))
                elif name.startswith("vm110.") and not name.startswith("vm110.expert."):
                    frame_.items.append(Item(name, el.get("show") or "", el.get("showname") or "",
                                             int(el.get("pos") or 0), int(el.get("size") or 0), _parent_name(el)))
        frames.append(frame_)
    return frames


def dissect_pdml(ws: Workspace, pcap: Path, prefs: Optional[dict[str, str]] = None,
                 extra: Sequence[str] = (), shared: bool = False) -> tuple[list[Frame], str]:
    """One tshark run over the capture: the frames, and stdout+stderr for error checks."""
    args = ["-r", str(pcap), "-T", "pdml", *pref_args(prefs), *extra]
    proc = ws.run(args, shared=shared)
    return parse_pdml(proc.stdout), proc.stdout + proc.stderr


# Per-packet decoding tests run with the stream analysis (issue 4) off: their captures are loose
# packets whose serials, intervals and command IDs mean nothing together. Analysis tests turn it on.
DECODE_ONLY = {"vm110.analysis": "FALSE"}


def glossary(ws: "Workspace", shared: bool = True) -> list[list[str]]:
    """The vm110 rows of `tshark -G fields` with the plugin loaded (-G must come first, so no
    ws.run prefix): its fields, experts included, and its protocol."""
    proc = ws.run(["-G", "fields", "-X", f"lua_script:{ws.plugin()}"], plugin=False, shared=shared)
    assert LUA_ERROR not in proc.stderr   # (stdout lists the field "Lua Error", _ws.lua.error)
    rows = [line.split("\t") for line in proc.stdout.splitlines()]
    return [r for r in rows if (r[0] == "F" and r[2].startswith("vm110")) or (r[0] == "P" and r[2] == "vm110")]


# A Lua tap of a user's own that reads one field with Field.new: how many values it saw.
_FIELD_COUNTER = """
local field = Field.new("%s")
local seen = 0
local tap = Listener.new("frame", "vm110")
function tap.packet() seen = seen + #{ field() } end
function tap.draw() io.stderr:write("values seen: ", seen, "\\n") end
"""


def field_counter(ws: "Workspace", field: str) -> list[str]:
    """tshark options that load a Lua tap counting the values of `field` (read with field_count)."""
    script = ws.dir / "field-counter.lua"
    script.write_text(_FIELD_COUNTER % field)
    return ["-X", f"lua_script:{ws.tshark.inner(script)}"]


def field_count(stderr: str) -> int:
    """What field_counter's tap said on tshark's standard error."""
    seen = [line for line in stderr.splitlines() if line.startswith("values seen: ")]
    assert len(seen) == 1, stderr[-2000:]
    return int(seen[0].rsplit(" ", 1)[1])


def pref_args(prefs: Optional[dict[str, str]]) -> list[str]:
    """`-o` arguments; the stream analysis is off unless `prefs` sets vm110.analysis."""
    merged = {**DECODE_ONLY, **(prefs or {})}
    return [a for key, value in merged.items() for a in ("-o", f"{key}:{value}")]


# --- From tshark's items to the vectors' canonical form -----------------------------------------
BYTE_FIELDS = frozenset({"vrpi_spare", "command_data", "periodic_data"})
STRING_FIELDS = frozenset({"type", "direction"})
NAMED_FIELDS = frozenset({"crc.status"})         # compared by display name
BOOL_FIELDS = frozenset({"es_relays_open"})
NOT_CANONICAL = frozenset({"undecoded"})          # tree filler for bytes no field owns
# Stream analysis (issue 4): not part of a single packet's decoding, checked by test_dissector_analysis.
ANALYSIS_PREFIXES = ("analysis.", "burst.", "reassembled")
ANALYSIS_EXPERTS = frozenset({
    "serial_gap", "serial_duplicate", "serial_out_of_order", "watchdog_vrpi", "watchdog_vrpo", "vrpo_interval", "time_backwards",
    "retransmission", "resend_interval", "spurious_retransmission", "ack_without_command", "duplicate_ack",
    "ack_late", "never_acked", "burst_missing", "burst_incomplete",
    "restart", "silent_until_end", "command_interrupted"})
_FIELD_IN_MESSAGE = re.compile(r"^vm110\.([a-z0-9_]+)")
PROBLEM_CODES = frozenset(p.value for p in C.Problem)
FIELD_WARNING_CODES = frozenset(w.value for w in C.WarningCode) - {C.WarningCode.EXTRA_PAYLOAD.value}


def showname_value(item: Item) -> str:
    return item.showname.split(": ", 1)[1] if ": " in item.showname else item.showname


def item_value(name: str, item: Item):
    if name in BYTE_FIELDS:
        return item.show.replace(":", "")
    if name in STRING_FIELDS:
        return item.show
    if name in NAMED_FIELDS:
        return re.sub(r" \(\d+\)$", "", showname_value(item))
    if name in BOOL_FIELDS:
        return item.show in ("1", "True")
    return int(item.show, 0)


def canonical_fields(frame_: Frame) -> dict:
    """{canonical name: value} of every vm110 field in the frame (first occurrence)."""
    out = {}
    for item in frame_.items:
        name = item.name[len("vm110."):]
        if name not in NOT_CANONICAL and not name.startswith(ANALYSIS_PREFIXES) and name not in out:
            out[name] = item_value(name, item)
    return out


def problems_and_warnings(frame_: Frame) -> tuple[list[str], list[str], list[str]]:
    """(problems, warnings, unattributed) from the experts: warnings as `code` or `code:field`."""
    problems, warnings, odd = [], [], []
    for e in frame_.experts:
        code = e.abbrev[len("vm110.expert."):]
        if code in PROBLEM_CODES:
            problems.append(code)
        elif code in FIELD_WARNING_CODES:
            match = _FIELD_IN_MESSAGE.match(e.message)
            if match is None or e.parent != f"vm110.{match.group(1)}":
                odd.append(f"{code}: {e.message!r} on {e.parent!r}")
            warnings.append(f"{code}:{match.group(1) if match else '?'}")
        elif code == C.WarningCode.EXTRA_PAYLOAD.value:
            warnings.append(code)
        elif code != "es_relays_open" and code not in ANALYSIS_EXPERTS:
            odd.append(f"unexpected expert {e.abbrev}: {e.message!r}")
    return sorted(problems), sorted(warnings), odd


def uncovered_bytes(frame_: Frame) -> list[int]:
    """Offsets of the vm110 payload that no vm110 field covers (the tree must cover them all)."""
    covered = set()
    for item in frame_.items:
        covered.update(range(item.pos, item.pos + item.size))
    return [p - frame_.pos for p in range(frame_.pos, frame_.pos + frame_.size) if p not in covered]


def python_expectation(decoded: dict) -> dict:
    """`vm110.decode()` output in the canonical form of `canonical_fields`."""
    return {k: (v.hex() if isinstance(v, bytes) else v)
            for k, v in decoded.items() if k not in ("problems", "warnings")}


def main() -> int:
    parser = argparse.ArgumentParser(description="The tshark versions the dissector tests run on.")
    parser.add_argument("--setup", action="store_true", help="build the chroots this host needs")
    args = parser.parse_args()
    for runner in RUNNERS:
        where = "the host's tshark" if runner.root is None else f"Debian {runner.suite} chroot {runner.root}"
        print(f"tshark {runner.version}: {where}", file=sys.stderr)
        if args.setup:
            try:
                runner.setup()
            except subprocess.CalledProcessError:
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
