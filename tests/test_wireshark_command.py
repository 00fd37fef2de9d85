"""`vm110 wireshark path/install`: the folders come from `tshark -G folders` (on every tshark), the
fallback without tshark is Wireshark's documented default on Linux, macOS and Windows (and agrees
with what tshark says here), and installing never harms the user's files. The wheel test
(test_wheel.py) installs from a built wheel and has tshark load the result; `check` is tested there."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path, PurePosixPath, PureWindowsPath

import pytest

from vm110 import cli
from vm110.wireshark_folders import CONFIG_KEY, PLUGINS_KEY, default, find_tshark, parse

REPO = Path(__file__).resolve().parents[1]
PLUGIN = (REPO / "dissector" / "vm110.lua").read_bytes()

# `tshark -G folders` of Wireshark 4.2 on Windows, as its documentation shows the layout.
WINDOWS_FOLDERS = (
    "Temp:                   \tC:\\Users\\ann\\AppData\\Local\\Temp\\\r\n"
    "Personal configuration: \tC:\\Users\\ann\\AppData\\Roaming\\Wireshark\r\n"
    "Global configuration:   \tC:\\Program Files\\Wireshark\r\n"
    "Personal Plugins:       \tC:\\Users\\ann\\AppData\\Roaming\\Wireshark\\plugins\\4.2\r\n"
    "Personal Lua Plugins:   \tC:\\Users\\ann\\AppData\\Roaming\\Wireshark\\plugins\r\n"
    "MaxMind database path:  \tC:\\a\r\n"
    "MaxMind database path:  \tC:\\b\r\n")


def test_parse_reads_posix_and_windows_paths():
    windows = parse(WINDOWS_FOLDERS)
    assert windows[PLUGINS_KEY] == "C:\\Users\\ann\\AppData\\Roaming\\Wireshark\\plugins"
    assert windows[CONFIG_KEY] == "C:\\Users\\ann\\AppData\\Roaming\\Wireshark"
    assert windows["MaxMind database path"] == "C:\\a"                      # the first of a repeated name
    posix = parse("Personal configuration:\t/home/ann/.config/wireshark\nPersonal Lua Plugins:\t/home/ann/.local/lib/"
                  "wireshark/plugins\nnonsense without a colon\nEmpty:\t\n")
    assert posix == {CONFIG_KEY: "/home/ann/.config/wireshark", PLUGINS_KEY: "/home/ann/.local/lib/wireshark/plugins"}


@pytest.mark.parametrize("system, env, plugins, config", [
    ("Linux", {}, "/home/ann/.local/lib/wireshark/plugins", "/home/ann/.config/wireshark"),
    ("Linux", {"XDG_CONFIG_HOME": "/xdg"}, "/home/ann/.local/lib/wireshark/plugins", "/xdg/wireshark"),
    ("Darwin", {}, "/home/ann/.local/lib/wireshark/plugins", "/home/ann/.config/wireshark"),
    ("Linux", {"WIRESHARK_CONFIG_DIR": "/etc/ws"}, "/home/ann/.local/lib/wireshark/plugins", "/etc/ws"),
    ("Windows", {"APPDATA": "C:\\Users\\ann\\AppData\\Roaming"},
     "C:\\Users\\ann\\AppData\\Roaming\\Wireshark\\plugins", "C:\\Users\\ann\\AppData\\Roaming\\Wireshark"),
    ("Windows", {},
     "C:\\Users\\ann\\AppData\\Roaming\\Wireshark\\plugins", "C:\\Users\\ann\\AppData\\Roaming\\Wireshark"),
    ("Windows", {"APPDATA": "C:\\R", "WIRESHARK_CONFIG_DIR": "D:\\ws"}, "D:\\ws\\plugins", "D:\\ws"),
])
def test_documented_defaults_per_system(system, env, plugins, config):
    home = "C:\\Users\\ann" if system == "Windows" else "/home/ann"
    found = default(system, env, home)
    flavour = PureWindowsPath if system == "Windows" else PurePosixPath
    assert (found.plugins, found.config) == (flavour(plugins), flavour(config))
    assert found.profiles == flavour(config) / "profiles"
    assert found.source == f"the default for {system}"


def test_a_legacy_dot_wireshark_folder_is_kept(tmp_path):
    (tmp_path / ".wireshark").mkdir()
    assert default("Linux", {}, str(tmp_path)).config == PurePosixPath(tmp_path / ".wireshark")
    (tmp_path / ".config" / "wireshark").mkdir(parents=True)          # the XDG one wins once it exists
    assert default("Linux", {}, str(tmp_path)).config == PurePosixPath(tmp_path / ".config" / "wireshark")


def test_the_linux_default_is_what_every_tshark_reports(ws):
    """The fallback agrees with tshark 4.0, 4.4 and 4.6 themselves, with and without XDG_CONFIG_HOME."""
    home = ws.dir / "ann"
    for extra in ({}, {"XDG_CONFIG_HOME": ws.tshark.inner(home / "xdg")}):
        env = {k: v for k, v in os.environ.items() if k not in ("XDG_CONFIG_HOME", "WIRESHARK_CONFIG_DIR")}
        env.update(HOME=ws.tshark.inner(home), **extra)
        said = parse(subprocess.run(ws.tshark.command(["-G", "folders"]), capture_output=True, text=True, env=env,
                                    timeout=120).stdout)
        ours = default("Linux", extra, ws.tshark.inner(home))
        assert (said[PLUGINS_KEY], said[CONFIG_KEY]) == (str(ours.plugins), str(ours.config)), extra


def test_find_tshark_knows_where_installers_put_it(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))                               # no tshark on the PATH
    assert find_tshark("/opt/x/tshark") == "/opt/x/tshark"
    assert find_tshark(system="Linux") is None
    exe = tmp_path / "Wireshark" / "tshark.exe"
    exe.parent.mkdir()
    exe.write_text("")
    assert find_tshark(system="Windows", env={"ProgramFiles": str(tmp_path)}) == str(exe)
    assert find_tshark(system="Windows", env={}) is None


@pytest.fixture
def user(tmp_path, monkeypatch) -> Path:
    """A user whose home is tmp_path/home, with the host's tshark on the PATH."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home / "cfg"))
    return home


def test_path_names_the_folders_and_where_they_come_from(user, capsys):
    assert cli.main(["wireshark", "path"]) == 0
    said = capsys.readouterr()
    out = said.out.splitlines()
    assert out[:2] == [f"plugins: {user}/.local/lib/wireshark/plugins",
                       f"profile: {user}/cfg/wireshark/profiles/VM-110"]
    assert out[2].endswith("tshark -G folders)")
    # (XDG_CONFIG_HOME moves the profile, not the plugin: tshark's own word, said)
    assert said.err == f"note: the plugin folder follows HOME, not XDG_CONFIG_HOME={user}/cfg (only the profile does)\n"


def test_without_tshark_the_default_is_used_and_said(user, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert cli.main(["wireshark", "path"]) == 0
    assert capsys.readouterr().out.splitlines()[2] == "(from the default for Linux (tshark not found))"
    # A tshark the user named that cannot say where its folders are is an error, not a default:
    # install would put the plugin where that Wireshark may never look.
    for action in ("path", "install", "check"):
        for named in (str(tmp_path / "nope"), ""):
            assert cli.main(["wireshark", action, "--tshark", named]) == 2
            assert f"'{named}'" in capsys.readouterr().err
    assert not (user / ".local").exists()
    assert cli.main(["wireshark", "check"]) == 2
    assert "tshark not found" in capsys.readouterr().err


def test_install_updates_its_files_and_leaves_the_users(user, capsys):
    plugins = user / ".local" / "lib" / "wireshark" / "plugins"
    profile = user / "cfg" / "wireshark" / "profiles" / "VM-110"
    profile.mkdir(parents=True)
    (profile / "recent").write_text("mine")
    (profile / "colorfilters").write_text("an older version")
    plugins.mkdir(parents=True)
    (plugins / "other.lua").write_text("-- another plugin")
    assert cli.main(["wireshark", "install", "--profile", "--examples"]) == 0
    out = capsys.readouterr().out
    assert f"installed: {plugins / 'vm110.lua'}" in out and f"updated: {profile / 'colorfilters'}" in out
    assert f"installed: {plugins / 'crane.lua'}" in out
    assert (plugins / "vm110.lua").read_bytes() == PLUGIN
    for name in ("colorfilters", "dfilter_buttons", "preferences"):
        assert (profile / name).read_bytes() == (REPO / "dissector" / "profile" / "VM-110" / name).read_bytes()
    assert (profile / "recent").read_text() == "mine" and (plugins / "other.lua").read_text() == "-- another plugin"
    assert sorted(p.name for p in plugins.iterdir()) == ["crane.lua", "other.lua", "vm110.lua"]   # no temporaries
    assert cli.main(["wireshark", "install"]) == 0
    assert f"unchanged: {plugins / 'vm110.lua'}" in capsys.readouterr().out


def test_check_names_the_version_when_another_plugin_prints(user, capsys):
    """Another Lua plugin that prints while loading (on tshark's standard output) does not take the
    place of the version line."""
    plugins = user / ".local" / "lib" / "wireshark" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "chatty.lua").write_text('print("hello from chatty")')
    assert cli.main(["wireshark", "install"]) == 0
    capsys.readouterr()
    assert cli.main(["wireshark", "check"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("tshark: ") and ": TShark (Wireshark) " in first, first


def test_check_says_that_a_plugin_gives_no_version(user, capsys):
    """A vm110.lua that sets no version in its plugin info (an old copy, another project's): check
    printed `(version ; differs ...)` (trial-readme). It says `no version`, exit 2 (no protocol)."""
    plugins = user / ".local" / "lib" / "wireshark" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "vm110.lua").write_text("-- an old copy")
    assert cli.main(["wireshark", "check"]) == 2
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("plugin: "))
    assert line.startswith(f"plugin: {plugins / 'vm110.lua'} (no version; differs from this package's"), line


def test_install_leaves_a_linked_plugin_alone(user, tmp_path, capsys):
    """A developer's link to a checkout is not written through: nothing is installed, exit 2."""
    plugins = user / ".local" / "lib" / "wireshark" / "plugins"
    plugins.mkdir(parents=True)
    checkout = tmp_path / "checkout.lua"
    checkout.write_text("-- my working copy")
    (plugins / "vm110.lua").symlink_to(checkout)
    assert cli.main(["wireshark", "install", "--profile"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("vm110 wireshark: ") and "is a symbolic link" in err and err.count("\n") == 1
    assert checkout.read_text() == "-- my working copy" and not (user / "cfg").exists()


def test_install_into_a_folder_that_is_a_file_is_one_line(user, capsys):
    (user / ".local" / "lib" / "wireshark").mkdir(parents=True)
    (user / ".local" / "lib" / "wireshark" / "plugins").write_text("not a folder")
    assert cli.main(["wireshark", "install"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vm110 wireshark: cannot write {user}/.local/lib/wireshark/plugins/vm110.lua: ")
    assert err.count("\n") == 1


def test_check_reads_the_protocol_list_of_every_version():
    """`tshark -G protocols`: name, short name, filter name; 4.6 adds flag columns after them."""
    from vm110.commands.wireshark import registers_vm110
    assert registers_vm110("VM-110 EG-Link\tVM110\tvm110")                              # 4.0, 4.4
    assert registers_vm110("VM-110 EG-Link\tVM110\tvm110\tT\tT\tT")                    # 4.6
    assert not registers_vm110("VM-110 EG-Link stream analysis\tVM110_END\tvm110_end\tT\tT\tT")
    assert not registers_vm110("vm110")
