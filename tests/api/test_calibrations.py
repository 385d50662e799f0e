"""/calibrations: from a take's stored calibration or from board views (a job), downloads in three formats."""

from __future__ import annotations

import numpy as np
import pytest

from calib.formats import read_calibration
from tests.api.conftest import AUTH, wait_job
from tests.api.fakework import make_take_file, small_calibration

BOARD = {"type": "chessboard", "corners": [7, 6], "square_mm": 100.0}


def _put(client, tmp_path, name, **kw):
    src = make_take_file(tmp_path / f"{name}.h5", 2, **kw)
    r = client.put(f"/takes/{name}", content=src.read_bytes(), headers={**AUTH, "Content-Type": "application/x-hdf5"})
    assert r.status_code == 201, r.text


def _board_take(path, images, names):
    """A take of board images (views x cameras x H x W) through stage.store."""
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter

    h, w = images.shape[2:4]
    with TakeWriter(path, [CameraSpec(c, w, h) for c in names], fps=30.0) as tw:
        for v in range(images.shape[0]):
            t = 10**9 + v * 33_333_333
            tw.write_set({c: Frame(np.ascontiguousarray(images[v, j]), c, v, t, t) for j, c in enumerate(names)},
                         time_ns=t)
    return path


def _calibrate_job(client, name, path, board) -> dict:
    """Upload the take at ``path`` as ``name``, calibrate it from its ``board`` views (a job): the job's status."""
    r = client.put(f"/takes/{name}", content=path.read_bytes(), headers={**AUTH, "Content-Type": "application/x-hdf5"})
    assert r.status_code == 201, r.text
    r = client.post("/calibrations", json={"take": name, "parameters": {"board": board}}, headers=AUTH)
    assert r.status_code == 202, r.text
    return wait_job(client, r.json()["job"], timeout=120)


def test_from_take_and_download_formats(client, tmp_path):
    cal = small_calibration(3)
    _put(client, tmp_path, "board", cameras=3, calibration=cal)
    r = client.post("/calibrations", json={"take": "board", "source": "take"}, headers=AUTH)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    assert r.json()["cameras"] == ["cam00", "cam01", "cam02"] and r.json()["take"] == "board"
    assert [c["id"] for c in client.get("/calibrations").json()] == [cid]
    for fmt in ("json", "toml", "yaml"):
        d = client.get(f"/calibrations/{cid}.{fmt}")
        assert d.status_code == 200, (fmt, d.text)
        path = tmp_path / f"down.{fmt}"
        path.write_bytes(d.content)
        back = read_calibration(path)
        assert back.names == cal.names
        for a, b in zip(back, cal):
            np.testing.assert_allclose(a.K, b.K, atol=1e-9)
            np.testing.assert_allclose(a.R, b.R, atol=1e-9)
            np.testing.assert_allclose(a.t, b.t, atol=1e-9)
    assert client.delete(f"/calibrations/{cid}", headers=AUTH).status_code == 204
    assert client.get(f"/calibrations/{cid}.json").status_code == 404


def test_from_board_views_runs_a_job(client, tmp_path, monkeypatch):
    import api.calibrations as mod

    cal = small_calibration(2)
    seen = {}

    def fake_calibrator(take, *, params, progress=None, cancel=None):
        seen["board"] = params.board
        progress("calibrate", 1, 1)
        return cal

    monkeypatch.setattr(mod, "_find_rig_calibrator", lambda: fake_calibrator)
    _put(client, tmp_path, "b")
    r = client.post("/calibrations", json={"take": "b", "parameters": {"board": BOARD}}, headers=AUTH)
    assert r.status_code == 202, r.text
    jid = r.json()["job"]
    st = wait_job(client, jid)
    assert st["state"] == "done" and st["kind"] == "calibrate", st
    assert seen["board"] == BOARD
    got = client.get(f"/calibrations/{jid}.json").json()
    assert [c["name"] for c in got["cameras"]] == ["cam00", "cam01"] and got["meta"]["source"] == "board"


def test_invalid_input(client, tmp_path, monkeypatch):
    import api.calibrations as mod
    from api.errors import UnavailableError

    with pytest.raises(ValueError, match="warn"):
        mod.calibrate_take(tmp_path / "any.h5", params=mod.CalibrateParams(board=BOARD), warn=["not", "callable"])

    _put(client, tmp_path, "nocal")
    assert client.post("/calibrations", json={"take": "nocal", "source": "take"}).status_code == 401
    assert client.post("/calibrations", json={"take": "nocal", "source": "take"},
                       headers={"Authorization": "Bearer no"}).status_code == 403
    r = client.post("/calibrations", json={"take": "nocal", "source": "take"}, headers=AUTH)
    assert r.status_code == 404 and "no calibration" in r.json()["detail"]
    assert client.post("/calibrations", json={"take": "zzz", "source": "take"}, headers=AUTH).status_code == 404
    assert client.post("/calibrations", json={"take": "nocal", "source": "magic"}, headers=AUTH).status_code == 422

    def missing():
        raise UnavailableError("no calibrator")

    for params in ({}, {"board": {"type": "hexagon"}}, {"board": BOARD, "step": 0}, {"board": BOARD, "extra": 1}):
        r = client.post("/calibrations", json={"take": "nocal", "parameters": params}, headers=AUTH)
        assert r.status_code == 400 and "parameters" in r.json()["detail"], (params, r.text)
    monkeypatch.setattr(mod, "_find_rig_calibrator", missing)
    assert client.post("/calibrations", json={"take": "nocal", "parameters": {"board": BOARD}},
                       headers=AUTH).status_code == 503
    unknown = "1" * 32
    assert client.get(f"/calibrations/{unknown}.json").status_code == 404
    assert client.get(f"/calibrations/{unknown}.xml").status_code in (400, 422)
    assert client.get("/calibrations/..%2Fjobs.json").status_code in (400, 404)
    assert client.delete(f"/calibrations/{unknown}", headers=AUTH).status_code == 404
    assert client.delete(f"/calibrations/{unknown}").status_code == 401


@pytest.mark.slow
def test_calibrate_rendered_board_take(make_client, tmp_path):
    """A take of a board waved through a simulated 4-camera dome, calibrated by
    calib.rig through the API: camera-to-camera distances within 1.5 % of the truth."""
    from scipy.spatial.distance import pdist

    client = make_client(max_upload_bytes=64 << 20)

    from calib.boards import parse_board
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    truth = make_dome(4, size=(320, 240), seed=0)
    views = render_board_views(parse_board(BOARD), truth, 20, seed=0)
    path = tmp_path / "board.h5"
    _board_take(path, views.images, truth.names)
    st = _calibrate_job(client, "board", path, BOARD)
    assert st["state"] == "done", st
    assert st["progress"]["detect"] == {"done": 20, "total": 20, "step": "detect"}  # frame sets
    got = client.get(f"/calibrations/{st['id']}.json").json()
    from calib.calibration import Calibration

    cal = Calibration.from_dict(got)
    assert cal.names == truth.names
    d_true, d_got = pdist(truth.centers()), pdist(cal.centers())
    assert np.max(np.abs(d_got - d_true) / d_true) < 0.015


def test_calibrate_take_passes_every_detection_with_the_cli_defaults(tmp_path, monkeypatch):
    """The job hands every detection to calib.rig.calibrate_rig (which selects the views for the
    rig) with stage calibrate's defaults: a board held still for two frames is seen twice by every
    camera, and per-camera novelty thinning would have dropped the repeats that link the cameras."""
    import calib.rig
    from api.calibrations import CalibrateParams, calibrate_take
    from calib.boards import parse_board
    from calib.detect import detect_board
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    truth = make_dome(4, size=(320, 240), seed=0)
    views = render_board_views(parse_board(BOARD), truth, 4, seed=0)
    images = np.repeat(views.images, 2, axis=0)  # each pose held for two frames
    path = tmp_path / "still.h5"
    _board_take(path, images, truth.names)
    seen = {}

    def spy(detections, sizes, board, **kw):
        seen.update(detections=detections, kw=kw)
        return "result"

    monkeypatch.setattr(calib.rig, "calibrate_rig", spy)
    assert calibrate_take(path, params=CalibrateParams(board=BOARD)) == "result"
    board = parse_board(BOARD)
    for j, c in enumerate(truth.names):
        want = [k for k in range(images.shape[0]) if detect_board(images[k, j], board) is not None]
        assert len(want) >= 4
        assert [d.frame for d in seen["detections"][c]] == want
    assert seen["kw"]["intrinsics"] == "prior" and seen["kw"]["holdout_folds"] == 5
    assert seen["kw"]["min_change"] == 0.02
    with pytest.raises(ValueError, match="holdout"):
        CalibrateParams(board=BOARD, holdout=1)
    with pytest.raises(ValueError, match="intrinsics"):
        CalibrateParams(board=BOARD, intrinsics="loose")


def test_a_calibration_job_that_warns_and_then_fails_keeps_its_warnings(make_client, tmp_path):
    """A board waved past two cameras of a dome, then past the other two: each camera's intrinsics warn (few views,
    little of the image covered), then the bundle adjustment fails (the pairs never see the board at once). The
    failed job's record keeps the warnings said before it failed, as calibrate_take says them in this process."""
    from api.calibrations import CalibrateParams, calibrate_take
    from calib.boards import parse_board
    from calib.intrinsics import CalibrationError
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    truth = make_dome(4, size=(320, 240), seed=0)
    images = render_board_views(parse_board(BOARD), truth, 32, seed=0).images.copy()
    images[16:, :2] = np.median(images[16:, :2])  # cam00, cam01: no board in the second half
    images[:16, 2:] = np.median(images[:16, 2:])  # cam02, cam03: none in the first
    path = _board_take(tmp_path / "apart.h5", images, truth.names)
    said: list[str] = []
    with pytest.raises(CalibrationError, match="could not connect every camera"):
        calibrate_take(path, params=CalibrateParams(board=BOARD), warn=said.append)
    assert {w.split(":")[0] for w in said if "board views; 10-20 views" in w} == {f"camera {n}" for n in truth.names}

    client = make_client(max_upload_bytes=64 << 20)
    st = _calibrate_job(client, "apart", path, BOARD)
    assert st["state"] == "failed" and "could not connect every camera" in st["error"], st
    assert "but never at the same time as a camera connected to the rest" in st["error"], st  # (not "never detected")
    assert st["warnings"] == said, st
    assert client.get("/jobs", params={"state": "failed"}).json()[0]["warnings"] == said


CHARUCO = {"type": "charuco", "squares": [7, 6], "square_mm": 100.0, "marker_mm": 75.0, "dictionary": "DICT_4X4_50"}


@pytest.fixture(scope="module")
def mirrored_take(tmp_path_factory):
    """A ChArUco board waved through a 4-camera dome; cam01 delivers its images flipped
    left-right, as a simulated camera with ``mirror_mode = true`` does (fake_cameras.device)."""
    from calib.boards import parse_board
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    truth = make_dome(4, size=(640, 480), seed=0)
    views = render_board_views(parse_board(CHARUCO), truth, 24, seed=0)
    images = views.images.copy()
    images[:, 1] = images[:, 1, :, ::-1]  # what the mirroring webcam delivers
    path = tmp_path_factory.mktemp("mirror") / "mirrored.h5"
    _board_take(path, images, truth.names)
    return truth, path


def test_calibrate_take_finds_a_mirrored_camera(make_client, mirrored_take):
    """The API's calibration job detects the mirroring camera as stage calibrate does (calib.mirror
    and calib.rig.resolve_flipped), records mirror = true and calibrates it: focal lengths within
    1 % and principal points within 5 px of the truth (tests/calib/test_handheld.py's tolerances),
    camera distances within 1.5 %. Forced ``mirror: {cam01: false}``: the job fails naming cam01."""
    from scipy.spatial.distance import pdist

    from calib.calibration import Calibration

    truth, path = mirrored_take
    client = make_client(max_upload_bytes=128 << 20)
    st = _calibrate_job(client, "mir", path, CHARUCO)
    assert st["state"] == "done", st
    got = client.get(f"/calibrations/{st['id']}.json").json()
    cal = Calibration.from_dict(got)
    assert cal.names == truth.names
    assert [c.name for c in cal if c.meta.get("mirror")] == ["cam01"]
    for est, tru in zip(cal, truth):
        np.testing.assert_allclose([est.K[0, 0], est.K[1, 1]], [tru.K[0, 0], tru.K[1, 1]], rtol=0.01,
                                   err_msg=est.name)
        assert np.linalg.norm(est.K[:2, 2] - tru.K[:2, 2]) < 5.0, est.name
    d_true, d_got = pdist(truth.centers()), pdist(cal.centers())
    assert np.max(np.abs(d_got - d_true) / d_true) < 0.015

    r = client.post("/calibrations", json={"take": "mir", "parameters": {"board": CHARUCO,
                                                                        "mirror": {"cam01": "false"}}}, headers=AUTH)
    assert r.status_code == 202, r.text
    st = wait_job(client, r.json()["job"], timeout=120)
    assert st["state"] == "failed" and "cam01" in str(st) and "mirror = false" in str(st), st
    # the message names the request field, not the command line's --mirror
    assert 'parameters.mirror.cam01 = "false"' in str(st) and "--mirror" not in str(st), st
    r = client.post("/calibrations", json={"take": "mir", "parameters": {"board": CHARUCO,
                                                                        "mirror": {"cam09": "true"}}}, headers=AUTH)
    st = wait_job(client, r.json()["job"], timeout=120)
    assert st["state"] == "failed" and 'parameters.mirror.cam09 = "true": unknown camera' in str(st), st
    r = client.post("/calibrations", json={"take": "mir", "parameters": {"board": CHARUCO,
                                                                        "mirror": {"cam01": "sometimes"}}}, headers=AUTH)
    assert r.status_code == 400 and "parameters" in r.json()["detail"], r.text


def test_board_report_is_strict_json_when_a_camera_has_no_held_out_views(client, tmp_path, monkeypatch):
    """A held-out fold can leave a camera without views: its held-out error is NaN in the calibrator's report.
    The job's ``report.json`` must still be JSON that a browser's ``JSON.parse`` reads (the control room's page
    waits on it): NaN is written as null, and the other figures as they were. The calibration's warnings are the
    job record's, each once."""
    import json

    import api.calibrations as mod

    cal = small_calibration(2)

    class Result:
        calibration = cal
        warnings = ["cam00: no held-out views", "cam00: no held-out views"]

        def to_dict(self):
            return {"summary": "2 cameras", "evaluation": {"held_out": {"per_camera": {
                "cam00": {"rms": float("nan"), "views": 0}, "cam01": {"rms": np.float64(0.25), "views": 3}},
                "rms": np.float64(np.nan)}}, "covariance": np.array([[1.0, np.inf]])}

    monkeypatch.setattr(mod, "_find_rig_calibrator", lambda: lambda take, **kw: Result())
    _put(client, tmp_path, "b")
    r = client.post("/calibrations", json={"take": "b", "parameters": {"board": BOARD}}, headers=AUTH)
    assert r.status_code == 202, r.text
    jid = r.json()["job"]
    st = wait_job(client, jid)
    assert st["state"] == "done" and st["warnings"] == ["cam00: no held-out views"], st  # (its record's, once)
    got = client.get(f"/jobs/{jid}/results/report.json")
    assert got.status_code == 200, got.text

    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    report = json.loads(got.text, parse_constant=refuse)
    held = report["evaluation"]["held_out"]
    assert held["per_camera"] == {"cam00": {"rms": None, "views": 0}, "cam01": {"rms": 0.25, "views": 3}}
    assert held["rms"] is None and report["covariance"] == [[1.0, None]] and report["summary"] == "2 cameras"
