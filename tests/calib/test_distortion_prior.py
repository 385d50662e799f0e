"""The zero-mean distortion prior of the per-camera Zhang solve (``distortion="prior"``,
calib.intrinsics): the maximum-a-posteriori solution against a slow reference, the limit of an
infinitely wide prior, the posterior information, and the validation of the new parameters."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from calib.bundle import bundle_adjust
from calib.camera import Camera, project_points, rodrigues_to_matrix
from calib.intrinsics import calibrate_intrinsics
from calib.rig import calibrate_rig
from calib.synthetic import synthetic_detections
from fake_cameras.handheld import HANDHELD_BOARD, handheld_poses, handheld_rig

TIGHT = {"p1": 1e-4, "p2": 1e-4, "k3": 0.01}  # tighter than the default, so the prior visibly pulls


@pytest.fixture(scope="module")
def views():
    truth, _ = handheld_rig(2, mirrored=(), sideways=(), seed=3)
    cam = truth[0]
    cam = Camera(cam.name, K=cam.K, dist=np.array([*cam.dist[:2], 1.5e-3, -1.2e-3, 0.0]), R=cam.R, t=cam.t,
                 size=cam.size)  # decentred, so the prior has something to pull
    truth = type(truth)((cam, truth[1]), units="mm")
    poses = handheld_poses(truth, HANDHELD_BOARD, 40, seed=5)
    dets = synthetic_detections(truth, HANDHELD_BOARD, [(T[:3, :3], T[:3, 3]) for T in poses], noise_px=0.3, seed=6)
    return cam, dets[cam.name]


def _slow_map(views, cam, start, sigma: dict):
    """Reference: dense least squares with a finite-difference Jacobian, projecting with
    calib.camera.project_points, of the same negative log-posterior."""
    obj = HANDHELD_BOARD.object_points()
    n_pts = sum(len(d) for d in views)
    dof = 2 * n_pts - 9 - 6 * len(views)
    noise = np.sqrt(start.rms ** 2 * n_pts / dof)  # per coordinate, of the unregularised solution
    names = ("k1", "k2", "p1", "p2", "k3")
    w = np.array([noise / sigma.get(k, np.inf) for k in names])

    def resid(x):
        fx, fy, cx, cy, *dist = x[:9]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        out = []
        for i, d in enumerate(views):
            uv = project_points(obj[d.ids], K=K, dist=np.array(dist), R=rodrigues_to_matrix(x[9 + 6 * i: 12 + 6 * i]),
                                t=x[12 + 6 * i: 15 + 6 * i])
            out.append((uv - d.corners).ravel())
        return np.concatenate(out + [w * np.asarray(dist)])

    x0 = np.concatenate([start.params, *[np.r_[r, t] for r, t in zip(start.rvecs, start.tvecs)]])
    return least_squares(resid, x0, method="lm", xtol=1e-14, ftol=1e-14, max_nfev=4000).x[:9]


def test_map_solution_matches_slow_reference(views):
    cam, dets = views
    dets = dets[:12]  # few views: the unregularised solve is poorly pinned (k3 ~ 2.4), the prior decides
    full = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion="full", reject_outliers=False)
    r = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion_sigma=TIGHT, reject_outliers=False)
    ref = _slow_map(dets, cam, full, TIGHT)
    np.testing.assert_allclose(r.params[:4], ref[:4], atol=5e-3)  # px
    np.testing.assert_allclose(r.params[4:], ref[4:], atol=1e-5)
    assert np.abs(r.dist[2:4]).max() < 0.5 * np.abs(full.dist[2:4]).max()  # the tight prior pulls p1, p2 in


def test_infinitely_wide_prior_is_the_unregularised_solve(views):
    cam, dets = views
    dets = dets[:12]
    full = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion="full", reject_outliers=False)
    for sigma in ({}, {"k1": 1e9, "k2": 1e9, "p1": 1e9, "p2": 1e9, "k3": 1e9}):
        r = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion_sigma=sigma, reject_outliers=False)
        np.testing.assert_allclose(r.params[:4], full.params[:4], atol=1e-2)  # px
        np.testing.assert_allclose(r.params[4:], full.params[4:], rtol=1e-4, atol=1e-5)
        assert r.rms == pytest.approx(full.rms, rel=1e-5)
        np.testing.assert_allclose(np.diag(r.covariance), np.diag(full.covariance), rtol=1e-2)


def test_held_terms_have_zero_std_and_fixed_aspect_keeps_its_ratio(views):
    """Held distortion terms report a standard deviation of 0 (as OpenCV does), with no
    "uncertainty undefined" warning; a fixed aspect ratio is kept under the default prior."""
    cam, dets = views
    r = calibrate_intrinsics(dets[:20], HANDHELD_BOARD, cam.size, fix_k3=True, zero_tangent=True, reject_outliers=False)
    assert np.all(np.isfinite(r.std["dist"])) and r.std["dist"][2:5].tolist() == [0.0, 0.0, 0.0]
    assert r.std["dist"][0] > 0 and not any("undefined" in w for w in r.warnings)
    a = calibrate_intrinsics(dets[:20], HANDHELD_BOARD, cam.size, fix_aspect_ratio=True, reject_outliers=False)
    assert a.K[0, 0] == pytest.approx(a.K[1, 1], rel=1e-9)


def test_posterior_information_is_data_plus_prior(views):
    """The posterior covariance's inverse is the views' information at the same solution plus the
    prior's diagonal (closed form; 2 % for the two noise estimates, with and without the prior rows)."""
    from calib.intrinsics import _zhang_covariance

    cam, dets = views
    r = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion_sigma=TIGHT, reject_outliers=False)
    data = _zhang_covariance(dets, HANDHELD_BOARD, r.K, r.dist, r.rvecs, r.tvecs, ())
    want = np.linalg.inv(data) + np.diag([0, 0, 0, 0, 0, 0, 1e8, 1e8, 1e4])
    np.testing.assert_allclose(np.diag(np.linalg.inv(r.covariance)), np.diag(want), rtol=0.02)
    full = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion="full", reject_outliers=False)
    assert r.std["cx"] < full.std["cx"] and r.std["dist"][2] < full.std["dist"][2]


def test_prior_brings_principal_points_closer_on_a_simulated_dome():
    """Four dome cameras, 15-27 views each (true |p1|, |p2| <= 0.001, k3 = 0): with the default prior
    every principal point is within 3 px of the truth and closer than without it (measured: at most
    2.0 px against 5.7 px)."""
    from calib.boards import Chessboard
    from calib.synthetic import random_board_poses
    from fake_cameras.dome import make_dome

    truth = make_dome(4)
    board = Chessboard((11, 8), 50.0)
    spread = 0.25 * float(np.median(np.linalg.norm(truth.centers() - truth.centers().mean(0), axis=1)))
    dets = synthetic_detections(truth, board, random_board_poses(truth, board, 40, seed=1, spread=spread),
                                noise_px=0.3, seed=2)
    for c in truth:
        full = calibrate_intrinsics(dets[c.name], board, c.size, distortion="full", reject_outliers=False)
        r = calibrate_intrinsics(dets[c.name], board, c.size, reject_outliers=False)
        err, err_full = (np.abs(x.K[:2, 2] - c.K[:2, 2]).max() for x in (r, full))
        assert err < 3.0 and err < err_full, (c.name, err, err_full)
        assert np.all(np.abs(r.dist[2:4] - c.dist[2:4]) < 3 * r.std["dist"][2:4]), c.name


def test_invalid_input(views):
    cam, dets = views
    for bad in ({"q1": 1.0}, {"p1": 0.0}, {"p2": -1e-3}, {"k3": float("nan")}, (1e-3, 1e-3)):
        with pytest.raises(ValueError, match="distortion_sigma"):
            calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion_sigma=bad)
    with pytest.raises(ValueError, match="distortion"):
        calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion="map")
    with pytest.raises(ValueError, match="distortion"):
        calibrate_rig({cam.name: dets}, {cam.name: cam.size}, HANDHELD_BOARD, distortion="map")
    obj = HANDHELD_BOARD.object_points()
    full = calibrate_intrinsics(dets, HANDHELD_BOARD, cam.size, distortion="full")
    d = dets[0]
    kw = dict(intrinsics=full.params[None], cam_rvec=np.zeros((1, 3)), cam_tvec=np.zeros((1, 3)),
              board_rvec=full.rvecs[:1], board_tvec=full.tvecs[:1], optimize_intrinsics=True,
              prior_cov=np.eye(9)[None])
    args = (np.zeros(len(d), int), np.zeros(len(d), int), obj[d.ids], d.corners)
    with pytest.raises(ValueError, match="prior_mean"):
        bundle_adjust(*args, prior_mean=np.zeros(9), **kw)
    with pytest.raises(ValueError, match="prior_mean"):
        bundle_adjust(*args, prior_mean=np.full((1, 9), np.nan), **kw)
