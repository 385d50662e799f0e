"""The process pool of the ``stage`` subcommands that run work in parallel (its workers die with
the command: :mod:`stage.workers`)."""

from __future__ import annotations

import concurrent.futures as cf

__all__ = ["worker_pool"]


def worker_pool(workers: int) -> cf.ProcessPoolExecutor | None:
    """A pool of ``workers`` processes (:func:`stage.workers.process_pool`), or None for ``workers <= 0``."""
    from stage.workers import process_pool

    return process_pool(workers) if workers > 0 else None
