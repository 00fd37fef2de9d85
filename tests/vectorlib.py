"""Loading the shared vectors (tests/vectors/*.json) for every implementation's tests."""
from __future__ import annotations

import json
import pathlib
from typing import Any

VECTOR_DIR = pathlib.Path(__file__).resolve().parent / "vectors"
BYTE_FIELDS = frozenset({"vrpi_spare", "command_data", "periodic_data"})


def load_vectors() -> list[dict[str, Any]]:
    vectors = []
    for path in sorted(VECTOR_DIR.glob("*.json")):
        vectors.extend(json.loads(path.read_text())["vectors"])
    return vectors


def packet_bytes(vector: dict[str, Any]) -> bytes:
    return bytes.fromhex(vector["hex"])


def expected_fields(vector: dict[str, Any]) -> dict[str, Any]:
    """The vector's fields with byte fields as bytes, as `vm110.decode` returns them."""
    return {k: bytes.fromhex(v) if k in BYTE_FIELDS else v for k, v in vector["fields"].items()}


def vector_ids(vectors: list[dict[str, Any]]) -> list[str]:
    return [v["name"] for v in vectors]
