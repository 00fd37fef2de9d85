"""Counts in our output's words: `1 packet`, `2 packets`."""
from __future__ import annotations

from typing import Optional


def plural(count: int, word: str, many: Optional[str] = None) -> str:
    """`count word`, the word in the plural (`many`, or with an s) unless count is 1."""
    return f"{count} {word if count == 1 else many or word + 's'}"
