"""stage.workers: the pool whose workers die with their parent (the CLI's and the server's)."""

import os
import subprocess
import sys
import time

import pytest

from stage.workers import process_alive, process_pool

_KILLED_PARENT = """
import os, signal
from stage.workers import process_pool
pool = process_pool(1)
print(pool.submit(os.getpid).result(), flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_process_alive_tells_a_zombie_and_a_gone_pid_from_a_running_one():
    assert process_alive(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 10
    while process_alive(child.pid) and time.monotonic() < deadline:  # exited, not reaped: a zombie
        time.sleep(0.05)
    assert not process_alive(child.pid)
    child.wait()
    assert not process_alive(child.pid)


def test_the_workers_exit_when_their_parent_is_killed():
    res = subprocess.run([sys.executable, "-c", _KILLED_PARENT], capture_output=True, text=True, timeout=60)
    assert res.returncode == -9, res.stderr
    worker = int(res.stdout.split()[0])
    deadline = time.monotonic() + 5
    while process_alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not process_alive(worker), f"worker {worker} outlived its killed parent"


def test_invalid_input():
    for bad in (0, -1, True, 1.5, "2"):
        with pytest.raises(ValueError, match="workers"):
            process_pool(bad)
