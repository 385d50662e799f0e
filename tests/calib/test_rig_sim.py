"""Rig calibration on the simulated 12-camera dome (calib.rig, calib.extrinsics, calib.bundle).

Corners are the true projections through the simulated cameras plus Gaussian
noise (sigma = 0.3 px per coordinate); the estimate is compared with the true
cameras after the best rigid alignment (the world frame is a choice of gauge;
the scale comes from the board and is not aligned).
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.boards import Charuco, Chessboard
from calib.bundle import bundle_adjust, project_batch, rodrigues_batch
from calib.camera import project_points
from calib.detect import Detection
from calib.extrinsics import calibrate_extrinsics, triangulate_board_error
from calib.intrinsics import CalibrationError, calibrate_intrinsics
from calib.rig import calibrate_rig
from calib.synthetic import random_board_poses, synthetic_detections

SIGMA = 0.3
N_VIEWS = 200

BOARDS = {
    "chessboard": Chessboard((11, 8), 50.0),
    "charuco": Charuco((12, 9), 50.0, 37.0, dictionary="DICT_4X4_100"),
}


@pytest.fixture(scope="module")
def truth():
    from fake_cameras import dome
    return dome.make_dome(12)


def _simulate(truth, board, n=N_VIEWS, seed=1):
    poses = random_board_poses(truth, board, n, seed=seed, spread=0.25 * 1560)
    return synthetic_detections(truth, board, poses, noise_px=SIGMA, seed=seed + 1)


def _align(est, tru):
    """Rigid (no scale) transform taking the estimate's world to the true world."""
    A = np.concatenate([est.centers()] + [np.stack([c.center + 300 * c.R[k] for c in est]) for k in range(3)])
    B = np.concatenate([tru.centers()] + [np.stack([c.center + 300 * c.R[k] for c in tru]) for k in range(3)])
    ma, mb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ma).T @ (B - mb))
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mb - R @ ma


@pytest.fixture(scope="module", params=list(BOARDS))
def solved(request, truth):
    board = BOARDS[request.param]
    dets = _simulate(truth, board)
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names)
    return board, dets, res


@pytest.mark.slow
def test_rig_accuracy(solved, truth):
    board, dets, res = solved
    est = res.calibration
    assert est.names == truth.names  # every camera connected
    R, t = _align(est, truth)
    for e, g in zip(est, truth):
        assert abs(e.K[0, 0] / g.K[0, 0] - 1) < 0.005 and abs(e.K[1, 1] / g.K[1, 1] - 1) < 0.005, e.name
        assert np.all(np.abs(e.K[:2, 2] - g.K[:2, 2]) < 2.0), (e.name, e.K[:2, 2] - g.K[:2, 2])
        centre = R @ e.center + t
        assert np.linalg.norm(centre - g.center) < 2.0, (e.name, np.linalg.norm(centre - g.center))
        dR = (e.R @ R.T) @ g.R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert angle < 0.1, (e.name, angle)
    # RMS per corner (2D) of pure Gaussian noise: sigma * sqrt(2) (minus the few fitted parameters)
    floor = SIGMA * np.sqrt(2)
    assert abs(res.extrinsics.rms - floor) < 0.1 * floor
    for name, v in res.extrinsics.per_camera_rms.items():
        assert abs(v - floor) < 0.1 * floor, name
    # the board triangulated from the calibrated cameras keeps its shape (mm)
    assert res.extrinsics.geometry["neighbor_rms"] < 1.0
    assert res.extrinsics.geometry["frames"] > 0.9 * N_VIEWS


@pytest.mark.slow
def test_world_frame_is_the_board(solved):
    board, dets, res = solved
    ext = res.extrinsics
    R, t = ext.board_poses[ext.world_frame]
    # the world frame is the chosen board turned face up: x along the board, z = -board z
    np.testing.assert_allclose(R, np.diag([1.0, -1.0, -1.0]), atol=1e-9)
    np.testing.assert_allclose(t, 0, atol=1e-9)


def test_bundle_projection_matches_camera_model():
    rng = np.random.default_rng(0)
    intr = np.array([[510, 505, 320, 240, -0.1, 0.02, 0.001, -0.002, 0.01]], float)
    r = rng.normal(0, 0.3, (1, 3))
    X = rng.uniform(-100, 100, (50, 3)) + [0, 0, 800]
    R = rodrigues_batch(r)[0]
    uv = project_batch(X @ R.T + [1, 2, 3], np.repeat(intr, 50, 0))
    K = np.array([[510, 0, 320], [0, 505, 240], [0, 0, 1.0]])
    ref = project_points(X, K=K, dist=intr[0, 4:], R=R, t=[1, 2, 3])
    np.testing.assert_allclose(uv, ref, atol=1e-9)


def test_bundle_adjust_recovers_perturbed_poses():
    """Exact data, perturbed start: the analytic-Jacobian LM and scipy's least_squares reach the truth."""
    rng = np.random.default_rng(3)
    C, B = 3, 6
    obj = Chessboard((5, 4), 30).object_points()
    intr = np.tile([600.0, 600, 320, 240, 0, 0, 0, 0, 0], (C, 1))
    cr = np.array([[0, 0, 0], [0, 0.4, 0], [0, -0.4, 0.0]])
    ct = np.array([[0, 0, 1000.0], [-400, 0, 1100], [400, 0, 1100]])
    br = rng.normal(0, 0.2, (B, 3))
    bt = rng.normal(0, 60, (B, 3)) - [60, 45, 0]
    oc, ob, op = [], [], []
    for c in range(C):
        for b in range(B):
            oc += [c] * len(obj)
            ob += [b] * len(obj)
            op.append(obj)
    oc, ob, op = np.array(oc), np.array(ob), np.concatenate(op)
    Xw = np.einsum("mij,mj->mi", rodrigues_batch(br)[ob], op) + bt[ob]
    uv = project_batch(np.einsum("mij,mj->mi", rodrigues_batch(cr)[oc], Xw) + ct[oc], intr[oc])
    for solver in ("lm", "scipy"):
        res = bundle_adjust(oc, ob, op, uv, intrinsics=intr, cam_rvec=cr + rng.normal(0, 0.01, cr.shape) * [[0], [1], [1]],
                            cam_tvec=ct + rng.normal(0, 5, ct.shape) * [[0], [1], [1]], board_rvec=br + 0.01,
                            board_tvec=bt + 3, reference=0, solver=solver)
        np.testing.assert_allclose(res.cam_tvec, ct, atol=1e-4)
        np.testing.assert_allclose(res.cam_rvec, cr, atol=1e-7)
        assert np.abs(res.residuals).max() < 1e-6


# -- bad input: an error naming the camera and saying what to do ---------------------------------


@pytest.fixture(scope="module")
def small(truth):
    board = BOARDS["charuco"]
    return board, _simulate(truth, board, n=25, seed=5)


def test_fix_k3_survives_the_bundle_adjustment(small, truth):
    """``fix_k3``: k3 is 0 after the intrinsics and stays 0 through the bundle adjustment,
    which still refines every other intrinsic (it used to free k3 again)."""
    board, dets = small
    sizes = {c.name: c.size for c in truth}
    fixed = calibrate_rig(dets, sizes, board, cameras=truth.names, fix_k3=True)
    free = calibrate_rig(dets, sizes, board, cameras=truth.names)
    for n in truth.names:
        assert fixed.intrinsics[n].camera().dist[4] == 0.0
        cam = fixed.calibration[n]
        assert cam.dist[4] == 0.0
        assert cam.K[0, 0] != fixed.intrinsics[n].camera().K[0, 0]  # the rest was refined
    assert any(free.calibration[n].dist[4] != 0.0 for n in truth.names)


def test_camera_without_board(small, truth):
    board, dets = small
    dets = dict(dets)
    dets["cam07"] = []
    with pytest.raises(CalibrationError, match=r"camera cam07: the board was never detected.*board file") as ei:
        calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names)
    assert ei.value.cameras == ("cam07",)


def test_too_few_views(small, truth):
    board, dets = small
    dets = dict(dets)
    dets["cam03"] = dets["cam03"][:2]
    with pytest.raises(CalibrationError, match=r"camera cam03: only 2 usable board view.*film the board"):
        calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names)


def test_camera_sharing_no_view(small, truth):
    board, dets = small
    dets = dict(dets)
    # cam05 sees the board only in frames nobody else saw
    dets["cam05"] = [Detection(d.ids, d.corners, frame=1000 + d.frame) for d in dets["cam05"]]
    intr = [calibrate_intrinsics(dets[c.name], board, c.size, name=c.name).camera() for c in truth]
    with pytest.raises(CalibrationError, match=r"camera cam05: saw the board in \d+ view\(s\) but never at the same "
                                               r"time.*show the board where cam05") as ei:
        calibrate_extrinsics(dets, intr, board)
    assert ei.value.cameras == ("cam05",)


def test_warn_hands_on_each_warning_as_it_is_known_and_before_a_failure(small, truth, monkeypatch):
    """``calibrate_rig(warn=)`` is handed the result's warnings, in their order, each once; when the bundle
    adjustment then fails, every camera's intrinsics warnings have been handed on before it raised (those the
    same detections' successful calibration has)."""
    import calib.rig

    board, dets = small
    sizes = {c.name: c.size for c in truth}
    said: list[str] = []
    res = calibrate_rig(dets, sizes, board, cameras=truth.names, warn=said.append)
    assert said == res.warnings and len(said) >= len(truth.names), said  # (25 views: every camera warns of them)
    intrinsics_said = [w for r in res.intrinsics.values() for w in r.warnings]

    def fails(*args, **kw):
        raise CalibrationError("could not connect every camera: cam05")

    monkeypatch.setattr(calib.rig, "calibrate_extrinsics", fails)
    said.clear()
    with pytest.raises(CalibrationError, match="cam05"):
        calibrate_rig(dets, sizes, board, cameras=truth.names, warn=said.append)
    assert said == intrinsics_said


def test_calibrate_rig_says_a_camera_saw_the_board_but_never_with_another(small, truth):
    """Through calibrate_rig (the bundle adjustment gets the frame sets two cameras share), a camera that saw the
    board only in frames nobody else saw is said to have seen it, every view counted, but never at the same time as
    the rest, not to have never seen it."""
    board, dets = small
    dets = dict(dets)
    dets["cam05"] = [Detection(d.ids, d.corners, frame=1000 + d.frame) for d in dets["cam05"]]
    with pytest.raises(CalibrationError, match=rf"could not connect every camera: camera cam05: saw the board in "
                                               rf"{len(dets['cam05'])} view\(s\) but never at the same time") as ei:
        calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names)
    assert ei.value.cameras == ("cam05",) and "never detected" not in str(ei.value)


def test_wrong_board_definition(truth):
    """The classic mistake: the board file counts squares (8 x 6) instead of inner corners (7 x 5).

    Nothing is detected and the error says to check the board file against the print.
    """
    from calib.detect import detect_board
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    cal = make_dome(4, size=(320, 240))
    views = render_board_views(Chessboard((7, 5), 100.0), cal, 2, seed=1)
    wrong = Chessboard((8, 6), 100.0)
    dets = {c.name: [d for d in (detect_board(views.images[v, i], wrong, frame=v) for v in range(2)) if d]
            for i, c in enumerate(cal)}
    assert not any(dets.values())
    with pytest.raises(CalibrationError, match="board file matches the print"):
        calibrate_rig(dets, {c.name: c.size for c in cal}, wrong, cameras=cal.names)


def test_detection_on_rendered_images(truth):
    """Real rendered images (fake_cameras.boards): detected corners agree with the true ones, same ids."""
    from calib.detect import detect_board
    from fake_cameras.boards import render_board_views
    from fake_cameras.dome import make_dome

    cal = make_dome(4, size=(640, 480))
    for board in (Chessboard((7, 6), 80.0), Charuco((5, 4), 120.0, 90.0, dictionary="DICT_4X4_50", inverted=True)):
        views = render_board_views(board, cal, 2, seed=1)
        found = 0
        for v in range(2):
            for c in range(len(cal)):
                d = detect_board(views.images[v, c], board)
                if d is None:
                    continue
                found += 1
                assert views.visible[v, c, d.ids].all()
                err = np.linalg.norm(d.corners - views.corners_2d[v, c, d.ids], axis=1)
                assert np.median(err) < 0.3 and err.max() < 1.0, (type(board).__name__, v, c, err.max())
        assert found >= 3


def test_invalid_input(small, truth):
    board, dets = small
    sizes = {c.name: c.size for c in truth}
    with pytest.raises(ValueError, match="board"):
        calibrate_rig(dets, sizes, "board.toml")
    with pytest.raises(ValueError, match="sizes"):
        calibrate_rig(dets, {"cam00": (640, 480)}, board, cameras=["cam00", "cam01"])
    with pytest.raises(ValueError, match="size"):
        calibrate_intrinsics(dets["cam00"], board, (0, 480))
    with pytest.raises(ValueError, match="detections"):
        calibrate_intrinsics([1, 2, 3, 4], board, (640, 480))
    cams = [c.replace() for c in truth]
    with pytest.raises(ValueError, match="world"):
        calibrate_extrinsics(dets, cams, board, world="floor")
    with pytest.raises(ValueError, match="at least 2 cameras"):
        calibrate_extrinsics(dets, cams[:1], board)
    with pytest.raises(ValueError, match="unknown camera"):
        calibrate_extrinsics({"nope": []}, cams, board)
    with pytest.raises(ValueError, match="loss"):
        bundle_adjust([0], [0], [[0, 0, 0]], [[0, 0]], intrinsics=np.ones((1, 9)), cam_rvec=np.zeros((1, 3)),
                      cam_tvec=np.zeros((1, 3)), board_rvec=np.zeros((1, 3)), board_tvec=np.zeros((1, 3)),
                      loss="l3")
    with pytest.raises(ValueError, match="fixed_intrinsics"):
        bundle_adjust([0], [0], [[0, 0, 0]], [[0, 0]], intrinsics=np.ones((1, 9)), cam_rvec=np.zeros((1, 3)),
                      cam_tvec=np.zeros((1, 3)), board_rvec=np.zeros((1, 3)), board_tvec=np.zeros((1, 3)),
                      optimize_intrinsics=True, fixed_intrinsics=("k4",))
    with pytest.raises(ValueError, match="equal length"):
        bundle_adjust([0, 0], [0], [[0, 0, 0]], [[0, 0]], intrinsics=np.ones((1, 9)), cam_rvec=np.zeros((1, 3)),
                      cam_tvec=np.zeros((1, 3)), board_rvec=np.zeros((1, 3)), board_tvec=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="noise_px"):
        synthetic_detections(truth, board, [], noise_px=-1)
    with pytest.raises(ValueError, match="warn"):
        calibrate_rig(dets, sizes, board, warn="print")
    with pytest.raises(ValueError, match="board"):
        triangulate_board_error(truth, dets, "board")
    with pytest.raises(ValueError, match="max_views"):
        calibrate_intrinsics(dets["cam00"], board, (640, 480), max_views=2)
def test_corner_warnings_name_the_remedy_without_a_command_line_option():
    """A camera uncertain by more than CORNER_WARN_PX at a corner is one warning; it reaches a calibration job's
    report too, so it names fixing k3 as ``stage calibrate --fix-k3`` and ``parameters.fix_k3`` both read it."""
    from calib.rig import CORNER_WARN_PX, corner_warnings

    points = ("centre", "top-left", "top-right", "bottom-left", "bottom-right")
    got = corner_warnings({"cam0": dict(zip(points, (0.3, 2.5, 1.0, 1.0, 1.0))),
                           "cam1": dict(zip(points, (0.2, CORNER_WARN_PX, 1.0, 1.0, 1.0)))})  # at the threshold: none
    assert got == ["camera cam0: its projection is uncertain by 2.500 px (1 sigma) at the image corners: the lens "
                   "distortion there is extrapolated from the board's views; film the board near the corners of "
                   "cam0's image (or fix k3 at zero for a mild lens)"]
    for bad in ({"cam0": 3.0}, {"cam0": {"centre": 0.3}}, [("cam0", {})]):
        with pytest.raises(ValueError, match="uncertainty"):
            corner_warnings(bad)


# -- the bundle adjustment's moves of the intrinsics, judged (calib.rig.intrinsics_moved) ----------


def _moved_to(calibration, name, params):
    """``calibration`` with camera ``name``'s intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3) set to ``params``."""
    from calib.calibration import Calibration

    K = np.array([[params[0], 0.0, params[2]], [0.0, params[1], params[3]], [0.0, 0.0, 1.0]])
    return Calibration([c.replace(K=K, dist=np.asarray(params[4:], float)) if c.name == name else c
                        for c in calibration.cameras])


def test_intrinsics_moved_warns_at_its_rate_for_accurate_cameras_and_names_a_wrong_one(small, truth):
    """Moves drawn from each camera's own uncertainty (accurate cameras: what the bundle adjustment of a rig the
    cameras agree on may do) make a rig warn at MOVE_WARN_P (binomial 4-sigma bound over 400 rigs of 12 cameras),
    where judging every intrinsic at 3 sigma warns for about one rig in five; a camera whose focal length the rig
    moved by 2 % (4.5 of its standard deviations) is named, and only it. On the simulated dome (corners with
    Gaussian noise, 25 views) the calibration warns of no camera."""
    from calib.rig import MOVE_WARN_P, intrinsics_moved

    board, dets = small
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names, holdout_folds=0)
    assert not any("bundle adjustment moved" in w for w in res.warnings)
    figures, warn = intrinsics_moved(res.intrinsics, res.calibration)
    assert warn == [] and set(figures) == set(truth.names)
    rng = np.random.default_rng(0)
    rigs, joint, each = 400, 0, 0
    for _ in range(rigs):
        cal = res.calibration
        moved_far = False
        for n, r in res.intrinsics.items():
            free = np.isfinite(np.diag(r.covariance))
            d = np.zeros(9)
            C = r.covariance[np.ix_(free, free)]
            d[free] = rng.multivariate_normal(np.zeros(free.sum()), C)
            moved_far |= bool(np.any(np.abs(d[free]) > 3 * np.sqrt(np.diag(C))))
            cal = _moved_to(cal, n, r.params + d)
        joint += bool(intrinsics_moved(res.intrinsics, cal)[1])
        each += moved_far
    bound = MOVE_WARN_P * rigs + 4 * np.sqrt(MOVE_WARN_P * rigs)
    assert joint <= bound < 10 and each > 40, (joint, each)
    wrong = res.intrinsics["cam03"].params * np.r_[1.02, 1.02, np.ones(7)]
    figures, warn = intrinsics_moved(res.intrinsics, _moved_to(res.calibration, "cam03", wrong))
    assert len(warn) == 1 and warn[0].startswith("camera cam03: the bundle adjustment moved its intrinsics")
    assert figures["cam03"]["p"] < MOVE_WARN_P / 12


def test_intrinsics_moved_invalid_input(small, truth):
    from calib.rig import intrinsics_moved

    board, dets = small
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names[:3], holdout_folds=0)
    with pytest.raises(ValueError, match="intrinsics must map"):
        intrinsics_moved({"cam00": 1.0}, res.calibration)
    with pytest.raises(ValueError, match="calibration must be a Calibration"):
        intrinsics_moved(res.intrinsics, None)
    with pytest.raises(ValueError, match="calibration must be a Calibration"):
        intrinsics_moved({"nope": res.intrinsics["cam00"]}, res.calibration)


def test_the_report_says_one_verdict_and_each_kind_of_warning_once(small, truth):
    """The report's first line is the verdict: consistent on the accurate simulated rig, "check cam03" when the rig's
    data disagree with cam03; per-camera warnings of one kind are said once, the other cameras named with the figure
    that differs."""
    import dataclasses

    from calib.rig import group_warnings

    board, dets = small
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names[:4], holdout_folds=2)
    assert res.report().splitlines()[0].startswith("verdict: consistent (held-out reprojection ")
    bad = dataclasses.replace(res, extra_warnings=(
        "camera cam03: the bundle adjustment moved its intrinsics further than its own calibration's uncertainty "
        "allows (fx +4.5 sigma, fy +4.5 sigma; together a chance of 9e-07): the rig data disagrees with what this "
        "camera saw alone (a moved camera, a bent board, or too few views of it)",))
    assert bad.verdict().startswith("verdict: check cam03: ")
    ws = [f"camera {n}: its projection is uncertain by {p} px (1 sigma) at the image corners: film the board near "
          f"the corners of {n}'s image (or fix k3 at zero for a mild lens)" for n, p in (("cam_a", 2.5), ("cam_b", 3.25))]
    assert group_warnings(ws + ["bundle adjustment did not converge: x", ws[0]]) == [
        ws[0] + "; the same for cam_b (3.25 px)", "bundle adjustment did not converge: x"]
    assert group_warnings([]) == []
    with pytest.raises(ValueError, match="warnings must be a sequence of strings"):
        group_warnings("camera a: x")
    with pytest.raises(ValueError, match="warnings must be a sequence of strings"):
        group_warnings([1])
