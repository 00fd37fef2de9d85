"""The verdict: totals, the findings they raise, and where each finding lies in the capture.

Every finding lists `items[]` (at most MAX_ITEMS, `more` counting the rest): the frame(s), the
time, the sender and what identifies it (serial, command ID, gap, ...), and a Wireshark display
filter that selects its frames. Only the first MAX_ITEMS items of a rule (by frame) are kept,
and a count of all: never one item per packet.
"""
from __future__ import annotations

from typing import Any, Optional

from .. import constants as C
from ..capture.linktypes import TUNNEL_PORTS, TUNNEL_PROTOCOLS, unread
from .commands import Tally
from ..words import plural
from .collect import CODE, TYPES

MAX_ITEMS = 100
# The IP fragment frames of datagrams not reassembled, in Wireshark (which reassembles by default, as
# both engines do): a fragment neither reassembled in a later frame nor the frame of a reassembly. An
# IPv6 atomic fragment (offset 0, no more) is a whole datagram, as the reader has it. (tshark needs
# its second pass, -2, to know `reassembled_in`.)
FRAGMENT_FILTER = ("((ip.flags.mf == 1 || ip.frag_offset > 0) && !ip.reassembled_in && !ip.fragments) || "
                   "((ipv6.fraghdr.more == 1 || ipv6.fraghdr.offset > 0) "
                   "&& !ipv6.reassembled.in && !ipv6.fragments)")
_PROTOCOLS = ", ".join(map(str, sorted(TUNNEL_PROTOCOLS)))
TUNNEL_FILTER = (f"ip.proto in {{{_PROTOCOLS}}} || ipv6.nxt in {{{_PROTOCOLS}}} || "
                 f"udp.dstport in {{{', '.join(map(str, sorted(TUNNEL_PORTS)))}}}")   # (shows the tunnels)

def _order(item: dict) -> tuple:
    return item["frame"], item.get("sender") or ""


class Kept:
    """The first MAX_ITEMS items of one rule in (frame, sender) order, ties in the order added,
    and how many were added."""

    def __init__(self) -> None:
        self.items: list[dict] = []
        self.total = 0

    def add(self, item: dict) -> None:
        self.items.append(item)
        self.total += 1
        if len(self.items) >= 2 * MAX_ITEMS:
            self._trim()

    def _trim(self) -> None:
        self.items.sort(key=_order)              # stable: earlier ones first among equals
        del self.items[MAX_ITEMS:]

    def first(self) -> list[dict]:
        self._trim()
        return self.items


Located = dict[str, Kept]
_ACK_CODE = {CODE[cmd]: CODE[ack] for ack, cmd in C.ACK_OF.items()}

TOTAL_NAMES = ("packets", "eglink_packets", "damaged", "lost", "duplicates", "out_of_order", "restarts", "illegal",
               "crc_invalid", "watchdog", "vrpo_outside_recommended", "commands", "retransmissions", "unacked",
               "failed", "interrupted", "spurious", "acks_without_command", "duplicate_acks", "relays_open",
               "vrpo_incomplete", "time_backwards", "snaplen_truncated", "capture_dropped", "jitter_max_ms",
               "interval_max_ms", "ack_latency_max_ms")
MAX_TOTALS = frozenset({"jitter_max_ms", "interval_max_ms", "ack_latency_max_ms"})   # combined by max, not sum

# (total, severity, message after the count: singular, plural) for each finding the verdict
# reports when its total is above 0, notes last. The severity is that of the dissector's experts of
# the same finding (test_dissector_analysis holds them together), as Wireshark's expert infos have
# it: an error fails the verdict; a note (TCP's retransmissions and duplicate ACKs are notes) is no
# problem, and fails nothing unless a --fail-on rule names it.
SEVERITIES = ("error", "warning", "note")
FINDINGS = (
    ("lost", "error", "packet lost (serial gaps)", "packets lost (serial gaps)"),
    ("illegal", "error", "illegal packet", "illegal packets"),
    ("watchdog", "error", "watchdog violation", "watchdog violations"),
    ("failed", "error", "command failed (no acknowledgement within the limit)",
     "commands failed (no acknowledgement within the limit)"),
    ("unacked", "error", "command never acknowledged", "commands never acknowledged"),
    ("restarts", "warning", "sender restart (serial counter started afresh)",
     "sender restarts (serial counter started afresh)"),
    ("relays_open", "warning", "episode with the ES-Link relays open", "episodes with the ES-Link relays open"),
    ("duplicates", "warning", "duplicated packet", "duplicated packets"),
    ("out_of_order", "warning", "packet out of order", "packets out of order"),
    ("acks_without_command", "warning", "acknowledgement without a command", "acknowledgements without a command"),
    ("vrpo_incomplete", "warning", "incomplete VRPO burst", "incomplete VRPO bursts"),
    ("time_backwards", "warning", "timestamp going backwards", "timestamps going backwards"),
    ("snaplen_truncated", "warning", "datagram cut short by the capture's snaplen",
     "datagrams cut short by the capture's snaplen"),
    ("interrupted", "note", "command interrupted by its sender's restart",
     "commands interrupted by their sender's restart"),
    ("spurious", "note", "retransmission after the acknowledgement", "retransmissions after the acknowledgement"),
    ("duplicate_acks", "note", "duplicate acknowledgement", "duplicate acknowledgements"),
    ("vrpo_outside_recommended", "note", "VRPO interval outside the recommended range",
     "VRPO intervals outside the recommended range"),
)

# The dissector's experts that mark exactly the frames of a rule's items (tshark -2, or the GUI):
# the filter that shows all of them, also those beyond the MAX_ITEMS the report keeps. The other
# rules have none: lost (the dissector also marks a gap whose packets all came later), failed (also
# a command still in flight at the end), vrpo_incomplete (marked on the burst's last packet),
# relays_open (marked on every packet of an episode) and snaplen_truncated (with other truncations).
def illegal_filter(input_port: int) -> str:
    """Wireshark gives an empty datagram no dissector ("UDP Len=0", a truncated EG-Link packet
    here): it is found by the EG-Link ports, those of the analysis."""
    return (" || ".join(f"vm110.expert.{problem.value}" for problem in C.Problem)
            + f" || (udp.length == 8 && udp.port in {{{input_port}, {input_port + C.OUTPUT_PORT - C.INPUT_PORT}}})")


RULE_FILTERS = {
    "illegal": illegal_filter(C.INPUT_PORT),
    "watchdog": "vm110.expert.watchdog_vrpi || vm110.expert.watchdog_vrpo || vm110.expert.silent_until_end",
    "unacked": "vm110.expert.never_acked",
    "restarts": "vm110.expert.restart",
    "interrupted": "vm110.expert.command_interrupted",
    "duplicates": "vm110.expert.serial_duplicate",
    "out_of_order": "vm110.expert.serial_out_of_order",
    "spurious": "vm110.expert.spurious_retransmission",
    "acks_without_command": "vm110.expert.ack_without_command",
    "duplicate_acks": "vm110.expert.duplicate_ack",
    "vrpo_outside_recommended": "vm110.expert.vrpo_interval",
    "time_backwards": "vm110.expert.time_backwards",
}


def frame_filter(frames: list[int]) -> str:
    """A display filter selecting exactly these frames, by number: no field of the analysis, whose
    verdicts hang on the preferences (a long command was once narrowed by its transmissions'
    `!vm110.analysis.serial_duplicate`, which shows other frames under another duplicate window,
    and illegal copies besides). Runs of consecutive numbers as ranges (`a..b`), to keep it short."""
    if len(frames) == 1:
        return f"frame.number == {frames[0]}"
    runs: list[list[int]] = []
    for f in sorted(set(frames)):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    return "frame.number in {" + ", ".join(str(a) if a == b else f"{a}..{b}" for a, b in runs) + "}"


def located_item(frames: Any, time: float, sender: Optional[str], **what: Any) -> dict:
    """One item of a finding: its frame(s), time, sender, details and the display filter that shows it
    (also the shape of `vm110 monitor`'s live findings)."""
    frames = [int(f) for f in frames] if isinstance(frames, list) else [int(frames)]
    item: dict = {"frame": frames[0]}
    if len(frames) > 1:
        item["frames"] = frames
    item["time"] = time
    if sender is not None:
        item["sender"] = sender
    item.update(what)
    item["filter"] = frame_filter(frames)
    return item


class Where:
    """Adds located items to the findings of a report under construction."""

    def __init__(self, located: Located) -> None:
        self.located = located

    def add(self, rule: str, frames: Any, time: float, sender: Optional[str], **what: Any) -> None:
        self._kept(rule).add(located_item(frames, time, sender, **what))

    def skip(self, rule: str, count: int) -> None:
        """Count items that lie beyond the first MAX_ITEMS of their rule without making them."""
        self._kept(rule).total += count

    def _kept(self, rule: str) -> Kept:
        kept = self.located.get(rule)
        if kept is None:
            kept = self.located[rule] = Kept()
        return kept


def locate_report(report: dict, tallies: dict[int, Tally], located: Located) -> None:
    """Items of the findings that the report's sections know of: commands, acks, illegal packets
    and relay episodes (serials, streams and bursts are located as they are judged)."""
    where = Where(located)
    for code, tally in tallies.items():
        kind = TYPES[code].value
        listed = report["commands"][kind]["list"]      # (in the tally's order, each with its `failed`)
        for c, entry in zip(tally.commands, listed):
            what = {"type": kind, "command_id": c.command_id}
            began = entry["time"]                      # (the first frame's own time)
            if c.interrupted_frame is not None:
                where.add("interrupted", c.frames, began, c.sender, interrupted_frame=c.interrupted_frame, **what)
            elif c.ack_frame is None:
                where.add("unacked", c.frames, began, c.sender, **what)
            if entry["failed"]:
                where.add("failed", c.frames + ([c.ack_frame] if c.ack_frame else []), began, c.sender,
                          latency_ms=c.latency_first_ms, ack_frame=c.ack_frame, **what)
            for f, t in zip(c.frames, c.times):
                if f in c.spurious_frames:
                    where.add("spurious", f, tally.time_of(f, t), c.sender, ack_frame=c.ack_frame, **what)
        ack = TYPES[_ACK_CODE[code]].value
        for f, t, cid, sender in tally.orphan_acks:
            where.add("acks_without_command", f, tally.time_of(f, t), sender, type=ack, command_id=cid)
        for f, t, cid, first, sender in tally.duplicate_acks:
            where.add("duplicate_acks", f, tally.time_of(f, t), sender, type=ack, command_id=cid, command_frame=first)
    for ex in report["illegal"]["examples"]:
        where.add("illegal", ex["frame"], ex["time"], ex["src"], type=ex["type"], reasons=ex["reasons"])
        if ex["reasons"] == ["truncated"]:
            where.add("snaplen_truncated", ex["frame"], ex["time"], ex["src"], type=ex["type"])
    for st in report["state"]:
        for e in st["episodes_relays_open"]:
            where.add("relays_open", e["frame"], e["start"], st["sender"], duration_s=e["duration_s"],
                      states=e["states"], open_at_end=e["open_at_end"])


def totals(report: dict) -> dict:
    """The numbers `--fail-on` rules refer to."""
    senders, periodic, cmds = report["senders"], report["periodic"], report["commands"]
    jitters = [p["jitter_ms"]["max"] for p in periodic if p["jitter_ms"] and p["jitter_ms"]["max"] is not None]
    maxes = [p["interval_ms"]["max"] for p in periodic if p["interval_ms"]["max"] is not None]
    lat = [c["ack_latency_ms"]["max"] for c in cmds.values() if c["ack_latency_ms"]["max"] is not None]
    return {
        "packets": report["capture"]["packets"],
        "eglink_packets": report["capture"]["eglink_packets"],
        "damaged": int(report["capture"]["problem"] is not None),
        "lost": sum(s["serial"]["lost"] for s in senders),
        "duplicates": sum(s["serial"]["duplicates"] for s in senders),
        "out_of_order": sum(s["serial"]["out_of_order"] for s in senders),
        "restarts": sum(s["serial"]["restarts"] for s in senders),
        "illegal": report["illegal"]["total"],
        "crc_invalid": report["crc"]["invalid"],
        "watchdog": sum(len(p["watchdog"]["violations"]) for p in periodic),
        "vrpo_outside_recommended": sum(p.get("outside_recommended", {}).get("count", 0) for p in periodic),
        "commands": sum(c["commands"] for c in cmds.values()),
        "retransmissions": sum(c["retransmissions"] for c in cmds.values()),
        "unacked": sum(c["unacked"] for c in cmds.values()),
        "failed": sum(c["failed"] for c in cmds.values()),
        "interrupted": sum(c["interrupted"] for c in cmds.values()),
        "spurious": sum(c["spurious_retransmissions"] for c in cmds.values()),
        "acks_without_command": sum(c["acks_without_command"] for c in cmds.values()),
        "duplicate_acks": sum(c["duplicate_acks"] for c in cmds.values()),
        "relays_open": sum(len(s["episodes_relays_open"]) for s in report["state"]),
        "vrpo_incomplete": report["vrpo_bursts"]["incomplete"],
        "time_backwards": report["capture"]["time_backwards"],
        "snaplen_truncated": report["capture"]["snaplen_truncated"],
        "capture_dropped": (report["capture"]["dropped"] or {}).get("total", 0),
        "jitter_max_ms": max(jitters) if jitters else 0.0,
        "interval_max_ms": max(maxes) if maxes else 0.0,
        "ack_latency_max_ms": max(lat) if lat else 0.0,
    }


def _items(kept: Kept) -> dict:
    out: dict = {"items": kept.first()}
    if kept.total > MAX_ITEMS:
        out["more"] = kept.total - MAX_ITEMS
    return out


# The pcapng names of the capture's drop counts (capture.dropped), as the message gives them.
_DROP_NAMES = {"ifdrop": "isb_ifdrop", "osdrop": "isb_osdrop", "dropcount": "epb_dropcount"}


def capture_dropped(dropped: dict, lost: int, ports: list[int]) -> str:
    """The warning that the capture itself dropped packets, which a serial gap cannot tell from
    packets the link lost: how many, against how many are counted lost, what helps, and where
    Wireshark shows them (frame.drop_count: the packets after a drop, where the packet blocks say)."""
    said = ", ".join(f"{_DROP_NAMES[k]} {dropped[k]}" for k in _DROP_NAMES if dropped[k] is not None)
    after = "; the packets after a drop: frame.drop_count > 0" if dropped["dropcount"] else ""
    share = (f"up to {min(dropped['total'], lost)} of the {plural(lost, 'packet')} counted lost (serial gaps) may "
             f"be the capture's, not the link's" if lost else "no packet is counted lost")
    return (f"the capture dropped {plural(dropped['total'], 'packet')} itself (pcapng {said}): {share}; capture with "
            f"a bigger buffer (dumpcap -B), a capture filter on the EG-Link ports "
            f"(-f \"udp port {ports[0]} or udp port {ports[1]}\"), a faster disk; Wireshark: Statistics > "
            f"Capture File Properties, Dropped packets{after}")


def verdict(report: dict, located: Located, prefs: Optional[list[str]], no_filters: Optional[str] = None) -> dict:
    """The findings; `prefs`: the dissector's preferences (not at their defaults) under which it
    judges as the report did, so that each rule's filter (RULE_FILTERS) is given with them; None:
    no preferences do, no rule filters (`no_filters` says why)."""
    tot = report["totals"]
    filters = {**RULE_FILTERS, "illegal": illegal_filter(report["capture"]["ports"][0])} if prefs is not None else {}
    findings = [{"rule": key, "severity": sev, "count": tot[key],
                 "message": f"{tot[key]} {one if tot[key] == 1 else many}",
                 **({"filter": filters[key]} if key in filters else {}), **_items(located.get(key, Kept()))}
                for key, sev, one, many in FINDINGS if tot[key] > 0]
    cap = report["capture"]
    if cap["problem"]:
        # Located by the last frame read before the damage (Wireshark stops there too).
        where = [{"frame": cap["packets"], "time": cap["last_time"], "offset": (cap["damage"] or {}).get("offset"),
                  "filter": frame_filter([cap["packets"]])}] if cap["packets"] else []
        findings.insert(0, {"rule": "damaged", "severity": "error", "count": 1,
                            "message": f"capture damaged: {cap['problem']}", "items": where})
    # Packets behind the analysis clock (rules.md), whose latencies and windows are that clock's: said
    # where no stream steps back in time, which time_backwards says (one cause, one finding).
    if cap["behind_clock"] and not cap["time_backwards"]:
        findings.insert(0, {"rule": "not_in_time_order", "severity": "warning", "count": cap["behind_clock"],
                            "message": f"{plural(cap['behind_clock'], 'EG-Link packet')} earlier than a packet "
                                       f"before {'it' if cap['behind_clock'] == 1 else 'them'} "
                                       "(captures appended, taps merged unsorted, a clock set back): latencies, "
                                       "fail limits and windows across them run on a clock that does not go back "
                                       "(docs/rules.md); where the time steps back: frame.time_delta < 0; records "
                                       "of several taps into time order: reordercap IN OUT", "items": []})
    if tot["capture_dropped"]:
        findings.insert(0, {"rule": "capture_dropped", "severity": "warning", "count": tot["capture_dropped"],
                            "message": capture_dropped(cap["dropped"], tot["lost"], cap["ports"]), "items": []})
    if cap["fragments"]:      # (not reassembled: what they carry is missing from everything above)
        findings.insert(0, {"rule": "ip_fragments", "severity": "warning", "count": cap["fragments"],
                            "message": f"{plural(cap['fragments'], 'IP fragment')} not analysed (never reassembled: "
                                       f"a fragment lost or cut by the capture, EG-Link packets in them then "
                                       f"counting as lost; or a mirror port's copy of a fragment that came after "
                                       f"its datagram was whole, which was analysed): {FRAGMENT_FILTER}", "items": []})
    if cap["unread_frames"]:  # (what they carry is missing from everything above, as with fragments)
        findings.insert(0, {"rule": "unread_link_type", "severity": "warning", "count": cap["unread_frames"],
                            "message": unread(cap["unread_frames"], cap["link_types"],
                                              "--engine tshark reads what Wireshark reads"), "items": []})
    if cap["tunnelled_frames"]:  # (what they carry is missing from everything above, as with fragments)
        findings.insert(0, {"rule": "tunnels", "severity": "warning", "count": cap["tunnelled_frames"],
                            "message": f"{plural(cap['tunnelled_frames'], 'frame')} of tunnels not unwrapped (IP in "
                                       f"IP, GRE with ERSPAN, VXLAN, GENEVE): EG-Link packets in them are not "
                                       f"analysed; --engine tshark unwraps them: {TUNNEL_FILTER}", "items": []})
    if not report["capture"]["eglink_packets"]:
        # (a link silent from the start is no clean verdict either: README, "Silence")
        findings.insert(0, {"rule": "no_eglink", "severity": "error", "count": 0,
                            "message": "no EG-Link packets in the capture", "items": []})
    # Errors first, then warnings, then notes (a reader stopping early sees the worst), the capture's
    # own findings first among their severity (stable: the order above within each).
    findings.sort(key=lambda f: SEVERITIES.index(f["severity"]))
    return {"ok": not any(f["severity"] == "error" for f in findings), "findings": findings,
            **({"wireshark_prefs": prefs} if prefs else {}),
            **({"no_filters": no_filters} if prefs is None and no_filters else {})}

