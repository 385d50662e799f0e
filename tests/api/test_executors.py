"""The same job through a Dask LocalCluster and through the local process pool gives the same result."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.executors import dask_available, dask_executor, local_pool, make_executor
from tests.api import served
from tests.api.conftest import AUTH, make_settings, wait_job
from tests.api.fakework import make_take_file

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def dask_handle():
    if not dask_available():
        pytest.skip("dask[distributed] is not installed (optional extra [dask]: pip install 'dask[distributed]')")
    h = dask_executor("local", n_workers=2)
    yield h
    h.close()


@pytest.fixture(scope="module")
def pool_handle():
    h = local_pool(2)
    yield h
    h.close()


def _run_job(tmp: Path, name: str, take: Path, handle, work) -> dict:
    data = tmp / name
    (data / "takes").mkdir(parents=True)
    (data / "takes" / "t.h5").write_bytes(take.read_bytes())
    app = create_app(make_settings(data), work=work, executor=handle)
    with TestClient(app) as c:
        jid = c.post("/jobs", json={"take": "t"}, headers=AUTH).json()["id"]
        st = wait_job(c, jid, timeout=120)
        assert st["state"] == "done", st
        return c.get(f"/jobs/{jid}/results/spine.json").json()


def test_dask_and_local_pool_agree_fake_work(tmp_path, dask_handle, pool_handle):
    take = make_take_file(tmp_path / "t.h5", 6)
    a = _run_job(tmp_path, "pool", take, pool_handle, "tests.api.fakework:process_take")
    b = _run_job(tmp_path, "dask", take, dask_handle, "tests.api.fakework:process_take")
    assert a == b and len(a["frames"]) == 6


def test_dask_and_local_pool_agree_process_take(tmp_path, dask_handle, pool_handle):
    take = served.simulated_take_file(tmp_path / "sim.h5")
    a = _run_job(tmp_path, "pool", take, pool_handle, "pipeline.process:process_take")
    served._REF.setdefault(served.SIM_KEY, a)  # an uninterrupted run: the reference of test_serve
    b = _run_job(tmp_path, "dask", take, dask_handle, "pipeline.process:process_take")
    assert a == b and a["format"].startswith("capture-stage/spine")


def test_invalid_input():
    with pytest.raises(ValueError, match="workers"):
        local_pool(0)
    from api.settings import Settings

    with pytest.raises(ValueError, match="dask"):
        Settings(dask="not-an-address")
    h = make_executor(dask=None, workers=1)
    try:
        assert h.kind == "local" and h.executor.submit(pow, 2, 5).result(timeout=60) == 32
    finally:
        h.close()
