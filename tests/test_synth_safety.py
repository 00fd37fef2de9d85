"""Issue 17, "nothing lost", for `vm110 synth` and `vm110 craft`: files go through a temporary file
renamed into place when complete, a failure leaves what was there, nothing the tool did not create
is ever deleted, and a target that is not a regular file (capture or OUT.truth.json) is refused up
front.

Failures are provoked without real devices: a directory, a FIFO or a device node of our own in
tmp_path (as root), or a capture writer that fails half-way. Commands that could block on a FIFO
run in a subprocess with a timeout.
"""
from __future__ import annotations

import contextlib
import errno
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vm110 import cli, synth
from vm110.errors import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, CliError

OLD_CAPTURE, OLD_TRUTH = b"old capture, not to be lost", '{"old": "truth"}\n'


def vm110(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=60)


def one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def old_files(folder: Path) -> Path:
    """OUT and OUT.truth.json with content that must survive."""
    out = folder / "run.pcap"
    out.write_bytes(OLD_CAPTURE)
    Path(synth.truth_path(str(out))).write_text(OLD_TRUTH)
    return out


def leftovers(folder: Path) -> list[str]:
    """Temporary files of the atomic writer left in `folder`."""
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


def make_node(path: Path, kind: str) -> None:
    if kind == "directory":
        path.mkdir()
        (path / "inside").write_text("kept")
    elif kind == "fifo":
        os.mkfifo(path)
    else:       # a node like /dev/full (writes fail), made here: no real device is touched
        try:
            os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 7))
        except OSError as exc:
            pytest.skip(f"cannot make a device node here: {exc.strerror}")


def unchanged_node(path: Path, kind: str) -> bool:
    mode = path.lstat().st_mode
    if kind == "directory":
        return stat.S_ISDIR(mode) and (path / "inside").read_text() == "kept"
    return stat.S_ISFIFO(mode) if kind == "fifo" else stat.S_ISCHR(mode)


@pytest.mark.parametrize("kind", ["directory", "fifo", "device"])
@pytest.mark.parametrize("where", ["capture", "truth"])
def test_a_target_that_is_not_a_regular_file_is_refused_up_front(tmp_path, kind, where):
    """Before: a failed write removed a device node given as --out; a FIFO blocked for ever; a
    directory at OUT.truth.json deleted the existing OUT and ended in a traceback."""
    out = old_files(tmp_path)
    node = out if where == "capture" else Path(synth.truth_path(str(out)))
    node.unlink()
    make_node(node, kind)
    result = vm110("synth", "normal", "--duration", "1", "--out", str(out))
    assert result.returncode == EXIT_USAGE
    assert str(node) in one_line(result.stderr) and "not a regular file" in result.stderr
    assert unchanged_node(node, kind)
    if where == "truth":
        assert out.read_bytes() == OLD_CAPTURE
    else:
        assert Path(synth.truth_path(str(out))).read_text() == OLD_TRUTH
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["directory", "fifo", "device"])
def test_craft_refuses_a_target_that_is_not_a_regular_file(tmp_path, kind):
    node = tmp_path / "crafted.pcap"
    make_node(node, kind)
    result = vm110("craft", "--out", str(node))
    assert result.returncode == EXIT_USAGE and "not a regular file" in one_line(result.stderr)
    assert unchanged_node(node, kind) and leftovers(tmp_path) == []


def failing_writer(monkeypatch, error: BaseException) -> None:
    """The capture writer writes its first batch, then raises `error`."""
    real = synth.open_writer

    def open_writer(stream, fmt="pcap"):
        writer = real(stream, fmt)
        written = []

        def write_many(frames):
            if written:
                raise error
            written.append(type(writer).write_many(writer, frames))
            writer.flush()
        writer.write_many = write_many
        return writer
    monkeypatch.setattr(synth, "open_writer", open_writer)


@pytest.mark.parametrize("error, code", [(OSError(errno.ENOSPC, "No space left on device"), EXIT_USAGE),
                                         (KeyboardInterrupt(), EXIT_INTERRUPTED)])
def test_a_failure_half_way_leaves_the_old_files(capsys, monkeypatch, tmp_path, error, code):
    """Before: a failed write deleted OUT and its truth; an interrupt left OUT cut short."""
    out = old_files(tmp_path)
    failing_writer(monkeypatch, error)
    assert cli.main(["synth", "normal", "--duration", "5", "--out", str(out)]) == code
    err = capsys.readouterr().err
    if code == EXIT_USAGE:
        assert str(out) in one_line(err) and "No space left on device" in err
    assert out.read_bytes() == OLD_CAPTURE
    assert Path(synth.truth_path(str(out))).read_text() == OLD_TRUTH
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_sigterm_or_sighup_half_way_leaves_the_old_files_and_no_temporary_file(tmp_path, sig):
    """Before: SIGTERM (`timeout`, a cancelled CI job) or SIGHUP (its terminal closed) killed the
    run and left its temporary file, .run.pcap.<hex>.tmp, beside OUT (13 MB after 3 s of `day`);
    now each is an interruption as Ctrl-C is: exit 130, the old files as they were, nothing left
    behind."""
    out = old_files(tmp_path)
    with subprocess.Popen([sys.executable, "-m", "vm110", "synth", "day", "--duration", "200000", "--out", str(out)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        deadline = time.monotonic() + 30
        while not leftovers(tmp_path) and time.monotonic() < deadline:     # the capture is being written
            time.sleep(0.05)
        assert leftovers(tmp_path), "the run never started writing"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == EXIT_INTERRUPTED and "Traceback" not in err, err
    assert out.read_bytes() == OLD_CAPTURE
    assert Path(synth.truth_path(str(out))).read_text() == OLD_TRUTH
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("args", [["normal", "--duration", "1", "--out", "run.pcap"], ["--list"]])
def test_a_standard_output_that_cannot_be_written_is_one_line(tmp_path, args):
    """Before: `> /dev/full` (a full disk) ended in a traceback, exit 1."""
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "vm110", "synth", *args], stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == EXIT_USAGE
    assert one_line(done.stderr) == "vm110 synth: cannot write standard output: No space left on device"


def test_a_failed_truth_write_keeps_the_old_capture(capsys, monkeypatch, tmp_path):
    """The truth is written before the capture is renamed: no new capture beside an old truth."""
    out = old_files(tmp_path)

    def fail(path, text):
        raise OSError(errno.EIO, "Input/output error", path)
    monkeypatch.setattr(synth, "write_text", fail)
    with pytest.raises(CliError, match="Input/output error"):
        synth.synthesize("normal", str(out), duration_s=3)
    assert out.read_bytes() == OLD_CAPTURE and leftovers(tmp_path) == []


def test_success_replaces_the_files_and_keeps_their_permissions(capsys, tmp_path):
    out = old_files(tmp_path)
    out.chmod(0o640)
    assert cli.main(["synth", "normal", "--duration", "3", "--out", str(out)]) == EXIT_OK
    assert out.read_bytes()[:4] == bytes.fromhex("d4c3b2a1") and stat.S_IMODE(out.stat().st_mode) == 0o640
    assert '"capture"' in Path(synth.truth_path(str(out))).read_text()
    assert leftovers(tmp_path) == []


def test_an_unwritable_folder_fails_before_the_run(capsys, monkeypatch, tmp_path):
    out = tmp_path / "no" / "such" / "run.pcap"
    monkeypatch.setattr(synth, "write_capture", lambda *args: pytest.fail("the scenario was run"))
    assert cli.main(["synth", "day", "--out", str(out)]) == EXIT_USAGE
    assert str(out) in one_line(capsys.readouterr().err)


@pytest.mark.parametrize("args, message", [
    (["--duration", "5e-7"], "argument --duration: '5e-7' is out of range: must be 1e-06 to"),   # wrote no packet
    (["--out", "-"], "--out - : synth writes a capture file and OUT.truth.json beside it"),     # wrote a file '-'
])
def test_options_that_made_nothing_or_a_file_named_dash_are_refused(capsys, monkeypatch, tmp_path, args, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) if args[0] == "--duration" else contextlib.nullcontext():
        assert cli.main(["synth", "normal", "--out", "x.pcap", *args]) == EXIT_USAGE
    assert message in one_line(capsys.readouterr().err) and list(tmp_path.iterdir()) == []


def test_the_library_refuses_durations_that_are_not_finite(tmp_path):
    for duration in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(ValueError):
            synth.synthesize("normal", str(tmp_path / "x.pcap"), duration_s=duration)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("link", ["truth", "capture"])
def test_a_capture_and_truth_that_are_one_file_through_a_link_are_refused(capsys, monkeypatch, tmp_path, link):
    """OUT.truth.json a link to OUT (or OUT a link to OUT.truth.json, not there yet): the second file
    written replaced the first, and synth said it wrote both (exit 0)."""
    out = tmp_path / "run.pcap"
    truth = Path(synth.truth_path(str(out)))
    if link == "truth":
        out.write_bytes(OLD_CAPTURE)
        truth.symlink_to(out.name)
    else:
        out.symlink_to(truth.name)
    monkeypatch.setattr(synth, "write_capture", lambda *args: pytest.fail("the scenario was run"))
    assert cli.main(["synth", "normal", "--out", str(out), "--duration", "1"]) == EXIT_USAGE
    assert "name the same file" in one_line(capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.pcap", "run.pcap.truth.json"][:1 + (link == "truth")]
    if link == "truth":
        assert out.read_bytes() == OLD_CAPTURE
