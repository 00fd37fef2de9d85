"""Install the Wireshark plugin (and the VM-110 profile) for this user, show where, check it loads.

`vm110 wireshark install [--profile] [--examples]` copies dissector/vm110.lua (as shipped in this
package) into the personal Lua plugins folder that `tshark -G folders` reports (the system's
default when there is no tshark, and it says so), and with --profile the VM-110 configuration
profile into the personal configuration folder's profiles/VM-110. Files are replaced atomically;
nothing else in those folders is touched. `vm110 wireshark path` prints the folders.
`vm110 wireshark check` runs tshark with the installed plugin: its version, whether vm110 is
registered and decodes sample packets, and any Lua error; exit 2 when it is broken.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Optional

from .. import resources
from ..errors import EXIT_OK, EXIT_USAGE, CliError
from ..fileio import check_target, write_bytes
from ..plugin import ROOT_HINT, lua_errors, registers_vm110, skips_lua_as_root
from ..wireshark_folders import Folders, find_tshark, locate, run_tshark


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    install = actions.add_parser("install", help="copy the plugin (and the profile) where this user's Wireshark looks")
    install.add_argument("--profile", action="store_true",
                         help="also install the VM-110 configuration profile (columns, colouring rules, filter "
                              "buttons)")
    install.add_argument("--examples", action="store_true",
                         help="also install the example machine plugins (dissector/examples, e.g. crane.lua)")
    actions.add_parser("path", help="print the personal Lua plugins folder and the profile folder")
    actions.add_parser("check", help="load the installed plugin in tshark and report what it finds (exit 2: broken)")
    for action in actions.choices.values():
        action.add_argument("--tshark", metavar="PATH",
                            help="the tshark whose folders to use (default: on the PATH, else where the "
                                 "Wireshark installer puts it)")


def run(args: argparse.Namespace) -> int:
    if args.action == "install":
        return install(args.tshark, args.profile, args.examples)
    if args.action == "path":
        folders = locate(args.tshark)
        print(f"plugins: {folders.plugins}")
        print(f"profile: {folders.profiles / resources.PROFILE_NAME}")
        print(f"(from {folders.source})")
        _note_overrides(folders)
        return EXIT_OK
    return check(args.tshark)


# --- install -------------------------------------------------------------------------------------
def install(tshark: Optional[str], profile: bool, examples: bool) -> int:
    folders = locate(tshark)
    plan = [(resources.plugin(), Path(folders.plugins))]
    if examples:
        plan += [(p, Path(folders.plugins)) for p in resources.example_plugins()]
    if profile:
        target = Path(folders.profiles) / resources.PROFILE_NAME
        plan += [(p, target) for p in resources.profile_files()]
    # Every target is checked before anything is written: a refused one (a link, not a file) changes nothing.
    for source, folder in plan:
        _check_target(folder / source.name)
    print(f"folders from {folders.source}")
    _note_overrides(folders)
    for source, folder in plan:
        print(f"{_copy(source, folder)}: {folder / source.name}")
    print("restart Wireshark (or Analyze > Reload Lua Plugins); `vm110 wireshark check` tests it"
          + ("; pick the VM-110 profile in the status bar (tshark -C VM-110)" if profile else ""))
    return EXIT_OK


def _note_overrides(folders: Folders) -> None:
    """Wireshark's Lua plugin folder follows HOME only: a user who set WIRESHARK_CONFIG_DIR or
    XDG_CONFIG_HOME to keep a trial install elsewhere is told that the plugin does not follow."""
    given = [f"{name}={os.environ[name]}" for name in ("WIRESHARK_CONFIG_DIR", "XDG_CONFIG_HOME")
             if os.environ.get(name) and not str(folders.plugins).startswith(os.environ[name])]
    if given:
        print(f"note: the plugin folder follows HOME, not {' or '.join(given)} (only the profile does)",
              file=sys.stderr)


def _check_target(target: Path) -> None:
    """A target that is a symbolic link (a developer's link to a checkout) or not a regular file
    is left alone: replacing it would overwrite what it points to, or the node itself."""
    if target.is_symlink():
        raise CliError(f"{target} is a symbolic link (to {os.readlink(target)}): left alone; remove it to "
                       "install a copy")
    check_target(target)


def _copy(source: Path, folder: Path) -> str:
    data = source.read_bytes()
    target = folder / source.name
    try:
        folder.mkdir(parents=True, exist_ok=True)
        old: Optional[bytes] = target.read_bytes()
    except FileNotFoundError:
        old = None
    except OSError as exc:
        raise CliError(f"cannot install into {folder}: {exc.strerror or exc}") from None
    if old == data:
        return "unchanged"
    write_bytes(target, data)
    return "installed" if old is None else "updated"


# --- check ---------------------------------------------------------------------------------------
def check(explicit: Optional[str]) -> int:
    tshark = find_tshark(explicit)
    if tshark is None:
        raise CliError("tshark not found (install Wireshark's tshark, or give --tshark PATH)")
    try:
        # (a Lua plugin may print while loading: the version is the line that says TShark)
        version = [line for line in run_tshark(tshark, ["-v"]).stdout.splitlines() if line.startswith("TShark")][:1]
        plugins = run_tshark(tshark, ["-G", "plugins"])
        protocols = run_tshark(tshark, ["-G", "protocols"])
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CliError(f"cannot run {tshark}: {exc}") from None
    print(f"tshark: {tshark}: {version[0] if version else 'no version'}")
    listed = [line.split("\t") for line in plugins.stdout.splitlines() if line.startswith(resources.PLUGIN_NAME + "\t")]
    registered = any(registers_vm110(line) for line in protocols.stdout.splitlines())
    errors = lua_errors(protocols.stderr)
    folders = locate(tshark)
    broken = []
    if listed:
        given = f"version {listed[0][1]}" if listed[0][1] else "no version"     # (one without `version`)
        print(f"plugin: {listed[0][-1]} ({given}; {_compare(Path(listed[0][-1]))})")
    else:
        expected = Path(folders.plugins) / resources.PLUGIN_NAME
        if expected.is_file():
            print(f"plugin: {expected} (not loaded; {_compare(expected)})")
            broken.append(f"tshark did not load {expected}")
        else:
            print(f"plugin: none in {folders.plugins}")
            broken.append("tshark lists no vm110.lua plugin: run `vm110 wireshark install`")
    print(f"registered: {'yes, protocol vm110' if registered else 'no'}")
    if registered:
        decoded = _decode_samples(tshark)
        print(f"decode: {decoded or 'ok, one packet of each type'}")
        if decoded:
            broken.append(decoded)
    elif listed:
        broken.append("vm110.lua is listed but registered no vm110 protocol")
    print("Lua errors: " + ("none" if not errors else "\n  " + "\n  ".join(errors)))
    if any(resources.PLUGIN_NAME in e for e in errors):
        broken.append("Lua errors in vm110.lua")
    profile = Path(folders.profiles) / resources.PROFILE_NAME
    state = "installed" if profile.is_dir() else "not installed: vm110 wireshark install --profile"
    print(f"profile: {profile} ({state})")
    if broken and not registered and skips_lua_as_root(version[0] if version else ""):
        broken.append(ROOT_HINT)
    for line in broken:
        print(f"vm110 wireshark check: {line}", file=sys.stderr)
    return EXIT_USAGE if broken else EXIT_OK


def _compare(installed: Path) -> str:
    try:
        same = installed.read_bytes() == resources.plugin().read_bytes()
    except OSError:
        return "cannot read it"
    return "the same as this package's" if same else "differs from this package's: `vm110 wireshark install` updates it"


def _decode_samples(tshark: str) -> str:
    """'' when tshark decodes one crafted packet of each type with the installed plugin, else why not."""
    from ..capture.writer import PcapWriter
    from .craft import sample_packets

    frames = sample_packets()
    expected = [bytes(f["VM110"])[:4].decode() for f in frames]
    with tempfile.TemporaryDirectory(prefix="vm110-check-") as folder:
        capture = os.path.join(folder, "samples.pcap")
        with open(capture, "wb") as stream, PcapWriter(stream) as writer:
            writer.write_many((round(f.time * 1_000_000), bytes(f)) for f in frames)
        try:
            done = run_tshark(tshark, ["-r", capture, "-T", "fields", "-e", "frame.number", "-e", "vm110.type"])
        except (OSError, subprocess.TimeoutExpired) as exc:
            return f"tshark failed on the sample packets: {exc}"
    # (the frames' lines only: a Lua plugin may print on standard output while loading)
    rows = [line.split("\t") for line in done.stdout.splitlines()]
    got = [row[1] for row in rows if len(row) == 2 and row[0].isdigit()]
    lua = [line for line in (done.stdout + done.stderr).splitlines() if "Lua Error" in line]
    if lua:
        return f"Lua error while decoding: {lua[0].strip()}"
    if done.returncode != 0 or got != expected:
        return f"the sample packets decode as {got or 'nothing'} (expected {expected}; exit {done.returncode})"
    return ""

