"""Worker processes that die with the process that started them.

A process pool's workers outlive a parent killed with SIGKILL (no handler runs): they sit blocked
on their queue, holding memory, and the forkserver and the resource tracker wait on them. Every
pool of the project (the ``stage`` commands', the server's) is made by :func:`process_pool`,
whose workers run :func:`exit_with`: a watchdog thread that ends the worker as soon as the
parent's pid is gone. The workers are children of the forkserver, not of the parent, so
``PR_SET_PDEATHSIG`` would watch the wrong process; a look at the parent's pid twice a second
works on every platform. Once the workers are gone, the forkserver and the resource tracker see
their pipes close and exit.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import signal
import threading
import time

__all__ = ["process_alive", "exit_with", "process_pool"]


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, killed and not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):  # PermissionError: the pid went to another user's process
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return fh.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True  # no /proc (macOS): kill(pid, 0) is all there is


def exit_with(parent_pid: int, interval_s: float = 0.5) -> None:
    """Pool-worker initializer: end this worker when process ``parent_pid`` is gone. Ctrl-C (SIGINT
    to the process group) is the parent's to handle: the worker ignores it, finishes its task and
    is shut down by the parent, instead of printing a traceback of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while process_alive(parent_pid):
            time.sleep(interval_s)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def process_pool(workers: int) -> cf.ProcessPoolExecutor:
    """A pool of ``workers`` processes started with ``forkserver`` that exit when this process dies.

    ``forkserver``, not ``fork``: workers start clean (OpenCV's thread pool does not survive a
    fork; the server runs threads) and stay warm across tasks.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("forkserver"),
                                  initializer=exit_with, initargs=(os.getpid(),))
