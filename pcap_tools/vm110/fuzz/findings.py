"""Findings on disk: one JSON and one pcap per finding, and `findings.json` for the run."""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..capture.writer import PcapWriter, UdpFlow
from ..errors import CliError
from .oracles import ORACLES

SCHEMA = 1


@dataclass
class Finding:
    oracle: str
    seed: int
    case_index: int
    family: str
    mutation: str                 # what the case did
    detail: str                   # what the oracle saw
    packet_hex: str               # the minimised packet (or the case's packet when it could not be)
    original_hex: str             # the packet as the case sent it
    valid_hex: str                # its valid twin: the minimised packet differs from this
    differences: int              # bytes that differ between packet_hex and valid_hex
    minimised: bool
    steps: list[dict[str, Any]]   # the case for replay: [{"hex", "valid_hex", "delay_ms", "expect_ack"}]
    pause_vrpi_ms: float = 0.0
    withhold_vrai_ms: float = 0.0
    stream: Optional[dict[str, Any]] = None
    settle_ms: float = 0.0
    output_hex: Optional[str] = None     # the controller packet judged (malformed_output)
    target: str = ""
    listen: str = ""
    group: Optional[str] = None
    target_cmd: Optional[str] = None
    time: float = field(default_factory=time.time)
    pcap: str = ""
    schema: int = SCHEMA

    def name(self, number: int) -> str:
        return f"finding-{number:03d}-{self.oracle}"


def write_finding(out: Path, number: int, finding: Finding,
                  traffic: list[tuple[float, bool, bytes, tuple[str, int]]], local: tuple[str, int]) -> Path:
    """Write `<name>.pcap` and `<name>.json`; returns the JSON path."""
    base = finding.name(number)
    finding.pcap = f"{base}.pcap"
    write_pcap(out / finding.pcap, traffic, local)
    path = out / f"{base}.json"
    path.write_text(json.dumps(asdict(finding), indent=2) + "\n")
    return path


def write_pcap(path: Path, traffic: list[tuple[float, bool, bytes, tuple[str, int]]], local: tuple[str, int]) -> None:
    """The traffic as a tap on the fuzzer's host would see it (Ethernet/IPv4/UDP)."""
    flows: dict[tuple[Any, ...], UdpFlow] = {}
    with path.open("wb") as stream, PcapWriter(stream) as writer:
        for t, outbound, data, peer in traffic:
            src, dst = (local, peer) if outbound else (peer, local)
            key = (src, dst)
            if key not in flows:
                flows[key] = UdpFlow(src[0], src[1], dst[0], dst[1])
            writer.write(int(t * 1_000_000), flows[key].frame(data))


def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    path = out / "findings.json"
    path.write_text(json.dumps(summary, indent=2) + "\n")
    return path


def load_finding(path: str) -> Finding:
    """A finding JSON written by `write_finding`; CliError when it is not one."""
    try:
        raw = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise CliError(f"{path} is not JSON: {exc}") from None
    if not isinstance(raw, dict) or raw.get("oracle") not in ORACLES or not isinstance(raw.get("steps"), list):
        raise CliError(f"{path} is not a vm110 fuzz finding")
    try:
        finding = Finding(**{k: v for k, v in raw.items() if k in Finding.__dataclass_fields__})
        for step in finding.steps:
            bytes.fromhex(step["hex"]), bytes.fromhex(step["valid_hex"]), float(step["delay_ms"])
        bytes.fromhex(finding.packet_hex)
    except (TypeError, KeyError, ValueError) as exc:
        raise CliError(f"{path} is not a valid vm110 fuzz finding: {exc}") from None
    return finding
