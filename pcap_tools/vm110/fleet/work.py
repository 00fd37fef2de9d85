"""The per-capture function every engine maps over the captures: analyse one capture with the
code and options of `vm110 analyze`, turn its report into rows and write them as the capture's
Parquet parts. It runs wherever the engine puts it (this process, a worker process, a Dask
worker) and returns a small summary; the driver only records it in the manifest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator, Optional

from .. import constants as C
from ..analysis import Options, analyze
from ..analysis.engine import looks_like_eglink
from ..capture.reader import CaptureReader, address
from ..decode import decode
from ..errors import CliError
from .dataset import COMMIT_TABLE, Dataset
from .sources import Source
from .tables import arrow_table, capture_rows, error_rows, table_schema

PACKET_BATCH = 65536        # rows of the packets table converted at a time


@dataclass(frozen=True)
class Settings:
    """What every capture of a build is analysed with (the options of `vm110 analyze`)."""

    dataset: str
    port: int = C.INPUT_PORT
    crc: str = "auto"
    crc_order: str = "auto"
    options: Options = field(default_factory=Options)
    packets: bool = False


@dataclass(frozen=True)
class Done:
    """What the driver records of one capture."""

    capture_id: str
    path: str
    size: Optional[int]
    sha256: Optional[str]
    status: str                  # ok, damaged, unreadable
    parts: tuple[str, ...]
    message: Optional[str] = None
    meta: tuple = ()


def build_one(source: Source, settings: Settings) -> Done:
    """Analyse `source` and write its parts; a capture that cannot be read gives error rows (and
    parts) like any other, never an exception. Messages leave out the path: rows have it in `file`."""
    meta = dict(source.meta)
    cid = source.capture_id
    report, message, status = _analyse(source, settings)
    if report is None:
        tables = error_rows(source.path, cid, source.size, source.sha256, message or "")
    else:
        tables = capture_rows(report, cid, source.size, source.sha256)
    dataset = Dataset(settings.dataset)
    parts = []
    if settings.packets and report is not None:
        packets = packet_rows(source.path, cid, settings.port, report["crc"]["variant"], report["crc"]["byte_order"])
        try:
            parts.append(dataset.write_part("packets", cid, table_schema("packets", meta),
                                            (arrow_table("packets", batch, meta) for batch in _batches(packets))))
        except CliError:
            raise                       # the dataset cannot be written: that ends the build
        except Exception as exc:        # the capture changed or broke since its analysis
            tables["errors"].append({"capture_id": cid, "file": source.path, "kind": "packets",
                                     "message": f"packets: {type(exc).__name__}: {_unnamed(str(exc), source.path)}",
                                     "file_offset": None})
    parts += [dataset.write_part(table, cid, table_schema(table, meta), [arrow_table(table, tables[table], meta)])
              for table in sorted(tables, key=lambda t: t == COMMIT_TABLE)      # the commit part last
              if tables[table] or table == COMMIT_TABLE]
    return Done(cid, source.path, source.size, source.sha256, status, tuple(parts), message, source.meta)


def _analyse(source: Source, settings: Settings) -> tuple[Optional[dict], Optional[str], str]:
    """(the report or None, message, status): `unreadable` with the reason, never an exception."""
    if source.problem is not None:
        return None, source.problem, "unreadable"       # never opened (a FIFO would wait for a writer)
    try:
        report = analyze(source.path, "fast", settings.port, settings.crc, settings.crc_order, settings.options)
    except CliError as exc:
        return None, _unnamed(str(exc), source.path), "unreadable"
    except MemoryError:
        return None, "out of memory", "unreadable"
    except Exception as exc:     # a broken file must give a row and one line, never end the build
        return None, f"cannot analyse: {type(exc).__name__}: {_unnamed(str(exc), source.path)}", "unreadable"
    report["capture"]["file"] = source.path
    problem = report["capture"]["problem"]
    return report, problem, "ok" if problem is None else "damaged"


def _unnamed(message: str, path: str) -> str:
    """`message` without `path` (`PATH: reason`, `cannot read PATH: reason`)."""
    if message.startswith(f"{path}: "):
        return message[len(path) + 2:]
    return message.replace(f" {path}:", ":").replace(path, "the file")


def _batches(rows: Iterator[dict]) -> Iterator[list[dict]]:
    batch = []
    for row in rows:
        batch.append(row)
        if len(batch) == PACKET_BATCH:
            yield batch
            batch = []
    if batch:
        yield batch


def packet_rows(path: str, cid: str, port: int, variant: str, order: str) -> Iterator[dict]:
    """One compact row per EG-Link datagram (on the two ports, or recognised by its header on
    another), decoded with the CRC the analysis used: for drill-down next to the findings."""
    ports = (port, port + C.OUTPUT_PORT_OFFSET)
    for ts, src, sport, dport, payload, frame in CaptureReader(path):
        if payload is None or (sport not in ports and dport not in ports and not looks_like_eglink(payload)):
            continue
        f = decode(payload, variant, order)
        time = round(ts * 1_000_000) if math.isfinite(ts) else None
        yield {"capture_id": cid, "file": path, "frame": frame, "time": time,
               "src": address(src, sport), "sport": sport, "dport": dport, "type": f.get("type") or None,
               "origin": f.get("origin"), "serial": f.get("serial"), "size": f.get("size"),
               "command_id": f.get("command_id"), "legal": not f["problems"],
               "problems": ",".join(f["problems"]) or None}

