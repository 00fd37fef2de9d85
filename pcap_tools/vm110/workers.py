"""One function over many items in worker processes, each worker given one item at a time, so
that a worker that dies (the kernel's out-of-memory killer, a crash in a library) costs its item
only: it is told as `Died` and the worker replaced. (A multiprocessing pool lost the item and
waited for its result for ever.) `vm110 analyze --jobs` and `vm110 fleet build` use it.
"""
from __future__ import annotations

import multiprocessing
import signal
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Iterator, Optional, Sequence


@dataclass(frozen=True)
class Died:
    """The worker ended before its item was done."""
    exitcode: Optional[int]

    def __str__(self) -> str:
        if self.exitcode == -signal.SIGKILL:
            how = "killed (SIGKILL: what the kernel's out-of-memory killer sends)"
        elif self.exitcode is not None and self.exitcode < 0:
            how = f"signal {-self.exitcode}"
        else:
            how = f"exit code {self.exitcode}"
        return f"the process analysing it ended before it was done: {how}"


def ignore_interrupt() -> None:
    """Ctrl-C goes to the whole process group: the driver stops the workers and keeps what is done;
    a worker that handled it too would print its own traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _serve(conn: Connection, fn: Callable[[Any], Any]) -> None:
    ignore_interrupt()
    # A driver killed alone (`kill PID`, a job scheduler's SIGTERM) closes no pipe of ours: the
    # workers forked after us hold its end. Its death is the sign to end: the workers waited for
    # ever, holding the driver's standard output and error open (a caller reading them hung too).
    parent = multiprocessing.parent_process()
    gone = [parent.sentinel] if parent is not None else []
    while not set(gone) & set(wait([conn, *gone])):
        item = conn.recv()
        if item is None:
            return
        conn.send(fn(item[0]))


class _Worker:
    def __init__(self, fn: Callable[[Any], Any]) -> None:
        self.conn, theirs = multiprocessing.Pipe()
        self.process = multiprocessing.Process(target=_serve, args=(theirs, fn), daemon=True)
        self.process.start()
        theirs.close()
        self.index: Optional[int] = None

    def give(self, index: Optional[int], items: Sequence[Any]) -> None:
        self.index = index
        try:
            self.conn.send(None if index is None else (items[index],))
        except OSError:           # dead already: its sentinel tells
            pass

    def result(self) -> Any:
        """Its result, or Died when it ended without one."""
        try:
            if self.conn.poll():
                return self.conn.recv()
        except (EOFError, OSError):
            pass
        self.process.join()
        return Died(self.process.exitcode)


def each(fn: Callable[[Any], Any], items: Sequence[Any], jobs: int) -> Iterator[tuple[int, Any]]:
    """(index, fn(item) or Died) for every item, as they complete: in this process for one job
    or one item, else in `jobs` worker processes. Stopping the iteration (Ctrl-C) ends them."""
    if jobs == 1 or len(items) <= 1:
        for index, item in enumerate(items):
            yield index, fn(item)
        return
    queue = list(reversed(range(len(items))))
    workers: list[_Worker] = []
    try:
        for _ in range(min(jobs, len(items))):
            workers.append(_Worker(fn))
            workers[-1].give(queue.pop(), items)
        while any(w.index is not None for w in workers):
            busy = [w for w in workers if w.index is not None]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
            for n, worker in enumerate(workers):
                if worker.index is None or (worker.conn not in ready and worker.process.sentinel not in ready):
                    continue
                index, result = worker.index, worker.result()
                if isinstance(result, Died):
                    workers[n] = _Worker(fn)
                workers[n].give(queue.pop() if queue else None, items)
                yield index, result
    finally:
        for worker in workers:          # (Ctrl-C, or the driver stopped: nothing half-done is kept)
            worker.process.terminate()
            worker.process.join()
            worker.conn.close()
