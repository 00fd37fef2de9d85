"""Where this user's Wireshark looks for Lua plugins and configuration profiles.

The truth is what tshark itself reports (`tshark -G folders`: "Personal Lua Plugins" and
"Personal configuration"), which follows every override (WIRESHARK_CONFIG_DIR, XDG_CONFIG_HOME, a
legacy ~/.wireshark, a portable Windows installation). Without a tshark the documented defaults
of the operating system stand in (Wireshark User's Guide, "Files and Folders"), and the caller
says so.
"""
from __future__ import annotations

import os
import platform
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import PurePath, PurePosixPath, PureWindowsPath
from typing import Mapping, Optional

from .errors import CliError

PLUGINS_KEY = "Personal Lua Plugins"
CONFIG_KEY = "Personal configuration"
TSHARK_TIMEOUT_S = 60

# Where installers put tshark when it is not on the PATH: (environment variable or "", path parts).
KNOWN_TSHARKS = {
    "Darwin": (("", "/Applications/Wireshark.app/Contents/MacOS/tshark"),),
    "Windows": (("ProgramFiles", "Wireshark", "tshark.exe"), ("ProgramFiles(x86)", "Wireshark", "tshark.exe")),
}


@dataclass(frozen=True)
class Folders:
    plugins: PurePath        # the personal Lua plugins folder
    config: PurePath         # the personal configuration folder (profiles/ below it)
    source: str              # where these came from, for the user

    @property
    def profiles(self) -> PurePath:
        return self.config / "profiles"


def parse(text: str) -> dict[str, str]:
    """`tshark -G folders` as {name: path}: one `Name:<tab>path` a line (a Windows path has a colon
    of its own: the name ends at the first one). The first of a repeated name counts."""
    folders: dict[str, str] = {}
    for line in text.splitlines():
        name, colon, path = line.partition(":")
        if colon and path.strip():
            folders.setdefault(name.strip(), path.strip())
    return folders


def default(system: str, env: Mapping[str, str], home: str) -> Folders:
    """The documented defaults for `system` (platform.system(): Linux, Darwin, Windows, ...)."""
    config: PurePath
    plugins: PurePath
    if system == "Windows":
        appdata = PureWindowsPath(env.get("APPDATA") or PureWindowsPath(home, "AppData", "Roaming"))
        override = env.get("WIRESHARK_CONFIG_DIR")
        config = PureWindowsPath(override) if override else appdata / "Wireshark"
        plugins = config / "plugins"           # on Windows the plugins live in the configuration folder
    else:
        base = PurePosixPath(home)
        if env.get("WIRESHARK_CONFIG_DIR"):
            config = PurePosixPath(env["WIRESHARK_CONFIG_DIR"])
        else:
            config = PurePosixPath(env.get("XDG_CONFIG_HOME") or base / ".config") / "wireshark"
            legacy = base / ".wireshark"
            if not os.path.isdir(config) and os.path.isdir(legacy):
                config = legacy            # Wireshark keeps using a pre-XDG folder that exists
        plugins = base / ".local" / "lib" / "wireshark" / "plugins"
    return Folders(plugins, config, f"the default for {system or 'this system'}")


def find_tshark(explicit: Optional[str] = None, system: Optional[str] = None,
                env: Optional[Mapping[str, str]] = None) -> Optional[str]:
    """`explicit`, else tshark on the PATH, else where the system's installer puts it; None when none."""
    if explicit is not None:
        return explicit
    found = shutil.which("tshark")
    if found:
        return found
    env = os.environ if env is None else env
    for variable, *parts in KNOWN_TSHARKS.get(system or platform.system(), ()):
        if variable and not env.get(variable):
            continue
        path = os.path.join(env[variable] if variable else "", *parts)
        if os.path.isfile(path):
            return path
    return None


def run_tshark(tshark: str, args: list[str]) -> subprocess.CompletedProcess:
    """tshark's output as text; OSError (not executable) and a timeout pass to the caller."""
    return subprocess.run([tshark, *args], capture_output=True, text=True, errors="replace",
                          timeout=TSHARK_TIMEOUT_S, check=False)


def from_tshark(tshark: str) -> tuple[Optional[Folders], str]:
    """The folders tshark reports, or None and why not."""
    try:
        done = run_tshark(tshark, ["-G", "folders"])
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f"{tshark} -G folders failed: {exc}"
    found = parse(done.stdout)
    if done.returncode != 0 or PLUGINS_KEY not in found or CONFIG_KEY not in found:
        return None, f"{tshark} -G folders did not name the personal folders (exit {done.returncode})"
    flavour = PureWindowsPath if platform.system() == "Windows" else PurePosixPath
    return Folders(flavour(found[PLUGINS_KEY]), flavour(found[CONFIG_KEY]), f"{tshark} -G folders"), ""


def locate(explicit_tshark: Optional[str] = None) -> Folders:
    """The folders of this user's Wireshark: tshark's word, else the system's defaults (`source`
    says which, and why). A tshark named by the user that cannot say is an error (CliError), not
    a reason to fall back."""
    tshark = find_tshark(explicit_tshark)
    why = "tshark not found"
    if tshark is not None:
        folders, why = from_tshark(tshark)
        if folders is not None:
            return folders
        if explicit_tshark is not None:
            raise CliError(f"--tshark {explicit_tshark!r}: {why}")
    fallback = default(platform.system(), os.environ, os.path.expanduser("~"))
    return Folders(fallback.plugins, fallback.config, f"{fallback.source} ({why})")
