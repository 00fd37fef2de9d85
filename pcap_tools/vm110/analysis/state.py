"""State timeline of a base unit from its VRPI packets: BU state, link statuses, armed RU, RU
state, battery and RSSI, and the episodes with the ES-Link relays open (BU state below 0x10)."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from .. import constants as C
from .. import protocol as P
from .collect import STATE, STATE_FIELDS

SEGMENT_FIELDS = ("bu_state", "eg_link", "ec_link", "c_link", "armed_ru", "ru_state")
LEVEL_FIELDS = ("ru_battery", "ru_rssi")
MAX_POINTS = 500          # battery/RSSI samples kept for plotting
_NAMES = {name: P.ENUM_FIELDS.get(name, {}) for name in SEGMENT_FIELDS}


def _name(field: str, value: int) -> str:
    names = _NAMES[field]
    if field == "armed_ru":
        return f"0x{value:04X}" if value else "none"
    return names.get(value, f"Unknown (0x{value:02x})")


class Timeline:
    """The state timeline of one base unit, fed its accepted VRPI packets a batch at a time: only
    the changes of state are kept (segments, battery/RSSI levels), not the packets."""

    def __init__(self) -> None:
        self.segments: dict = {f: [] for f in SEGMENT_FIELDS}
        self.levels: dict = {f: [] for f in LEVEL_FIELDS}
        self.last_state = None            # the state bytes of the last packet
        self.last_time: Optional[float] = None

    def feed(self, times: Sequence[float], states: np.ndarray, frames: Sequence[int]) -> None:
        """VRPI times, state bytes (collect.STATE) and frame numbers, in arrival order."""
        if not len(states):
            return
        first = self.last_state is None or states[0] != self.last_state
        at = ([0] if first else []) + (np.flatnonzero(states[1:] != states[:-1]) + 1).tolist()
        segments, levels = self.segments, self.levels
        for i in at:
            when, frame = float(times[i]), int(frames[i])
            st = dict(zip(STATE_FIELDS, STATE.unpack(states[i].tobytes())))
            for f in SEGMENT_FIELDS:
                seg = segments[f]
                if not seg or seg[-1]["value"] != st[f]:
                    if seg:
                        seg[-1]["end"] = when
                    seg.append({"start": when, "end": None, "value": st[f], "name": _name(f, st[f]), "frame": frame})
            for f in LEVEL_FIELDS:
                if not levels[f] or levels[f][-1][1] != st[f]:
                    levels[f].append((when, st[f]))
        self.last_state = states[-1].copy()
        self.last_time = float(times[-1])

    def report(self, end_time: Optional[float]) -> dict:
        """Segments per field, battery/RSSI samples, and ES-Link relay open episodes; `end_time`:
        the capture's last record."""
        segments = {f: [dict(seg) for seg in segs] for f, segs in self.segments.items()}
        for seg in segments.values():
            if seg:
                seg[-1]["end"] = self.last_time
        out = {"segments": segments, "episodes_relays_open": relay_episodes(segments["bu_state"], end_time)}
        for f in LEVEL_FIELDS:
            levels = self.levels[f]
            values = [v for _, v in levels]
            step = max(1, len(levels) // MAX_POINTS)
            out[f] = {"min": min(values) if values else None, "max": max(values) if values else None,
                      "last": values[-1] if values else None,
                      "samples": [[t, v] for t, v in levels[::step]]}
        return out


def relay_episodes(bu_segments: list, end_time: Optional[float]) -> list[dict]:
    """Runs of segments with BU state below Disarmed, merged when adjacent."""
    episodes: list[dict] = []
    for seg in bu_segments:
        if seg["value"] < C.ES_RELAYS_CLOSED_FROM:
            if episodes and episodes[-1]["_open"]:
                episodes[-1]["states"].append(seg["name"])
                continue
            episodes.append({"start": seg["start"], "end": None, "states": [seg["name"]],
                             "frame": seg["frame"], "_open": True})
        elif episodes and episodes[-1]["_open"]:
            episodes[-1]["end"] = seg["start"]
            episodes[-1]["_open"] = False
    for ep in episodes:
        still = ep.pop("_open")
        ep["open_at_end"] = still
        if still:
            ep["end"] = end_time
        ep["duration_s"] = None if ep["end"] is None else ep["end"] - ep["start"]
    return episodes
