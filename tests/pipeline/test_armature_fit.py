"""pipeline.armature_fit on a deep chain: a pose carried from frame to frame stays a pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.armature_fit import ArticulatedModel, _forward, fit_frame, predict_pose
from tests.pipeline.armature_chain import chain_model


def test_a_pose_tracked_along_a_deep_chain_stays_rotations():
    """Eight frames of a 40-part chain curling at constant velocity, every frame fitted from the
    constant-velocity prediction of the last two fits: every part's rotation stays a rotation (to
    1e-9) and the fit lands on the frame (mean error under 1 % of a part's length). Carried through
    ``R_parent^T R_p`` without projection, the rounding grew with every pass along the chain: the
    rotations were 1e-3 from rotations at the second frame and NaN at the eighth."""
    m = chain_model()
    P = m.skeleton.n_parts
    om = np.random.default_rng(0).normal(scale=0.05, size=(P, 3))
    pose, before = m.identity(), None
    for s in range(1, 9):
        R = Rotation.from_rotvec(s * om).as_matrix()
        truth = _forward(m, R[0], m.pivots[0] - R[0] @ m.pivots[0], R)
        start = pose if before is None else predict_pose(m, pose, before)
        before, (pose, err) = pose, fit_frame(m, m.deform(truth), start, iterations=5)
        assert np.abs(np.einsum("pji,pjk->pik", pose.R, pose.R) - np.eye(3)).max() < 1e-9
        assert np.all(np.abs(np.linalg.det(pose.R) - 1.0) < 1e-9)
        assert err < 0.1, (s, err)


def _dense_normal_equations(m: ArticulatedModel, pose, x, y):
    """The slow reference: the 3V x 3(P+1) Jacobian ``[I, -[A_v0]_x, ..., -[A_vP-1]_x]`` formed row by row."""
    P = m.skeleton.n_parts
    vp, w = m.vertex_parts, m.weights
    cw = np.einsum("pij,pj->pi", pose.R, m.pivots) + pose.t
    rows, res = [], []
    for v in range(len(x)):
        q = np.einsum("kij,j->ki", pose.R[vp[v]], x[v]) + pose.t[vp[v]]
        res.append(w[v] @ q - y[v])
        J = np.zeros((3, 3 * (P + 1)))
        J[:, :3] = np.eye(3)
        for p in range(P):
            a = sum(w[v, k] * (q[k] - cw[p]) for k in range(vp.shape[1]) if m.below[vp[v, k], p])
            if np.any(a):
                J[:, 3 * (p + 1):3 * (p + 2)] = -np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        rows.append(J)
    J, r = np.concatenate(rows), np.concatenate(res)
    return float(r @ r), J.T @ J, J.T @ r


def test_normal_equations_match_the_dense_jacobian():
    """The normal equations from the influences' moments summed over subtrees equal J^T J and J^T r
    of the dense Jacobian, on a 12-part chain with three influences a vertex (1e-9 relative)."""
    from pipeline.armature_fit import _lsq_weights, _normal_equations

    base = chain_model(12, 4)
    P, V = base.skeleton.n_parts, len(base.vertices)
    rng = np.random.default_rng(2)
    part = base.influences[:, 0]
    infl = np.c_[part, np.clip(part - 1, 0, P - 1), np.clip(part + 1, 0, P - 1)]
    w = rng.random((V, 3))
    m = ArticulatedModel(base.vertices, base.faces, base.skeleton, infl, w / w.sum(1, keepdims=True))
    R = Rotation.from_rotvec(rng.normal(scale=0.3, size=(P, 3))).as_matrix()
    pose = _forward(m, R[0], rng.normal(size=3), R)
    y = m.vertices + rng.normal(scale=2.0, size=m.vertices.shape)
    sse, H, g, _ = _normal_equations(m, pose, m.vertices, y, _lsq_weights(m, None))
    sse0, H0, g0 = _dense_normal_equations(m, pose, m.vertices, y)
    assert abs(sse - sse0) <= 1e-9 * sse0
    np.testing.assert_allclose(H, H0, rtol=0, atol=1e-9 * np.abs(H0).max())
    np.testing.assert_allclose(g, g0, rtol=0, atol=1e-9 * np.abs(g0).max())


def test_fit_subset_is_fit_frame_on_its_rows():
    """``fit_subset`` given the least-squares subset's targets lands on the pose ``fit_frame`` finds from the
    whole frame (the same iterations), and says what is wrong with its input."""
    import pytest

    from pipeline.armature_fit import fit_subset

    m = chain_model(12, 6)
    P = m.skeleton.n_parts
    R = Rotation.from_rotvec(np.random.default_rng(3).normal(scale=0.1, size=(P, 3))).as_matrix()
    target = m.deform(_forward(m, R[0], np.zeros(3), R))
    pose, _ = fit_frame(m, target, m.identity(), iterations=4, max_points=40)
    alone = fit_subset(m, target[m.subset(40)], m.identity(), iterations=4, max_points=40)
    np.testing.assert_array_equal(alone.R, pose.R)
    np.testing.assert_array_equal(alone.t, pose.t)
    with pytest.raises(ValueError, match="target"):
        fit_subset(m, target, m.identity(), max_points=40)
    with pytest.raises(ValueError, match="start"):
        fit_subset(m, target[m.subset(40)], "pose", max_points=40)


def test_twist_prior_holds_a_parts_turn_about_its_axis_by_its_exact_optimum():
    """Two parts on the x axis, a ring of radius 3 around each, the targets the rest with the second part turned
    by 0.6 rad about the axis; the prior keeps the second part's turn relative to the first at rest (strength s; the
    vertices have no normals, so every vertex's whole motion counts).
    The root turns by ``alpha`` and the second part by ``tau`` relative to it, both about the axis, and the fit's
    sum of squares is ``2 D (1 - cos alpha) + 2 D (1 - cos(alpha + tau - 0.6)) + s D tau^2`` (``D = 9 n``, n
    vertices a ring): the fit's sum of squares is within 1e-4 of that minimum's (scipy's; the Levenberg-Marquardt stops
    once a step promises less than 1e-4 of it) and its turns within 1e-3 rad of the minimum's. Its twist is
    ``relative_twists``', and without the prior the part follows its targets (1e-9)."""
    import pytest
    from scipy.optimize import minimize

    from pipeline.armature_fit import fit_subset
    from pipeline.armature_twist import relative_twists, twist_prior

    m = chain_model(2, 12)
    turn = 0.6
    R = Rotation.from_rotvec([[0.0, 0.0, 0.0], [turn, 0.0, 0.0]]).as_matrix()
    target = m.deform(_forward(m, R[0], np.zeros(3), R))
    free = fit_subset(m, target, m.identity(), iterations=50, tol=1e-12, max_points=None)
    assert np.abs(free.R - R).max() < 1e-9
    for s in (0.5, 2.0):
        prior = twist_prior(m, m.identity(), s, max_points=None)
        assert prior.weights[1] == pytest.approx(s * 9.0 * 12)
        pose = fit_subset(m, target, m.identity(), iterations=50, tol=1e-12, max_points=None, twist=prior)
        def f(z, s=s, D=9.0 * 12):
            return 2 * D * (1 - np.cos(z[0])) + 2 * D * (1 - np.cos(z[0] + z[1] - turn)) + s * D * z[1] ** 2

        alpha, tau = minimize(f, [0.0, 0.0], method="BFGS", options={"gtol": 1e-12}).x
        got_alpha = np.arctan2(pose.R[0][2, 1], pose.R[0][1, 1])
        local = pose.R[0].T @ pose.R[1]
        got_tau = np.arctan2(local[2, 1], local[1, 1])
        assert f([got_alpha, got_tau]) <= (1 + 1e-4) * f([alpha, tau])
        assert abs(got_alpha - alpha) < 1e-3 and abs(got_tau - tau) < 1e-3, (s, got_alpha, alpha, got_tau, tau)
        assert relative_twists(m, pose, prior)[1] == pytest.approx(got_tau, abs=1e-9)
    # the weight counts the share of the turn that slides the surface along itself: a ring's radial normals see
    # none of it (all 9 n counts), normals along the turn's motion all of it (nothing counts)
    x = m.vertices - m.pivots[1]
    radial = x - x[:, :1] * [1.0, 0.0, 0.0]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert twist_prior(m, m.identity(), 2.0, normals=radial, max_points=None).weights[1] == pytest.approx(2.0 * 9 * 12)
    along = np.cross([1.0, 0.0, 0.0], x)
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    assert twist_prior(m, m.identity(), 2.0, normals=along, max_points=None).weights[1] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="normals"):
        twist_prior(m, m.identity(), 1.0, normals=radial[:3])
    with pytest.raises(ValueError, match="strength"):
        twist_prior(m, m.identity(), 0.0)
    with pytest.raises(ValueError, match="reference"):
        twist_prior(m, "pose", 1.0)
    with pytest.raises(ValueError, match="model"):
        twist_prior(object(), m.identity(), 1.0)
    with pytest.raises(ValueError, match="axes"):
        twist_prior(m, m.identity(), 1.0, axes=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="twist"):
        fit_subset(m, target, m.identity(), max_points=None, twist="prior")
