"""/rig: cameras and state, capture by frames / duration, stop, previews (test drivers; no hardware)."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from stage.store import TakeReader
from tests.api.conftest import AUTH, make_settings
from tests.api.pattern_rig import RIG, PatternCamera


@pytest.fixture
def rig_client(data_root):
    data_root.mkdir(parents=True, exist_ok=True)
    (data_root / "rig.toml").write_text(RIG)
    app = create_app(make_settings(data_root), work="tests.api.fakework:process_take", driver_factory=PatternCamera,
                     start_runner=False)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _wait_capture(c, timeout=15.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        st = c.get("/rig/capture").json()
        if st["state"] != "capturing":
            return st
        time.sleep(0.02)
    raise AssertionError("capture did not end")


def test_rig_and_capture_by_frames(rig_client, data_root):
    rig = rig_client.get("/rig").json()
    assert rig["name"] == "testrig" and [c["id"] for c in rig["cameras"]] == ["left", "right"]
    assert {c["state"] for c in rig["cameras"]} == {"idle"}
    r = rig_client.post("/rig/capture", json={"take": "cap1", "frames": 10}, headers=AUTH)
    assert r.status_code == 202, r.text
    st = _wait_capture(rig_client)
    assert st["state"] == "done" and st["frames_written"] == 10, st
    with TakeReader(data_root / "takes" / "cap1.h5") as rd:
        assert len(rd) == 10 and rd.cameras == ["left", "right"]
        assert int(rd.frame("right", 3)[0, 0, 0]) == 200
    assert rig_client.get("/takes/cap1").json()["frames"] == 10


def test_capture_by_duration_and_stop(rig_client, data_root):
    r = rig_client.post("/rig/capture", json={"take": "long", "duration_s": 30}, headers=AUTH)
    assert r.status_code == 202
    t0 = time.monotonic()
    while rig_client.get("/rig/capture").json()["frames_written"] < 3 and time.monotonic() - t0 < 15:
        time.sleep(0.02)
    assert {c["state"] for c in rig_client.get("/rig").json()["cameras"]} == {"capturing"}
    assert rig_client.post("/rig/capture", json={"take": "other", "frames": 1}, headers=AUTH).status_code == 409
    assert rig_client.get("/rig/cameras/left/preview.jpg").status_code == 409  # busy
    assert rig_client.post("/rig/capture/stop", headers=AUTH).status_code == 200
    st = _wait_capture(rig_client)
    assert st["state"] == "stopped" and 3 <= st["frames_written"] < 30 * 50, st
    with TakeReader(data_root / "takes" / "long.h5") as rd:
        assert len(rd) == st["frames_written"] and rd.complete
    assert rig_client.post("/rig/capture/stop", headers=AUTH).status_code == 409


def test_preview(rig_client):
    r = rig_client.get("/rig/cameras/right/preview.jpg")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (24, 32, 3) and abs(float(img.mean()) - 200) < 3


def test_invalid_input(rig_client, make_client, tmp_path):
    assert rig_client.post("/rig/capture", json={"take": "x", "frames": 1}).status_code == 401
    assert rig_client.post("/rig/capture", json={"take": "x", "frames": 1},
                           headers={"Authorization": "Bearer bad"}).status_code == 403
    assert rig_client.post("/rig/capture/stop").status_code == 401
    for body in ({"take": "x"}, {"take": "x", "frames": 1, "duration_s": 1}, {"take": "x", "frames": 0},
                 {"take": "../x", "frames": 1}, {"take": "x", "duration_s": -1}):
        assert rig_client.post("/rig/capture", json=body, headers=AUTH).status_code == 422, body
    assert rig_client.get("/rig/cameras/nope/preview.jpg").status_code == 404
    assert rig_client.get("/rig/cameras/..%2F..%2Fetc/preview.jpg").status_code in (400, 404)
    # no rig file: 503 with a message
    c = make_client(data=tmp_path / "norig")
    r = c.get("/rig")
    assert r.status_code == 503 and "rig" in r.json()["detail"]
    assert c.post("/rig/capture", json={"take": "x", "frames": 1}, headers=AUTH).status_code == 503
