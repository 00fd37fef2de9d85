"""Text from outside (command data off the network, a capture's file name) in a line of our own
output: a control character in it could forge a line or reach the terminal as an escape sequence."""
from __future__ import annotations


def escaped(text: str) -> str:
    """`text` with each character that is not printable as its escape (a newline as \\n, ESC as \\x1b)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def unicode_text(text: str) -> str:
    """`text` as valid Unicode: the bytes of a file name that are no UTF-8 (Python's surrogate
    escapes of them, which no UTF-8 encoder takes) as their escapes, `\\udcff`, as `escaped` shows them."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text
