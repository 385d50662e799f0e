"""The live 3-D preview follows the session's calibration: the one its board session made (once the
calibration job has saved it), or one chosen later (``PUT /stage/calibration/{id}``)."""

from __future__ import annotations

import time
from functools import partial
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.calibrations import CalibrationLibrary
from api.control import ControlRoom
from api.live3d import Live3D
from api.settings import Settings
from stage.session import StageSession
from tests.polling import wait_until
from tests.stage.frames import calibration
from tests.stage.paced import make_drivers, rig_for

IDS = ["c0", "c1"]
JOB = "ab" * 16  # a calibration job's id: its calibration is saved under it


_wait = partial(wait_until, timeout=60.0, poll=0.1)


@pytest.fixture
def room(tmp_path):
    session = StageSession(rig_for(IDS, fps=20), tmp_path / "takes", drivers=make_drivers(IDS, fps=20)).open()
    room = ControlRoom(session, calibrations=CalibrationLibrary(tmp_path / "calibrations"))
    yield room
    room.close()
    session.close()


def test_the_preview_takes_up_the_calibration_the_board_session_made(room):
    live = room.live3d = Live3D(room, resolution=16, rate_hz=10).start()
    _wait(lambda: live.latest()["state"] == "unavailable", what="no calibration yet")
    room.board_session = SimpleNamespace(job=JOB, running=False, stop=lambda: None)  # calibrating: job queued
    time.sleep(1.5)
    assert live.latest()["state"] == "unavailable" and room.calibration_version == 0  # the job has not saved it yet
    room.calibrations.save(calibration(IDS), JOB)  # the job is done
    made = f"calibration {JOB} (board session)"
    st = _wait(lambda: (s := live.latest()).get("calibration") == made and s["state"] in ("ok", "empty") and s,
               what="the preview on the board session's calibration")
    assert room.calibration_version == 1 and st["updates"] >= 0
    # another calibration (here one of the session's own cameras moved): the worker starts again on it
    moved = calibration(IDS)
    room.use_calibration(moved, "calibration chosen")
    _wait(lambda: live.latest().get("calibration") == "calibration chosen", what="the chosen calibration")
    assert room.calibration() is moved and room.calibration_version == 2


def test_a_calibration_is_chosen_through_the_api(room, tmp_path):
    settings = Settings(data=tmp_path / "data", api_token="t")
    app = create_app(settings, control=room, start_runner=False)
    app.state.calibrations.save(calibration(IDS), JOB)
    app.state.calibrations.save(calibration(["x", "y"]), "cd" * 16)
    with TestClient(app) as c:
        assert c.put(f"/stage/calibration/{JOB}").status_code == 401
        auth = {"Authorization": "Bearer t"}
        r = c.put(f"/stage/calibration/{JOB}", headers=auth)
        assert r.status_code == 200 and r.json()["calibration"] == f"calibration {JOB}", r.text
        assert list(room.calibration().names) == IDS
        assert c.put(f"/stage/calibration/{'ef' * 16}", headers=auth).status_code == 404
        r = c.put(f"/stage/calibration/{'cd' * 16}", headers=auth)
        assert r.status_code == 409 and "none of the rig's cameras" in r.text
        assert c.put("/stage/calibration/not-an-id", headers=auth).status_code == 400


def test_volume_edges_names_the_sides_a_hull_reaches():
    """Against the sides set by hand: every side but the floor is named when the hull has a voxel in the
    grid's outer layer there; one voxel inside the outer layer names nothing."""
    from api.live3d import volume_edges

    occ = np.zeros((6, 7, 8), bool)
    occ[1:5, 1:6, 0:7] = True  # standing on the floor, inside every other side
    assert volume_edges(occ) == []
    for side, index in (("x min", (0, 3, 3)), ("x max", (5, 3, 3)), ("y min", (3, 0, 3)), ("y max", (3, 6, 3)),
                        ("z max", (3, 3, 7))):
        hit = occ.copy()
        hit[index] = True
        assert volume_edges(hit) == [side], side
    assert volume_edges(np.ones((2, 2, 2), bool)) == ["x min", "x max", "y min", "y max", "z max"]


def test_invalid_input():
    from api.live3d import volume_edges

    for bad in (np.zeros((3, 3), bool), np.zeros((3, 3, 3), np.uint8), np.zeros((0, 3, 3), bool)):
        with pytest.raises(ValueError, match="occupancy"):
            volume_edges(bad)


def test_the_view_says_how_old_its_frame_set_is(monkeypatch):
    """latest()'s age_s: from the set's time (host monotonic clock) to now, exact on a fixed clock; none before
    the first set."""
    import api.live3d as live3d

    live = Live3D(room=None)
    assert live.latest()["age_s"] is None
    live._set(state="ok", set=7, set_time_ns=10_000_000_000)
    monkeypatch.setattr(live3d.time, "monotonic_ns", lambda: 10_450_000_000)
    assert live.latest()["age_s"] == pytest.approx(0.45, abs=1e-12)
