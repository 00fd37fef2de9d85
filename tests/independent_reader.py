"""A reader of EG-Link captures written from TS-0006 and interpretation.md alone, to check the
synthesis ground truth against: it imports nothing of vm110 (its own pcap/pcapng parsing, its own
framing and counting; the CRC is the textbook one of reference_crc), so that the simulators, the
truth and the analysis agreeing with each other does not make it agree too.

It reads the captures `vm110 synth` writes (Ethernet or raw IPv4, no fragments) and gives the
figures of the truth file (`read`), under the reading the synthesis was given.
"""
from __future__ import annotations

import struct
from collections import defaultdict
from typing import Any, Iterator, Optional

from reference_crc import reference_crc

# Fixed payload sizes (interpretation.md, "Framing"); VRPO at least its packet number.
MIN_SIZE = {b"VRPI": 46, b"VRCI": 22, b"VRCO": 22, b"VRAO": 2, b"VRAI": 2, b"VRPO": 2}
# The order in which a sender's per-type counters are listed (the truth's convention).
TYPE_ORDER = ("VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO")
MODULUS = 1 << 16
DUP_WINDOW = 1.0          # s: duplicate window, also the window of a late packet
CONFIRM = 4               # a restart is confirmed by serial s + 1 ... s + 4
NEW_PORT_SILENCE = 0.25   # s
FAIL = 2.0                # s: VRCI fail limit, VRCO give-up, command ID reuse gap
WATCHDOG = {"VRPI": 0.5, "VRPO": 2.0}
BURST_GAP = 0.020
FULL = 488


def records(path: str) -> Iterator[tuple[int, int, bytes]]:
    """(timestamp in µs, link type, frame) of every record of a pcap or pcapng file."""
    with open(path, "rb") as f:
        data = f.read()
    magic = data[:4]
    if magic in (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d"):
        e = "<" if magic[0] in (0xD4, 0x4D) else ">"
        nano = magic in (b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
        link = struct.unpack(e + "I", data[20:24])[0] & 0xFFFF
        off = 24
        while off + 16 <= len(data):
            sec, frac, incl, _ = struct.unpack(e + "IIII", data[off:off + 16])
            yield sec * 1_000_000 + (frac // 1000 if nano else frac), link, data[off + 16:off + 16 + incl]
            off += 16 + incl
        return
    assert magic == b"\x0a\x0d\x0d\x0a", f"{path}: not pcap or pcapng"
    off, e = 0, "<"
    interfaces: list[tuple[int, int]] = []      # (link type, ticks per second)
    while off + 12 <= len(data):
        if data[off:off + 4] == b"\x0a\x0d\x0d\x0a":           # section header: byte order
            e = "<" if data[off + 8:off + 12] == b"\x4d\x3c\x2b\x1a" else ">"
            interfaces = []
        btype, blen = struct.unpack(e + "II", data[off:off + 8])
        body = data[off + 8:off + blen - 4]
        if btype == 1:              # interface description: link type, if_tsresol
            resolution, o = 6, 8
            while o + 4 <= len(body):
                code, length = struct.unpack(e + "HH", body[o:o + 4])
                if code == 0:
                    break
                if code == 9:
                    resolution = body[o + 4]
                o += 4 + ((length + 3) & ~3)
            assert not resolution & 0x80, "binary if_tsresol not expected"
            interfaces.append((struct.unpack(e + "H", body[:2])[0], 10 ** resolution))
        elif btype == 6:            # enhanced packet
            iface, high, low, captured = struct.unpack(e + "IIII", body[:16])
            link, per_second = interfaces[iface]
            yield ((high << 32) | low) * 1_000_000 // per_second, link, body[20:20 + captured]
        off += blen


def udp_of(link: int, frame: bytes) -> Optional[tuple[str, int, bytes]]:
    """(source IP, source port, UDP payload cut by the UDP length), or None when not IPv4/UDP."""
    if link == 1:               # Ethernet, VLAN tags skipped
        ethertype, ip = struct.unpack(">H", frame[12:14])[0], frame[14:]
        while ethertype == 0x8100:
            ethertype, ip = struct.unpack(">H", ip[2:4])[0], ip[4:]
        if ethertype != 0x0800:
            return None
    else:
        assert link in (101, 228), f"link type {link} not expected"
        ip = frame
    if ip[0] >> 4 != 4 or ip[9] != 17:
        return None
    udp = ip[(ip[0] & 15) * 4:struct.unpack(">H", ip[2:4])[0]]
    sport, _, length = struct.unpack(">HHH", udp[:6])
    return ".".join(map(str, ip[12:16])), sport, udp[8:length]


def reasons_of(packet: bytes, crc: str, order: str) -> list[str]:
    """Every reason of interpretation.md's "Illegal packets" that holds for an EG-Link packet."""
    reasons = [] if packet[:4] in MIN_SIZE else ["unknown_id"]
    if len(packet) < 20:
        return [*reasons, "truncated"]
    revision, size = struct.unpack("<H", packet[4:6])[0], struct.unpack("<H", packet[10:12])[0]
    if revision:
        reasons.append("revision")
    if size > 492:
        reasons.append("size_too_large")
    if len(packet) != 20 + size:
        reasons.append("size_mismatch")
    if packet[:4] in MIN_SIZE and size < MIN_SIZE[packet[:4]]:
        reasons.append("truncated")
    end = 16 + size if 20 + size <= len(packet) else len(packet) - 4     # the CRC after `size`
    if int.from_bytes(packet[end:end + 4], order) != reference_crc(packet[:end], crc):
        reasons.append("bad_crc")
    return reasons


class Counter:
    """One serial counter (interpretation.md, "Serial numbers" and "Sender restarts")."""

    def __init__(self) -> None:
        self.h: Optional[int] = None
        self.seen: dict[int, float] = {}                  # serial -> when last received
        self.missing: dict[int, tuple[float, dict]] = {}  # serial -> (when its gap opened, the gap)
        self.lost_before: list[int] = []                  # still missing at a restart: lost for good
        self.times: list[float] = []                      # its packets since its start or restart
        self.life = 0.0
        self.previous = 0.0
        self.pending: Optional[tuple[int, float, int, int]] = None   # restart candidate
        self.received = self.wraps = 0
        self.duplicates: list[int] = []
        self.out_of_order: list[int] = []
        self.gaps: list[dict] = []
        self.restarts: list[dict] = []

    def lost(self) -> list[int]:
        return self.lost_before + list(self.missing)

    def _reset(self, s: int, t: float) -> None:
        self.lost_before += list(self.missing)
        self.h, self.seen, self.missing, self.life, self.times = s, {s: t}, {}, t, []

    def feed(self, s: int, t: float, frame: int) -> tuple[bool, Optional[float]]:
        """Classify serial `s`: (a duplicate?, the time of the restart it confirms, if any)."""
        self.received += 1
        restart = None
        if self.pending is not None:
            ps, pt, pframe, ph = self.pending
            if s == ps and t - pt < DUP_WINDOW:        # a copy of the candidate: wait on
                self.duplicates.append(s)
                self.previous = t
                return True, None
            self.pending = None
            if 1 <= (s - ps) % MODULUS <= CONFIRM:
                self.restarts.append({"time": round(pt, 6), "frame": pframe, "from": ph, "to": ps})
                self._reset(ps, pt)
                self.times.append(pt)
                restart = pt
            else:
                self.out_of_order.append(ps)
        duplicate = self._classify(s, t, frame)
        self.previous = t
        self.times.append(t)
        return duplicate, restart

    def _classify(self, s: int, t: float, frame: int) -> bool:
        if self.h is None:
            self._reset(s, t)
            return False
        if s in self.seen and t - self.seen[s] < DUP_WINDOW:
            self.duplicates.append(s)
            return True
        d = (s - self.h) % MODULUS
        if d == 1:
            self._advance(s, t)
        elif s in self.missing and t - self.missing[s][0] < DUP_WINDOW:
            gap = self.missing.pop(s)[1]
            gap["late"] = gap.get("late", 0) + 1
            self.out_of_order.append(s)
            self.seen[s] = t
        elif 1 < d < MODULUS // 2 and d - 1 <= 64 + 4 * max(self._rate(t), 20) * (t - self.previous):
            gap = {"after": self.h, "count": d - 1, "time": round(t, 6), "frame": frame}
            self.gaps.append(gap)
            for k in range(1, d):
                self.missing[(self.h + k) % MODULUS] = (t, gap)
            self._advance(s, t)
        else:
            self.pending = (s, t, frame, self.h)
        return False

    def _rate(self, t: float) -> float:
        span = min(10.0, t - self.life)
        return sum(1 for x in self.times if x >= t - 10.0) / span if span > 0 else 0.0

    def _advance(self, s: int, t: float) -> None:
        assert self.h is not None
        self.wraps += s < self.h
        self.h = s
        self.seen[s] = t

    def finish(self) -> None:
        if self.pending is not None:
            self.out_of_order.append(self.pending[0])
            self.pending = None


def read(path: str, crc: str = "mpeg2", order: str = "little", scope: str = "sender",
         vrpo_start: int = 0) -> dict[str, Any]:
    """The truth file's figures (all but `schema_version`) for the capture at `path`."""
    packets, by_reason = [], defaultdict(int)
    count = eglink = bad_crc = illegal = 0
    first = last = None
    for frame, (ts, link, data) in enumerate(records(path), 1):
        count += 1
        first = ts if first is None else min(first, ts)
        last = ts if last is None else max(last, ts)
        udp = udp_of(link, data)
        if udp is None or udp[2][:2] != b"VR":
            continue
        eglink += 1
        payload = udp[2]
        reasons = reasons_of(payload, crc, order)
        bad_crc += "bad_crc" in reasons
        if reasons:
            illegal += 1
            for reason in reasons:
                by_reason[reason] += 1
            continue
        origin, serial, size = struct.unpack("<HHH", payload[6:12])
        direction = "Input" if payload[3:4] == b"I" else "Output"
        packets.append({"frame": frame, "t": ts / 1e6, "type": payload[:4].decode(), "direction": direction,
                        "origin": origin, "ip": udp[0], "port": udp[1], "serial": serial,
                        "sender": f"{direction} {udp[0]}:{udp[1]} origin 0x{origin:04x}",
                        "payload": payload[16:16 + size]})
    end = None if last is None else last / 1e6
    span = None if first is None or last is None else (first / 1e6, (last - first) / 1e6)
    senders, counters, taken_over, restarts = _serials(packets, scope)
    accepted = [p for p in packets if not p["duplicate"]]
    return {
        "capture": {"packets": count, "eglink_packets": eglink,
                    "first_time": span and round(span[0], 6), "last_time": None if end is None else round(end, 6),
                    "duration_s": round(span[1], 6) if span else 0.0},
        "crc": {"variant": crc, "byte_order": order, "valid": eglink - bad_crc, "invalid": bad_crc},
        "illegal": {"total": illegal, "by_reason": dict(sorted(by_reason.items()))},
        "senders": [_sender_report(senders[sid], counters, scope) for sid in sorted(senders)],
        "periodic": _periodic(accepted, taken_over, end),
        "commands": {kind: _commands(accepted, kind, ack, restarts, end)
                     for kind, ack in (("VRCI", "VRAO"), ("VRCO", "VRAI"))},
        "vrpo_bursts": _bursts(accepted, vrpo_start),
    }


def _serials(packets: list[dict], scope: str) -> tuple[dict, dict, dict, dict]:
    """Marks each packet a duplicate or not; returns the senders, the counters by (sender, type or
    None), the new-port takeovers (new sender -> old) and each sender's restart times."""
    senders: dict[str, dict] = {}
    counters: dict[tuple[str, Optional[str]], Counter] = {}
    taken_over: dict[str, str] = {}
    restarts: dict[str, list[float]] = defaultdict(list)
    for p in packets:
        sender = senders.get(p["sender"])
        if sender is None:
            sender = senders[p["sender"]] = {"id": p["sender"], "p": p, "by_type": defaultdict(int),
                                             "last": None, "link": None}
            earlier = [s for s in senders.values() if s is not sender and s["p"]["direction"] == p["direction"]
                       and s["p"]["origin"] == p["origin"] and s["p"]["ip"] == p["ip"]
                       and p["t"] - s["last"] >= NEW_PORT_SILENCE]
            if earlier:
                old = max(earlier, key=lambda s: s["last"])
                taken_over[p["sender"]] = old["id"]
                restarts[old["id"]].append(p["t"])
                key = None if scope == "sender" else p["type"] if (old["id"], p["type"]) in counters else \
                    old["last_type"]
                before = counters.get((old["id"], key))
                sender["link"] = {"time": round(p["t"], 6), "frame": p["frame"],
                                  "from": before.h if before else 0, "to": p["serial"],
                                  "port_from": old["p"]["port"], "port_to": p["port"]}
        sender["by_type"][p["type"]] += 1
        sender["last"], sender["last_type"] = p["t"], p["type"]
        key = (p["sender"], None if scope == "sender" else p["type"])
        counter = counters.setdefault(key, Counter())
        p["duplicate"], restart = counter.feed(p["serial"], p["t"], p["frame"])
        if restart is not None:
            restarts[p["sender"]].append(restart)
    for counter in counters.values():
        counter.finish()
    return senders, counters, taken_over, restarts


def _sender_report(sender: dict, counters: dict, scope: str) -> dict:
    keys = sorted((k for k in counters if k[0] == sender["id"]),
                  key=lambda k: -1 if k[1] is None else TYPE_ORDER.index(k[1]))
    mine = [counters[k] for k in keys]
    lost = [s for c in mine for s in c.lost()]
    events = sorted((r for c in mine for r in c.restarts), key=lambda r: r["frame"])
    if sender["link"]:
        events.insert(0, sender["link"])
    p = sender["p"]
    return {"id": sender["id"], "direction": p["direction"], "origin": p["origin"], "src": f"{p['ip']}:{p['port']}",
            "by_type": dict(sorted(sender["by_type"].items())),
            "serial": {"scope": scope, "received": sum(c.received for c in mine), "lost": len(lost),
                       "duplicates": sum(len(c.duplicates) for c in mine),
                       "out_of_order": sum(len(c.out_of_order) for c in mine),
                       "wraps": sum(c.wraps for c in mine), "lost_serials": lost,
                       "duplicate_serials": [s for c in mine for s in c.duplicates],
                       "out_of_order_serials": [s for c in mine for s in c.out_of_order],
                       "gaps": sorted((g for c in mine for g in c.gaps), key=lambda g: g["frame"]),
                       "restarts": len(events), "restart_events": events}}


def _periodic(accepted: list[dict], taken_over: dict[str, str], end: Optional[float]) -> list[dict]:
    streams: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for p in accepted:
        if p["type"] in WATCHDOG:
            streams[(p["type"], p["sender"])].append(p)
    out = []
    for kind, sender in sorted(streams):
        limit, stream, violations = WATCHDOG[kind], streams[(kind, sender)], []
        # A new port's stream goes on from the old port's last packet.
        old = streams.get((kind, taken_over.get(sender, "")))
        previous = old[-1] if old else None
        for p in stream:
            if previous is not None and p["t"] - previous["t"] > limit:
                violations.append({"start": round(previous["t"], 6), "gap_ms": round((p["t"] - previous["t"]) * 1e3, 3),
                                   "until_end": False, "frame": p["frame"]})
            previous = p
        assert previous is not None and end is not None
        if sender not in taken_over.values() and end - previous["t"] > limit:
            violations.append({"start": round(previous["t"], 6), "gap_ms": round((end - previous["t"]) * 1e3, 3),
                               "until_end": True, "frame": previous["frame"]})
        out.append({"type": kind, "sender": sender, "count": len(stream),
                    "watchdog": {"limit_ms": round(limit * 1e3), "violations": violations}})
    return out


def _commands(accepted: list[dict], kind: str, ack_kind: str, restarts: dict[str, list[float]],
              end: Optional[float]) -> dict:
    figures = dict.fromkeys(("commands", "transmissions", "retransmissions", "acked", "unacked", "interrupted",
                             "failed", "spurious_retransmissions", "acks_without_command", "duplicate_acks"), 0)
    commands: list[dict] = []
    latest: dict[tuple[str, int], dict] = {}
    for p in accepted:
        if p["type"] not in (kind, ack_kind):
            continue
        cid = struct.unpack("<H", p["payload"][:2])[0]
        if p["type"] == kind:
            figures["transmissions"] += 1
            c = latest.get((p["sender"], cid))
            restarted = c is not None and any(c["tx"][-1] < r <= p["t"] for r in restarts[p["sender"]])
            if c is not None and p["t"] - c["tx"][-1] < FAIL and not restarted:
                figures["retransmissions"] += 1
                figures["spurious_retransmissions"] += c["ack"] is not None
                c["tx"].append(p["t"])
                c["frames"].append(p["frame"])
            else:
                c = latest[(p["sender"], cid)] = {"sender": p["sender"], "id": cid, "tx": [p["t"]],
                                                  "frames": [p["frame"]], "ack": None}
                commands.append(c)
            continue
        candidates = [c for c in commands if c["id"] == cid]
        if not candidates:
            figures["acks_without_command"] += 1
        elif candidates[-1]["ack"] is not None:
            figures["duplicate_acks"] += 1
        else:
            c = candidates[-1]
            c["ack"], c["ack_frame"], c["last_before"] = p["t"], p["frame"], c["tx"][-1]
    listed = []
    for c in commands:
        figures["commands"] += 1
        first = c["tx"][0]
        if c["ack"] is not None:
            figures["acked"] += 1
            figures["failed"] += c["ack"] - first > FAIL
        elif any(first < r and r - first <= FAIL for r in restarts[c["sender"]]):
            figures["interrupted"] += 1
        elif end is not None and end - first > FAIL:    # still within its limit at the end: not failed
            figures["failed"] += 1
        acked = c["ack"] is not None
        listed.append({"sender": c["sender"], "command_id": c["id"], "frames": c["frames"],
                       "ack_frame": c.get("ack_frame"),
                       "latency_first_ms": round((c["ack"] - first) * 1e3, 3) if acked else None,
                       "latency_last_ms": round((c["ack"] - c["last_before"]) * 1e3, 3) if acked else None})
    figures["unacked"] = figures["commands"] - figures["acked"] - figures["interrupted"]
    return {**figures, "list": listed}


def _bursts(accepted: list[dict], start: int) -> dict[str, int]:
    """VRPO packets of a sender less than BURST_GAP apart, until complete: numbered from `start`,
    all but the last with 488 bytes of data, the last with fewer."""
    def complete(parts: list[tuple[int, int]]) -> bool:
        numbers, sizes = [n for n, _ in parts], [z for _, z in parts]
        return numbers == list(range(start, start + len(parts))) and sizes[-1] < FULL and \
            all(z == FULL for z in sizes[:-1])

    figures = {"complete": 0, "incomplete": 0}
    open_bursts: dict[str, tuple[float, list[tuple[int, int]]]] = {}
    for p in accepted:
        if p["type"] != "VRPO":
            continue
        part = (struct.unpack("<H", p["payload"][:2])[0], len(p["payload"]) - 2)
        burst = open_bursts.get(p["sender"])
        if burst is not None and p["t"] - burst[0] < BURST_GAP and not complete(burst[1]):
            open_bursts[p["sender"]] = (p["t"], sorted([*burst[1], part]))
            continue
        if burst is not None:
            figures["complete" if complete(burst[1]) else "incomplete"] += 1
        open_bursts[p["sender"]] = (p["t"], [part])
    for _, parts in open_bursts.values():
        figures["complete" if complete(parts) else "incomplete"] += 1
    return figures
