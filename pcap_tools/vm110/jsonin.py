"""JSON that came from outside (finding files, corpus cases, remote scripts, metadata, manifests)."""
from __future__ import annotations

import json
from typing import Any, Callable, Optional, Union


def loads(raw: Union[str, bytes], parse_constant: Optional[Callable[[str], Any]] = None) -> Any:
    """`json.loads`; nesting too deep for Python's recursive parser is a ValueError, as any other
    malformed JSON is, not a RecursionError."""
    try:
        return json.loads(raw, parse_constant=parse_constant)
    except RecursionError:
        raise ValueError("nested too deeply") from None
