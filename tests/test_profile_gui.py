"""The VM-110 profile in the Wireshark GUI itself (the host's Wireshark, under a virtual X server
of the test's own): what tshark cannot show, the packet list's column widths."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections import Counter
from typing import Iterator

import numpy as np
import png
import pytest

import tshark_runner as T

PROFILE = T.REPO / "dissector" / "profile" / "VM-110"
# The packet list's columns, in order: (title, format); the profile's own are custom ones ("%Cus:...").
COLUMNS = re.findall(r'^\t"([^"]+)", "([^"]+)"', (PROFILE / "preferences").read_text(), re.M)
TOOLS = ("wireshark", "Xvfb", "xdotool", "import")
pytestmark = pytest.mark.skipif(not all(shutil.which(t) for t in TOOLS), reason=f"needs {', '.join(TOOLS)}")


@pytest.fixture
def display() -> Iterator[str]:
    """A virtual X server on a free display number."""
    read, write = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1600x900x24", "-nolisten", "tcp"],
                              pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as pipe:
        number = pipe.readline().strip()
    try:
        yield f":{number}"
    finally:
        server.terminate()
        server.wait()


def grey(shot: bytes) -> np.ndarray:
    width, height, rows, _ = png.Reader(bytes=shot).asRGBA8()
    return np.array([list(r) for r in rows], dtype=np.int32).reshape(height, width, 4)[:, :, :3].mean(axis=2)


def header(image: np.ndarray) -> tuple[int, int, list[int]]:
    """The packet list header: its rows (top, bottom) and the x of its section separators, found as
    the vertical lines (a pixel darker than both neighbours) of the same height that end on the
    same row: the most common such line in the upper half of the window."""
    line = np.zeros(image.shape, dtype=bool)
    line[:, 1:-1] = (image[:, 1:-1] < image[:, :-2] - 20) & (image[:, 1:-1] < image[:, 2:] - 20)
    runs = {}
    for x in range(image.shape[1]):
        best, run = (0, 0), 0
        for y in range(image.shape[0] // 2):
            run = run + 1 if line[y, x] else 0
            best = max(best, (run, y))
        if best[0] >= 15:
            runs[x] = best
    (height, bottom), _ = Counter(runs.values()).most_common(1)[0]
    return bottom + 1 - height, bottom + 1, [x for x, run in runs.items() if run == (height, bottom)]


def cells(image: np.ndarray, top: int, bottom: int, left: int, right: int) -> tuple[np.ndarray, np.ndarray]:
    """The text (dark pixels) of a column's cells from `top` to `bottom`, aligned on its left and
    on its right edge (a cell's text is aligned on one of them)."""
    text = image[top:bottom, left + 1:right] < 110
    used = np.nonzero(text.any(axis=0))[0]
    if not len(used):
        return text[:, :0], text[:, :0]
    return text[:, :used.max() + 1], text[:, used.min():]


def test_profile_columns_show_their_titles_and_values(tmp_path, display):
    """With the profile's columns at the width Wireshark gives them (nothing in `recent`), every
    column title and value on screen is whole: it looks as it does after View > Resize Columns
    (each column as wide as its title and values). Trial: the "Command ID" title showed as
    "Command I" (Wireshark sizes a column by its title only when the title is longer than ten
    characters, and then in the monospace font)."""
    config = tmp_path / "config"
    shutil.copytree(PROFILE, config / "profiles" / "VM-110")
    (config / "profiles" / "VM-110" / "recent").write_text(
        "gui.geometry_main_width: 1500\ngui.geometry_main_height: 500\n")
    # (HOME: no plugin installed for this user, which would make the -X copy stand aside)
    env = dict(os.environ, DISPLAY=display, WIRESHARK_CONFIG_DIR=str(config), HOME=str(tmp_path))
    gui = subprocess.Popen(["wireshark", "-C", "VM-110", "-X", f"lua_script:{T.PLUGIN}",
                            "-r", str(T.REPO / "captures" / "restart.pcapng")], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        def xdotool(*args: str) -> str:
            return subprocess.run(["xdotool", *args], env=env, capture_output=True, text=True, check=True,
                                  timeout=60).stdout

        def settled() -> np.ndarray:
            """The window once two screenshots in a row are the same (the capture loaded, drawn)."""
            last = None
            for _ in range(40):
                shot = subprocess.run(["import", "-window", window, "png:-"], env=env, capture_output=True,
                                      check=True, timeout=60).stdout
                if shot == last:
                    return grey(shot)
                last = shot
                xdotool("sleep", "0.5")
            raise AssertionError("the Wireshark window never settled")

        window = xdotool("search", "--sync", "--onlyvisible", "--name", "restart").split()[0]
        before = settled()
        xdotool("windowfocus", "--sync", window, "key", "ctrl+shift+r")   # View > Resize Columns
        after = settled()
    finally:
        gui.terminate()
        gui.wait(timeout=60)
    top, bottom, seps = header(before)
    _, _, resized = header(after)
    assert len(seps) == len(resized) == len(COLUMNS) - 1, (seps, resized)   # (the last column, Info, has none)
    rows = bottom + 5 * (bottom - top)      # (the first rows of the list, the selected first one white)
    cut = []
    for number, (title, form) in enumerate(COLUMNS):
        if not form.startswith("%Cus:"):
            continue        # (Wireshark's own columns, at their usual widths)
        (left, right), (new_left, new_right) = [([0] + x)[number:number + 2] for x in (seps, resized)]
        for part, (y0, y1) in (("title", (top, bottom)), ("values", (bottom, rows))):
            shown, whole = cells(before, y0, y1, left, right), cells(after, y0, y1, new_left, new_right)
            if not any(s.shape == w.shape and (s == w).all() for s, w in zip(shown, whole)):
                cut.append(f"{title} {part}")
    assert not cut, cut
