"""The README's examples hold: its Python examples run, the output it quotes is what the commands
print now, and every option it gives a `vm110` command is one that command takes."""
from __future__ import annotations

import argparse
import pathlib
import re
import shlex
import subprocess
import sys

from vm110.cli import build_parser

REPO = pathlib.Path(__file__).resolve().parent.parent
README = REPO / "README.md"


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
    the Info column example came from a restart.pcapng regenerated since (no [Serial Gap] now)."""
    examples = re.findall(r"```text\n\$ (vm110 [^\n]*)\n(.*?)```", README.read_text(), re.S)
    assert len(examples) >= 3
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
    """Every `--option` the README writes after `vm110 COMMAND` on one line (or one continued with
    a backslash) is an option of that command: a renamed option leaves no example behind."""
    text = README.read_text().replace("\\\n", " ")
    parser = build_parser()
    checked = 0
    for written in re.findall(r"\bvm110 ([a-z][^`\n|#]*)", text):
        command = re.sub(r"\"[^\"]*\"|'[^']*'", "''", written)      # a quoted argument is a value
        words = command.split()
        if words[0] not in parser.commands or words[0] == "dissect":   # dissect passes on tshark's
            continue
        known = _options(parser.commands[words[0]], words[1:])
        for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", command):
            assert option in known, f"README: `vm110 {command.strip()}`: {option} is no option of it"
            checked += 1
    assert checked > 50
