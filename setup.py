"""Packaging beyond what pyproject.toml can declare: the package's folders of data that live
outside it in the source tree. The wheel maps dissector/ (the Lua plugin, the VM-110 profile, the
examples) into the package as vm110/dissector and docs/ as vm110/schema (only the report's JSON
Schema): the repository's files are the only copy (vm110/resources.py finds them either way)."""
from setuptools import find_packages, setup

DATA = {
    "vm110.dissector": ("dissector", ["vm110.lua", "profile/VM-110/*", "examples/*.lua"]),
    "vm110.schema": ("docs", ["report.schema.json"]),
}

setup(
    packages=[*find_packages("pcap_tools"), *DATA],
    package_dir={"": "pcap_tools", **{name: folder for name, (folder, _) in DATA.items()}},
    package_data={name: files for name, (_, files) in DATA.items()},
    include_package_data=False,
)
