"""Hostile requests: links out of the data root, odd bodies and numbers, two jobs on one take."""

from __future__ import annotations

import json
import logging
import uuid
from pathlib import Path

import pytest

from tests.api.conftest import AUTH, add_take, wait_job
from tests.api.fakework import make_take_file


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    d = tmp_path / "outside"
    d.mkdir()
    return d


def test_links_out_of_the_data_root_are_never_read(client, data_root, outside, caplog):
    add_take(data_root, "real")
    # a take, a calibration, a result and a mesh, each a link to a file outside the data root
    make_take_file(outside / "secret.h5", 2)
    (data_root / "takes" / "evil.h5").symlink_to(outside / "secret.h5")
    from tests.stage.frames import calibration

    (outside / "cal.json").write_text(json.dumps(calibration(["a"]).to_dict()))
    cal_id = uuid.uuid4().hex
    (data_root / "calibrations").mkdir(exist_ok=True)
    (data_root / "calibrations" / f"{cal_id}.json").symlink_to(outside / "cal.json")
    with caplog.at_level(logging.WARNING, logger="api"):
        assert [t["id"] for t in client.get("/takes", headers=AUTH).json()] == ["real"]
        assert client.get("/calibrations", headers=AUTH).json() == []
    assert "points outside the data root" in caplog.text
    assert client.get("/takes/evil", headers=AUTH).status_code == 400
    assert client.get(f"/calibrations/{cal_id}.json", headers=AUTH).status_code in (400, 404)

    jid = client.post("/jobs", json={"take": "real"}, headers=AUTH).json()["id"]
    assert wait_job(client, jid)["state"] == "done"
    job_dir = data_root / "jobs" / jid
    (outside / "spine.json").write_text((job_dir / "spine.json").read_text())
    (job_dir / "spine.json").unlink()
    (job_dir / "spine.json").symlink_to(outside / "spine.json")
    (outside / "m.ply").write_bytes((job_dir / "meshes" / "frame_000000.ply").read_bytes())
    (job_dir / "meshes" / "frame_000000.ply").unlink()
    (job_dir / "meshes" / "frame_000000.ply").symlink_to(outside / "m.ply")
    listing = client.get(f"/jobs/{jid}/results/", headers=AUTH).json()
    assert "spine.json" not in listing["files"] and 0 not in listing["meshes"] and 1 in listing["meshes"]
    for name in ("spine.json", "spine.glb", "spine_rig.glb", "meshes/frame_000000.ply", "meshes/0.glb"):
        r = client.get(f"/jobs/{jid}/results/{name}", headers=AUTH)
        assert r.status_code in (400, 404), (name, r.status_code)
        assert b"capture-stage" not in r.content


def test_error_bodies_and_numbers(client):
    r = client.post("/jobs", json={"take": 5, "steps": "x"}, headers=AUTH)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert isinstance(detail, list) and all(isinstance(d["loc"], list) and d["msg"] and d["type"] for d in detail)
    r = client.get("/jobs", params={"offset": 2**63}, headers=AUTH)
    assert r.status_code == 422, r.text
    assert client.get("/jobs", params={"offset": 10**9}, headers=AUTH).json() == []
    # a chunked body (no Content-Length) over the limit is 413, as a declared one is
    big = (b"x" * (1 << 16) for _ in range(40))
    r = client.post("/jobs", content=big, headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 413, r.text
    # the token is checked before the job is looked up
    unknown = uuid.uuid4().hex
    for method, url in (("DELETE", f"/jobs/{unknown}"), ("POST", f"/jobs/{unknown}/cancel")):
        assert client.request(method, url).status_code in (401, 403), (method, url)
        assert client.request(method, url, headers=AUTH).status_code == 404, (method, url)


@pytest.mark.slow
def test_two_jobs_on_one_take_match_one_job_alone(make_client, tmp_path):
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take

    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    take = record_take(simulate_take("starfish", n_cameras=4, frames=3, size=(160, 120), seed=3), data / "takes" / "t.h5")
    ref_dir = tmp_path / "alone"
    (ref_dir / "takes").mkdir(parents=True)
    for p in take.parent.glob("t.*"):
        (ref_dir / "takes" / p.name).write_bytes(p.read_bytes())
    process_take(ref_dir / "takes" / "t.h5", ref_dir / "out", params={"resolution": 32})
    alone = json.loads((ref_dir / "out" / "spine.json").read_text())

    c = make_client(work="pipeline.process:process_take", data=data, max_concurrent_jobs=2)
    ids = [c.post("/jobs", json={"take": "t", "parameters": {"resolution": 32}}, headers=AUTH).json()["id"] for _ in range(2)]
    for jid in ids:
        st = wait_job(c, jid, timeout=120)
        assert st["state"] == "done", st
        assert str(data) not in json.dumps(st) and "DATA/jobs/" in json.dumps(st["result"])  # no server paths
        spine = c.get(f"/jobs/{jid}/results/spine.json", headers=AUTH).json()
        assert spine["graph"] == alone["graph"] and spine["frames"] == alone["frames"]


def test_upload_checks_free_space_first(client, data_root, tmp_path, monkeypatch):
    from stage.store import space

    src = make_take_file(tmp_path / "a.h5", 2)
    monkeypatch.setattr(space, "free_bytes", lambda p: 1000)
    r = client.put("/takes/a", content=src.read_bytes(), headers={**AUTH, "Content-Type": "application/x-hdf5"})
    assert r.status_code == 507 and "free" in r.json()["detail"], r.text
    assert str(data_root) not in r.text
    assert not [p for p in (data_root / "takes").iterdir()]
