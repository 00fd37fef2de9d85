"""Files the package ships that the source tree keeps outside it: dissector/ (the Lua plugin, the
VM-110 configuration profile, the examples) and docs/report.schema.json.

A wheel carries them as package data, vm110/dissector and vm110/schema (setup.py maps the folders:
the repository's files are the only copy); an editable install (`make setup`) finds them beside the
package's source, pcap_tools/vm110 -> ../../dissector and ../../docs.
"""
from __future__ import annotations

from pathlib import Path

from .errors import CliError

PACKAGE = Path(__file__).resolve().parent
SOURCE_TREE = PACKAGE.parents[1]
PLUGIN_NAME = "vm110.lua"
PROFILE_NAME = "VM-110"
SCHEMA_NAME = "report.schema.json"


def _first(candidates: tuple[Path, ...], what: str) -> Path:
    for path in candidates:
        if path.is_file():
            return path
    raise CliError(f"{what} is missing from this installation of vm110 (looked for {candidates[0]})")


def plugin() -> Path:
    """dissector/vm110.lua."""
    return _first((PACKAGE / "dissector" / PLUGIN_NAME, SOURCE_TREE / "dissector" / PLUGIN_NAME),
                  "the Wireshark plugin")


def dissector_dir() -> Path:
    """dissector/: vm110.lua, profile/VM-110/, examples/."""
    return plugin().parent


def profile_files() -> list[Path]:
    """The files of the VM-110 configuration profile (preferences, colouring rules, filter buttons)."""
    return sorted(p for p in (dissector_dir() / "profile" / PROFILE_NAME).iterdir() if p.is_file())


def example_plugins() -> list[Path]:
    """The example machine plugins, dissector/examples/*.lua."""
    return sorted((dissector_dir() / "examples").glob("*.lua"))


def report_schema() -> Path:
    """docs/report.schema.json, the JSON Schema of `vm110 analyze --json`."""
    return _first((PACKAGE / "schema" / SCHEMA_NAME, SOURCE_TREE / "docs" / SCHEMA_NAME),
                  "the report's JSON Schema")
