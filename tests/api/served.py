"""A real ``stage serve`` subprocess for the tests (:class:`Server`), and the small simulated take its
jobs process with the spine of an uninterrupted in-process run (cached per test process)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "serve-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``python -m stage serve`` in its own process group."""

    def __init__(self, data: Path, *, work: str | None = None, workers: int = 2) -> None:
        self.data, self.work, self.workers = data, work, workers
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Server":
        env = dict(os.environ, STAGE_API_TOKEN=TOKEN, STAGE_HEARTBEAT_S="0.2", STAGE_STALE_AFTER_S="1.0",
                   STAGE_POLL_S="0.05", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        if self.work:
            env["STAGE_WORK"] = self.work
        self.log = open(self.data.parent / f"serve-{self.port}.log", "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "stage", "serve", "--port", str(self.port), "--data", str(self.data),
             "--workers", str(self.workers), "--log-level", "warning"],
            cwd=ROOT, env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True,
        )
        t0 = time.monotonic()
        while time.monotonic() - t0 < 30:
            if self.proc.poll() is not None:
                raise RuntimeError(f"stage serve exited with {self.proc.returncode}: {self.logtext()}")
            try:
                if httpx.get(self.url + "/health", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                time.sleep(0.1)
        raise RuntimeError("stage serve did not come up in 30 s")

    def logtext(self) -> str:
        return (self.data.parent / f"serve-{self.port}.log").read_text(errors="replace")[-3000:]

    def kill(self) -> None:
        """SIGKILL the server process only (its pool workers notice and exit on their own)."""
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def cleanup(self) -> None:
        if self.proc is not None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)  # the group we started: server and its workers
            except ProcessLookupError:
                pass
            self.proc.wait(10)
        self.log.close()


def simulated_take_file(path: Path) -> Path:
    """A simulated take (6 cameras, 160x120, 8 frames) written through stage.store."""
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    sim = simulate_take("starfish", n_cameras=6, frames=8, size=(160, 120), seed=0)
    return record_take(sim, path)


_REF: dict = {}
SIM_KEY = "starfish-6-8-160x120-0"  # what simulated_take_file makes (the file bytes hold a creation time)


def reference_spine(take: Path, tmp: Path) -> dict:
    """``spine.json`` of an uninterrupted in-process run of process_take."""
    from pipeline.process import process_take

    key = SIM_KEY
    if key not in _REF:
        process_take(take, tmp / "ref")
        _REF[key] = json.loads((tmp / "ref" / "spine.json").read_text())
    return _REF[key]
