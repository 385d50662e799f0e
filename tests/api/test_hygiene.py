"""The server's own leftovers: uploads of a server that is gone are removed at startup (those of a
live server sharing the data root stay); the pool is joined at shutdown."""

from __future__ import annotations

import os
import subprocess
import sys

from api.executors import local_pool


def test_startup_removes_stale_upload_files_of_servers_that_are_gone(make_client, data_root):
    takes = data_root / "takes"
    takes.mkdir(parents=True)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    stale = [takes / f".upload-{dead}-{'a' * 32}.part", takes / f".upload-{'b' * 32}.part"]
    live = takes / f".upload-{os.getppid()}-{'c' * 32}.part"
    for p in (*stale, live):
        p.write_bytes(b"x" * 1000)
    client = make_client()
    assert client.get("/takes").status_code == 200
    assert not any(p.exists() for p in stale)
    assert live.exists()


def test_close_joins_the_pool():
    h = local_pool(1)
    assert h.executor.submit(os.getpid).result() != os.getpid()
    procs = list(h.executor._processes.values())
    manager = h.executor._executor_manager_thread
    h.close(timeout_s=5)
    assert not any(p.is_alive() for p in procs) and not manager.is_alive()
