"""The terminal dashboard: plain ANSI (home, clear to end of line), so that it works in any
terminal of 80x24 or more and over SSH; redrawn about once a second. `render` is pure: the
lines for a view, a width and a height."""
from __future__ import annotations

import datetime
import shutil
import sys
from typing import Optional, Protocol

from ..printable import escaped
from ..timefmt import utc_iso

_ENTER, _LEAVE = "\033[?1049h\033[?25l", "\033[?25h\033[?1049l"


def clock(t: Optional[float]) -> str:
    """The header's UTC date and time of `t` to the millisecond (it changes every second)."""
    if t is None:
        return "--:--:--.---"
    try:
        return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
    except (OverflowError, OSError, ValueError):
        return f"{t:.3f}"


def _ms(v: Optional[float]) -> str:
    if v is None:
        return "-"
    return f"{v / 1000:.1f} s" if v >= 10_000 else f"{v:.0f} ms"


def short(sid: str) -> str:
    # "input 127.0.0.10:5825 origin 0x0101" -> "127.0.0.10:5825 0x0101"
    parts = sid.split()
    return f"{parts[1]} {parts[3]}" if len(parts) == 4 else sid


# A sender's serial scope; None until `auto` has chosen it: choosing, or one packet type so far.
_SCOPES = {"sender": "one counter", "type": "per type", None: "one type so far"}


def sender_lines(s: dict) -> list[str]:
    role = "BU " if s["role"] == "BU" else "CTL"
    head = (f"{role} {short(s['sender']):<28} {s['state'].upper():<8} {s['type']} {_ms(s['age_ms'])} ago  "
            f"jitter {'-' if s['jitter_ms'] is None else format(s['jitter_ms'], '.1f') + ' ms'}")
    loss = (f"    loss {s['lost_1m']}/{s['lost']}  dup {s['duplicates_1m']}/{s['duplicates']} (1m/all)"
            f"  restarts {s['restarts']}  serials {'choosing' if s['serial_choosing'] else _SCOPES[s['serial_scope']]}")
    if s["role"] == "BU":
        if "bu_state" in s:
            relays = "OPEN" if s["relays_open"] else "closed"
            second = (f"    {s['bu_state']} RU {s['armed_ru']} {s['ru_state']} bat {s['ru_battery']}% "
                      f"rssi {s['ru_rssi']}%  relays {relays}")
        else:
            second = "    no VRPI yet"
    else:
        span = s["interval_1m_ms"]
        low, high = s["recommended_ms"]
        second = (f"    VRPO interval {_ms(s['interval_ms'])}"
                  + (f" (1m {span[0]:.0f}-{span[1]:.0f})" if span else "")
                  + f", outside {low:g}-{high:g}: {s['outside_recommended_1m']}/{s['outside_recommended']}")
    return [head, loss, second]


def when(t: float, today: Optional[str] = None) -> str:
    """A finding's time: ISO 8601 UTC with its date (a run of days), as the project's times; on
    the dashboard, whose header gives the date (`today`, YYYY-MM-DD), the time alone on that day
    (an 80-column line keeps room for the message)."""
    stamp = utc_iso(t)
    return stamp[11:] if stamp[:10] == today else stamp


def finding_line(f: dict, today: Optional[str] = None) -> str:
    sev = "ERROR" if f["severity"] == "error" else "warn "
    event = {"raised": "!", "cleared": "ok", "found": ""}.get(f["event"], "")
    who = f" {short(f['sender'])}" if f.get("sender") else ""
    where = (f.get("item") or {}).get("filter")
    rule = f"{f['rule']} {event}" if event else f["rule"]
    # (a message may quote the network: an illegal packet's ID "\x1b[2J" would clear the screen)
    return escaped(f"{when(f['time'], today)} #{f['frame']} {sev} {rule}{who}: {f['message']}" + (
        f"  [{where}]" if where else ""))


def render(header: dict, view: dict, findings: list[dict], width: int, height: int) -> list[str]:
    """The dashboard's lines (at most `height`, each at most `width` characters)."""
    width, height = max(width, 20), max(height, 5)
    c = view["commands"]
    lat = c["ack_latency_ms"]
    # (the source last: a long path is cut, never the status or the time)
    now = clock(header["now"])
    today = now[:10]
    lines = [f"vm110 monitor  {header['status']}  {now} UTC  {header['source']}",
             (f"packets {header['packets']} ({header['rate']:.0f}/s)  EG-Link {header['eglink']}  "
              f"illegal {header['illegal']}  alarms {len(header['alarms'])}")]
    lines += [f"  ALARM {a['rule']} {short(a.get('sender') or '')} since {when(a['time'], today)} #{a['frame']}"
              for a in header["alarms"][:3]]
    lines.append("")
    senders = view["senders"]
    # Room for every sender while the commands and two findings still fit; then a count.
    fit = max(0, (height - len(lines) - 4) // 3)
    for s in senders[:fit]:
        lines += sender_lines(s)
    if len(senders) > fit:
        lines.append(f"... {len(senders) - fit} more sender(s): see --json-lines")
    lines.append(f"commands {c['commands']}: in flight {c['in_flight']}  unacked {c['unacked']}  failed {c['failed']}"
                 f"  ack {_ms(lat['last'])} (1m max {_ms(lat['max_1m'])})")
    room = height - len(lines) - 1
    if room > 0:
        lines.append("findings (latest last):")
        lines += [finding_line(f, today) for f in findings[-room:]] if findings else ["  none"]
    return [escaped(ln)[:width] for ln in lines[:height]]      # (the source: a file name of any bytes)


class Writer(Protocol):
    def write(self, text: str) -> object: ...

    def flush(self) -> object: ...


class Dashboard:
    """Draws on `out` (a terminal; standard output as it is when made)."""

    def __init__(self, out: Optional[Writer] = None) -> None:
        self.out = sys.stdout if out is None else out
        self.on = False

    def draw(self, lines: list[str]) -> None:
        if not self.on:
            self.out.write(_ENTER)
            self.on = True
        # No newline after the last line: a full screen must not scroll.
        self.out.write("\033[H" + "\033[K\r\n".join(lines) + "\033[K\033[J")
        self.out.flush()

    @staticmethod
    def size() -> tuple[int, int]:
        size = shutil.get_terminal_size((80, 24))
        return size.columns, size.lines

    def close(self) -> None:
        if self.on:
            self.on = False                # (once, should the terminal be gone)
            self.out.write(_LEAVE)
            self.out.flush()
