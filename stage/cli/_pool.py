"""The process pool of the ``stage`` subcommands that run work in parallel.

Its workers die with the command: each runs a watchdog thread that ends the worker as soon as the
``stage`` process that started the pool is gone (killed with SIGKILL, which no handler sees).
The workers are children of the forkserver, not of the command, so ``PR_SET_PDEATHSIG`` would
watch the wrong parent; a look at the command's pid twice a second works on every platform.
Once the workers are gone, the forkserver and the resource tracker see their pipes close and exit.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import signal
import threading
import time

__all__ = ["worker_pool", "exit_with"]


def _alive(pid: int) -> bool:
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
    to the process group) is the command's to handle: the worker ignores it and is shut down by it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while _alive(parent_pid):
            time.sleep(interval_s)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def worker_pool(workers: int) -> cf.ProcessPoolExecutor | None:
    """A pool of ``workers`` processes started with ``forkserver``, or None for ``workers <= 0``.

    ``forkserver``, not ``fork``: workers start clean (OpenCV's thread pool does not survive
    a fork) and stay warm across steps. The workers exit by themselves when this process dies.
    """
    if workers <= 0:
        return None
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("forkserver"),
                                  initializer=exit_with, initargs=(os.getpid(),))
