"""Where the per-capture function runs: here and in worker processes (`local`), or on the workers
of a Dask cluster (`dask`). Both only map `build_one` over the captures and hand back each
`Done` as it completes; Dask schedules, retries and moves results itself, the local workers
(`vm110.workers`) are given one capture at a time, so that a worker that dies costs that capture only.
"""
from __future__ import annotations

import logging
import signal
import threading
from contextlib import ExitStack
from dataclasses import replace
from functools import partial
from typing import Iterator, Optional, Sequence

from ..errors import CliError
from ..workers import Died, each
from .sources import Source
from .work import Done, Settings, build_one

CONNECT_TIMEOUT_S = 10


def run_local(todo: Sequence[Source], settings: Settings, jobs: int) -> Iterator[Done]:
    """In this process for one job (as `vm110 analyze --jobs 1`), else `jobs` worker processes
    (`workers.each`): a worker that dies gives its capture an unreadable row that says why."""
    for index, done in each(partial(_build_one, settings=settings), todo, jobs):
        if isinstance(done, CliError):
            raise done                  # the dataset cannot be written (a full disk): that ends the build
        yield build_one(replace(todo[index], problem=str(done)), settings) if isinstance(done, Died) else done


def _build_one(source: Source, settings: Settings) -> "Done | CliError":
    """`build_one`, its CliError handed back to the driver to say in one line: raised, it ended the
    worker process with a traceback on standard error (a full disk: one per worker)."""
    try:
        return build_one(source, settings)
    except CliError as exc:
        return exc


def run_dask(todo: Sequence[Source], settings: Settings, jobs: int, scheduler: Optional[str]) -> Iterator[Done]:
    """`build_one` mapped over the captures with dask.distributed: on the cluster at `scheduler`,
    or on a LocalCluster of `jobs` single-threaded worker processes on the loopback interface."""
    from distributed import Client, LocalCluster, as_completed      # (missing: said by commands.fleet)
    from distributed.scheduler import KilledWorker
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
