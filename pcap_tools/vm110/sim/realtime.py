"""Run nodes on the wall clock over UDP sockets: one loop, `select` until the next deadline.

Several nodes may share one runner (the tests run a base unit and the reference controller in
one thread); `start_thread` runs it in the background for in-process use.
"""
from __future__ import annotations

import select
import threading
from typing import Optional, Sequence

from .clock import WallClock, seconds
from .node import Node
from .transport import UdpTransport

_MAX_WAIT_S = 0.05          # wake up at least this often to notice `stop()`
_MAX_TICKS_PER_ROUND = 64   # a node that does not advance its schedule must not hang the loop


class RealtimeRunner:
    """Drives (node, transport) pairs. Opens the transports that are not open yet."""

    def __init__(self, pairs: Sequence[tuple[Node, UdpTransport]], clock: Optional[WallClock] = None) -> None:
        self.pairs = list(pairs)
        self.clock = clock or WallClock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._started = False

    def prepare(self) -> None:
        """Open the sockets and attach the nodes (idempotent); `run` does it when needed."""
        if self._started:
            return
        for node, transport in self.pairs:
            if transport.rx is None:
                transport.open()
            node.attach(transport.send)
            node.restart_source = transport.restart_source
            transport.on_send_error = node.send_failed
            transport.on_impaired = node.impaired
            if transport.impairer is not None:
                transport.impairer.set_origin(self.clock.now())
        now = self.clock.now()
        for node, _ in self.pairs:
            node.start(now)
        self._started = True

    def run(self, duration_s: Optional[float] = None) -> None:
        """Run until `duration_s` has passed (None: until `stop()`); closes the sockets at the end."""
        self.prepare()
        end = None if duration_s is None else self.clock.now() + seconds(duration_s)
        by_fd = {transport.rx.fileno(): (node, transport) for node, transport in self.pairs if transport.rx}
        try:
            while not self._stop.is_set():
                now = self.clock.now()
                if end is not None and now >= end:
                    break
                for node, transport in self.pairs:
                    for _ in range(_MAX_TICKS_PER_ROUND):
                        due = node.next_due()
                        if due is None or due > now:
                            break
                        node.tick(now)
                    transport.flush(now)
                deadlines = [d for node, transport in self.pairs for d in (node.next_due(), transport.next_due())
                             if d is not None]
                if end is not None:
                    deadlines.append(end)
                wait = (min(deadlines) - self.clock.now()) / 1e6 if deadlines else _MAX_WAIT_S
                ready, _, _ = select.select(list(by_fd), [], [], min(max(wait, 0.0), _MAX_WAIT_S))
                for fd in ready:
                    node, transport = by_fd[fd]
                    for data, src in transport.recv_all():
                        node.receive(data, self.clock.now(), src)
        finally:
            for node, transport in self.pairs:
                node.impaired_held.update(transport.held())    # (never sent: the summary says so)
                transport.close()

    def start_thread(self, duration_s: Optional[float] = None) -> threading.Thread:
        """Run in a daemon thread; sockets are open when this returns."""
        self.prepare()
        self._thread = threading.Thread(target=self.run, args=(duration_s,), daemon=True, name="vm110-sim")
        self._thread.start()
        return self._thread

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
