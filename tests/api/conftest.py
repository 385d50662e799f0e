"""Fixtures of the API tests: an app on a temporary data root, a client, the token."""

from __future__ import annotations

import concurrent.futures as cf
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.executors import ExecutorHandle
from api.settings import Settings
from tests.api import fakework

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def make_settings(data: Path, **kw) -> Settings:
    base = dict(data=data, api_token=TOKEN, heartbeat_s=0.1, stale_after_s=0.5, poll_s=0.02, max_upload_bytes=1 << 20)
    base.update(kw)
    return Settings(**base)


@pytest.fixture
def data_root(tmp_path: Path) -> Path:
    return tmp_path / "data"


@pytest.fixture
def make_client(data_root: Path):
    """``make_client(**settings) -> TestClient`` running jobs on a thread pool with the fake work."""
    clients = []

    def make(work=fakework.process_take, data: Path | None = None, **kw) -> TestClient:
        settings = make_settings(data if data is not None else data_root, **kw)
        handle = ExecutorHandle(cf.ThreadPoolExecutor(2), "threads", "test threads")
        app = create_app(settings, work=work, executor=handle)
        c = TestClient(app, raise_server_exceptions=False)
        c.__enter__()
        clients.append((c, handle))
        return c

    yield make
    for c, h in clients:
        c.__exit__(None, None, None)
        h.close()


@pytest.fixture
def client(make_client) -> TestClient:
    return make_client()


def add_take(data_root: Path, name: str = "take1", frames: int = 6) -> Path:
    (data_root / "takes").mkdir(parents=True, exist_ok=True)
    return fakework.make_take_file(data_root / "takes" / f"{name}.h5", frames)


def wait_job(client: TestClient, job_id: str, *, states=("done", "failed", "cancelled"), timeout: float = 20.0) -> dict:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        st = client.get(f"/jobs/{job_id}").json()
        if st["state"] in states:
            return st
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} still {st['state']} after {timeout}s")
