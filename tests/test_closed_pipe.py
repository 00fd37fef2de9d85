"""A reader that goes away (`vm110 analyze x | head`): the command ends quietly (no traceback, no
"Exception ignored" from the interpreter's last flush), its report files are still written, and
a --fail-on violation still exits 1. Real pipes: `vm110` runs as a subprocess whose standard output
is a pipe that the test closes after the first line, or before the command writes anything."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from vm110.errors import EXIT_FINDINGS, EXIT_OK, EXIT_USAGE

CAPTURES = Path(__file__).resolve().parent.parent / "captures"
PIPE_BUFFER = 1 << 16      # Linux: a pipe holds 64 KiB; more output than that must meet the closed end


def after_first_line(*args: str) -> tuple[int, str, bytes]:
    """Exit code, standard error and the first line of `vm110 ARGS | head -n 1`."""
    with subprocess.Popen([sys.executable, "-m", "vm110", *args], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        first = proc.stdout.readline()
        proc.stdout.close()
        err = proc.stderr.read().decode()
        return proc.wait(timeout=120), err, first


def closed_from_the_start(*args: str, cwd: Path) -> tuple[int, str]:
    """Exit code and standard error of `vm110 ARGS` writing into a pipe nobody reads any more."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run([sys.executable, "-m", "vm110", *args], stdout=write_end, stderr=subprocess.PIPE,
                              cwd=cwd, timeout=120, check=False)
    finally:
        os.close(write_end)
    return done.returncode, done.stderr.decode()


def output_size(*args: str) -> int:
    return len(subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, check=False).stdout)


@pytest.mark.parametrize("args, code, first", [
    (["decode", str(CAPTURES / "overlap.pcapng")], EXIT_OK, b"     1 2025-06-15T15:06:40"),
    (["analyze", str(CAPTURES / "overlap.pcapng"), str(CAPTURES / "loss.pcapng"), "--html", "-", "--quiet"], EXIT_OK, b"<!DOCTYPE"),
    (["analyze", str(CAPTURES / "overlap.pcapng"), "--json", "-", "--quiet", "--fail-on", "lost>0"], EXIT_FINDINGS,
     b"{"),
])
def test_a_long_output_cut_after_one_line_ends_quietly_with_its_verdict(args, code, first):
    assert output_size(*args) > 2 * PIPE_BUFFER      # so the closed end is met for certain
    got, err, line = after_first_line(*args)
    assert line.startswith(first)
    assert "Traceback" not in err and "Exception ignored" not in err and "BrokenPipe" not in err, err
    assert got == code, err
    if code == EXIT_FINDINGS:
        assert err.splitlines() and all(line.startswith(f"fail-on: {args[1]}: lost=") for line in err.splitlines())


@pytest.mark.parametrize("fail_on, code", [([], EXIT_OK), (["--fail-on", "lost>0,duplicates>0"], EXIT_FINDINGS),
                                           (["--fail-on", "illegal>0"], EXIT_OK)])
def test_analyze_into_a_closed_pipe_still_writes_its_report_and_keeps_the_verdict(tmp_path, fail_on, code):
    got, err = closed_from_the_start("analyze", str(CAPTURES / "loss.pcapng"), "--json", "r.json", *fail_on,
                                     cwd=tmp_path)
    assert got == code, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert all(line.startswith("fail-on: ") for line in err.splitlines())
    truth = json.loads((CAPTURES / "loss.pcapng.truth.json").read_text())
    report = json.loads((tmp_path / "r.json").read_text())
    assert sum(s["serial"]["lost"] for s in report["senders"]) == sum(s["serial"]["lost"] for s in truth["senders"])


def test_decode_into_a_closed_pipe_ends_quietly(tmp_path):
    got, err = closed_from_the_start("decode", str(CAPTURES / "normal.pcap"), "--json", cwd=tmp_path)
    assert (got, err) == (EXIT_OK, "")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("args", [
    ["decode", str(CAPTURES / "loss.pcapng")],
    ["decode", str(CAPTURES / "loss.pcapng"), "--json"],
    ["analyze", str(CAPTURES / "loss.pcapng")],
    ["analyze", str(CAPTURES / "loss.pcapng"), "--quiet", "--json", "-"],
    ["wireshark", "path"],
], ids=lambda a: " ".join(a[:1] + a[2:]))
def test_a_standard_output_that_cannot_be_written_is_one_line_and_exit_2(args):
    """`> /dev/full` (a full disk): a traceback, exit 1 (the sim trial found it in simulate and
    synth; every command had it). Now one line naming standard output, exit 2: the output is
    incomplete."""
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "vm110", *args], stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=120, check=False)
    assert done.returncode == EXIT_USAGE, done.stderr
    assert done.stderr.splitlines()[-1] == f"vm110 {args[0]}: cannot write standard output: No space left on device"
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("args, said", [(["--help"], "vm110"), (["--version"], "vm110"),
                                        (["analyze", "--help"], "vm110 analyze")])
def test_help_that_cannot_be_written_is_one_line_and_exit_2(args, said):
    """`vm110 --help > /dev/full` was exit 0 and no word: the help lost, unsaid."""
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "vm110", *args], stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=120, check=False)
    assert (done.returncode, done.stderr) == (EXIT_USAGE, f"{said}: cannot write standard output: No space left on device\n")
    got, err = closed_from_the_start(*args, cwd=Path.cwd())
    assert (got, err) == (EXIT_OK, "")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_analyze_on_a_full_disk_still_writes_its_report_and_says_its_verdict(tmp_path):
    """What follows the summary still runs: the report file is written and the --fail-on line said,
    and exit 2 (output incomplete) wins over 1."""
    report = tmp_path / "r.json"
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "vm110", "analyze", str(CAPTURES / "loss.pcapng"), "--json",
                               str(report), "--fail-on", "lost>0"], stdout=full, stderr=subprocess.PIPE, text=True,
                              timeout=120, check=False)
    assert done.returncode == EXIT_USAGE and "fail-on: " in done.stderr and "Traceback" not in done.stderr
    assert json.loads(report.read_text())["totals"]["lost"] > 0
