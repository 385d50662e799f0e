"""How sure the extrinsics are: the rotation covariance of the bundle adjustment, its Schur
complement, per-camera held intrinsics, and the distortion model chosen by the views
(calib.bundle, calib.rig, calib.intrinsics)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix

from calib.bundle import _camera_block_inverse, bundle_adjust
from calib.calibration import Calibration
from calib.extrinsics import calibrate_extrinsics
from calib.intrinsics import calibrate_intrinsics
from calib.rig import fold_rotation_spread, rotation_sigma
from calib.synthetic import synthetic_detections
from fake_cameras.handheld import HANDHELD_BOARD, handheld_poses, handheld_rig


@pytest.fixture(scope="module")
def rig():
    truth, _ = handheld_rig(3, mirrored=(), sideways=())
    poses = [(T[:3, :3], T[:3, 3]) for T in handheld_poses(truth, HANDHELD_BOARD, 40, seed=3)]
    return truth, poses


def _angle(R):
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def test_schur_complement_is_the_camera_block_of_the_inverse():
    rng = np.random.default_rng(0)
    n_cam, nb = 9, 5
    n = n_cam + 6 * nb
    J = rng.normal(size=(4 * n, n))
    rows = np.arange(4 * n) % nb  # each residual sees one board pose, as in a bundle adjustment
    for b in range(nb):
        J[rows != b, n_cam + 6 * b: n_cam + 6 * b + 6] = 0.0
    A = J.T @ J
    assert np.all(A[n_cam:n_cam + 6, n_cam + 6:] == 0)  # block-diagonal board part
    np.testing.assert_allclose(_camera_block_inverse(csr_matrix(A), n_cam), np.linalg.inv(A)[:n_cam, :n_cam],
                               rtol=1e-9, atol=1e-12)


def test_rotation_sigma_matches_the_spread_over_noise(rig):
    """The covariance figure against Monte Carlo: 16 noise draws, relative rotations' RMS angle error."""
    truth, poses = rig
    cams = list(truth.cameras)
    errs, predicted = {}, {}
    for seed in range(16):
        dets = synthetic_detections(truth, HANDHELD_BOARD, poses, noise_px=0.3, seed=100 + seed)
        ext = calibrate_extrinsics(dets, cams, HANDHELD_BOARD, optimize_intrinsics=False, loss="linear")
        est = ext.calibration
        rs = rotation_sigma(est, ext.meta["rotation_cov"], ext.meta["reference"])
        assert rs["per_camera"][rs["reference"]] == 0.0
        for a in range(3):
            for b in range(a + 1, 3):
                key = f"{est[a].name} - {est[b].name}"
                d = (est[a].R @ est[b].R.T) @ (truth[a].R @ truth[b].R.T).T
                errs.setdefault(key, []).append(_angle(d))
                predicted.setdefault(key, []).append(rs["pairs"][key])
    for key, e in errs.items():
        mc = float(np.sqrt(np.mean(np.square(e))))
        assert np.mean(predicted[key]) == pytest.approx(mc, rel=0.35), key


def test_fold_spread_is_the_grouped_jackknife(rig):
    truth, _ = rig
    from scipy.spatial.transform import Rotation

    names = truth.names
    tilt = [0.1, -0.1, 0.2, -0.2]  # degrees about z on camera 1, one per fold
    cals = []
    for t in tilt:
        cams = [c if i != 1 else c.replace(R=Rotation.from_euler("z", t, degrees=True).as_matrix() @ c.R)
                for i, c in enumerate(truth.cameras)]
        cals.append(Calibration(tuple(cams), units="mm"))
    out = fold_rotation_spread(cals, names, names[0])
    k = len(tilt)
    want = np.sqrt((k - 1) / k * np.sum(np.square(tilt)))  # mean tilt is 0
    assert out["per_camera"][names[1]] == pytest.approx(want, rel=1e-6)
    assert out["pairs"][f"{names[0]} - {names[1]}"] == pytest.approx(want, rel=1e-6)
    assert out["per_camera"][names[2]] == pytest.approx(0.0, abs=1e-6)
    assert fold_rotation_spread(cals[:2], names, names[0]) == {}  # too few folds to tell


def _views(truth, poses, dist, seed=5):
    cam = truth[0].replace(dist=np.asarray(dist, dtype=np.float64))
    one = Calibration((cam,), units="mm")
    return cam, synthetic_detections(one, HANDHELD_BOARD, poses, noise_px=0.3, seed=seed)[cam.name]


def test_per_camera_held_intrinsics_stay_put(rig):
    truth, poses = rig
    dets = synthetic_detections(truth, HANDHELD_BOARD, poses, noise_px=0.3, seed=11)
    intr = [calibrate_intrinsics(dets[c.name], HANDHELD_BOARD, c.size, name=c.name) for c in truth]
    cams = [r.camera() for r in intr]
    held = np.zeros((3, 9), bool)
    held[1, 6:9] = True  # camera 1 keeps p1, p2, k3
    ext = calibrate_extrinsics(dets, cams, HANDHELD_BOARD, optimize_intrinsics=True, fixed_intrinsics=held)
    out = ext.calibration
    np.testing.assert_array_equal(out[1].dist[2:], cams[1].dist[2:])
    assert np.all(out[0].dist[2:] != cams[0].dist[2:])  # the others refined them
    cov = ext.meta["intrinsics_cov"]
    assert np.all(np.isnan(cov[1][6:9])) and np.all(np.isfinite(cov[0]))
    # every camera holding the same terms: the same solution as naming them
    same = calibrate_extrinsics(dets, cams, HANDHELD_BOARD, optimize_intrinsics=True,
                                fixed_intrinsics=np.tile(held[1], (3, 1)))
    named = calibrate_extrinsics(dets, cams, HANDHELD_BOARD, optimize_intrinsics=True,
                                 fixed_intrinsics=("p1", "p2", "k3"))
    for a, b in zip(same.calibration, named.calibration):
        np.testing.assert_allclose(a.K, b.K, rtol=1e-9)
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)


def test_auto_distortion_holds_only_unsupported_terms(rig):
    truth, _ = rig
    poses = [(T[:3, :3], T[:3, 3]) for T in handheld_poses(truth, HANDHELD_BOARD, 160, seed=4)]
    _, plain = _views(truth, poses, [-0.15, 0.05, 0.0, 0.0, 0.0])
    r = calibrate_intrinsics(plain, HANDHELD_BOARD, truth[0].size, distortion="auto")
    assert r.dropped and set(r.dropped) <= {"p1", "p2", "k3"} and set(r.dropped) <= set(r.held)
    assert all(r.dist[("k1", "k2", "p1", "p2", "k3").index(k)] == 0.0 for k in r.dropped)
    assert "held at 0" in r.summary()
    full = calibrate_intrinsics(plain, HANDHELD_BOARD, truth[0].size)
    assert full.dropped == () and full.held == ()
    cam, decentred = _views(truth, poses, [-0.15, 0.05, 0.01, -0.01, 0.0])
    r = calibrate_intrinsics(decentred, HANDHELD_BOARD, truth[0].size, distortion="auto")
    assert "p1" not in r.dropped  # a real decentring is kept
    np.testing.assert_allclose(r.dist[2:4], cam.dist[2:4], atol=2e-3)


def test_invalid_input(rig):
    truth, poses = rig
    _, views = _views(truth, poses, [0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="distortion"):
        calibrate_intrinsics(views, HANDHELD_BOARD, truth[0].size, distortion="some")
    dets = synthetic_detections(truth, HANDHELD_BOARD, poses, noise_px=0.3, seed=1)
    from calib.rig import calibrate_rig

    with pytest.raises(ValueError, match="distortion"):
        calibrate_rig(dets, {c.name: c.size for c in truth}, HANDHELD_BOARD, distortion="some")
    with pytest.raises(ValueError, match="fixed_intrinsics"):
        bundle_adjust(np.zeros(4, int), np.zeros(4, int), np.zeros((4, 3)), np.zeros((4, 2)),
                      intrinsics=np.ones((1, 9)), cam_rvec=np.zeros((1, 3)), cam_tvec=np.zeros((1, 3)),
                      board_rvec=np.zeros((1, 3)), board_tvec=np.ones((1, 3)), fixed_intrinsics=np.zeros((2, 9), bool))
    assert rotation_sigma(truth, None, None) == {}
