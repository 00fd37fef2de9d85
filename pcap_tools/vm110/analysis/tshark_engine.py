"""The tshark engine: the capture read through the project's Lua dissector (dissector/vm110.lua)
with pyshark, into the same `Collected` as the fast engine.

Per packet it takes the dissector's fields (`vm110.<name>`, tests/vectors/README.md) and its
expert infos `vm110.expert.<reason>`; a packet with an expert for an illegal reason is illegal.
CRC `auto` dissects once per candidate variant and byte order (dissector preferences
`vm110.crc_variant`, `vm110.crc_byte_order`) when the default one leaves packets invalid. File-level
facts that tshark does not report (format, link types, a file cut short) come from the reader.
"""
from __future__ import annotations

import contextlib
import ipaddress
import os
import re
import shutil
import struct
import tempfile
from pathlib import Path
from typing import Iterator, Optional

from .. import constants as C
from ..capture.reader import CaptureReader, address
from ..crc import BYTE_ORDERS, DEFAULT_BYTE_ORDER, DEFAULT_VARIANT, VARIANTS
from ..errors import CliError
from ..plugin import PLUGIN_ENV, list_protocols, plugin_path
from .collect import RECORD, STATE, STATE_FIELDS, Collected
from .engine import crc_candidates
from .incremental import Analysis

REASONS = frozenset(p.value for p in C.Problem)
_EXPERT = "vm110.expert."
_HEADER = struct.Struct("<4sHHHHI")      # what the fast engine records: packet ID and header ...
_AUX = struct.Struct("<H")                 # ... then the command ID or VRPO packet number
_BATCH = 4096 * RECORD.size                # bytes of records fed to the analysis at a time


_CHECKED: set[tuple] = set()     # the tshark and plugin files, and tshark's folders, found fine


def _stat(path: Path) -> tuple:
    found = path.stat()
    return str(path.resolve()), found.st_mtime_ns, found.st_size, found.st_ino


def check_available() -> None:
    """CliError (exit 2) when tshark or the dissector is missing, or the dissector does not load.

    Checked once per process for the same tshark, plugin file and personal folders (a run of
    several captures ran tshark once more for each, 0.3 s)."""
    tshark = shutil.which("tshark")
    if tshark is None:
        raise CliError("--engine tshark needs tshark (Wireshark's command-line tool) on the PATH")
    plugin = plugin_path()
    if not plugin.is_file():
        raise CliError(f"--engine tshark needs the Lua dissector; not found at {plugin} (set {PLUGIN_ENV})")
    key = (_stat(Path(tshark)), _stat(plugin), os.environ.get("HOME"), os.environ.get("XDG_CONFIG_HOME"))
    if key in _CHECKED:
        return
    loaded, done = list_protocols("tshark", plugin)
    if not loaded:
        lines = [ln for ln in done.stderr.splitlines() if "dangerous" not in ln]
        raise CliError(f"the Lua dissector {plugin} did not load in tshark: {(lines or ['no vm110 protocol'])[0]}")
    # A plugin in the user's plugin folder loads first, and this one stands aside (it says so on
    # tshark's standard error, which the analysis does not show): an older copy would decode.
    first = _LOADED_ALREADY.search(done.stderr)
    if first is not None and not _same_file(Path(first[1]), plugin):
        raise CliError(f"--engine tshark would decode with the plugin tshark loads first, {first[1]} (version "
                       f"{first[2]}), not {plugin}: they differ; `vm110 wireshark install` updates it (or remove it)")
    _CHECKED.add(key)


@contextlib.contextmanager
def _default_configuration() -> Iterator[None]:
    """tshark (started meanwhile: it takes the environment then) with an empty personal
    configuration: a protocol the user disabled in Wireshark (Enabled Protocols: vm110, or IP), a
    heuristic switched off or a Decode As entry of theirs changed what it decoded (no EG-Link
    packet at all, said as no_eglink), beyond what the `-o` options pin."""
    before = os.environ.get(_CONFIG_DIR)
    with tempfile.TemporaryDirectory(prefix="vm110-wireshark-") as empty:
        os.environ[_CONFIG_DIR] = empty
        try:
            yield
        finally:
            if before is None:
                del os.environ[_CONFIG_DIR]
            else:
                os.environ[_CONFIG_DIR] = before


_CONFIG_DIR = "WIRESHARK_CONFIG_DIR"        # (Linux: not the plugin folder, which check_available checks)
_LOADED_ALREADY = re.compile(r"the VM-110 dissector is loaded already from (.+) \(version ([^)]*)\)")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.read_bytes() == b.read_bytes()
    except OSError:
        return False


def _int(value: str) -> int:
    return int(value, 0)


_NSEC = re.compile(r"\(?(\d+)")


def _epoch(text: str, pcap: bool) -> float:
    """A frame's time from tshark's frame.time_epoch (geninfo's timestamp, pyshark's
    sniff_timestamp, wraps at 2^31 seconds). A decimal fraction has 9 digits at most. A pcap
    record's fraction of a second or more (damage) leaves wiretap's nanoseconds out of range, and
    tshark prints them as they are: "S.1250000000" (4.0), "S.(1250000000 nanosec" (4.4 and later),
    and a negative one as "-S.326043208": the minus is the fraction's (a pcap's seconds are
    unsigned), the time S less those nanoseconds. (Self-fuzz and trials found a ValueError, a
    second lost and a time wrapped at 2^31 s.)"""
    sec, _, frac = text.partition(".")
    negative = sec.startswith("-")
    if not negative and frac.isdigit() and len(frac) <= 9:
        return float(text)
    digits = _NSEC.match(frac)
    if digits is None:
        return float(text)
    nsec = int(digits.group(1)) if frac.startswith("(") or len(digits.group(1)) > 9 else \
        int(digits.group(1).ljust(9, "0"))
    if negative and pcap:
        return int(sec[1:]) - nsec * 1e-9
    return int(sec) + (-nsec if negative and int(sec) == 0 else nsec) * 1e-9


def _empty_on(udp, ports: frozenset) -> bool:
    """An empty datagram on one of `ports`. (get_field: a UDP header cut short lacks its length;
    self-fuzz found the AttributeError.)"""
    length, sport, dport = (udp.get_field(name) for name in ("length", "srcport", "dstport"))
    return length == "8" and sport is not None and dport is not None and not ports.isdisjoint((int(sport), int(dport)))


def _raw_type(layer) -> str:
    """The packet ID's bytes as the fast engine shows them (Latin-1): tshark's text drops or
    escapes bytes that are no UTF-8, differently by version ("VPO", "V\\x12PO", "aaaaaaaa")."""
    field = layer.get_field("type")
    raw = getattr(field, "raw_value", None) if field is not None else None
    try:
        return bytes.fromhex(raw).decode("latin-1") if raw else ""
    except ValueError:
        return str(field)


def _fragment(pkt, layers: set) -> bool:
    """An IPv4 or IPv6 fragment, as the reader counts them (an IPv6 atomic fragment, offset 0 and no
    more, is a whole datagram). get_field: a damaged IP header may lack a field (self-fuzz found
    the AttributeError)."""
    if "ip" in layers and (pkt.ip.get_field("flags_mf") in ("1", "True")
                           or pkt.ip.get_field("frag_offset") not in (None, "0")):
        return True
    return "ipv6" in layers and (pkt.ipv6.get_field("fraghdr_more") in ("1", "True")
                                 or pkt.ipv6.get_field("fraghdr_offset") not in (None, "0"))


def _fragment_frames(pkt, layers: set) -> Optional[int]:
    """How many fragment frames made the datagram Wireshark reassembled at this one (itself
    included); None when it reassembled none here (a first fragment it could not take, cut short
    by the snaplen, it dissects as it is)."""
    count = pkt.ip.get_field("fragment_count") if "ip" in layers else None
    if count is None and "ipv6" in layers:
        count = pkt.ipv6.get_field("fragment_count")
    return int(count) if count is not None else None


class TsharkEngine:
    def __init__(self, port: int = C.INPUT_PORT, crc: str = "auto", crc_order: str = "auto") -> None:
        self.port, self.crc, self.crc_order = port, crc, crc_order
        self.stopped: Optional[str] = None     # tshark's last error line when it stopped early

    def _params(self, variant: str, order: str) -> list[str]:
        # IP fragments reassembled, IPv4 and IPv6, as Wireshark does by default and the fast engine
        # does too (capture/reassembly.py). The heuristic first: EG-Link on a port Wireshark gives
        # another protocol (7000: AFS) is found, as the fast engine finds it.
        return ["-X", f"lua_script:{plugin_path()}", "-o", "ip.defragment:TRUE", "-o", "ipv6.defragment:TRUE",
                "-o", "udp.try_heuristic_first:TRUE",
                "-o", f"vm110.input_port:{self.port}",
                "-o", f"vm110.crc_variant:{variant}", "-o", f"vm110.crc_byte_order:{order}",
                # (the user's Wireshark preferences would otherwise decide: no CRC checked, no other ports)
                "-o", "vm110.check_crc:TRUE", "-o", "vm110.heuristic:TRUE"]

    def _packets(self, path: str, variant: str, order: str) -> Iterator:
        from .tshark_packets import TsharkStopped, packets     # pyshark: the CLI starts without it
        try:
            with _default_configuration():
                yield from packets(path, self._params(variant, order))
        except TsharkStopped as stop:
            self.stopped = str(stop)

    def collect(self, path: str, opt) -> Collected:
        """Read the capture through tshark, feeding its legal packets to an `Analysis` with `opt`."""
        check_available()
        with CaptureReader(path) as reader:    # clean errors for unreadable files, and file facts
            for _ in reader.batches():
                pass
        if reader.damage is None:
            return self._collect(path, path, reader, opt)
        # tshark gets the intact part only: the same frames the reader took, and no crash.
        with tempfile.TemporaryDirectory(prefix="vm110-") as tmp:
            intact = os.path.join(tmp, "intact" + os.path.splitext(path)[1])
            with open(path, "rb") as src, open(intact, "wb") as dst:
                left = reader.damage
                while left > 0:
                    block = src.read(min(left, 1 << 20))
                    if not block:
                        break
                    dst.write(block)
                    left -= len(block)
            got = self._collect(intact, path, reader, opt)
        got.problem, got.damage = reader.problem, reader.damage
        return got

    def _collect(self, path: str, name: str, reader: CaptureReader, opt) -> Collected:
        """Read `path` through tshark; report it as `name`."""
        variants = VARIANTS if self.crc == "auto" else (self.crc,)
        orders = BYTE_ORDERS if self.crc_order == "auto" else (self.crc_order,)
        candidates = [(v, o) for v in variants for o in orders]
        first = (DEFAULT_VARIANT, DEFAULT_BYTE_ORDER) if (DEFAULT_VARIANT, DEFAULT_BYTE_ORDER) in candidates \
            else candidates[0]
        got = self._pass(path, name, reader, opt, *first)
        if len(candidates) > 1 and got.crc_checked > got.crc_counts[first]:
            # Some packet failed the default: count what each candidate validates in one Python
            # pass over the datagrams (not one tshark run per candidate: the self-fuzzer saw 8).
            counts = crc_candidates(path, (self.port, self.port + C.OUTPUT_PORT_OFFSET))
            best = max(candidates, key=lambda c: (counts[c], -candidates.index(c)))
            if best != first:
                got = self._pass(path, name, reader, opt, *best)
            for c in candidates:
                got.crc_counts[c] = counts[c]
        return got

    def _pass(self, path: str, name: str, reader: CaptureReader, opt, variant: str, order: str) -> Collected:
        got = Collected(path=name, engine="tshark", analysis=Analysis(opt), format=reader.format,
                        link_types=sorted(reader.link_types),
                        ports=(self.port, self.port + C.OUTPUT_PORT_OFFSET), crc_variant=variant,
                        crc_order=order, crc_auto=self.crc == "auto" or self.crc_order == "auto",
                        problem=reader.problem, dropped=reader.drops.report(),
                        first_ts=reader.first_ts, last_ts=reader.last_ts,
                        earliest_ts=reader.earliest, latest_ts=reader.latest)
        frames, ports, ts, pcap = 0, frozenset(got.ports), 0.0, reader.format == "pcap"
        for pkt in self._packets(path, variant, order):
            frames += 1
            # A packet without a time (a pcapng simple packet block: no frame.time_epoch) takes the
            # last packet's, as the reader gives it; records that are no packets (no
            # encapsulation) set none.
            when = pkt.frame_info.get_field("time_epoch")
            if when is not None and pkt.frame_info.get_field("encap_type") is not None:
                ts = _epoch(when, pcap)
            layers = {layer.layer_name for layer in pkt.layers}
            fragment = _fragment(pkt, layers)
            whole = _fragment_frames(pkt, layers) if fragment and "udp" in layers else None
            if whole is not None:    # a datagram reassembled here: its other fragments are analysed
                got.fragments -= whole - 1
            elif fragment or "udp" not in layers:
                got.non_udp += 1
                got.fragments += fragment
                continue
            got.udp += 1
            if "vm110" in layers:
                self._eglink(got, pkt, layers, ts)
            elif _empty_on(pkt.udp, ports):
                self._empty(got, pkt, layers, ts)
            else:
                got.other_udp += 1
            if len(got.records) >= _BATCH:
                got.flush()
        got.flush()
        got.frames = frames
        if self.stopped is not None and got.problem is None:
            got.problem = f"tshark stopped reading after frame {frames}: {self.stopped}"
        self.stopped = None
        got.crc_counts[(variant, order)] = got.crc_checked - got.illegal_reasons[C.Problem.BAD_CRC.value]
        return got

    def _empty(self, got: Collected, pkt, layers: set, ts: float) -> None:
        """An empty datagram on an EG-Link port, to which Wireshark gives no dissector: a truncated
        EG-Link packet, as the fast engine has it."""
        got.eglink += 1
        src = ipaddress.ip_address(pkt.ip.src if "ip" in layers else pkt.ipv6.src).packed
        got.add_illegal(int(pkt.frame_info.number), ts, address(src, int(pkt.udp.srcport)),
                        "", [C.Problem.TRUNCATED.value])

    def _eglink(self, got: Collected, pkt, layers: set, ts: float) -> None:
        f = pkt.vm110._all_fields
        got.eglink += 1
        frame = int(pkt.frame_info.number)
        src_text = pkt.ip.src if "ip" in layers else pkt.ipv6.src
        src = ipaddress.ip_address(src_text).packed
        sport = int(pkt.udp.srcport)
        reasons = sorted(k[len(_EXPERT):] for k in f if k.startswith(_EXPERT) and k[len(_EXPERT):] in REASONS)
        if "vm110.crc.status" in f:
            got.crc_checked += 1
        # (the dissector names a datagram the capture cut short truncated, and nothing else)
        if reasons == [C.Problem.TRUNCATED.value] and int(pkt.frame_info.cap_len) < int(pkt.frame_info.len):
            got.snap_truncated += 1
        if reasons:
            got.add_illegal(frame, ts, address(src, sport), _raw_type(pkt.vm110), reasons)
            return
        ptype = f["vm110.type"]
        if ptype == C.PacketType.VRPI.value:
            body = STATE.pack(*(_int(f[f"vm110.{name}"]) for name in STATE_FIELDS))
        else:
            body = _AUX.pack(_int(f.get("vm110.command_id", f.get("vm110.packet_number", "0"))))
        head = _HEADER.pack(ptype.encode(), _int(f["vm110.revision"]), _int(f["vm110.origin"]),
                            _int(f["vm110.serial"]), _int(f["vm110.size"]), _int(f["vm110.spare"]))
        got.add_legal(ts, frame, src, sport, head + body)
