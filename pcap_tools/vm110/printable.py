"""Text from outside (command data off the network, a capture's file name) in a line of our own
output: a control character in it could forge a line or reach the terminal as an escape sequence."""
from __future__ import annotations


def escaped(text: str) -> str:
    """`text` with each character that is not printable as its escape (a newline as \\n, ESC as \\x1b)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)
