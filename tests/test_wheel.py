"""The package as a user without a clone gets it: a wheel built from this tree (offline, with the
project's pinned setuptools), installed into a fresh virtual environment, whose `vm110 wireshark
install --profile` puts the plugin and the profile where tshark looks for this user (HOME in a
temporary folder), and every tshark (4.0 here, 4.4 and 4.6 in their chroots) then lists the plugin,
decodes a bundled capture with it and shows the profile's columns.

Wireshark 4.4 and later load no personal Lua plugin as root, so tshark runs as `nobody` when the
tests run as root (as a user would run it)."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import zipfile
from pathlib import Path
from typing import Iterator

import pytest

import tshark_runner as T

REPO = Path(__file__).resolve().parents[1]
NOBODY = "65534"
SOURCES = ("pyproject.toml", "setup.py", "README.md", "pcap_tools", "dissector", "docs/report.schema.json")
SHIPPED = {                                     # in the wheel -> in the repository
    "vm110/dissector/vm110.lua": "dissector/vm110.lua",
    "vm110/dissector/examples/crane.lua": "dissector/examples/crane.lua",
    "vm110/schema/report.schema.json": "docs/report.schema.json",
    **{f"vm110/dissector/profile/VM-110/{p.name}": f"dissector/profile/VM-110/{p.name}"
       for p in (REPO / "dissector" / "profile" / "VM-110").iterdir()},
}


def run(args: list, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=300, **kwargs)
    assert done.returncode == 0, f"{args} exited {done.returncode}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    return done


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the tree (the build leaves nothing in the repository)."""
    base = tmp_path_factory.mktemp("wheel")
    src = base / "src"
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(REPO / name, src / name)
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
         "-w", base / "dist", src])
    (found,) = (base / "dist").glob("vm110-*.whl")
    return found


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh virtual environment with only the wheel installed (its dependencies come from the
    project's environment, added after the install so that pip sees no other vm110)."""
    env = tmp_path_factory.mktemp("venv")
    run([sys.executable, "-m", "venv", "--without-pip", env])
    python = env / "bin" / "python"
    run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel])
    site = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    Path(site, "_vm110_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return env


def test_the_wheel_carries_the_repository_files(wheel):
    with zipfile.ZipFile(wheel) as whl:
        names = set(whl.namelist())
        assert set(SHIPPED) <= names, set(SHIPPED) - names
        for inside, outside in SHIPPED.items():
            assert whl.read(inside) == (REPO / outside).read_bytes(), inside


def test_the_installed_package_uses_its_own_copies(venv):
    script = "import vm110, vm110.resources as r; print(vm110.__file__); print(r.plugin()); print(r.report_schema())"
    where = run([venv / "bin" / "python", "-c", script])
    for line in where.stdout.splitlines():
        assert Path(line).is_relative_to(venv), where.stdout         # not the source tree's
    schema = run([venv / "bin" / "vm110", "analyze", "--schema"]).stdout
    assert schema == (REPO / "docs" / "report.schema.json").read_text()


@pytest.fixture
def home(ws) -> Iterator[Path]:
    """A home folder that the workspace's tshark sees, readable by `nobody`."""
    folder = Path(tempfile.mkdtemp(prefix="vm110-home-")) if ws.tshark.root is None else ws.dir / "home"
    folder.mkdir(exist_ok=True)
    try:
        yield folder
    finally:
        if ws.tshark.root is None:
            shutil.rmtree(folder)


def _as_user(ws: T.Workspace, home: Path, args: list[str]) -> subprocess.CompletedProcess:
    """tshark of the workspace with HOME and XDG_CONFIG_HOME in `home`, as `nobody` when we are root."""
    inner = ws.tshark.inner(home)
    env = {**os.environ, "HOME": inner, "XDG_CONFIG_HOME": f"{inner}/config"}
    command = ws.tshark.command(args, user=NOBODY if os.geteuid() == 0 else None)
    if os.geteuid() == 0:
        top = home if ws.tshark.root is None else ws.dir
        for folder in [home, *home.parents]:     # our own temporary folders, opened for `nobody`
            folder.chmod(0o755)
            if folder == top:
                break
        if ws.tshark.root is None:
            command = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *command]
    return run(command, env=env)


def test_install_then_tshark_loads_and_decodes(ws, venv, home):
    config = home / "config"
    profile = config / "wireshark" / "profiles" / "VM-110"
    profile.mkdir(parents=True)
    (profile / "recent").write_text("# the user's own file\n")
    env = {**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(config)}
    done = run([venv / "bin" / "vm110", "wireshark", "install", "--profile"], env=env)
    plugin = home / ".local" / "lib" / "wireshark" / "plugins" / "vm110.lua"
    assert f"installed: {plugin}" in done.stdout and "tshark -G folders" in done.stdout
    assert plugin.read_bytes() == (REPO / "dissector" / "vm110.lua").read_bytes()
    assert (profile / "colorfilters").read_bytes() == (REPO / "dissector/profile/VM-110/colorfilters").read_bytes()
    assert (profile / "recent").read_text() == "# the user's own file\n"
    capture = home / "normal.pcap"
    shutil.copyfile(REPO / "captures" / "normal.pcap", capture)

    listed = _as_user(ws, home, ["-G", "plugins"]).stdout
    row = f"vm110.lua\t0.1.0\tlua script\t{ws.tshark.inner(plugin)}"
    assert row in listed.lower().splitlines(), listed                   # 4.6 says "Lua script"
    # Decoded by the plugin, with the profile's Type and Serial columns before the Info column.
    first = _as_user(ws, home, ["-C", "VM-110", "-r", ws.tshark.inner(capture), "-c", "1"]).stdout
    assert re.search(r"VM110 108 VRPI 65400 +VRPI Armed RU 0x0C07 Enabled bat 90%, serial 65400$", first.strip()), first

def test_check_reports_an_installed_plugin_and_a_broken_one(venv, tmp_path):
    """`vm110 wireshark check` as this user (root is fine for 4.0): ok after install; a plugin with
    a Lua error is reported with the error, exit 2."""
    env = {**os.environ, "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config")}
    vm110 = venv / "bin" / "vm110"
    run([vm110, "wireshark", "install"], env=env)
    done = run([vm110, "wireshark", "check"], env=env)
    assert "registered: yes, protocol vm110" in done.stdout and "decode: ok" in done.stdout
    assert "Lua errors: none" in done.stdout and "the same as this package's" in done.stdout
    plugin = tmp_path / ".local" / "lib" / "wireshark" / "plugins" / "vm110.lua"
    plugin.write_text(plugin.read_text() + "\nerror('broken on purpose')\n")
    broken = subprocess.run([vm110, "wireshark", "check"], capture_output=True, text=True, env=env, timeout=300)
    assert broken.returncode == 2
    assert "broken on purpose" in broken.stdout and f"plugin: {plugin} (not loaded; differs" in broken.stdout
    assert f"vm110 wireshark check: tshark did not load {plugin}" in broken.stderr.splitlines()
    assert "vm110 wireshark check: Lua errors in vm110.lua" in broken.stderr.splitlines()
