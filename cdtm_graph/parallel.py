"""Run independent tasks on all local cores or on a Dask cluster, results in task order.

Studies and accuracy maps are embarrassingly parallel: many independent, picklable
tasks, each worth a fraction of a second of work. :func:`map_tasks` runs them

* in this process (one worker: no pool, no pickling),
* on a local :class:`concurrent.futures.ProcessPoolExecutor` (default: all cores), or
* on a Dask cluster given by its scheduler address (``dask.distributed``, imported lazily).

Results come back in task order whatever the backend and worker count, so a caller whose
tasks carry their own seeds (never the worker's identity) gets the same numbers every way.
Worker processes are forked from a fork server that has already imported the task's
module: each worker starts in milliseconds without importing GTSAM again, and the server
is single-threaded, so forking it is safe even if the caller runs threads (Dask, GUIs).
"""

from __future__ import annotations

import enum
import logging
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

from cdtm_graph.errors import CdtmError

log = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

#: Seconds to wait for a Dask scheduler to answer before giving up.
DASK_CONNECT_TIMEOUT_S = 10.0


class ParallelBackend(enum.Enum):
    """Where tasks run."""

    SERIAL = "serial"  # this process, in order
    PROCESSES = "processes"  # a local process pool
    DASK = "dask"  # a dask.distributed cluster


@dataclass(frozen=True)
class ParallelSettings:
    """How to run independent tasks.

    Attributes:
        workers: local worker processes; ``None`` uses every core this process may run on.
            One worker runs the tasks in this process. Ignored with a scheduler.
        scheduler_address: address of a running Dask scheduler (e.g.
            ``tcp://10.0.0.5:8786``); the tasks then run on its workers, which must be able
            to import ``cdtm_graph``.
    """

    workers: int | None = None
    scheduler_address: str | None = None

    def __post_init__(self) -> None:
        if self.workers is not None and (isinstance(self.workers, bool)
                                         or int(self.workers) != self.workers
                                         or self.workers < 1):
            raise CdtmError(f"workers = {self.workers!r}, expected an integer >= 1")

    @property
    def backend(self) -> ParallelBackend:
        if self.scheduler_address:
            return ParallelBackend.DASK
        return ParallelBackend.SERIAL if self.n_local_workers() == 1 else ParallelBackend.PROCESSES

    def n_local_workers(self) -> int:
        """Local worker processes this setting asks for (at least 1)."""
        return max(1, int(self.workers) if self.workers is not None else available_cores())


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def map_tasks(fn: Callable[[T], R], tasks: Sequence[T],
              settings: ParallelSettings | None = None) -> list[R]:
    """``[fn(task) for task in tasks]``, run in parallel as ``settings`` say.

    Args:
        fn: a module-level (picklable) function of one task.
        tasks: picklable task descriptions; each should be worth well over a millisecond
            of work, so that per-task overhead (pickling, scheduling) stays small.
        settings: backend and worker count; default: all local cores.

    Returns:
        The results, in the order of ``tasks``.

    Raises:
        CdtmError: Dask is asked for but not installed, or its scheduler is unreachable.
        Any exception ``fn`` raises (the first one, re-raised here).
    """
    settings = settings or ParallelSettings()
    tasks = list(tasks)
    backend = settings.backend
    if backend is ParallelBackend.DASK:
        return _map_dask(fn, tasks, settings.scheduler_address)
    n_workers = min(settings.n_local_workers(), len(tasks))
    if backend is ParallelBackend.SERIAL or n_workers <= 1:
        return [fn(task) for task in tasks]
    log.info("running %d tasks on %d local processes", len(tasks), n_workers)
    with ProcessPoolExecutor(max_workers=n_workers,
                             mp_context=_process_context(fn.__module__)) as pool:
        try:
            # chunksize 1: tasks are already chunks of work; finer dealing balances the tail.
            return list(pool.map(fn, tasks, chunksize=1))
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def _process_context(preload_module: str) -> multiprocessing.context.BaseContext:
    """A fork server that has imported the task module; spawn where there is none."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        # Only takes effect when the server starts (first pool of this process); every
        # task module lives in cdtm_graph, whose import brings in GTSAM and numba once.
        if preload_module not in ("__main__", "__mp_main__"):
            ctx.set_forkserver_preload([preload_module])
        return ctx
    return multiprocessing.get_context("spawn")


def _map_dask(fn: Callable[[T], R], tasks: list[T], address: str | None) -> list[R]:
    try:
        from dask.distributed import Client
    except ImportError:
        raise CdtmError("a Dask scheduler was given but dask.distributed is not installed: "
                        "pip install 'cdtm-graph[dask]'") from None
    try:
        client = Client(address, timeout=DASK_CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise CdtmError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    with client:
        log.info("running %d tasks on the Dask cluster at %s", len(tasks), address)
        # pure=False: tasks are cheap to describe, and two equal tasks must both run.
        futures = client.map(fn, tasks, pure=False)
        return list(client.gather(futures))
