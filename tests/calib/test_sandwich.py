"""The rig adjustment's covariance when its intrinsics prior is each camera's own solve on some of the same
corners: the sandwich of the estimator (calib.bundle ``prior_jacobian``, ``reduced_intrinsics_jacobian``)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.bundle import bundle_adjust, reduced_intrinsics_jacobian
from calib.camera import matrix_to_rodrigues
from fake_cameras.handheld import HANDHELD_BOARD, handheld_poses, handheld_rig

NOISE = 0.05  # px: small enough that the estimator is linear in the noise
DRAWS = 48


@pytest.fixture(scope="module")
def toy():
    """Two cameras, every view of each in the rig's frame sets (the shared corners as many as can be)."""
    truth, _ = handheld_rig(2, mirrored=(), sideways=())
    poses = handheld_poses(truth, HANDHELD_BOARD, 12, seed=3)
    obj = HANDHELD_BOARD.object_points()
    views = []  # (camera, frame, ids, clean pixels)
    for ci, c in enumerate(truth):
        for f, T in enumerate(poses):
            uv, z = c.project(obj @ T[:3, :3].T + T[:3, 3], return_depth=True)
            inside = (z > 0) & c.in_image(uv, margin=2)
            if inside.sum() >= 12:
                views.append((ci, f, np.flatnonzero(inside), uv[inside]))
    intr = np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist] for c in truth])
    return truth, poses, obj, views, intr


def _two_solves(toy, rng, *, covariance: bool):
    """Each camera's own solve (its views alone), then the rig adjustment under their posteriors as prior.
    Returns the rig's intrinsics and, with ``covariance``, its covariance with and without the shared
    corners' terms (all zero ``prior_jacobian``) and the plain inverse normal matrix."""
    truth, poses, obj, views, intr = toy
    noisy = [(ci, f, ids, uv + rng.normal(0, NOISE, uv.shape)) for ci, f, ids, uv in views]
    own, cov, rows = [], [], {}
    for ci, c in enumerate(truth):
        mine = [v for v in noisy if v[0] == ci]
        ob = np.concatenate([np.full(len(v[2]), i) for i, v in enumerate(mine)])
        op, ouv = np.concatenate([obj[v[2]] for v in mine]), np.concatenate([v[3] for v in mine])
        z = bundle_adjust(np.zeros(ob.size, int), ob, op, ouv, intrinsics=intr[ci:ci + 1], cam_rvec=np.zeros((1, 3)),
                          cam_tvec=np.zeros((1, 3)),
                          board_rvec=np.stack([matrix_to_rodrigues(c.R @ poses[v[1]][:3, :3]) for v in mine]),
                          board_tvec=np.stack([c.R @ poses[v[1]][:3, 3] + c.t for v in mine]),
                          optimize_intrinsics=True, loss="linear", covariance=True, ftol=1e-14)
        own.append(z.intrinsics[0])
        cov.append(z.intrinsics_cov[0])
        if covariance:
            _, J, _ = reduced_intrinsics_jacobian(ob, op, ouv, intrinsics=z.intrinsics[0], board_rvec=z.board_rvec,
                                                  board_tvec=z.board_tvec)
            at = 0
            for v in mine:
                rows.update({(ci, v[1], int(i)): J[at + k] for k, i in enumerate(v[2])})
                at += len(v[2])
    oc = np.concatenate([np.full(len(v[2]), v[0]) for v in noisy])
    ob = np.concatenate([np.full(len(v[2]), v[1]) for v in noisy])
    op, ouv = np.concatenate([obj[v[2]] for v in noisy]), np.concatenate([v[3] for v in noisy])
    kw = dict(intrinsics=np.stack(own), cam_rvec=np.stack([matrix_to_rodrigues(c.R) for c in truth]),
              cam_tvec=np.stack([c.t for c in truth]),
              board_rvec=np.stack([matrix_to_rodrigues(T[:3, :3]) for T in poses]),
              board_tvec=np.stack([T[:3, 3] for T in poses]), optimize_intrinsics=True, prior_cov=np.stack(cov),
              prior_scale=1.1 * NOISE)  # the prior's weight need not match the residuals' scale
    if not covariance:
        return bundle_adjust(oc, ob, op, ouv, **kw).intrinsics, None
    G = np.stack([rows[(v[0], v[1], int(i))] for v in noisy for i in v[2]])
    with_cross = bundle_adjust(oc, ob, op, ouv, prior_jacobian=G, covariance=True, **kw)
    no_cross = bundle_adjust(oc, ob, op, ouv, prior_jacobian=0 * G, covariance=True, **kw)
    plain = bundle_adjust(oc, ob, op, ouv, covariance=True, **kw)
    # the covariance changes, the estimate does not (to the bit)
    assert np.array_equal(with_cross.intrinsics, plain.intrinsics)
    assert np.array_equal(with_cross.cam_rvec, plain.cam_rvec)
    return with_cross.intrinsics, {"sandwich": with_cross.intrinsics_cov, "no cross terms": no_cross.intrinsics_cov,
                                   "inverse normal matrix": plain.intrinsics_cov}


def test_sandwich_is_the_covariance_of_the_two_solves(toy):
    """Over noise draws (fixed seed), the rig's intrinsics errors against each covariance: chi-square / dof.
    Its standard error over 48 draws x 2 cameras x 9 dof is 0.05; the sandwich's is 1 within 0.15, and
    without the shared corners' terms (as with the inverse normal matrix) the figure is about 1.4."""
    rng = np.random.default_rng(11)
    _, covs = _two_solves(toy, rng, covariance=True)  # the covariances of one draw (they hardly vary)
    intr_true = toy[4]
    chi2 = {k: [] for k in covs}
    for _ in range(DRAWS):
        est, _ = _two_solves(toy, rng, covariance=False)
        for k, cov in covs.items():
            for c in range(2):
                d = est[c] - intr_true[c]
                chi2[k].append(float(d @ np.linalg.solve(cov[c], d)) / 9)
    fig = {k: float(np.mean(v)) for k, v in chi2.items()}
    assert abs(fig["sandwich"] - 1.0) < 0.15, fig
    assert fig["no cross terms"] > 1.25 and fig["inverse normal matrix"] > 1.25, fig


def test_reduced_jacobian_is_the_schur_complement(toy):
    """``J^T J`` of the reduced rows equals the intrinsics block of the inverse of the inverse normal matrix's
    intrinsics block: the one-camera covariance ``sigma^2 (J^T J)^-1`` of bundle_adjust."""
    truth, poses, obj, views, intr = toy
    c = truth[0]
    mine = [v for v in views if v[0] == 0]
    rng = np.random.default_rng(2)
    ob = np.concatenate([np.full(len(v[2]), i) for i, v in enumerate(mine)])
    op = np.concatenate([obj[v[2]] for v in mine])
    ouv = np.concatenate([v[3] for v in mine]) + rng.normal(0, NOISE, (ob.size, 2))
    kw = dict(board_rvec=np.stack([matrix_to_rodrigues(c.R @ poses[v[1]][:3, :3]) for v in mine]),
              board_tvec=np.stack([c.R @ poses[v[1]][:3, 3] + c.t for v in mine]))
    z = bundle_adjust(np.zeros(ob.size, int), ob, op, ouv, intrinsics=intr[:1], cam_rvec=np.zeros((1, 3)),
                      cam_tvec=np.zeros((1, 3)), optimize_intrinsics=True, loss="linear", covariance=True,
                      ftol=1e-14, **kw)
    r, J, s = reduced_intrinsics_jacobian(ob, op, ouv, intrinsics=z.intrinsics[0], board_rvec=z.board_rvec,
                                          board_tvec=z.board_tvec)
    np.testing.assert_allclose(r, z.residuals, atol=1e-9)
    np.testing.assert_allclose(s, z.sigma_px, rtol=1e-9)
    np.testing.assert_allclose(s**2 * np.linalg.inv(np.einsum("mai,maj->ij", J, J)), z.intrinsics_cov[0],
                               rtol=1e-6)


def test_invalid_input(toy):
    truth, poses, obj, views, intr = toy
    ob, op, uv = np.zeros(12, int), obj[:12], np.zeros((12, 2))
    pose = dict(board_rvec=np.zeros((1, 3)), board_tvec=np.array([[0.0, 0.0, 1000.0]]))
    with pytest.raises(ValueError, match="intrinsics"):
        reduced_intrinsics_jacobian(ob, op, uv, intrinsics=intr[0][:4], **pose)
    with pytest.raises(ValueError, match="held"):
        reduced_intrinsics_jacobian(ob, op, uv, intrinsics=intr[0], held=np.zeros(4, bool), **pose)
    with pytest.raises(ValueError, match="obs_cam, obs_board"):
        reduced_intrinsics_jacobian(ob, op, uv[:3], intrinsics=intr[0], **pose)
    kw = dict(intrinsics=intr[:1], cam_rvec=np.zeros((1, 3)), cam_tvec=np.zeros((1, 3)), optimize_intrinsics=True,
              **pose)
    with pytest.raises(ValueError, match="prior_jacobian needs prior_cov"):
        bundle_adjust(np.zeros(12, int), ob, op, uv, prior_jacobian=np.zeros((12, 2, 9)), **kw)
    with pytest.raises(ValueError, match="prior_jacobian must"):
        bundle_adjust(np.zeros(12, int), ob, op, uv, prior_jacobian=np.zeros((11, 2, 9)), prior_cov=np.eye(9)[None],
                      **kw)
