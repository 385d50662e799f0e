"""The intrinsics prior of the bundle adjustment, the Zhang covariance it comes from, and the
evaluation figures (calib.bundle, calib.intrinsics, calib.evaluate, calib.rig)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.bundle import bundle_adjust
from calib.evaluate import projection_uncertainty, reprojection_errors
from calib.intrinsics import calibrate_intrinsics
from calib.rig import calibrate_rig
from calib.synthetic import synthetic_detections
from fake_cameras.handheld import HANDHELD_BOARD, handheld_poses, handheld_rig


@pytest.fixture(scope="module")
def rig():
    truth, _ = handheld_rig(3, mirrored=(), sideways=())
    poses = handheld_poses(truth, HANDHELD_BOARD, 80, seed=7)
    dets = synthetic_detections(truth, HANDHELD_BOARD, [(T[:3, :3], T[:3, 3]) for T in poses], noise_px=0.3, seed=8)
    return truth, dets


def test_zhang_covariance_matches_opencv_standard_deviations(rig):
    truth, dets = rig
    r = calibrate_intrinsics(dets["cam_0"], HANDHELD_BOARD, truth[0].size, distortion="full")  # OpenCV's own stds
    sd = np.sqrt(np.diag(r.covariance))
    want = np.array([r.std["fx"], r.std["fy"], r.std["cx"], r.std["cy"], *r.std["dist"]])
    np.testing.assert_allclose(sd, want, rtol=1e-3)  # the same Jacobian, with the correlations kept
    np.testing.assert_allclose(r.covariance, r.covariance.T, rtol=1e-6, atol=1e-12)


def _ba_inputs(truth, dets):
    obj = HANDHELD_BOARD.object_points()
    intr = [calibrate_intrinsics(dets[c.name], HANDHELD_BOARD, c.size) for c in truth]
    frames = sorted({d.frame for n in truth.names for d in dets[n]})
    fi = {f: i for i, f in enumerate(frames)}
    oc, ob, op, ouv = [], [], [], []
    for ci, c in enumerate(truth):
        for d in dets[c.name]:
            oc.append(np.full(len(d), ci))
            ob.append(np.full(len(d), fi[d.frame]))
            op.append(obj[d.ids])
            ouv.append(d.corners)
    from calib.camera import matrix_to_rodrigues

    poses = handheld_poses(truth, HANDHELD_BOARD, 80, seed=7)
    return (np.concatenate(oc), np.concatenate(ob), np.concatenate(op), np.concatenate(ouv),
            dict(intrinsics=np.stack([r.params for r in intr]),
                 cam_rvec=np.stack([matrix_to_rodrigues(c.R) for c in truth]), cam_tvec=np.stack([c.t for c in truth]),
                 board_rvec=np.stack([matrix_to_rodrigues(poses[f][:3, :3]) for f in frames]),
                 board_tvec=np.stack([poses[f][:3, 3] for f in frames])), intr)


def test_prior_limits_how_far_intrinsics_move(rig):
    truth, dets = rig
    oc, ob, op, ouv, kw, intr = _ba_inputs(truth, dets)
    p0 = kw["intrinsics"]
    free = bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, **kw)
    tight = bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, prior_cov=np.stack([np.eye(9) * 1e-12] * 3),
                          prior_scale=0.3, **kw)
    loose = bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, prior_cov=np.stack([np.eye(9) * 1e12] * 3),
                          prior_scale=0.3, **kw)
    np.testing.assert_allclose(tight.intrinsics, p0, atol=1e-3)  # a tight prior holds them
    np.testing.assert_allclose(loose.intrinsics[:, :4], free.intrinsics[:, :4], atol=1e-3)  # a vague one does not
    assert np.abs(free.intrinsics[:, :4] - p0[:, :4]).max() > 0.1
    # the covariance is finite and, with a prior, smaller than without
    cov_free = bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, covariance=True, **kw).intrinsics_cov
    cov_prior = bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, covariance=True,
                              prior_cov=np.stack([r.covariance for r in intr]), prior_scale=0.3, **kw).intrinsics_cov
    assert np.all(np.isfinite(cov_free)) and np.all(np.diagonal(cov_prior, axis1=1, axis2=2)
                                                     <= np.diagonal(cov_free, axis1=1, axis2=2) * (1 + 1e-9))


def test_projection_uncertainty_is_the_linear_propagation(rig):
    truth, dets = rig
    r = calibrate_intrinsics(dets["cam_0"], HANDHELD_BOARD, truth[0].size)
    cam = r.camera()
    u = projection_uncertainty(cam, r.covariance)
    # the centre: d(pixel)/d(intrinsics) at the principal point's ray is ~ identity on cx, cy
    c = np.array([(cam.width - 1) / 2, (cam.height - 1) / 2])
    # reference: finite differences of the projection of the fixed ray, sampled covariance
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(r.params, r.covariance, 4000)
    from calib.camera import project_points

    ray = cam.rays(c[None])[1][0]
    pix = np.array([project_points(ray[None], K=[[s[0], 0, s[2]], [0, s[1], s[3]], [0, 0, 1]], dist=s[4:],
                                   R=np.eye(3), t=np.zeros(3))[0] for s in samples])
    worst = np.sqrt(np.linalg.eigvalsh(np.cov(pix.T))[-1])
    assert u["centre"] == pytest.approx(worst, rel=0.1)
    assert u["top-left"] > u["centre"]


def test_report_figures(rig):
    truth, dets = rig
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, HANDHELD_BOARD, cameras=truth.names, holdout_folds=3)
    ev = res.evaluation
    assert res.report().splitlines()[1].startswith("held-out reprojection RMS (3-fold")
    for n in truth.names:
        ho, af = ev["held_out"]["per_camera"][n]["rms"], ev["all_frames"]["per_camera"][n]["rms"]
        assert 0.3 < af < ho < 0.8  # noise 0.3 px per coordinate: sqrt(2) * 0.3 = 0.42 px in-sample
        assert set(ev["uncertainty"][n]) == {"centre", "top-left", "top-right", "bottom-left", "bottom-right"}
        assert set(ev["moved_sigma"][n]) >= {"fx", "fy", "cx", "cy"}
    # all-frames error of the true cameras on the same detections: the noise level
    true_err = reprojection_errors(truth, dets, HANDHELD_BOARD)
    assert true_err["rms"] == pytest.approx(0.3 * np.sqrt(2), rel=0.1)
    from calib.extrinsics import triangulate_board_error

    with_truth = triangulate_board_error(truth, dets, HANDHELD_BOARD)  # what the noise alone gives
    assert ev["geometry_all"]["frames"] == with_truth["frames"] > 0
    assert ev["geometry_all"]["neighbor_rms"] < 1.2 * with_truth["neighbor_rms"]
    assert res.to_dict()["summary"] == res.summary()
    # how sure the rotations are: the covariance figure and the folds' spread, per camera vs the reference
    rs, rf = ev["rotation_sigma_deg"], ev["rotation_folds_deg"]
    assert rs["per_camera"][rs["reference"]] == 0.0 and rf["folds"] == 3
    est = res.calibration
    for a in range(len(est)):
        for b in range(a + 1, len(est)):
            key = f"{est[a].name} - {est[b].name}"
            d = (est[a].R @ est[b].R.T) @ (truth[a].R @ truth[b].R.T).T
            err = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
            # independent noise: the true error within 3 sigma, the folds' spread near the covariance
            assert err < 3 * rs["pairs"][key], (key, err, rs["pairs"][key])
            assert rs["pairs"][key] / 3 < rf["pairs"][key] < 3 * rs["pairs"][key], key
    assert "rotation deg vs " + rs["reference"] in res.report()
    assert not any("errors shared by whole views" in w for w in res.warnings)  # independent noise only


def test_invalid_input(rig):
    truth, dets = rig
    sizes = {c.name: c.size for c in truth}
    with pytest.raises(ValueError, match="intrinsics"):
        calibrate_rig(dets, sizes, HANDHELD_BOARD, intrinsics="loose")
    with pytest.raises(ValueError, match="holdout_folds"):
        calibrate_rig(dets, sizes, HANDHELD_BOARD, holdout_folds=1)
    with pytest.raises(ValueError, match="max_sets"):
        calibrate_rig(dets, sizes, HANDHELD_BOARD, max_sets=1)
    with pytest.raises(ValueError, match="flipped"):
        calibrate_rig(dets, sizes, HANDHELD_BOARD, flipped=["nope"])
    with pytest.raises(ValueError, match="calibration"):
        reprojection_errors("calib.toml", dets, HANDHELD_BOARD)
    with pytest.raises(ValueError, match="not in the calibration"):
        reprojection_errors(truth, {"nope": []}, HANDHELD_BOARD)
    with pytest.raises(ValueError, match="covariance"):
        projection_uncertainty(truth[0], np.eye(4))
    oc, ob, op, ouv, kw, _ = _ba_inputs(truth, dets)
    with pytest.raises(ValueError, match="prior_cov"):
        bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, prior_cov=np.eye(9), **kw)
    with pytest.raises(ValueError, match="prior_scale"):
        bundle_adjust(oc, ob, op, ouv, optimize_intrinsics=True, prior_cov=np.stack([np.eye(9)] * 3), prior_scale=0,
                      **kw)
