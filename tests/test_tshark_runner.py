"""The test matrix's own machinery (tests/tshark_runner.py): every runner is the Wireshark version
it stands for, and the overlay that gives the package's commands a chroot's tshark (on a host whose
own loads no Lua plugin) runs that tshark on the host's files."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

import tshark_runner as T

CAPTURE = T.REPO / "captures" / "normal.pcap"
CHROOTS = [r for r in T.RUNNERS if r.root is not None]


def first_types(done: subprocess.CompletedProcess) -> list[str]:
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_the_matrix_is_4_0_4_4_4_6():
    assert [r.version for r in T.RUNNERS] == ["4.0", "4.4", "4.6"]


@pytest.mark.parametrize("runner", T.RUNNERS, ids=lambda r: r.name)
def test_each_runner_is_the_version_it_stands_for(runner, tmp_path):
    try:
        with runner.workspace(tmp_path):
            first = subprocess.run(runner.command(["--version"]), capture_output=True, text=True,
                                   timeout=120).stdout.split("\n")[0]
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert re.match(rf"TShark \(Wireshark\) {re.escape(runner.version)}\.\d+", first), first


@pytest.mark.skipif(not CHROOTS, reason="the host stands for every version: no chroot")
@pytest.mark.parametrize("runner", CHROOTS, ids=lambda r: r.name)
def test_overlay_runs_the_chroot_tshark_on_host_files(runner, tmp_path):
    try:
        runner.check()
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    capture = tmp_path / CAPTURE.name          # outside the chroot: the overlay sees the host's files
    shutil.copyfile(CAPTURE, capture)
    env = dict(os.environ, PATH=f"{T.overlay_bin(runner)}{os.pathsep}{os.environ.get('PATH', '')}")
    version = subprocess.run(["tshark", "--version"], capture_output=True, text=True, env=env, timeout=120)
    assert version.stdout.startswith(f"TShark (Wireshark) {runner.version}."), version.stdout[:200]
    fields = ["-r", str(capture), "-c", "2", "-T", "fields", "-e", "vm110.type"]
    direct = subprocess.run(["tshark", "-X", f"lua_script:{T.PLUGIN}", *fields], capture_output=True,
                            text=True, env=env, timeout=120)
    assert first_types(direct) == ["VRPI", "VRPO"]
    # The package's own command finds that tshark on the PATH, as the tests of it do.
    dissect = subprocess.run([sys.executable, "-m", "vm110", "dissect", str(capture), "--", *fields[2:]],
                             capture_output=True, text=True, env=env, timeout=120)
    assert first_types(dissect) == ["VRPI", "VRPO"]


def test_the_host_s_tshark_is_found_past_an_overlay(tmp_path, monkeypatch):
    """A pytest-xdist worker inherits the PATH with the overlay in front: it must still judge the
    host's own tshark (and so make the same runners as its parent)."""
    real = shutil.which("tshark")
    monkeypatch.setattr(T, "CACHE", tmp_path)
    overlay = tmp_path / "bookworm-bin"
    overlay.mkdir()
    (overlay / "tshark").write_text("#!/bin/sh\nexit 1\n")
    (overlay / "tshark").chmod(0o755)
    monkeypatch.setenv("PATH", f"{overlay}{os.pathsep}{os.environ.get('PATH', '')}")
    assert shutil.which("tshark") == str(overlay / "tshark")
    assert T.host_tshark() == real


def untimed(pdml: str) -> str:
    return re.sub(r' time="[^"]*"', "", pdml, count=1)


def test_a_shared_run_is_made_once_per_input_and_shows_the_caller_s_paths(tmp_path, monkeypatch):
    """`ws.run(..., shared=True)` (tests/sessionwide.py): the same tshark, arguments and file
    contents run once in a session, whichever workspace asks; a changed file runs again; paths in
    the output are the asking workspace's."""
    runner = T.RUNNERS[-1]
    started = []
    real = subprocess.run
    monkeypatch.setattr(T.subprocess, "run", lambda cmd, **kw: started.append(cmd) or real(cmd, **kw))
    outputs = []
    try:
        for name, capture in (("a", CAPTURE), ("b", CAPTURE), ("c", T.REPO / "captures" / "illegal.pcap")):
            with runner.workspace(tmp_path / name) as ws:
                local = ws.dir / "capture.pcap"
                shutil.copyfile(capture, local)
                shared = ws.run(["-r", str(local), "-T", "pdml", "-c", "1"], shared=True)
                assert f'capture_file="{ws.tshark.inner(local)}"' in shared.stdout
                own = ws.run(["-r", str(local), "-T", "pdml", "-c", "1"])
                assert (shared.returncode, shared.stderr) == (own.returncode, own.stderr)
                assert untimed(shared.stdout) == untimed(own.stdout)    # (PDML says when it was made)
                outputs.append(shared.stdout)
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
    assert len(started) == 5                       # a: shared and own; b: own alone; c: both
    assert outputs[0] != outputs[2]
