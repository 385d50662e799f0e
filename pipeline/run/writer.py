"""Files of a task written in order by one background thread."""

from __future__ import annotations

import concurrent.futures as cf
from pathlib import Path

from calib.fileio import atomic_write

__all__ = ["BackgroundWriter"]


class BackgroundWriter:
    """Files of a task written in order by one background thread (each atomically and durably,
    :func:`calib.fileio.atomic_write`): the disk's waits (fsync) overlap the next frame's
    computation; :meth:`close` waits and re-raises a failed write."""

    def __init__(self) -> None:
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="results-writer")
        self._pending: list[cf.Future] = []

    def write(self, path: Path, data: bytes | str) -> None:
        self._pending.append(self._pool.submit(atomic_write, path, data))

    def close(self) -> None:
        try:
            for fut in self._pending:
                fut.result()
        finally:
            self._pool.shutdown(wait=True)
