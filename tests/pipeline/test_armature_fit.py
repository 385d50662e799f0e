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
