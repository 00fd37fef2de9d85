"""The analysis report's JSON Schema (docs/report.schema.json) as the tests apply it.

tests/conftest.py holds every report the suite makes to it: those `vm110.analysis.analyze` returns
in-process, and every JSON report `vm110 analyze --json` writes under a test's tmp_path. A test
that reads a report from standard output calls `check` itself.
"""
from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any, Callable

from jsonschema import Draft202012Validator

REPO = Path(__file__).resolve().parents[1]
SCHEMA_PATH = REPO / "docs" / "report.schema.json"
SCHEMA = json.loads(SCHEMA_PATH.read_text())
SHOWN = 10


def _inlined(node: Any, defs: dict, depth: int = 0) -> Any:
    """The schema with each `$ref` to its `$defs` replaced by the definition (the schema has no
    recursion): the same verdicts, in half the time (a ref resolved at every use took half of it)."""
    if depth > 64:
        raise ValueError("a recursive $ref: cannot be inlined")
    if isinstance(node, list):
        return [_inlined(item, defs, depth) for item in node]
    if not isinstance(node, dict):
        return node
    out = {key: _inlined(value, defs, depth) for key, value in node.items() if key not in ("$ref", "$defs")}
    ref = node.get("$ref")
    if ref is None:
        return out
    assert ref.startswith("#/$defs/"), ref
    target = _inlined(defs[ref[len("#/$defs/"):]], defs, depth + 1)
    return {"allOf": [target], **out} if out else target      # (siblings of a $ref apply beside it)


VALIDATOR = Draft202012Validator(_inlined(SCHEMA, SCHEMA.get("$defs", {})))
_VALID: set[bytes] = set()        # digests of reports found valid: the suite makes many alike


def problems(document: Any) -> list[str]:
    """Where `document` breaks the schema, as it would be written (tuples as lists; NaN refused)."""
    text = json.dumps(document, allow_nan=False, sort_keys=True)
    digest = hashlib.sha256(text.encode()).digest()
    if digest in _VALID:
        return []
    errors = sorted(VALIDATOR.iter_errors(json.loads(text)), key=lambda e: list(map(str, e.absolute_path)))
    if not errors:
        _VALID.add(digest)
    return [f"{e.json_path}: {e.message[:300]}" for e in errors]


def check(document: Any, what: str = "report") -> None:
    found = problems(document)
    shown = "\n  ".join(found[:SHOWN])
    assert not found, f"{what} does not match {SCHEMA_PATH.name} ({len(found)} errors):\n  {shown}"


def validating(analyze: Callable[..., dict]) -> Callable[..., dict]:
    """`analyze` whose every report is checked against the schema."""
    @functools.wraps(analyze)
    def checked(*args: Any, **kwargs: Any) -> dict:
        report = analyze(*args, **kwargs)
        check(report)
        return report
    return checked


def is_report(document: Any) -> bool:
    """A report of `vm110 analyze --json` (one capture's, or several), not other JSON (ground truth,
    decode output, fuzz cases)."""
    return isinstance(document, dict) and "schema_version" in document and ("tool" in document or "reports" in document)


def check_written(folder: Path) -> int:
    """Check every JSON report under `folder`; returns how many there were."""
    seen = 0
    for path in sorted(folder.rglob("*.json")):
        if not path.is_file():
            continue                          # a FIFO or a folder a test made on purpose: never opened
        try:
            document = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError):
            continue                          # not JSON (or half a file, or a nesting, a test made on purpose)
        if is_report(document):
            check(document, str(path))
            seen += 1
    return seen
