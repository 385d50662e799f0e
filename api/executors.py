"""Where the per-frame work runs: one ``concurrent.futures.Executor`` interface.

* default: an embedded local process pool (nothing to install or start);
* ``dask="tcp://host:8786"``: an existing Dask distributed cluster, through
  ``distributed.Client(address).get_executor()``. Workers open takes by path, so
  the data root must be on a filesystem they share with the server;
* ``dask="local"``: a Dask ``LocalCluster`` started here (benchmarks, tests).

Dask is an optional extra (``pip install 'capture-stage[dask]'``).
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any

__all__ = ["ExecutorHandle", "DaskUnavailableError", "make_executor", "local_pool", "dask_executor", "dask_available"]

log = logging.getLogger(__name__)


class DaskUnavailableError(RuntimeError):
    """Dask was asked for but ``dask[distributed]`` is not installed."""


def dask_available() -> bool:
    """Whether ``distributed`` can be imported."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class ExecutorHandle:
    """An executor and what must be closed with it.

    Attributes
    ----------
    executor : concurrent.futures.Executor
        ``submit``/``map``/``shutdown``; futures are ``concurrent.futures.Future``.
    kind : str
        ``"local"`` or ``"dask"``.
    description : str
        Human-readable (pool size or scheduler address).
    """

    executor: cf.Executor
    kind: str
    description: str
    _closers: list[Any] = field(default_factory=list, repr=False)

    def close(self, timeout_s: float = 10.0) -> None:
        """Shut the executor down and close the Dask client/cluster if we opened them.

        A local pool is joined: queued tasks are cancelled, running ones get ``timeout_s`` to
        finish, then their workers are terminated, and the pool's management thread is joined, so
        its queues (and their semaphores) are released before the process exits.
        """
        procs = list((getattr(self.executor, "_processes", None) or {}).values())
        manager = getattr(self.executor, "_executor_manager_thread", None)  # holds the pool's queues
        try:
            self.executor.shutdown(wait=False, cancel_futures=True)
        except TypeError:  # executors without cancel_futures
            self.executor.shutdown(wait=False)
        if procs:
            deadline = time.monotonic() + timeout_s
            for p in procs:
                p.join(max(0.0, deadline - time.monotonic()))
            for p in procs:
                if p.is_alive():
                    log.warning("pool worker %d still busy after %.0f s at shutdown; terminated", p.pid, timeout_s)
                    p.terminate()
                    p.join(2.0)
        if manager is not None:
            manager.join(max(1.0, timeout_s))
        for c in reversed(self._closers):
            try:
                c.close()
            except Exception as exc:  # closing best-effort: log, keep closing the rest
                log.warning("closing %s failed: %s", type(c).__name__, exc)
        self._closers.clear()


def local_pool(workers: int | None = None) -> ExecutorHandle:
    """A process pool of ``workers`` processes (default: CPU count) started with ``forkserver``.

    ``forkserver`` (not ``fork``) because the server process runs threads. Workers
    exit by themselves when the server process dies (:mod:`stage.workers`).
    """
    from stage.workers import process_pool

    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    n = workers or os.cpu_count() or 1
    return ExecutorHandle(process_pool(n), "local", f"local process pool ({n} workers)")


#: Environment of local Dask workers. Dask's nannies set ``MALLOC_TRIM_THRESHOLD_=65536``, which
#: also pins glibc's mmap threshold at 128 KiB: every image-sized temporary is then a fresh mmap
#: and its page faults, and keying a camera takes 5x longer (1.05 s instead of 0.20 s measured);
#: arrays up to 64 MiB come from the heap again with the mmap threshold, and stay there between
#: frames with the trim threshold (at 64 KiB the heap's top went back to the system after every
#: frame: key tasks spent 1.2-1.9x the CPU of a pool worker's, now the same).
DASK_WORKER_ENV = {
    "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 1 << 26,
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": 1 << 26,
}


def dask_executor(address: str, *, n_workers: int = 2, threads_per_worker: int = 1) -> ExecutorHandle:
    """An executor on a Dask cluster: ``address`` of a scheduler, or ``"local"`` for a new ``LocalCluster``.

    Raises
    ------
    DaskUnavailableError
        When ``dask[distributed]`` is not installed.
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise DaskUnavailableError(
            "Dask is not installed: pip install 'dask[distributed]' (the [dask] extra of capture-stage)"
        ) from None
    closers: list[Any] = []
    if address == "local":
        with dask.config.set(DASK_WORKER_ENV):
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker, processes=True,
                                   dashboard_address=None, worker_dashboard_address=None, host="127.0.0.1")
        closers.append(cluster)
        client = Client(cluster)
        desc = f"dask LocalCluster ({n_workers} workers)"
    else:
        client = Client(address, timeout=30)
        desc = f"dask cluster at {address}"
    closers.append(client)
    # pure=False: a task is never answered from the cluster's memory of an earlier task with the same
    # arguments (a take re-imported under the same path must be read again)
    return ExecutorHandle(client.get_executor(pure=False), "dask", desc, closers)


def make_executor(*, dask: str | None = None, workers: int | None = None) -> ExecutorHandle:
    """The executor the settings ask for: Dask when ``dask`` is set, else the local pool."""
    if dask:
        return dask_executor(dask)
    return local_pool(workers)
