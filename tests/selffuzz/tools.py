"""The tools under test and where they run: `vm110 decode` and `vm110 analyze` (fast engine) once,
`vm110 analyze --engine tshark` and the dissector (`tshark -V`, `tshark -2 -V -z vm110,stat`) on
every tshark of tshark_runner.RUNNERS. A run is one process group, killed whole on a timeout
(pyshark's tshark and the chroot's children included)."""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional, Sequence

import tshark_runner as T

PYTHON_EXITS = frozenset({0, 1, 2})       # ok, a --fail-on rule held, unreadable input or bad arguments
VM110 = [sys.executable, "-m", "vm110"]


@dataclass(frozen=True)
class Site:
    """One tshark installation with a workspace it can see (tshark_runner.Workspace)."""

    ws: T.Workspace
    version: str
    tshark_exits: frozenset[int] = frozenset({0, 2})     # tshark's own: ok, and for damaged files

    def place(self, name: str, data: bytes) -> Path:
        path = self.ws.dir / name
        path.write_bytes(data)
        return path


@dataclass(frozen=True)
class Tool:
    name: str
    site: Site
    kind: str                                              # "python" or "tshark": which oracles apply
    argv: Callable[[Path, Path], list[str]]                # (capture, scratch dir) -> command
    env: dict[str, str] = field(default_factory=dict)
    versioned: bool = True                                 # runs on each tshark (else once, on the host)
    # Runs of one `agrees` group must give the same report: the fast engine (the group's first tool)
    # and the tshark engine on each tshark, with the same options.
    agrees: str = ""

    @property
    def label(self) -> str:
        return f"{self.name} (tshark {self.site.version})" if self.versioned else self.name

    @property
    def exits(self) -> frozenset[int]:
        return self.site.tshark_exits if self.kind == "tshark" else PYTHON_EXITS


@dataclass
class Run:
    tool: Tool
    command: list[str]
    returncode: Optional[int]          # None: killed at the timeout
    stdout: str
    stderr: str
    seconds: float
    scratch: Path
    capture: Path


@contextlib.contextmanager
def sites(base: Path) -> Iterator[list[Site]]:
    """A site per tshark runner; TsharkUnavailable when one cannot be used."""
    with contextlib.ExitStack() as stack:
        out = []
        for runner in T.RUNNERS:
            ws = stack.enter_context(runner.workspace(base / runner.name))
            ws.plugin_file()
            ws.pyshark_tshark_path()
            banner = subprocess.run(runner.command(["-v"]), capture_output=True, text=True).stdout
            out.append(Site(ws, re.search(r"\d+\.\d+\.\d+", banner).group(), _damage_exits(ws)))
        yield out


def _damage_exits(ws: T.Workspace) -> frozenset[int]:
    """0 and the codes tshark itself (no plugin) exits with on a cut file, a record over its size
    limit and a file of no known format: 2 for all three up to 4.4, 14, 14 and 3 on 4.6."""
    good = (T.REPO / "captures" / "normal.pcap").read_bytes()
    samples = {"cut": good[:1000], "huge": good[:32] + (1 << 31).to_bytes(4, "little") + good[36:],
               "junk": b"no capture " * 10}
    codes = {0}
    for name, data in samples.items():
        path = ws.dir / f"damage-{name}.pcap"
        path.write_bytes(data)
        codes.add(subprocess.run(ws.tshark.command(["-r", ws.tshark.inner(path)]), capture_output=True).returncode)
        path.unlink()
    return frozenset(codes)


def tools(all_sites: Sequence[Site], crc_auto: bool = True) -> list[Tool]:
    """Every tool on every site; the version-independent ones on the first (the host). Without
    `crc_auto` the tshark engine dissects once, not once per CRC variant and byte order (8 times on
    a capture with bad CRCs): the bounded run's time goes to more files instead."""
    host = all_sites[0]
    crc = [] if crc_auto else ["--crc", "mpeg2", "--crc-order", "little"]
    out = [Tool("decode", host, "python", lambda f, s: [*VM110, "decode", str(f)], versioned=False),
           Tool("analyze", host, "python", lambda f, s: [*VM110, "analyze", "--json", str(s / "report.json"),
                                                         "--html", str(s / "report.html"), str(f)],
                versioned=False, agrees="engines" if crc_auto else "")]
    if not crc_auto:    # (the fast engine with the tshark engine's options, to compare their reports)
        out.append(Tool("analyze " + " ".join(crc), host, "python",
                        lambda f, s: [*VM110, "analyze", *crc, "--json", str(s / "report.json"), str(f)],
                        versioned=False, agrees="engines"))
    for site in all_sites:
        ws = site.ws
        env = {} if ws.tshark.root is None else {
            "PATH": f"{Path(ws.pyshark_tshark_path()).parent}{os.pathsep}{os.environ.get('PATH', '')}",
            "VM110_DISSECTOR": str(ws.plugin_file()), "TMPDIR": str(ws.dir)}
        out.append(Tool("analyze --engine tshark", site, "python",
                        lambda f, s: [*VM110, "analyze", "--engine", "tshark", *crc, "--json",
                                      str(s / "report.json"), str(f)], env, agrees="engines"))
        out.append(Tool("tshark -V", site, "tshark", _dissect(ws, ["-V"])))
        out.append(Tool("tshark -2 -V -z vm110,stat", site, "tshark", _dissect(ws, ["-2", "-V", "-z", "vm110,stat"])))
    return out


def _dissect(ws: T.Workspace, extra: list[str]) -> Callable[[Path, Path], list[str]]:
    return lambda f, s: ws.tshark.command(["-X", f"lua_script:{ws.plugin()}", "-r", ws.tshark.inner(f), *extra])


def run(tool: Tool, capture: Path, scratch: Path, timeout: float) -> Run:
    """Run one tool on one capture; the whole process group is killed after `timeout` seconds."""
    scratch.mkdir(parents=True, exist_ok=True)
    command = tool.argv(capture, scratch)
    start = time.monotonic()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            env={**os.environ, **tool.env})
    try:
        out, err = proc.communicate(timeout=timeout)
        code: Optional[int] = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = None
    return Run(tool, command, code, out.decode(errors="replace"), err.decode(errors="replace"),
               time.monotonic() - start, scratch, capture)
