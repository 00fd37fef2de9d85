"""Random EG-Link traffic for the property tests, written with `struct` and the reference's own CRC:
no `vm110` code at all (not the simulator, not the encoder, not the capture writer).

A scenario (drawn by Hypothesis: the structure, plus a seed for the jitter and the per-packet dice)
has base units and controllers. Each device keeps one serial counter for everything it sends
(or, one device in four, one counter per packet type, as some devices number: interpretation.md,
"Serial numbers"): base units send VRPI every ~125 ms, VRCI commands (resent every ~100 ms until a VRAO arrives,
given up after 2 s) and VRAI acks; controllers send VRPO every 15-200 ms (unsplit; or split into
bursts of 488-byte parts and a shorter last one; or, for a periodic data size that is a multiple of
488, 1-3 parts of exactly 488 bytes, a fixed number per device), VRCO commands and VRAO acks.
Devices fall silent (in the middle, or for good while the capture goes on), restart (counter afresh
at 0, 1, a random value, above 32767; on the same or a new source port; command IDs afresh), reuse
command IDs after a pause, wrap IDs and serials. The network loses packets (both ways, or only at
the capture point), duplicates them (mirror copies 0.05-3 ms later), reorders them, delivers
single ones very late, corrupts some (bad CRC, wrong size, unknown ID, revision 1) and there is
unrelated UDP and ARP traffic.

`build(scenario)` gives the frames in arrival order with strictly increasing timestamps and the
generator's own notes (fuzzy: what it meant, not what the rules make of it); `write_capture`
writes pcap (Ethernet, optionally VLAN-tagged, or Linux cooked) or pcapng. `stepped_scenarios`
adds a clock that steps back: from a frame on, every timestamp is earlier by a fixed amount, or
the whole capture follows itself again with its own timestamps (two captures of the same link
appended, as `mergecap -a` does).
"""
from __future__ import annotations

import random
import struct
from typing import Any, Optional

from hypothesis import strategies as st

from .analyser import crc32_mpeg2

GROUP = bytes([239, 255, 42, 20])
IN_PORT, OUT_PORT = 5825, 5827
BASE_US = 1_760_000_000_000_000


# --- packets ------------------------------------------------------------------------------------
def packet(ptype: str, origin: int, serial: int, payload: bytes, revision: int = 0) -> bytes:
    body = ptype.encode() + struct.pack("<HHHHI", revision, origin, serial, len(payload), 0) + payload
    return body + struct.pack("<I", crc32_mpeg2(body))


def vrpi_payload(rng: random.Random, armed: bool) -> bytes:
    if armed:
        head = struct.pack("<BBBBBBHBBBBBB", 0x11, 1, 0, 1, 1, 1, 0x2345, 3, rng.randint(10, 100),
                           rng.randint(0, 100), 0, 0, 0)
        sticks = struct.pack("<4h", *(rng.randint(-1000, 1000) for _ in range(4)))
        switches = struct.pack("<8h", *(rng.randint(0, 1) for _ in range(8)))
        tail = struct.pack("<BB", rng.randint(0, 255), 0) + bytes(6)
    else:
        head = struct.pack("<BBBBBBHBBBBBB", 0x10, 1, 1, 1, 1, 6, 0, 0, 0, 0, 0, 0, 0)
        sticks, switches, tail = bytes(8), bytes(16), bytes(8)
    out = head + sticks + switches + tail
    assert len(out) == 46
    return out


def command_payload(cid: int, rng: random.Random) -> bytes:
    return struct.pack("<HI", cid, 0) + bytes(rng.randint(0, 255) for _ in range(16))


def ack_payload(cid: int) -> bytes:
    return struct.pack("<H", cid)


def corrupt(data: bytes, how: str) -> bytes:
    """An illegal variant of a legal packet."""
    if how == "bad_crc":
        return data[:-1] + bytes([data[-1] ^ 0x5A])
    if how == "extra_bytes":                 # UDP longer than 20 + size, CRC still right after size
        return data + b"\x00\x01"
    if how == "unknown_id":
        body = b"VRXX" + data[4:-4]
        return body + struct.pack("<I", crc32_mpeg2(body))
    if how == "revision":
        body = data[:4] + struct.pack("<H", 1) + data[6:-4]
        return body + struct.pack("<I", crc32_mpeg2(body))
    if how == "size_too_large":              # a consistent VRPO of 500 bytes
        body = data[:10] + struct.pack("<H", 500) + data[12:16] + bytes(500)
        return body + struct.pack("<I", crc32_mpeg2(body))
    raise ValueError(how)


CORRUPTIONS = ("bad_crc", "extra_bytes", "unknown_id", "revision", "size_too_large")


# --- scenario strategy --------------------------------------------------------------------------
SERIAL_STARTS = st.one_of(st.sampled_from([0, 1, 32767, 32768, 65530, 65535]), st.integers(0, 65535))


@st.composite
def _restart(draw: Any, duration: int, new_port_ok: bool) -> dict:
    new_port = new_port_ok and draw(st.booleans())
    silence = draw(st.integers(400, 3000)) if new_port else draw(st.sampled_from([0, 30, 150, 600, 2500, 4000]))
    return {"at": draw(st.integers(1500, max(1500, duration - 500))),
            "silence": silence,
            "serial": draw(st.one_of(st.sampled_from([0, 1, "wrap"]), st.integers(0, 65535),
                                     st.integers(32768, 65535))),
            "cid": draw(st.one_of(st.sampled_from([0, 1]), st.integers(0, 65535))),
            "new_port": new_port}


@st.composite
def _device(draw: Any, kind: str, duration: int, index: int) -> dict:
    dev = {"kind": kind, "index": index,
           "serial": draw(SERIAL_STARTS),
           "cid": draw(st.one_of(st.sampled_from([0, 65534, 65535]), st.integers(0, 65535))),
           "origin": (0x0101 + index) if kind == "bu" else 0,
           "ip": f"10.0.{1 if kind == 'bu' else 2}.{10 + index}",
           "port": (IN_PORT if kind == "bu" else draw(st.sampled_from([OUT_PORT, OUT_PORT, 49152 + index]))),
           # (15 ms: faster than recommended, unsplit packets closer than the 20 ms burst gap)
           "period": 125 if kind == "bu" else draw(st.sampled_from([15, 50, 100, 100, 150, 200])),
           # VRPO: unsplit (0..60 bytes), split (2-3 parts, the last short) or "full": a periodic
           # data size that is a multiple of 488, every VRPO 1-3 parts of exactly 488 bytes
           "vrpo": draw(st.sampled_from(["unsplit"] * 5 + ["split"] * 2 + ["full"] * 2)) if kind == "ctl" else None,
           "full_parts": draw(st.integers(1, 3)) if kind == "ctl" else 0,
           "armed": draw(st.booleans()),
           "commands": sorted(draw(st.lists(st.integers(0, duration - 200), max_size=8))),
           "reuse_p": draw(st.sampled_from([0.0, 0.0, 0.3])),
           "silences": draw(st.lists(st.tuples(st.integers(200, duration), st.integers(100, 4000)), max_size=2)),
           # (10 s or more: a restart candidate just before one is released after 10 s, and a
           # restart it hides is confirmed late, changing no command: rules.md rule 5)
           "outages": draw(st.lists(st.tuples(st.integers(200, duration),
                                              st.one_of(st.integers(300, 6000), st.integers(9500, 12000))),
                                    max_size=1)),
           "stop": draw(st.one_of(st.none(), st.integers(duration // 2, duration))),
           "start": draw(st.sampled_from([0, 0, 0, 300])),
           "restarts": draw(st.lists(_restart(duration, True), max_size=2)),
           "mirror": draw(st.integers(0, 5)) == 0,        # every packet of the device seen twice
           "numbering": draw(st.sampled_from(["sender", "sender", "sender", "type"])),
           }
    dev["restarts"].sort(key=lambda r: r["at"])
    return dev


@st.composite
def scenarios(draw: Any) -> dict:
    """A random traffic scenario; `build` turns it into frames."""
    duration = draw(st.integers(3000, 16000))
    bus = [draw(_device("bu", duration, i)) for i in range(draw(st.integers(1, 2)))]
    ctls = [draw(_device("ctl", duration, i)) for i in range(draw(st.integers(1, 2)))]
    return {
        "seed": draw(st.integers(0, 2 ** 32 - 1)),
        "duration": duration,
        "devices": bus + ctls,
        "net_loss": draw(st.sampled_from([0.0, 0.01, 0.05, 0.1])),
        "capture_loss": draw(st.sampled_from([0.0, 0.02, 0.05])),
        "dup": draw(st.sampled_from([0.0, 0.01, 0.05])),
        "reorder": draw(st.sampled_from([0.0, 0.01, 0.03])),
        "late": draw(st.sampled_from([0.0, 0.003, 0.01, 0.03])),
        "corrupt": draw(st.sampled_from([0.0, 0.01, 0.03])),
        "ack_loss": draw(st.sampled_from([0.0, 0.1, 0.3])),
        "slow_ack": draw(st.sampled_from([0.0, 0.0, 0.2])),     # the peer acks 1.5-2.6 s late
        "unrelated": draw(st.integers(0, 20)),
        "tail": draw(st.integers(0, 3000)),            # capture goes on this long after the last planned send
        "format": draw(st.sampled_from(["pcap", "pcap", "pcapng"])),
        "link": draw(st.sampled_from(["eth", "eth", "vlan", "cooked"])),
    }


@st.composite
def stepped_scenarios(draw: Any) -> dict:
    """A scenario whose capture clock steps back once (see `step_back`)."""
    sc = draw(scenarios())
    sc["step_back"] = draw(st.one_of(   # (microseconds: within and beyond the limits of the rules)
        st.tuples(st.just("shift"), st.floats(0.1, 0.9), st.sampled_from([200, 300_000, 900_000, 1_200_000,
                                                                           2_500_000, 40_000_000])),
        st.just(("append", 0.0, 0)),
        st.tuples(st.just("append"), st.floats(0.1, 0.9), st.just(0))))
    return sc


def step_back(frames: list[tuple[int, bytes]], how: tuple) -> list[tuple[int, bytes]]:
    """("shift", f, us): the frames from fraction f on are `us` microseconds earlier; ("append", f, 0):
    the capture, then again its part before fraction f (all of it for 0) with the same timestamps: a
    shorter capture appended leaves the clock ahead of its records."""
    kind, fraction, us = how
    if kind == "append":
        return frames + frames[:max(1, int(len(frames) * fraction)) if fraction else len(frames)]
    cut = max(1, int(len(frames) * fraction))
    return frames[:cut] + [(t - us, b) for t, b in frames[cut:]]


# --- simulation ---------------------------------------------------------------------------------
class _Dev:
    """A device's life: when it is active, its counter epochs and its source ports."""

    def __init__(self, d: dict, duration: int) -> None:
        self.d = d
        self.end = d["stop"] if d["stop"] is not None else duration
        self.gaps = [(a, a + n) for a, n in d["silences"]]
        self.restarts = []        # (resume time, silence start, serial, cid, port)
        port = d["port"]
        for k, r in enumerate(d["restarts"]):
            if r["new_port"]:
                port = 40000 + 100 * d["index"] + 10 * k + (1 if d["kind"] == "bu" else 2)
            self.restarts.append({"at": r["at"], "from": r["at"] - r["silence"], "serial": r["serial"],
                                  "cid": r["cid"], "port": port})
            if r["silence"]:
                self.gaps.append((r["at"] - r["silence"], r["at"]))

    def active(self, t: float) -> bool:
        if t < self.d["start"] or t >= self.end:
            return False
        return not any(a <= t < b for a, b in self.gaps)

    def epoch(self, t: float) -> int:
        return sum(1 for r in self.restarts if t >= r["at"])

    def port(self, t: float) -> int:
        e = self.epoch(t)
        return self.d["port"] if e == 0 else self.restarts[e - 1]["port"]

    def next_epoch_at(self, t: float) -> Optional[float]:
        later = [r["from"] for r in self.restarts if r["at"] > t]
        return min(later) if later else None


def build(sc: dict) -> tuple[list[tuple[int, bytes]], dict]:
    """Frames as (time in us since the capture's base, frame bytes) in arrival order, strictly
    increasing; plus the generator's notes."""
    rng = random.Random(sc["seed"])
    duration = sc["duration"]
    devs = [_Dev(d, duration) for d in sc["devices"]]
    bus = [x for x in devs if x.d["kind"] == "bu"]
    ctls = [x for x in devs if x.d["kind"] == "ctl"]
    sends: dict[int, list[dict]] = {i: [] for i in range(len(devs))}   # per device: planned packets
    notes: dict[str, Any] = {"restarts": [], "commands": 0}

    def outage(dev: _Dev, t: float) -> bool:
        return any(a <= t < a + n for a, n in dev.d["outages"])

    def delivered(dev: _Dev, t: float) -> bool:
        return not outage(dev, t) and rng.random() >= sc["net_loss"]

    # periodic traffic
    for i, dev in enumerate(devs):
        t = dev.d["start"] + rng.uniform(0, dev.d["period"])
        while t < duration:
            if dev.active(t):
                if dev.d["kind"] == "bu":
                    sends[i].append({"t": t, "type": "VRPI", "payload": vrpi_payload(rng, dev.d["armed"])})
                else:
                    vrpo = dev.d["vrpo"]
                    parts = rng.randint(2, 3) if vrpo == "split" else dev.d["full_parts"] if vrpo == "full" else 1
                    tp = t
                    for n in range(parts):
                        if vrpo == "full" or n < parts - 1:
                            size = 488
                        else:
                            size = rng.randint(0, 487 if parts > 1 else 60)
                        sends[i].append({"t": tp, "type": "VRPO",
                                         "payload": struct.pack("<H", n) + bytes(rng.randint(0, 255)
                                                                                 for _ in range(size))})
                        tp += rng.uniform(0.1, 3.0)
            t += dev.d["period"] + rng.uniform(-6, 6)

    # commands, resent until acked (the peer acks every copy it receives)
    for i, dev in enumerate(devs):
        peers = ctls if dev.d["kind"] == "bu" else bus
        if not peers:
            continue
        peer = peers[dev.d["index"] % len(peers)]
        j = devs.index(peer)
        ctype, atype = ("VRCI", "VRAO") if dev.d["kind"] == "bu" else ("VRCO", "VRAI")
        cid_by_epoch: dict[int, int] = {}
        prev_cid: Optional[int] = None
        for t0 in dev.d["commands"]:
            if not dev.active(t0):
                continue
            e = dev.epoch(t0)
            if e not in cid_by_epoch:
                cid_by_epoch[e] = dev.d["cid"] if e == 0 else dev.restarts[e - 1]["cid"]
                prev_cid = None
            if prev_cid is not None and rng.random() < dev.d["reuse_p"]:
                cid = prev_cid
            else:
                cid = cid_by_epoch[e]
                cid_by_epoch[e] = (cid + 1) % 65536
            prev_cid = cid
            notes["commands"] += 1
            stop_at = dev.next_epoch_at(t0)
            acked_at = None
            t = t0
            data = command_payload(cid, rng)
            while t < t0 + 2000 and t < duration and dev.active(t) and (stop_at is None or t < stop_at):
                if acked_at is not None and t >= acked_at:
                    break
                ok = delivered(dev, t)
                sends[i].append({"t": t, "type": ctype, "payload": data, "net_ok": ok})
                arrive = t + 0.3
                if ok and peer.active(arrive):
                    ta = arrive + (rng.uniform(1500, 2600) if rng.random() < sc["slow_ack"] else rng.uniform(0.5, 40))
                    if peer.active(ta) and ta < duration:
                        back = delivered(peer, ta) and rng.random() >= sc["ack_loss"]
                        sends[j].append({"t": ta, "type": atype, "payload": ack_payload(cid), "net_ok": back})
                        if back and (acked_at is None or ta + 0.3 < acked_at):
                            acked_at = ta + 0.3
                t += 100 + rng.uniform(-4, 4) + (rng.choice([0, 0, 0, 150]) if rng.random() < 0.05 else 0)

    # serials, ports and the network
    frames: list[tuple[float, int, bytes]] = []
    seq = 0
    for i, dev in enumerate(devs):
        pk = sorted(sends[i], key=lambda p: p["t"])
        epoch = -1
        first = 0
        serials: dict[str, int] = {}       # counter ("" for the device's one) -> its next serial
        mirror_dup = dev.d["mirror"]
        for p in pk:
            e = dev.epoch(p["t"])
            if e != epoch:
                if e == 0:
                    first = dev.d["serial"]
                else:
                    r = dev.restarts[e - 1]
                    # "wrap": the new counter wraps right after the restart
                    first = 65535 - rng.randint(0, 3) if r["serial"] == "wrap" else r["serial"]
                    notes["restarts"].append({"device": i, "at": r["at"], "serial": first,
                                              "port": r["port"]})
                serials = {}                       # every counter afresh, each at the same serial
                epoch = e
            counter = p["type"] if dev.d["numbering"] == "type" else ""
            serial = serials.get(counter, first)
            serials[counter] = (serial + 1) % 65536
            data = packet(p["type"], dev.d["origin"], serial, p["payload"])
            ok = p.get("net_ok")
            if ok is None:
                ok = delivered(dev, p["t"])
            if not ok or rng.random() < sc["capture_loss"]:
                continue
            t = p["t"] + rng.uniform(0.05, 0.5)
            roll = rng.random()
            if roll < sc["late"]:
                t += rng.uniform(100, 900)
            elif roll < sc["late"] + sc["reorder"]:
                t += rng.uniform(1, 30)
            if rng.random() < sc["corrupt"]:
                data = corrupt(data, rng.choice(CORRUPTIONS if p["type"] == "VRPO" else CORRUPTIONS[:4]))
            sport = dev.port(p["t"])
            dport = IN_PORT if dev.d["kind"] == "bu" else OUT_PORT
            fr = _udp_frame(dev.d["ip"], sport, dport, data, sc["link"])
            frames.append((t, seq, fr))
            seq += 1
            if mirror_dup or rng.random() < sc["dup"]:
                frames.append((t + rng.uniform(0.05, 3.0), seq, fr))
                seq += 1
    # unrelated traffic: other UDP ports, ARP (Ethernet only), one at the very end sometimes
    end = duration + sc["tail"]
    for k in range(sc["unrelated"]):
        t = rng.uniform(0, end)
        payload = b"XX" + bytes(rng.randint(0, 255) for _ in range(rng.randint(0, 60)))
        frames.append((t, seq, _udp_frame("10.0.9.9", rng.choice([53, 123, 5353, 40000]),
                                          rng.choice([53, 123, 5826, 6000]), payload, sc["link"])))
        seq += 1
        if sc["link"] != "cooked" and k % 5 == 0:
            frames.append((rng.uniform(0, end), seq, _arp_frame()))
            seq += 1
    if sc["tail"] > 0:
        frames.append((end, seq, _udp_frame("10.0.9.9", 123, 123, b"XXend", sc["link"])))
        seq += 1
    frames.sort(key=lambda x: (x[0], x[1]))
    out: list[tuple[int, bytes]] = []
    last = -1
    for t, _s, fr in frames:
        us = max(int(t * 1000), last + 1)
        out.append((us, fr))
        last = us
    return out, notes


# --- frames and files ---------------------------------------------------------------------------
def _ip_checksum(header: bytes) -> int:
    total = sum(struct.unpack("!10H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def _udp_frame(src: str, sport: int, dport: int, payload: bytes, link: str) -> bytes:
    udp = struct.pack("!HHHH", sport, dport, 8 + len(payload), 0) + payload
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0x4000, 1, 17, 0,
                     bytes(int(x) for x in src.split(".")), GROUP)
    ip = ip[:10] + struct.pack("!H", _ip_checksum(ip)) + ip[12:]
    if link == "cooked":
        return struct.pack("!HHH8sH", 0, 1, 6, bytes.fromhex("02fc00000001") + b"\0\0", 0x0800) + ip + udp
    mac = bytes.fromhex("01005e7f2a14") + bytes.fromhex("02fc00000001")
    if link == "vlan":
        eth = mac + struct.pack("!HHH", 0x8100, 42, 0x0800)
    else:
        eth = mac + struct.pack("!H", 0x0800)
    return (eth + ip + udp).ljust(60, b"\0")


def _arp_frame() -> bytes:
    return (bytes.fromhex("ffffffffffff02fc000000090806") + bytes.fromhex("0001080006040001")
            + bytes.fromhex("02fc00000009") + bytes([10, 0, 9, 9]) + bytes(6) + bytes([10, 0, 9, 1])).ljust(60, b"\0")


def write_capture(path: str, frames: list[tuple[int, bytes]], fmt: str = "pcap", link: str = "eth") -> None:
    """pcap (little-endian, microseconds) or pcapng (one section, one interface, enhanced packet
    blocks, microseconds); link type Ethernet (1) or Linux cooked (113)."""
    linktype = 113 if link == "cooked" else 1
    with open(path, "wb") as out:
        if fmt == "pcap":
            out.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, linktype))
            for us, fr in frames:
                sec, frac = divmod(BASE_US + us, 1_000_000)
                out.write(struct.pack("<IIII", sec, frac, len(fr), len(fr)) + fr)
            return
        shb_body = struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1)
        out.write(struct.pack("<II", 0x0A0D0D0A, 12 + len(shb_body)) + shb_body
                  + struct.pack("<I", 12 + len(shb_body)))
        opts = struct.pack("<HHB3x", 9, 1, 6) + struct.pack("<HH", 0, 0)
        idb_body = struct.pack("<HHI", linktype, 0, 65535) + opts
        out.write(struct.pack("<II", 1, 12 + len(idb_body)) + idb_body + struct.pack("<I", 12 + len(idb_body)))
        for us, fr in frames:
            ts = BASE_US + us
            pad = bytes(-len(fr) % 4)
            body = struct.pack("<IIIII", 0, ts >> 32, ts & 0xFFFFFFFF, len(fr), len(fr)) + fr + pad
            out.write(struct.pack("<II", 6, 12 + len(body)) + body + struct.pack("<I", 12 + len(body)))


def write_scenario(path: str, sc: dict) -> dict:
    """Build the scenario and write it; returns the generator's notes (with the frame count)."""
    frames, notes = build(sc)
    if sc.get("step_back"):
        frames = step_back(frames, sc["step_back"])
    write_capture(path, frames, sc["format"], sc["link"])
    notes["frames"] = len(frames)
    return notes
