"""The user documentation's examples hold (the README, captures/README.md and docs/*.md): the
README's Python examples run, the output a document quotes is what the commands print now, every
option it gives a `vm110` command is one that command takes, every option a command takes is
documented, and the format versions it cites are the current ones."""
from __future__ import annotations

import argparse
import pathlib
import re
import shlex
import subprocess
import sys
from typing import Iterator

from vm110.analysis.report import SCHEMA_VERSION
from vm110.cli import build_parser
from vm110.fleet.dataset import FORMAT_VERSION

REPO = pathlib.Path(__file__).resolve().parent.parent
README = REPO / "README.md"
DOCS = (README, REPO / "captures" / "README.md", *sorted((REPO / "docs").glob("*.md")))


def test_python_examples_run(tmp_path):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks
    for number, code in enumerate(blocks):
        script = tmp_path / f"example{number}.py"
        script.write_text(code)
        result = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True)
        assert result.returncode == 0, f"README example {number} failed:\n{result.stderr}"


def _squeeze(line: str) -> str:
    return " ".join(line.split())      # column widths are the tool's (and tshark's) layout, not content


def test_quoted_output_is_current():
    """A ```text block that starts with `$ vm110 ...` quotes that command's output as run in the
    repository: each run of lines between `...` lines is a run of consecutive output lines, in
    order. Trial: the analyze excerpt (frame 11, serial 13 after 9) matched no bundled capture, and
    the Info column example came from a restart.pcapng regenerated since (no [Serial Gap] now);
    docs/monitor.md's finding line (silent 1125 ms) came from no command it showed: with the
    default `--crc auto` that alarm is held until the CRC is chosen (silent 3125 ms)."""
    examples = [found for doc in DOCS
                for found in re.findall(r"```text\n\$ (vm110 [^\n]*)\n(.*?)```", doc.read_text(), re.S)]
    assert len(examples) >= 4
    for command, quoted in examples:
        argv = shlex.split(command)
        done = subprocess.run([sys.executable, "-m", *argv], cwd=REPO, capture_output=True, text=True)
        assert done.returncode == 0, f"{command}: {done.stderr}"
        printed = [_squeeze(line) for line in done.stdout.splitlines()]
        at = 0
        for chunk in re.split(r"^\.\.\.\n", quoted, flags=re.M):
            lines = [_squeeze(line) for line in chunk.splitlines()]
            if not lines:
                continue
            found = next((i for i in range(at, len(printed) - len(lines) + 1)
                          if printed[i:i + len(lines)] == lines), None)
            assert found is not None, f"`{command}` no longer prints (after line {at}):\n{chunk}"
            at = found + len(lines)


def _options(parser: argparse.ArgumentParser, words: list[str]) -> set[str]:
    """The options of the (sub)command `words` names; of all its subcommands when it stops short."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    options = {o for a in parser._actions for o in a.option_strings}
    if not subs:
        return options
    choices = subs[0].choices
    if words and words[0] in choices:
        return options | _options(choices[words[0]], words[1:])
    return options.union(*(_options(p, []) for p in choices.values()))


def test_options_exist():
    """Every `--option` a document writes after `vm110 COMMAND` on one line (or one continued with
    a backslash) is an option of that command: a renamed option leaves no example behind."""
    text = "\n".join(doc.read_text() for doc in DOCS).replace("\\\n", " ")
    parser = build_parser()
    checked = 0
    for written in re.findall(r"\bvm110 ([a-z][^`\n|#]*)", text):
        command = re.sub(r"\"[^\"]*\"|'[^']*'", "''", written)      # a quoted argument is a value
        words = command.split()
        if words[0] not in parser.commands or words[0] == "dissect":   # dissect passes on tshark's
            continue
        known = _options(parser.commands[words[0]], words[1:])
        for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", command):
            assert option in known, f"docs: `vm110 {command.strip()}`: {option} is no option of it"
            checked += 1
    assert checked > 50


def _option_actions(parser: argparse.ArgumentParser, path: str) -> Iterator[tuple[str, argparse.Action]]:
    """(command, action) for every option but --help of the command `path` and its subcommands."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _option_actions(sub, f"{path} {name}")
        elif action.option_strings and "--help" not in action.option_strings:
            yield path, action


def test_every_option_is_documented():
    """Every long option a `vm110` command takes is named in the documentation, so its --help is not
    the only place to learn of it. Trial: `simulate --origin`, `--command-id-start`, `--data-size`,
    `monitor --interface` and `vm110 --version` were in --help alone."""
    text = "\n".join(doc.read_text() for doc in DOCS)
    missing = [f"{command} {option}" for command, action in _option_actions(build_parser(), "vm110")
               for option in action.option_strings if option.startswith("--")
               if not re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text)]
    assert not missing, f"options no document names: {missing}"


def test_cited_versions_are_current():
    """The report's schema_version and the fleet dataset's format_version, wherever a document cites
    one as the current version, are the code's. Trial: captures/README.md said the ground truth had
    `schema_version` 2; it has 6."""
    current = {"schema_version": SCHEMA_VERSION, "format_version": FORMAT_VERSION}
    cited = [(doc.relative_to(REPO), key, int(number)) for doc in DOCS
             for key, number in re.findall(r"\b(schema_version|format_version)`?(?: ✓)?(?: \|)? (\d+)\b", doc.read_text())]
    assert {key for _, key, _ in cited} == set(current)
    assert [c for c in cited if c[2] != current[c[1]]] == []


def test_every_option_help_says_what_it_is():
    """An option's --help line says what it does, not only the range of its value. Trial: `simulate
    controller --help` gave `--vrco-timeout MS  0.001 to 3600000 ms (default 2000)` (give up a VRCO
    after it? stop sending?), `--vrpi-timeout`, `--delay` and `--seed` alike, `fleet query --format`
    nothing."""
    bare = [f"{command} {action.option_strings[-1]}: {action.help!r}"
            for command, action in _option_actions(build_parser(), "vm110")
            if not action.help or re.match(r"[\d(]", action.help)]
    assert not bare, f"options whose help is only a range: {bare}"


def test_the_layout_names_every_part_of_the_tree():
    """The README's Layout table: every path it gives exists, and it names every tracked top-level
    entry, every file of docs/ and scripts/ and every module of the package. Trial: it named
    neither docs/monitor.md, docs/screenshots.md, the VM-110 profile, the Makefile and .ci/, nor
    scripts/fuzz-self and tshark-chroot.sh, nor the package's timefmt (which the README cites),
    errors (the exit codes) and cli."""
    section = README.read_text().split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.split(" | ", 1) for line in section.splitlines() if line.startswith("| `")]
    paths = [p for first, _ in rows for p in re.findall(r"`([^`]+)`", first)]
    assert [p for p in paths if not list(REPO.glob(p.rstrip("/")))] == []
    named = set(re.findall(r"`([^`]+)`", section))
    tracked = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout.split()

    def is_named(path: str) -> bool:
        return any(p.rstrip("/") == path or pathlib.PurePath(path).match(p) for p in named) or \
            pathlib.PurePath(path).name in named
    top = {f.split("/")[0] for f in tracked} - {"README.md", ".gitignore"}
    assert sorted(t for t in top if not any(p.rstrip("/") == t or p.startswith(t + "/") for p in paths)) == []
    assert sorted(f for f in tracked if f.startswith(("docs/", "scripts/")) and not is_named(f)) == []
    package_row = next(what for first, what in rows if first == "| `pcap_tools/vm110/`")
    modules = {p.stem if p.is_file() else p.name + "/" for p in (REPO / "pcap_tools" / "vm110").iterdir()
               if not p.name.startswith("_") and (p.suffix == ".py" or (p / "__init__.py").exists())}
    assert sorted(modules - set(re.findall(r"`([^`]+)`", package_row))) == []
