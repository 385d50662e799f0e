"""The process pool of the ``stage`` subcommands that run work in parallel."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing

__all__ = ["worker_pool"]


def worker_pool(workers: int) -> cf.ProcessPoolExecutor | None:
    """A pool of ``workers`` processes started with ``forkserver``, or None for ``workers <= 0``.

    ``forkserver``, not ``fork``: workers start clean (OpenCV's thread pool does not survive
    a fork) and stay warm across steps.
    """
    if workers <= 0:
        return None
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("forkserver"))
