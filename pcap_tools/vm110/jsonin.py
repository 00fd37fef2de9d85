"""JSON that came from outside (finding files, corpus cases, remote scripts, metadata, manifests)."""
from __future__ import annotations

import json
from typing import Any, Callable, Optional, Union

from .errors import CliError
from .fileio import read_at_most


_MAX_DIGITS = 4300      # Python's own limit for int(): its message names its internals


def _integer(text: str) -> int:
    if len(text.lstrip("-")) > _MAX_DIGITS:
        raise ValueError(f"a number of {len(text.lstrip('-'))} digits (at most {_MAX_DIGITS})")
    return int(text)


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(pairs)
    if len(out) < len(pairs):      # which one counts? (the last did, silently: a trial's "steps" twice)
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"the key {key[:40]!r} is given twice in one object")
            seen.add(key)
    return out


def loads(raw: Union[str, bytes], parse_constant: Optional[Callable[[str], Any]] = None) -> Any:
    """`json.loads`; nesting too deep for Python's recursive parser is a ValueError, as any other
    malformed JSON is, not a RecursionError; so is an integer of more digits than Python reads,
    and a key given twice in one object."""
    try:
        return json.loads(raw, parse_constant=parse_constant, parse_int=_integer, object_pairs_hook=_object)
    except RecursionError:
        raise ValueError("nested too deeply") from None


def load_file(path: str, limit: int, what: str) -> Any:
    """The JSON of an input file of at most `limit` bytes; CliError (one line) when it cannot be
    read, is larger (`what` names what it should have been) or is no JSON."""
    try:
        data = read_at_most(path, limit)
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise CliError(f"{path} is not {what}: {exc}") from None
    try:
        return loads(data)
    except UnicodeDecodeError as exc:   # (json guesses UTF-16 or -32 from zero bytes: its codec's words)
        raise CliError(f"{path} is not JSON: not text (UTF-8, UTF-16 or UTF-32) at byte {exc.start}") from None
    except ValueError as exc:    # also numbers of more digits than Python converts
        raise CliError(f"{path} is not JSON: {str(exc)[:120]}") from None
