"""Restarts of the peer a node hears, packet by packet, by interpretation.md ("Sender restarts").

A receiver must know when its peer rebooted: the peer's command stream starts afresh there, so a
command ID it reuses afterwards is a new command even within the reuse gap. A counter restarts at
a serial that is none of in order, a duplicate, late or a plausible gap, once the counter's next
packet that is not a copy of it confirms it (serial + 1 … + 4), changing the commands only when
that comes less than 10 s after it (rules.md rule 5); a sender that appears on a new
source port of the same origin and address after 250 ms of silence of the old one restarted too.
"""
from __future__ import annotations

from collections import deque
from typing import Any, Hashable, Optional

from .. import constants as C
from .clock import US_PER_S, ms

# The rule's numbers (the ground truth, `sim.truth`, judges by them too).
DUP_WINDOW_US = ms(1000)            # a serial accepted less than this ago is a duplicate
NEW_PORT_SILENCE_US = ms(250)       # an earlier sender silent this long may reappear on a new port
RATE_WINDOW_US = 10 * US_PER_S      # the counter's rate: its packets in the 10 s before
PLAUSIBLE_BASE, PLAUSIBLE_FACTOR, MIN_RATE = 64, 4, 20     # plausible loss: d - 1 <= 64 + 4 max(r, 20) dt
CONFIRM = 4                         # a restart candidate s is confirmed by s + 1 .. s + 4
CANDIDATE_WAIT_US = 10 * US_PER_S   # a restart confirmed this long after its candidate changes no command
_HALF = C.SERIAL_HALF


class SerialCounter:
    """One sender's serial counter as a receiver follows it (times in µs)."""

    def __init__(self, serial: int, now: int) -> None:
        self._reset(serial, now)

    @property
    def candidate(self) -> Optional[int]:
        """The serial of a restart not yet confirmed, if any."""
        return None if self._candidate is None else self._candidate[0]

    def _reset(self, serial: int, now: int) -> None:
        self.high, self.start, self.last = serial, now, now
        self._seen: dict[int, int] = {serial: now}                # serial -> when, within the window
        self._recent: deque[tuple[int, int]] = deque([(now, serial)])   # (when, serial) of `_seen`
        self._heard: deque[int] = deque([now])                      # when, for the rate
        self._gaps: deque[tuple[int, int, int]] = deque()          # (opened, first missing, count)
        self._candidate: Optional[tuple[int, int]] = None          # (serial, when): a restart unconfirmed

    def feed(self, serial: int, now: int) -> Optional[tuple[int, int]]:
        """Note a legal packet; (serial, time) of the packet that restarted the counter when this one
        confirms a restart that changes the commands, else None."""
        self._expire(now)
        candidate = self._candidate
        if candidate is not None:
            if serial == candidate[0]:
                return None                      # a copy of it confirms nothing
            self._candidate = None
            if 1 <= (serial - candidate[0]) & 0xFFFF <= CONFIRM:
                self._reset(*candidate)
                self._advance(serial, now)
                return candidate if now - candidate[1] < CANDIDATE_WAIT_US else None
        if serial in self._seen:
            return None                          # a duplicate (within the window: `_expire`)
        d = (serial - self.high) & 0xFFFF
        if d == 1 or (1 < d < _HALF and self._plausible(d - 1, now)):
            self._advance(serial, now)
        elif self._late(serial):
            self._note(serial, now)
        else:
            self._candidate = (serial, now)      # out of order until the next packet says more
        return None

    def _plausible(self, missing: int, now: int) -> bool:
        """Could the counter have lost `missing` packets in its silence, at its rate?"""
        life = min(RATE_WINDOW_US, now - self.start)
        rate = len(self._heard) * US_PER_S / life if life > 0 else 0.0
        return missing <= PLAUSIBLE_BASE + PLAUSIBLE_FACTOR * max(rate, MIN_RATE) * (now - self.last) / US_PER_S

    def _late(self, serial: int) -> bool:
        return any((serial - first) & 0xFFFF < count for _, first, count in self._gaps)

    def _advance(self, serial: int, now: int) -> None:
        missing = ((serial - self.high) & 0xFFFF) - 1
        if missing:
            self._gaps.append((now, (self.high + 1) & 0xFFFF, missing))
        self.high = serial
        self._note(serial, now)

    def _note(self, serial: int, now: int) -> None:
        self._seen[serial] = now
        self._recent.append((now, serial))
        self._heard.append(now)
        self.last = now

    def _expire(self, now: int) -> None:
        recent, seen, heard = self._recent, self._seen, self._heard
        while recent and now - recent[0][0] >= DUP_WINDOW_US:
            t, serial = recent.popleft()
            if seen.get(serial) == t:
                del seen[serial]
        while heard and now - heard[0] >= RATE_WINDOW_US:
            heard.popleft()
        while self._gaps and now - self._gaps[0][0] >= DUP_WINDOW_US:
            self._gaps.popleft()


class PeerRestarts:
    """The senders a node hears, by (origin, source address): which of them restarted, and when.
    `per_type`: the peer numbers each packet type on its own (`--serial-scope type`), a counter each."""

    def __init__(self, per_type: bool = False) -> None:
        self.per_type = per_type
        self._counters: dict[tuple[int, Any, Any], SerialCounter] = {}

    def _key(self, origin: int, src: Any, ptype: Any) -> tuple[int, Any, Any]:
        return origin, src, ptype if self.per_type else None

    def pending(self, origin: int, src: Any, ptype: Any, serial: int) -> bool:
        """Is `serial` the counter's restart still to be confirmed (its last packet)?"""
        counter = self._counters.get(self._key(origin, src, ptype))
        return counter is not None and counter.candidate == serial

    def restarted(self, origin: int, src: Any, ptype: Any, serial: int,
                  now: int) -> tuple[Optional[tuple[int, int]], list[tuple[int, Any]]]:
        """Feed a legal packet: ((first serial, time) of the sender's restart, when this packet shows
        it; the earlier
        senders, (origin, source), of the same origin and address this new source replaces)."""
        key = self._key(origin, src, ptype)
        counter = self._counters.get(key)
        if counter is not None:
            return counter.feed(serial, now), []
        new_sender = not any(k[:2] == key[:2] for k in self._counters)
        self._counters[key] = SerialCounter(serial, now)
        gone = self._new_port(origin, src, now) if new_sender else []
        return ((serial, now) if gone else None), gone

    def _new_port(self, origin: int, src: Any, now: int) -> list[tuple[int, Any]]:
        """Earlier senders with this one's origin and address, silent for 250 ms: they restarted on
        this new source port (and are forgotten)."""
        host, last = _host(src), dict[tuple[int, Any], int]()
        for (o, s, _), counter in self._counters.items():
            if o == origin and s != src and _host(s) == host:
                last[(o, s)] = max(last.get((o, s), counter.last), counter.last)
        gone = [sender for sender, t in last.items() if now - t >= NEW_PORT_SILENCE_US]
        self._counters = {k: c for k, c in self._counters.items() if k[:2] not in gone}
        return gone


def _host(src: Hashable) -> Hashable:
    """The address part of a source (host, port); a bare host as it is."""
    return src[0] if isinstance(src, tuple) else src
