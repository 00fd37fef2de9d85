"""Where the per-capture function runs: here and in worker processes (`local`), or on the workers
of a Dask cluster (`dask`). Both only map `build_one` over the captures and hand back each
`Done` as it completes; Dask schedules, retries and moves results itself, the local workers are
given one capture at a time, so that a worker that dies costs that capture only.
"""
from __future__ import annotations

import logging
import multiprocessing
import signal
import threading
from contextlib import ExitStack
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from typing import Iterator, Optional, Sequence

from ..errors import CliError
from .sources import Source
from .work import Done, Settings, build_one

CONNECT_TIMEOUT_S = 10


def _ignore_interrupt() -> None:
    """Ctrl-C goes to the whole process group: the driver stops the pool and keeps what is done;
    a worker that handled it too would print its own traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _serve(conn: Connection, settings: Settings) -> None:
    """A worker: build each capture the driver sends, until it sends None."""
    _ignore_interrupt()
    while (source := conn.recv()) is not None:
        conn.send(build_one(source, settings))


class _Worker:
    """A worker process and the one capture it is building (the driver gives one at a time, so
    that it knows which capture a worker that dies took with it)."""

    def __init__(self, settings: Settings) -> None:
        self.conn, theirs = multiprocessing.Pipe()
        self.process = multiprocessing.Process(target=_serve, args=(theirs, settings), daemon=True)
        self.process.start()
        theirs.close()
        self.source: Optional[Source] = None

    def give(self, source: Optional[Source]) -> None:
        self.source = source
        try:
            self.conn.send(source)
        except OSError:           # dead already: its sentinel tells, and the capture is said
            pass


def run_local(todo: Sequence[Source], settings: Settings, jobs: int) -> Iterator[Done]:
    """In this process for one job (as `vm110 analyze --jobs 1`), else `jobs` worker processes.
    A worker that dies (the kernel's out-of-memory killer, a crash in a library) gives its capture
    an unreadable row and is replaced; a process pool lost that capture and waited for it for ever."""
    if jobs == 1 or len(todo) <= 1:
        for source in todo:
            yield build_one(source, settings)
        return
    queue = list(reversed(todo))
    workers: list[_Worker] = []
    try:
        for _ in range(min(jobs, len(todo))):
            worker = _Worker(settings)
            workers.append(worker)
            worker.give(queue.pop())
        while any(w.source is not None for w in workers):
            busy = [w for w in workers if w.source is not None]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
            for n, worker in enumerate(workers):
                if worker.source is None or (worker.conn not in ready and worker.process.sentinel not in ready):
                    continue
                done = _result(worker)
                if done is None:                # it died: a new worker in its place
                    worker.process.join()
                    done = build_one(replace(worker.source, problem=_death(worker.process.exitcode)), settings)
                    workers[n] = _Worker(settings)
                workers[n].give(queue.pop() if queue else None)
                yield done
    finally:
        for worker in workers:          # (Ctrl-C, or the driver stopped: nothing half-done is kept)
            worker.process.terminate()
            worker.process.join()
            worker.conn.close()


def _result(worker: _Worker) -> Optional[Done]:
    """The worker's Done, or None when it died without one."""
    try:
        if worker.conn.poll():
            return worker.conn.recv()
    except (EOFError, OSError):
        pass
    return None


def _death(exitcode: Optional[int]) -> str:
    if exitcode == -signal.SIGKILL:
        how = "killed (SIGKILL: what the kernel's out-of-memory killer sends)"
    else:
        how = f"signal {-exitcode}" if exitcode is not None and exitcode < 0 else f"exit code {exitcode}"
    return f"the process analysing it ended before it was done: {how}"


def run_dask(todo: Sequence[Source], settings: Settings, jobs: int, scheduler: Optional[str]) -> Iterator[Done]:
    """`build_one` mapped over the captures with dask.distributed: on the cluster at `scheduler`,
    or on a LocalCluster of `jobs` single-threaded worker processes on the loopback interface."""
    try:
        from distributed import Client, LocalCluster, as_completed
        from distributed.scheduler import KilledWorker
    except ImportError as exc:
        raise CliError(f"--engine dask needs dask.distributed ({exc}); make setup installs it") from None
    with ExitStack() as stack:
        if scheduler:
            try:
                client = stack.enter_context(Client(scheduler, timeout=CONNECT_TIMEOUT_S))
            except (OSError, TimeoutError, ValueError) as exc:
                raise CliError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        else:
            # Its worker processes start with Ctrl-C ignored (as the pool's): this process stops
            # the cluster and keeps what is done.
            main = threading.current_thread() is threading.main_thread()
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
            try:
                # (":0": the scheduler's HTTP server takes 8787 even without a dashboard, and a
                # second cluster on the machine then warns and moves)
                cluster = stack.enter_context(LocalCluster(
                    n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
                    dashboard_address=":0", silence_logs=logging.CRITICAL))    # (a task that fails is said once, below)
            finally:
                if main:
                    signal.signal(signal.SIGINT, previous)
            client = stack.enter_context(Client(cluster))
        if not todo:
            return
        futures = client.map(build_one, list(todo), settings=settings, pure=False)
        source = {future.key: s for future, s in zip(futures, todo)}
        try:
            for future in as_completed(futures):
                try:
                    done = future.result()
                except CliError:
                    raise                       # the dataset cannot be written: that ends the build
                except Exception as exc:        # its workers died, or it failed on a worker
                    done = build_one(replace(source[future.key], problem=_task_failed(exc, KilledWorker)), settings)
                yield done
        finally:
            client.cancel(futures)


def _task_failed(exc: Exception, killed: type) -> str:
    if isinstance(exc, killed):
        return ("every Dask worker that analysed it died before it was done (KilledWorker; the kernel's "
                "out-of-memory killer?)")
    first = str(exc).splitlines()[0][:200] if str(exc) else ""
    return f"the Dask task failed: {type(exc).__name__}" + (f": {first}" if first else "")
