"""Where the per-capture function runs: here and in worker processes (`local`), or on the workers
of a Dask cluster (`dask`). Both only map `build_one` over the captures and hand back each
`Done` as it completes; scheduling, retries and moving results are the pool's or Dask's job.
"""
from __future__ import annotations

import logging
import multiprocessing
import signal
import threading
from contextlib import ExitStack
from typing import Iterator, Optional, Sequence

from ..errors import CliError
from .sources import Source
from .work import Done, Settings, build_one

CONNECT_TIMEOUT_S = 10


def _call(job: tuple[Source, Settings]) -> Done:
    return build_one(*job)


def _ignore_interrupt() -> None:
    """Ctrl-C goes to the whole process group: the driver stops the pool and keeps what is done;
    a worker that handled it too would print its own traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_local(todo: Sequence[Source], settings: Settings, jobs: int) -> Iterator[Done]:
    """In this process for one job (as `vm110 analyze --jobs 1`), else a pool of `jobs` processes
    (as `vm110 analyze --jobs N`)."""
    if jobs == 1 or len(todo) <= 1:
        for source in todo:
            yield build_one(source, settings)
        return
    with multiprocessing.Pool(min(jobs, len(todo)), initializer=_ignore_interrupt) as pool:
        yield from pool.imap_unordered(_call, [(s, settings) for s in todo])


def run_dask(todo: Sequence[Source], settings: Settings, jobs: int, scheduler: Optional[str]) -> Iterator[Done]:
    """`build_one` mapped over the captures with dask.distributed: on the cluster at `scheduler`,
    or on a LocalCluster of `jobs` single-threaded worker processes on the loopback interface."""
    try:
        from distributed import Client, LocalCluster, as_completed
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
                    dashboard_address=":0", silence_logs=logging.ERROR))
            finally:
                if main:
                    signal.signal(signal.SIGINT, previous)
            client = stack.enter_context(Client(cluster))
        if not todo:
            return
        futures = client.map(build_one, list(todo), settings=settings, pure=False)
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            client.cancel(futures)
