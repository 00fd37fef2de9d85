"""vm110.fileio: atomic replacement, nothing lost on failure, special files refused."""
from __future__ import annotations

import os
import stat

import pytest

from vm110.errors import CliError
from vm110.fileio import atomic_writer, check_target, write_bytes, write_text


def leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_writes_and_replaces(tmp_path):
    target = tmp_path / "out.json"
    write_text(target, "one\n")
    assert target.read_text() == "one\n"
    write_bytes(target, b"two")
    assert target.read_bytes() == b"two"
    assert leftovers(tmp_path) == []


def test_new_file_mode_follows_umask_and_a_replaced_file_keeps_its_mode(tmp_path):
    old = os.umask(0o027)
    try:
        write_text(tmp_path / "new", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new").stat().st_mode) == 0o640
    kept = tmp_path / "kept"
    kept.write_text("old")
    kept.chmod(0o604)
    write_text(kept, "new")
    assert stat.S_IMODE(kept.stat().st_mode) == 0o604


def test_failure_in_the_middle_leaves_the_old_file(tmp_path):
    target = tmp_path / "capture.pcap"
    target.write_bytes(b"precious")
    with pytest.raises(RuntimeError), atomic_writer(target) as stream:
        stream.write(b"half")
        raise RuntimeError("writer failed")
    assert target.read_bytes() == b"precious"
    assert leftovers(tmp_path) == []


def test_os_error_becomes_a_cli_error_naming_the_file(tmp_path):
    target = tmp_path / "x.json"
    target.write_text("old")
    with pytest.raises(CliError, match=r"x\.json"), atomic_writer(target):
        raise OSError(28, "No space left on device")
    assert target.read_text() == "old" and leftovers(tmp_path) == []


def test_missing_folder_is_a_cli_error(tmp_path):
    with pytest.raises(CliError, match="cannot write"):
        write_text(tmp_path / "no" / "such" / "file", "x")


@pytest.mark.parametrize("make", ["directory", "fifo", "device"])
def test_special_targets_are_refused_and_kept(tmp_path, make):
    target = tmp_path / "target"
    if make == "directory":
        target.mkdir()
    elif make == "fifo":
        os.mkfifo(target)
    else:
        try:
            os.mknod(target, stat.S_IFCHR | 0o600, os.makedev(1, 3))   # like /dev/null
        except PermissionError:
            pytest.skip("needs root to make a device node")
    before = target.lstat()
    with pytest.raises(CliError, match="not a regular file") as info:
        write_bytes(target, b"data")
    assert str(target) in str(info.value)
    after = target.lstat()
    assert (after.st_ino, after.st_mode) == (before.st_ino, before.st_mode)
    assert leftovers(tmp_path) == []


def test_dev_null_is_refused():
    with pytest.raises(CliError, match="/dev/null"):
        check_target("/dev/null")


def test_standard_output_named_by_its_path_is_refused_as_a_pipe():
    # `vm110 craft --out /dev/stdout | ...` said "cannot write /dev/stdout: No such file or directory"
    # (its link leads to "pipe:[...]", no file); it is refused as any pipe is (`--out -` writes there)
    read, write = os.pipe()
    try:
        with pytest.raises(CliError, match=f"refusing to write /dev/fd/{write}: it exists and is not a regular file"):
            check_target(f"/dev/fd/{write}")
    finally:
        os.close(read)
        os.close(write)


def test_a_symbolic_link_stays_a_link(tmp_path):
    real = tmp_path / "real.json"
    real.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    write_text(link, "new")
    assert link.is_symlink() and real.read_text() == "new"
    (tmp_path / "to-null").symlink_to("/dev/null")
    with pytest.raises(CliError, match="not a regular file"):
        write_text(tmp_path / "to-null", "x")
