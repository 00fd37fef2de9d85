"""A deliberately plain reference analyser, written from interpretation.md and docs/rules.md alone.

It imports nothing from `vm110`: its own pcap/pcapng reader (Ethernet with 802.1Q/802.1ad tags,
Linux cooked v1/v2, raw IPv4; IPv4/UDP), its own CRC-32/MPEG-2, its own legality checks. Plain
lists and dicts, one packet at a time, no fast paths. Times are kept as integer nanoseconds so that
no rounding decides a comparison; a comparison that lands within `TIE_NS` of a limit (where an
engine's float arithmetic could go either way) is recorded in `result["ambiguous"]` so that
property tests can skip such captures instead of reporting a float-rounding coin toss.

Readings chosen where docs/rules.md leaves room (interpretation.md decides; see the final report):
  R1 New port, "of the one heard last, when several are": among the earlier senders with the same
     direction, origin and address whose last legal packet lies >= 250 ms before, the one whose last
     legal packet is latest. "Last legal packet" includes duplicates (they are legal); when counting
     only accepted packets would decide differently the capture is flagged ambiguous.
  R2 A restart candidate is decided by the counter's next legal packet whose serial is not the
     candidate's, whatever that packet is (also a copy of an older serial).  Copies of the candidate
     in between are duplicates, also those after the duplicate window (rules.md says so explicitly).
  R3 The candidate is accepted when it arrives (it counts for dt and r either way); a confirmed
     restart then resets the counter to: h = s, start = t_candidate, only s accepted, no open gaps;
     serials lost before the restart stay lost and can no longer be filled.
  R4 VRCO commands fail like VRCI ones (interpretation.md "Timing": "a VRCO not acknowledged within
     it has failed, as a VRCI has"); docs/report.md's "failed is 0 for VRCO" is outdated.
  R5 Periodic intervals use accepted packets only (rules.md, interpretation.md "Serial numbers");
     docs/report.md's "duplicates included" is outdated.
  R6 An acknowledgement considers commands that began before it in file order (equal timestamps:
     the frame order decides, as the bundled captures need); among the
     not-interrupted ones with its ID (from any sender) the one that began last. If that one is
     already acknowledged the ack is a duplicate ack, even if an older one is still open.
  R7 A command whose fail limit passed before a restart, unacknowledged, is not interrupted; it
     stays failed (and unacked), and may still be acknowledged later if it is then the latest
     command with its ID.
  R8 A restart of the sender (same port) happens at the candidate's frame: the candidate itself,
     if it is a VRCI/VRCO, already belongs to the new life (a new command even within the reuse gap).
     Only a restart confirmed less than 10 s after its candidate (the confirming packet's time minus
     the candidate's, analysis clock) does so (rules.md rule 5): one confirmed later is counted
     and located, but interrupts nothing and starts no new command.
  R9 Silence to the end: a stream whose sender was taken over by a new-port sender has no
     silence to the end, whether or not the new sender sends that periodic type.
 R11 A new-port restart also counts as a restart of the earlier sender for its own commands: a
     late VRCI/VRCO of the earlier port arriving after the new sender's first packet begins a new
     command (its outstanding ones were interrupted) rather than joining an interrupted one.
 R12 "The earlier sender whose last legal packet lies at least 250 ms before it" is judged at the
     new sender's first packet (interpretation.md: "an earlier sender that *has been* silent"):
     packets of the earlier port that arrive later (late or reordered) do not undo the restart.
     Likewise `from` is the earlier counter's highest serial at that moment, and the new stream's
     first interval is from the earlier sender's last packet of the type before the new stream's
     first one.
 R10 A sender exists (senders[], periodic[]) only with at least one legal packet; illegal packets
     are attributed to nobody.
 R13 "The capture went on past the limit" (rules.md, "Failed") is judged on the analysis clock the
     command's times run on: the capture's latest time is the later of its last record and its
     latest legal packet (appended captures: the clock stays ahead of a later, shorter part).
 R14 VRPO bursts (docs/rules.md "VRPO bursts", interpretation.md "VRPO split"; data size option 0,
     infer, the default and the only one handled here): a sender's accepted VRPO packets in capture
     order (duplicates are not parts), each less than 20 ms after the one before on its own
     timestamp and not before it, belong to one burst. A burst is complete when its numbers are
     0..n-1 each once (in any order), all but the last by number carry 488 bytes, and either the
     last carries fewer, or it carries 488 too (every packet 488) and the sender sent, in the bursts
     before it, no accepted VRPO packet of fewer than 488 bytes and no complete burst of 488-byte
     packets with more packets than it. A burst is over (the next packet begins another, even
     within the gap) when it is complete with a short last packet; when the next packet carries
     number 0 and the burst already holds a 0; or when its packets all carry 488 bytes, are
     numbered 0..n-1 each once, n at least the length of the sender's longest complete burst of
     488-byte packets, with no packet of fewer than 488 bytes before, and the next packet's number
     is not n (the one after its highest). Reading: "as many as in the sender's longest complete
     such burst or more" and "the size inferred" need such a burst: before the sender's first
     complete burst of 488-byte packets no size is inferred and this ending does not apply (so an
     out-of-order first burst stays one burst, as rules.md promises). An incomplete burst marks
     its last packet in capture order: frames[..]["burst_incomplete"].
 R15 A sender restarted on a new port already lives on in its successor: it is restarted on a new
     port no more (rules.md, "A sender on a new port").
 R16 The rules run on the analysis clock, but the moments a report names (gaps, restart events)
     are the frames' own timestamps (rules.md, "the analysis clock").
 R17 Serial scope `auto` (docs/rules.md, "Choosing the scope"), per sender, on its legal packets
     (duplicates included) by their analysis-clock times. A sender of one packet type has one
     counter under either scope: `sender`. Otherwise the choice is made on its packets from its
     first packet of a type other than its first packet's (P): the looks at 10, 20, 40, ... 320 s
     after P each take the packets from P on before that moment and classify them from scratch,
     once with one counter and once with one per type (a candidate still open at the end is out of
     order); anomalies = gaps (one each, however many serials) + duplicates + out of order +
     restarts.
     Per-type counters when they have 4 anomalies fewer; one counter when
     they have as many or more; otherwise the packets cannot tell and the next look decides (the
     last look decides for one counter). The 4096th packet from P on decides on those 4096
     packets; the end of the capture on all from P on. Whether a look happens before the capture
     ends does not matter: without more packets it sees the same ones. The scope chosen holds for
     all the sender's packets (before P, of one type, both scopes judge alike).
 R18 Scope `type`, a new-port restart's `from`: the earlier sender's counter of the new sender's
     first packet type, when the earlier sender had packets of that type before it; else the
     counter of the earlier sender's last legal packet before it.
"""
from __future__ import annotations

import itertools
import struct
from typing import Any, Optional

# --- constants (TS-0006, interpretation.md) -----------------------------------------------------
DIRECTIONS = {b"VRPI": "Input", b"VRCI": "Input", b"VRAI": "Input",
              b"VRPO": "Output", b"VRCO": "Output", b"VRAO": "Output"}
MIN_PAYLOAD = {"VRPI": 46, "VRCI": 22, "VRCO": 22, "VRAO": 2, "VRAI": 2, "VRPO": 2}
MAX_PAYLOAD = 492
ACK_OF = {"VRAO": "VRCI", "VRAI": "VRCO"}
TIE_NS = 3_000                   # 3 us: comparisons this close to a limit are flagged ambiguous
NS = 1_000_000_000
CANDIDATE_WAIT = 10 * NS         # rules.md rule 5: a restart confirmed this long after changes no command
MS = 1_000_000


# --- CRC-32/MPEG-2 ------------------------------------------------------------------------------
def _make_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else (crc << 1)
            crc &= 0xFFFFFFFF
        table.append(crc)
    return table


_TABLE = _make_table()


def crc32_mpeg2(data: bytes) -> int:
    """poly 0x04C11DB7, init 0xFFFFFFFF, MSB first, no reflection, no final XOR."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ _TABLE[((crc >> 24) ^ byte) & 0xFF]
    return crc


assert crc32_mpeg2(b"123456789") == 0x0376E6E7


# --- capture reading ----------------------------------------------------------------------------
def read_records(path: str) -> list[dict]:
    """Every record of a pcap or pcapng file: {"frame", "t" (ns), "linktype", "data"}."""
    with open(path, "rb") as f:
        blob = f.read()
    if blob[:4] == b"\x0a\x0d\x0d\x0a":
        return _read_pcapng(blob)
    return _read_pcap(blob)


def _read_pcap(blob: bytes) -> list[dict]:
    magic = blob[:4]
    if magic in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1"):
        end = "<"
    elif magic in (b"\xa1\xb2\xc3\xd4", b"\xa1\xb2\x3c\x4d"):
        end = ">"
    else:
        raise ValueError("not a pcap or pcapng file")
    nano = magic in (b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
    linktype = struct.unpack(end + "I", blob[20:24])[0] & 0xFFFF
    records = []
    pos = 24
    while pos + 16 <= len(blob):
        sec, frac, incl, _orig = struct.unpack(end + "IIII", blob[pos:pos + 16])
        data = blob[pos + 16:pos + 16 + incl]
        if len(data) < incl:
            break
        t = sec * NS + (frac if nano else frac * 1000)
        records.append({"frame": len(records) + 1, "t": t, "linktype": linktype, "data": data})
        pos += 16 + incl
    return records


def _read_pcapng(blob: bytes) -> list[dict]:
    records: list[dict] = []
    end = "<"
    interfaces: list[dict] = []
    pos = 0
    last_t = 0
    while pos + 12 <= len(blob):
        btype_raw = blob[pos:pos + 4]
        if btype_raw == b"\x0a\x0d\x0d\x0a":
            bom = blob[pos + 8:pos + 12]
            end = "<" if bom == b"\x4d\x3c\x2b\x1a" else ">"
            interfaces = []
        btype, blen = struct.unpack(end + "II", blob[pos:pos + 8])
        if blen < 12 or pos + blen > len(blob):
            break
        body = blob[pos + 8:pos + blen - 4]
        if btype == 1:                                   # interface description
            linktype = struct.unpack(end + "H", body[0:2])[0]
            units, offset = 10 ** 6, 0
            opos = 8
            while opos + 4 <= len(body):
                code, olen = struct.unpack(end + "HH", body[opos:opos + 4])
                value = body[opos + 4:opos + 4 + olen]
                if code == 0:
                    break
                if code == 9 and olen >= 1:
                    v = value[0]
                    units = 2 ** (v & 0x7F) if v & 0x80 else 10 ** v
                if code == 14 and olen == 8:
                    offset = struct.unpack(end + "q", value)[0]
                opos += 4 + olen + (-olen % 4)
            interfaces.append({"linktype": linktype, "units": units, "offset": offset})
        elif btype in (6, 2):                            # enhanced / obsolete packet block
            if btype == 6:
                iface, hi, lo, incl, _orig = struct.unpack(end + "IIIII", body[0:20])
            else:
                iface, _drops, hi, lo, incl, _orig = struct.unpack(end + "HHIIII", body[0:20])
            itf = interfaces[iface]
            ts = (hi << 32) | lo
            t = ts * NS // itf["units"] + itf["offset"] * NS
            last_t = t
            records.append({"frame": len(records) + 1, "t": t, "linktype": itf["linktype"],
                            "data": body[20:20 + incl]})
        elif btype == 3:                                 # simple packet block: no timestamp
            orig = struct.unpack(end + "I", body[0:4])[0]
            itf = interfaces[0]
            records.append({"frame": len(records) + 1, "t": last_t, "linktype": itf["linktype"],
                            "data": body[4:4 + orig]})
        pos += blen
    return records


def udp_datagram(linktype: int, data: bytes) -> Optional[dict]:
    """{"src", "sport", "dport", "payload"} of an IPv4/UDP frame, else None (fragments: None)."""
    ip: bytes
    if linktype == 1:                                    # Ethernet
        off = 12
        etype = int.from_bytes(data[off:off + 2], "big")
        off += 2
        while etype in (0x8100, 0x88A8, 0x9100):
            etype = int.from_bytes(data[off + 2:off + 4], "big")
            off += 4
        if etype != 0x0800:
            return None
        ip = data[off:]
    elif linktype == 113:                                # Linux cooked v1
        if int.from_bytes(data[14:16], "big") != 0x0800:
            return None
        ip = data[16:]
    elif linktype == 276:                                # Linux cooked v2
        if int.from_bytes(data[0:2], "big") != 0x0800:
            return None
        ip = data[20:]
    elif linktype in (101, 228, 12, 14):                 # raw IP
        ip = data
    else:
        return None
    if len(ip) < 20 or ip[0] >> 4 != 4:
        return None
    ihl = (ip[0] & 0x0F) * 4
    total = int.from_bytes(ip[2:4], "big")
    frag = int.from_bytes(ip[6:8], "big")
    if ip[9] != 17 or frag & 0x3FFF:
        return None
    ip = ip[:total]
    udp = ip[ihl:]
    if len(udp) < 8:
        return None
    sport, dport, ulen = struct.unpack("!HHH", udp[0:6])
    return {"src": ".".join(str(b) for b in ip[12:16]), "sport": sport, "dport": dport,
            "payload": udp[8:ulen]}


def is_eglink(dgram: dict, ports: tuple[int, int]) -> bool:
    if dgram["sport"] in ports or dgram["dport"] in ports:
        return True
    p = dgram["payload"]
    return len(p) >= 20 and p[:4] in DIRECTIONS and int.from_bytes(p[10:12], "little") == len(p) - 20


def problems(p: bytes) -> list[str]:
    """Reasons an EG-Link payload is illegal (interpretation.md, "Illegal packets")."""
    n = len(p)
    out = []
    if n < 16:
        if n >= 4 and p[:4] not in DIRECTIONS:
            out.append("unknown_id")
        out.append("truncated")
        return out
    pid = p[:4]
    rev, _origin, _serial, size, _spare = struct.unpack("<HHHHI", p[4:16])
    if pid not in DIRECTIONS:
        out.append("unknown_id")
    crc_at = min(16 + size, n - 4)        # "find the CRC from size / the UDP length"
    if n >= 20:
        stored = int.from_bytes(p[crc_at:crc_at + 4], "little")
        if crc32_mpeg2(p[:crc_at]) != stored:
            out.append("bad_crc")
    if rev != 0:
        out.append("revision")
    if n != 20 + size:
        out.append("size_mismatch")
    if size > MAX_PAYLOAD:
        out.append("size_too_large")
    if n < 20:
        out.append("truncated")
        return out
    if pid in DIRECTIONS and rev == 0 and crc_at - 16 < MIN_PAYLOAD[pid.decode()]:
        out.append("truncated")
    return out


# --- the analysis -------------------------------------------------------------------------------
def sender_id(direction: str, src: str, port: int, origin: int) -> str:
    return f"{direction} {src}:{port} origin 0x{origin:04x}"


def _sec(t: int) -> float:
    return round(t / NS, 6)


def _ms(dt: int) -> float:
    return round(dt / MS, 6)


class _Flags:
    def __init__(self) -> None:
        self.items: list[str] = []

    def near(self, value: int, limit: int, what: str) -> None:
        if abs(value - limit) <= TIE_NS:
            self.items.append(f"{what}: {value} ns vs limit {limit} ns")


def analyse(path: str, dup_window_ms: float = 1000, reuse_gap_ms: float = 2000,
            vrci_fail_ms: float = 2000, vrco_give_up_ms: float = 2000,
            vrpi_watchdog_ms: float = 500, vrpo_watchdog_ms: float = 2000,
            ports: tuple[int, int] = (5825, 5827), new_port_silence_ms: float = 250,
            serial_scope: str = "sender") -> dict[str, Any]:
    """The reference result of one capture (key names as in the JSON report, docs/report.md);
    `serial_scope` is `sender`, `type` or `auto` (R17)."""
    dup_w = int(dup_window_ms * MS)
    reuse = int(reuse_gap_ms * MS)
    fail_limit = {"VRCI": int(vrci_fail_ms * MS), "VRCO": int(vrco_give_up_ms * MS)}
    watchdog = {"VRPI": int(vrpi_watchdog_ms * MS), "VRPO": int(vrpo_watchdog_ms * MS)}
    silence = int(new_port_silence_ms * MS)
    flags = _Flags()

    records = read_records(path)
    last_record_t = records[-1]["t"] if records else 0

    # 1. legal packets, illegal reasons
    by_reason: dict[str, int] = {}
    illegal_total = 0
    legal: list[dict] = []
    eglink = 0
    clock: Optional[int] = None    # rules.md "the analysis clock": the latest legal timestamp so far
    for rec in records:
        dg = udp_datagram(rec["linktype"], rec["data"])
        if dg is None or not is_eglink(dg, ports):
            continue
        eglink += 1
        p = dg["payload"]
        why = problems(p)
        if why:
            illegal_total += 1
            for reason in why:
                by_reason[reason] = by_reason.get(reason, 0) + 1
            continue
        ptype = p[:4].decode()
        _rev, origin, serial, _size, _spare = struct.unpack("<HHHHI", p[4:16])
        clock = rec["t"] if clock is None else max(clock, rec["t"])
        # "t": the time of the sender, serial and command rules; "own": the periodic streams'
        pkt = {"frame": rec["frame"], "t": clock, "own": rec["t"], "type": ptype, "direction": DIRECTIONS[p[:4]],
               "origin": origin, "serial": serial, "src": dg["src"], "sport": dg["sport"],
               "cid": None}
        if ptype in ("VRCI", "VRCO", "VRAO", "VRAI"):
            pkt["cid"] = int.from_bytes(p[16:18], "little")
        if ptype == "VRPO":
            pkt["number"], pkt["data"] = int.from_bytes(p[16:18], "little"), _size - 2
        pkt["sender"] = sender_id(pkt["direction"], dg["src"], dg["sport"], origin)
        legal.append(pkt)

    # 2. senders, and new-port restarts (at a sender's first legal packet)
    senders: dict[str, dict] = {}
    order: list[str] = []
    for pkt in legal:
        sid = pkt["sender"]
        if sid not in senders:
            pred = None
            best_t = None
            for other_id in order:
                o = senders[other_id]
                if (o["direction"], o["origin"], o["ip"]) != (pkt["direction"], pkt["origin"], pkt["src"]):
                    continue
                if o["taken_over"]:          # R15: restarted on a new port already, it lives on there
                    continue
                flags.near(pkt["t"] - o["last_legal_t"], silence, f"new-port silence {other_id}")
                if pkt["t"] - o["last_legal_t"] >= silence and (best_t is None or o["last_legal_t"] > best_t):
                    pred, best_t = other_id, o["last_legal_t"]
            senders[sid] = {"id": sid, "direction": pkt["direction"], "origin": pkt["origin"],
                            "ip": pkt["src"], "port": pkt["sport"], "packets": [], "pred": pred,
                            "taken_over": False, "last_legal_t": pkt["t"],
                            "first_frame": pkt["frame"], "first_t": pkt["t"], "first_own": pkt["own"]}
            order.append(sid)
            if pred is not None:
                senders[pred]["taken_over"] = True
        s = senders[sid]
        s["packets"].append(pkt)
        s["last_legal_t"] = pkt["t"]

    # 3. serial numbers, per sender (by the counter(s) of its scope)
    frames: dict[int, dict] = {}          # frame -> expected per-frame analysis (dissector fields)
    restart_at: dict[int, dict] = {}      # frame of a restart -> {"sender", "t"} (for commands)
    for sid in order:
        _serials(senders[sid], serial_scope, dup_w, flags, frames, restart_at)
    # R1: flag captures where counting duplicates as the last legal packet decides a new-port restart
    _check_accepted_silence(order, senders, legal, silence, flags)

    for sid in order:
        s = senders[sid]
        if s["pred"] is not None:
            p = senders[s["pred"]]
            restart_at[s["first_frame"]] = {"sender": p["id"], "t": s["first_t"]}
            # R12: "from" is the earlier counter's highest serial when the new sender starts
            h_then = _highest_before(p, s["first_frame"], s["packets"][0]["type"])
            ev = {"time": _sec(s["first_own"]), "frame": s["first_frame"], "from": h_then,
                  "to": s["packets"][0]["serial"], "port_from": p["port"], "port_to": s["port"]}
            s["restart_events"].append(ev)
            s["restart_events"].sort(key=lambda e: e["frame"])
            f = frames.setdefault(s["first_frame"], {})
            f["restart"] = h_then
            f["restart_port_from"] = p["port"]

    # 4. periodic streams
    periodic = []
    for sid in order:
        s = senders[sid]
        for ptype in ("VRPI", "VRPO"):
            pk = [p for p in s["packets"] if p["type"] == ptype and p["accepted"]]
            if not pk:
                continue
            limit = watchdog[ptype]
            intervals: list[tuple[int, int, int]] = []        # (start t, interval, frame after)
            if s["pred"] is not None:
                # R12: the earlier sender's last packet of the type before this stream's first
                before = [p for p in senders[s["pred"]]["packets"]
                          if p["type"] == ptype and p["accepted"] and p["frame"] < pk[0]["frame"]]
                if before:
                    intervals.append((before[-1]["own"], pk[0]["own"] - before[-1]["own"], pk[0]["frame"]))
            for a, b in itertools.pairwise(pk):
                intervals.append((a["own"], b["own"] - a["own"], b["frame"]))
            violations = []
            for start, gap, after in intervals:
                flags.near(gap, limit, f"{ptype} interval of {sid}")
                if gap > limit:
                    violations.append({"start": _sec(start), "gap_ms": _ms(gap), "until_end": False,
                                       "frame": after})
                    frames.setdefault(after, {})["watchdog"] = ptype
            if not s["taken_over"]:
                gap = last_record_t - pk[-1]["own"]
                flags.near(gap, limit, f"{ptype} silence to the end of {sid}")
                if gap > limit:
                    violations.append({"start": _sec(pk[-1]["own"]), "gap_ms": _ms(gap), "until_end": True,
                                       "frame": pk[-1]["frame"]})
                    frames.setdefault(pk[-1]["frame"], {})["silent_until_end"] = _ms(gap)
            periodic.append({"type": ptype, "sender": sid, "count": len(pk),
                             "interval_ms": {"max": _ms(max(i[1] for i in intervals)) if intervals else None},
                             "watchdog": {"limit_ms": limit / MS, "violations": violations}})
    periodic.sort(key=lambda e: (e["type"], e["sender"]))

    # 4b. VRPO bursts (R14)
    bursts = {"complete": 0, "incomplete": 0}
    for sid in order:
        earlier: list[tuple[list[dict], bool]] = []         # the sender's bursts so far, with verdicts
        burst: list[dict] = []
        for q in (q for q in senders[sid]["packets"] if q["type"] == "VRPO" and q["accepted"]):
            if burst:
                step = q["own"] - burst[-1]["own"]
                over = _burst_over(burst, q, earlier)
                if not over:                                 # the gap decides
                    flags.near(step, BURST_GAP_NS, f"VRPO burst gap of {sid}, frame {q['frame']}")
                if over or not 0 <= step < BURST_GAP_NS:
                    earlier.append((burst, _burst_judge(burst, earlier, bursts, frames)))
                    burst = []
            burst.append(q)
        if burst:
            earlier.append((burst, _burst_judge(burst, earlier, bursts, frames)))

    # 5. commands
    # R13: the capture went on past a command's limit when its latest time did: the later of its
    # last record and the analysis clock (a step back of the records' time leaves the clock ahead).
    commands = _commands(legal, senders, restart_at, reuse, fail_limit, max(last_record_t, clock or last_record_t),
                         flags, frames)

    sender_list = []
    for sid in sorted(order):
        s = senders[sid]
        sender_list.append({"id": sid, "direction": s["direction"], "origin": s["origin"],
                            "src": f"{s['ip']}:{s['port']}", "serial": s["serial"]})
        s["serial"]["restart_events"] = s["restart_events"]
        s["serial"]["restarts"] = len(s["restart_events"])
    return {
        "capture": {"packets": len(records), "eglink_packets": eglink,
                    "last_time": _sec(last_record_t) if records else None},
        "illegal": {"total": illegal_total, "by_reason": by_reason},
        "senders": sender_list,
        "periodic": periodic,
        "commands": commands,
        "vrpo_bursts": bursts,
        "frames": frames,
        "ambiguous": flags.items,
    }


BURST_GAP_NS = 20 * MS


def _numbered_from_zero(burst: list[dict]) -> bool:
    """R14: the packet numbers are 0, 1, .., n-1, each once (in any order)."""
    return sorted(q["number"] for q in burst) == list(range(len(burst)))


def _by_number(burst: list[dict]) -> list[dict]:
    return sorted(burst, key=lambda q: q["number"])


def _well_formed(burst: list[dict]) -> bool:
    """R14: numbers 0..n-1 each once, every packet but the last by number 488 bytes."""
    return _numbered_from_zero(burst) and all(q["data"] == 488 for q in _by_number(burst)[:-1])


def _burst_over(burst: list[dict], q: dict, earlier: list[tuple[list[dict], bool]]) -> bool:
    """R14: the burst is over before q (the sender's next packet, within the gap)."""
    if _well_formed(burst) and _by_number(burst)[-1]["data"] < 488:
        return True                                  # complete by its own packets
    if q["number"] == 0 and any(p["number"] == 0 for p in burst):
        return True                                  # q restarts the numbering
    # inferring: as many full packets, numbered from 0, as the sender's longest complete burst of
    # full packets (there must be one: the size inferred), no shorter packet before, and q's number
    # does not follow the highest (if it does, the size inferred was too small: the burst goes on)
    full_before = [len(parts) for parts, complete in earlier
                   if complete and all(p["data"] == 488 for p in parts)]
    short_before = any(p["data"] < 488 for parts, _complete in earlier for p in parts)
    return (all(p["data"] == 488 for p in burst) and _numbered_from_zero(burst) and bool(full_before)
            and len(burst) >= max(full_before) and not short_before and q["number"] != len(burst))


def _burst_complete(burst: list[dict], earlier: list[tuple[list[dict], bool]]) -> bool:
    """R14, inferring the data size: a short last packet; or every packet 488 bytes, with no packet
    of fewer than 488 bytes and no longer complete burst of 488-byte packets before it."""
    if not _well_formed(burst):
        return False
    last = _by_number(burst)[-1]["data"]
    if last < 488:
        return True
    if last != 488:
        return False
    for parts, complete in earlier:
        if any(q["data"] < 488 for q in parts):
            return False
        if complete and all(q["data"] == 488 for q in parts) and len(parts) > len(burst):
            return False
    return True


def _burst_judge(burst: list[dict], earlier: list[tuple[list[dict], bool]], bursts: dict, frames: dict) -> bool:
    """Count a finished burst; an incomplete one marks its last packet in capture order."""
    complete = _burst_complete(burst, earlier)
    bursts["complete" if complete else "incomplete"] += 1
    if not complete:
        frames.setdefault(burst[-1]["frame"], {})["burst_incomplete"] = True
    return complete


def _check_accepted_silence(order: list[str], senders: dict, legal: list[dict], silence: int,
                            flags: _Flags) -> None:
    """R1: flag a capture where counting only accepted packets would decide a new-port restart
    differently from counting every legal packet."""
    last_acc: dict[str, int] = {}
    last_legal: dict[str, int] = {}
    for pkt in legal:
        sid = pkt["sender"]
        s = senders[sid]
        if sid not in last_legal:
            for other_id, t_legal in last_legal.items():
                o = senders[other_id]
                if (o["direction"], o["origin"], o["ip"]) != (s["direction"], s["origin"], s["ip"]):
                    continue
                t_acc = last_acc.get(other_id, t_legal)
                if (pkt["t"] - t_legal >= silence) != (pkt["t"] - t_acc >= silence):
                    flags.items.append(f"new-port silence of {other_id}: a duplicate decides")
        last_legal[sid] = pkt["t"]
        if pkt["accepted"]:
            last_acc[sid] = pkt["t"]


def _plausible(d: int, ctr: dict, t: int, flags: _Flags, where: str) -> bool:
    """rules.md 4: d - 1 <= 64 + 4 * max(r, 20) * dt."""
    dt = t - ctr["prev_t"]
    window = min(10 * NS, t - ctr["start"])

    def rhs(count: int) -> float:
        r = count * NS / window if window > 0 else 0.0
        return 64 + 4 * max(r, 20.0) * dt / NS

    count = 0
    edge = 0                    # packets within TIE_NS of the window's lower edge
    for at in ctr["acc_times"]:
        if t - window <= at < t:
            count += 1
        if window > 0 and abs(at - (t - window)) <= TIE_NS and at != ctr["start"]:
            edge += 1
    ok = d - 1 <= rhs(count)
    if abs((d - 1) - rhs(count)) < 1e-3 or (edge and (d - 1 <= rhs(count - edge)) != ok) \
            or (window > 0 and (d - 1 <= rhs(count + 1)) != ok and abs(window - 10 * NS) <= TIE_NS):
        flags.items.append(f"plausible gap at {where}: d={d} count={count} dt={dt}")
    return ok


def _classify(packets: list[dict], dup_w: int, flags: _Flags) -> dict:
    """One counter over its packets in arrival order (rules.md "Serial numbers"), touching none of
    them: per packet (by position) whether it is accepted, the per-frame marks and the counter's
    highest serial as the packet after it finds it; the counts; the restarts (by the candidate's
    position)."""
    received = lost_frozen = duplicates = out_of_order = wraps = 0
    gaps: list[dict] = []
    restarts: list[dict] = []
    marks: list[tuple[int, str, int]] = []             # (position, frame field, value)
    accepted = [False] * len(packets)
    h_after: list[Optional[int]] = [None] * len(packets)
    ctr: Optional[dict] = None
    pending: Optional[dict] = None

    def accept(i: int) -> None:
        assert ctr is not None
        ctr["accepted"][packets[i]["serial"]] = packets[i]["t"]
        ctr["prev_t"] = packets[i]["t"]
        ctr["acc_times"].append(packets[i]["t"])
        accepted[i] = True

    for i, pkt in enumerate(packets):
        if i:
            h_after[i - 1] = ctr["h"] if ctr is not None else None
        received += 1
        sv, t, fr = pkt["serial"], pkt["t"], pkt["frame"]
        if ctr is None:
            ctr = {"h": sv, "start": t, "accepted": {}, "missing": [], "prev_t": t, "acc_times": []}
            accept(i)
            continue
        if pending is not None:
            if sv == pending["serial"]:
                # R2: a copy of the candidate is a duplicate, whenever it comes
                duplicates += 1
                marks.append((i, "serial_duplicate", 1))
                continue
            if (sv - pending["serial"]) % 65536 in (1, 2, 3, 4):
                # confirmed: a restart at the candidate (R3)
                flags.near(t - pending["t"], CANDIDATE_WAIT, f"candidate wait, frame {fr}")
                restarts.append({"at": pending["at"], "from": ctr["h"], "to": pending["serial"],
                                 "commands": t - pending["t"] < CANDIDATE_WAIT})        # R8
                marks.append((pending["at"], "restart", ctr["h"]))
                lost_frozen += len(ctr["missing"])
                ctr = {"h": pending["serial"], "start": pending["t"], "accepted": {pending["serial"]: pending["t"]},
                       "missing": [], "prev_t": pending["t"], "acc_times": [pending["t"]]}
            else:
                out_of_order += 1
                marks.append((pending["at"], "serial_out_of_order", 1))
            pending = None
        h = ctr["h"]
        d = (sv - h) % 65536
        last_acc = ctr["accepted"].get(sv)
        if last_acc is not None:
            flags.near(t - last_acc, dup_w, f"duplicate window, frame {fr}")
        if last_acc is not None and t - last_acc < dup_w:                       # 1. duplicate
            duplicates += 1
            marks.append((i, "serial_duplicate", 1))
            continue
        if d == 1:                                                             # 2. in order
            if sv < h:
                wraps += 1
            ctr["h"] = sv
            accept(i)
            continue
        late = None
        for k, (ms_serial, opened) in enumerate(ctr["missing"]):
            if ms_serial == sv:
                flags.near(t - opened, dup_w, f"late window, frame {fr}")
                if t - opened < dup_w:
                    late = k
        if late is not None:                                                   # 3. late
            del ctr["missing"][late]
            out_of_order += 1
            marks.append((i, "serial_out_of_order", 1))
            accept(i)
            continue
        if 1 < d < 32768 and _plausible(d, ctr, t, flags, f"frame {fr}"):     # 4. gap
            for k in range(1, d):
                ctr["missing"].append(((h + k) % 65536, t))
            gaps.append({"after": h, "count": d - 1, "time": _sec(pkt["own"]), "frame": fr})
            marks.append((i, "serial_missing", d - 1))
            if sv < h:
                wraps += 1
            ctr["h"] = sv
            accept(i)
            continue
        pending = {"serial": sv, "t": t, "at": i}                              # 5. candidate
        accept(i)
    if packets:
        h_after[-1] = ctr["h"] if ctr is not None else None
    if pending is not None:
        out_of_order += 1
        marks.append((pending["at"], "serial_out_of_order", 1))
    lost = lost_frozen + (len(ctr["missing"]) if ctr else 0)
    return {"received": received, "lost": lost, "duplicates": duplicates, "out_of_order": out_of_order,
            "wraps": wraps, "gaps": gaps, "restarts": restarts, "marks": marks, "accepted": accepted,
            "h_after": h_after, "anomalies": len(gaps) + duplicates + out_of_order + len(restarts)}


def _counters(packets: list[dict], scope: str) -> dict[Optional[str], list[dict]]:
    """The sender's packets by counter: one (None) for scope `sender`, one per packet type for `type`."""
    out: dict[Optional[str], list[dict]] = {}
    for pkt in packets:
        out.setdefault(pkt["type"] if scope == "type" else None, []).append(pkt)
    return out


LOOKS_S = (10, 20, 40, 80, 160, 320)     # R17
LOOK_PACKETS = 4096


def _verdict(packets: list[dict], dup_w: int, flags: _Flags) -> tuple[str, bool]:
    """R17: the scope these packets ask for, and whether they tell (not when per-type counters
    explain them better but not by the margin: 4 anomalies fewer)."""
    one = _classify(packets, dup_w, flags)["anomalies"]
    per_type = sum(_classify(part, dup_w, flags)["anomalies"] for part in _counters(packets, "type").values())
    if per_type >= one:
        return "sender", True
    if per_type + 4 <= one:
        return "type", True
    return "sender", False


def _auto_scope(packets: list[dict], dup_w: int, flags: _Flags) -> str:
    """R17: from the sender's first packet of a second type (P) on: the look at 10 s from P, on
    the packets before it; while they cannot tell, again at 20, 40, ... 320 s; on the first 4096
    packets once as many have come; at the end of the capture, on all. One type only: `sender`."""
    second = [i for i, p in enumerate(packets) if p["type"] != packets[0]["type"]]
    if not second:
        return "sender"
    packets = packets[second[0]:]
    first = packets[0]["t"]
    for look in LOOKS_S:
        limit = look * NS
        for pkt in packets:
            flags.near(pkt["t"] - first, limit, f"scope look at {look} s, frame {pkt['frame']}")
        inside = [p for p in packets if p["t"] - first < limit]
        if len(inside) >= LOOK_PACKETS:
            return _verdict(packets[:LOOK_PACKETS], dup_w, flags)[0]
        scope, tells = _verdict(inside, dup_w, flags)
        if tells or look == LOOKS_S[-1] or len(inside) == len(packets):
            return scope
    raise AssertionError("the last look decides")


def _serials(s: dict, scope: str, dup_w: int, flags: _Flags, frames: dict, restart_at: dict) -> None:
    """The sender's serial verdicts, by the counter(s) of its scope (auto: chosen, R17)."""
    if scope == "auto":
        scope = _auto_scope(s["packets"], dup_w, flags)
    s["scope"] = scope
    total = {"received": 0, "lost": 0, "duplicates": 0, "out_of_order": 0, "wraps": 0, "gaps": []}
    events = []
    for part in _counters(s["packets"], scope).values():
        res = _classify(part, dup_w, flags)
        for key in total:
            total[key] += res[key]
        for i, pkt in enumerate(part):
            pkt["accepted"], pkt["h_after"] = res["accepted"][i], res["h_after"][i]
        for i, field, value in res["marks"]:
            frames.setdefault(part[i]["frame"], {})[field] = value
        for r in res["restarts"]:
            cand = part[r["at"]]
            events.append({"time": _sec(cand["own"]), "frame": cand["frame"], "from": r["from"], "to": r["to"]})
            if r["commands"]:
                restart_at[cand["frame"]] = {"sender": s["id"], "t": cand["t"]}
    total["gaps"].sort(key=lambda g: g["frame"])
    events.sort(key=lambda e: e["frame"])
    s["restart_events"] = events
    s["serial"] = {**total, "scope": scope}


def _highest_before(s: dict, frame: int, first_type: str) -> int:
    """R12, R18: the sender's highest serial just before `frame`: of its counter of `first_type`
    when it has one then (scope `type`), else of the counter of its last legal packet before it."""
    before = [q for q in s["packets"] if q["frame"] < frame]
    if s["scope"] == "type" and any(q["type"] == first_type for q in before):
        before = [q for q in before if q["type"] == first_type]
    return before[-1]["h_after"]


def _commands(legal: list[dict], senders: dict, restart_at: dict, reuse: int, fail_limit: dict, latest_t: int,
              flags: _Flags, frames: dict) -> dict:
    cmds: list[dict] = []
    latest: dict[tuple, dict] = {}        # (kind, sender, cid) -> its latest command
    life: dict[str, int] = {}             # sender -> restarts so far
    counts = {k: {"transmissions": 0, "spurious_retransmissions": 0, "acks_without_command": 0,
                  "duplicate_acks": 0} for k in ("VRCI", "VRCO")}
    for pkt in legal:
        fr, t = pkt["frame"], pkt["t"]
        if fr in restart_at:              # R8: before the packet itself
            ev = restart_at[fr]
            victim = ev["sender"]
            life[victim] = life.get(victim, 0) + 1
            for c in cmds:
                if c["sender"] != victim or c["acked"] or c["interrupted_by"] is not None:
                    continue
                age = ev["t"] - c["first_t"]
                flags.near(age, fail_limit[c["kind"]], f"interrupt vs fail limit, frame {fr}")
                if age <= fail_limit[c["kind"]]:
                    c["interrupted_by"] = fr
        if not pkt["accepted"]:
            continue
        ptype = pkt["type"]
        if ptype in ("VRCI", "VRCO"):
            key = (ptype, pkt["sender"], pkt["cid"])
            counts[ptype]["transmissions"] += 1
            c = latest.get(key)
            if c is not None:
                flags.near(t - c["last_t"], reuse, f"reuse gap, frame {fr}")
            if c is not None and c["life"] == life.get(pkt["sender"], 0) and t - c["last_t"] < reuse:
                c["frames"].append(fr)
                c["last_t"] = t
                frames.setdefault(fr, {})["retransmission_of"] = c["frames"][:-1]
                if c["acked"]:
                    counts[ptype]["spurious_retransmissions"] += 1
            else:
                c = {"kind": ptype, "sender": pkt["sender"], "cid": pkt["cid"], "first_t": t, "last_t": t,
                     "frames": [fr], "acked": False, "ack_t": None, "ack_frame": None,
                     "interrupted_by": None, "life": life.get(pkt["sender"], 0)}
                cmds.append(c)
                latest[key] = c
        elif ptype in ACK_OF:
            kind = ACK_OF[ptype]
            best = None
            for c in cmds:
                # cmds holds the commands in the order they began (file order), all before this ack
                if c["kind"] == kind and c["cid"] == pkt["cid"] and c["interrupted_by"] is None:
                    best = c
            if best is None:
                counts[kind]["acks_without_command"] += 1
                frames.setdefault(fr, {})["ack_without_command"] = 1
            elif best["acked"]:
                counts[kind]["duplicate_acks"] += 1
                frames.setdefault(fr, {})["duplicate_ack"] = 1
            else:
                best["acked"], best["ack_t"], best["ack_frame"] = True, t, fr
                frames.setdefault(best["frames"][0], {})["ack_in"] = fr
    out = {}
    for kind in ("VRCI", "VRCO"):
        mine = [c for c in cmds if c["kind"] == kind]
        acked = sum(1 for c in mine if c["acked"])
        interrupted = sum(1 for c in mine if c["interrupted_by"] is not None)
        failed = 0
        for c in mine:
            if c["interrupted_by"] is not None:
                frames.setdefault(c["frames"][0], {})["interrupted_by"] = c["interrupted_by"]
                continue
            if not c["acked"]:
                frames.setdefault(c["frames"][0], {})["never_acked"] = 1
                # failed only if the capture went on past its limit (docs/rules.md, "Failed")
                flags.near(latest_t - c["first_t"], fail_limit[kind], f"open at the end, frame {c['frames'][0]}")
                if latest_t - c["first_t"] > fail_limit[kind]:
                    failed += 1
                continue
            flags.near(c["ack_t"] - c["first_t"], fail_limit[kind], f"ack vs fail limit, frame {c['ack_frame']}")
            if c["ack_t"] - c["first_t"] > fail_limit[kind]:
                failed += 1
        n = len(mine)
        out[kind] = {"commands": n, "transmissions": counts[kind]["transmissions"],
                     "retransmissions": counts[kind]["transmissions"] - n, "acked": acked,
                     "unacked": n - acked - interrupted, "failed": failed, "interrupted": interrupted,
                     "spurious_retransmissions": counts[kind]["spurious_retransmissions"],
                     "acks_without_command": counts[kind]["acks_without_command"],
                     "duplicate_acks": counts[kind]["duplicate_acks"],
                     "list": [{"sender": c["sender"], "command_id": c["cid"], "frames": c["frames"],
                               "ack_frame": c["ack_frame"], "interrupted_by": c["interrupted_by"]}
                              for c in mine]}
    return out
