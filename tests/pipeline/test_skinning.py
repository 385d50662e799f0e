"""Bone heat skinning weights (pipeline.skinning) and the rig built on them (pipeline.armature_spine)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.armature_spine import NoCompleteFrameError, armature_from_spine, reference_frame, rigged_model
from pipeline.geodesic import vertex_areas
from pipeline.skinning import (
    SkinningError,
    bone_heat_weights,
    cotangent_laplacian,
    limit_influences,
    segment_distances,
)
from tests.pipeline.creature_truth import creature_take, surface, true_spine


def _grid(n=6, *, seed=0, jitter=0.2):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    interior = (x.ravel() > 0) & (x.ravel() < n - 1) & (y.ravel() > 0) & (y.ravel() < n - 1)
    v[interior, :2] += rng.uniform(-jitter, jitter, (interior.sum(), 2))
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [(a, b, c), (a, c, d)]
    return v, np.array(f), interior


def _slow_laplacian(v, f):
    n = len(v)
    L = np.zeros((n, n))
    for tri in f:
        for k in range(3):
            i, j, o = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            a, b = v[i] - v[o], v[j] - v[o]
            cot = np.dot(a, b) / np.linalg.norm(np.cross(a, b))
            L[i, j] -= cot / 2
            L[j, i] -= cot / 2
    L[np.diag_indices(n)] = -L.sum(1)
    return L


def test_cotangent_laplacian_matches_slow_reference_and_kills_linear_functions():
    v, f, interior = _grid()
    L = cotangent_laplacian(v, f).toarray()
    np.testing.assert_allclose(L, _slow_laplacian(v, f), atol=1e-12)
    np.testing.assert_allclose(L, L.T, atol=1e-12)
    np.testing.assert_allclose(L.sum(1), 0, atol=1e-12)
    # the cotangent Laplacian is exact on linear functions at interior vertices of a flat mesh
    lin = 2.0 * v[:, 0] - 3.0 * v[:, 1] + 1.0
    np.testing.assert_allclose((L @ lin)[interior], 0, atol=1e-10)


def test_lumped_mass_sums_to_area():
    """The mass matrix of the heat equation is geodesic.vertex_areas: it sums to the area."""
    v, f, _ = _grid(5)
    assert vertex_areas(v, f).sum() == pytest.approx(16.0, rel=1e-12)


def test_segment_distances_match_dense_sampling():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(50, 3))
    A = rng.normal(size=(4, 3))
    B = rng.normal(size=(4, 3))
    D = segment_distances(P, A, B)
    s = np.linspace(0, 1, 20001)
    for b in range(4):
        pts = A[b] + s[:, None] * (B[b] - A[b])
        slow = np.linalg.norm(P[:, None] - pts[None], axis=2).min(1)
        np.testing.assert_allclose(D[:, b], slow, atol=1e-3)


def test_limit_influences_keeps_largest_and_normalises():
    rng = np.random.default_rng(2)
    W = rng.random((30, 7))
    idx, w = limit_influences(W, max_influences=4)
    assert idx.shape == (30, 4)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)
    for r in range(30):
        top = np.sort(W[r])[::-1][:4]
        np.testing.assert_allclose(w[r], top / top.sum())
        assert set(idx[r]) == set(np.argsort(W[r])[::-1][:4])


def _tube(*, rings=41, sections=24, length=10.0, radius=1.0):
    """Closed cylinder along z (from -length/2 to length/2) with capped ends."""
    z = np.linspace(-length / 2, length / 2, rings)
    a = 2 * np.pi * np.arange(sections) / sections
    v = np.array([[radius * np.cos(t), radius * np.sin(t), zz] for zz in z for t in a])
    v = np.vstack([v, [[0, 0, z[0]], [0, 0, z[-1]]]])
    f = []
    for r in range(rings - 1):
        for s in range(sections):
            p, q = r * sections + s, r * sections + (s + 1) % sections
            f += [(p, q, q + sections), (p, q + sections, p + sections)]
    lo, hi = len(v) - 2, len(v) - 1
    top = (rings - 1) * sections
    for s in range(sections):
        f += [(lo, (s + 1) % sections, s), (hi, top + s, top + (s + 1) % sections)]
    return v, np.array(f)


def test_bone_heat_on_a_cylinder_blends_at_the_joint():
    v, f = _tube()
    A = np.array([[0, 0, -5.0], [0, 0, 0.0]])
    B = np.array([[0, 0, 0.0], [0, 0, 5.0]])
    W = bone_heat_weights(v, f, A, B)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-12)
    assert W.min() >= 0 and W.max() <= 1
    far_lo, far_hi = v[:, 2] < -2.5, v[:, 2] > 2.5
    assert W[far_lo, 0].min() > 0.95 and W[far_hi, 1].min() > 0.95
    # smooth blend: the weight of the lower bone decreases with height through the joint
    mid = np.abs(v[:, 2]) < 1.5
    order = np.argsort(v[mid, 2])
    assert np.corrcoef(v[mid, 2][order], W[mid, 0][order])[0, 1] < -0.9
    assert 0.3 < W[np.abs(v[:, 2]) < 0.1, 0].mean() < 0.7


@pytest.mark.parametrize("name", ["starfish", "quadruped"])
def test_dominant_joint_is_the_true_limb(name):
    """>= 95 % of limb vertices have their dominant joint on the limb they belong to.

    Truth: ``Pose.label_at`` (the nearest capsule's limb); body vertices
    (label -1) are excluded: the body is bound to the limbs' first bones,
    which run inside it from the junction.
    """
    _, poses = creature_take(name, 12)
    spine = true_spine(name, poses)
    ref = reference_frame(spine)
    v, f = surface(poses[ref], step=8.0)
    model = rigged_model(spine, v, f, reference=ref)
    np.testing.assert_allclose(model.weights.sum(1), 1.0, atol=1e-12)
    assert model.joints.shape[1] <= 4
    joint_limb = np.array([spine.limb_ids.index(e) if e in spine.limb_ids else -1 for e in model.rig.element])
    label = poses[ref].label_at(v)
    names = poses[ref].names
    truth = np.array([spine.limb_ids.index(names[lab]) if lab >= 0 else -1 for lab in label])
    sel = truth >= 0
    acc = float((joint_limb[model.joints[sel, 0]] == truth[sel]).mean())
    print(f"{name}: dominant joint on the true limb for {acc:.1%} of {sel.sum()} limb vertices")
    assert acc >= 0.95


def test_rig_joints_follow_the_spine_in_every_frame():
    _, poses = creature_take("quadruped", 12)
    spine = true_spine("quadruped", poses)
    rig = armature_from_spine(spine, segments=4)
    # joint count: the root + (segments + 1) per axis (6 limbs, 2 junction axes)
    assert rig.n_joints == 1 + 8 * 5
    assert np.all(rig.parents[1:] < np.arange(1, rig.n_joints))
    tip = {lb: rig.names.index(f"{lb}.tip") for lb in spine.limb_ids}
    for t in range(spine.frame_count):
        P = rig.joint_positions(t)
        for lb in spine.limb_ids:
            np.testing.assert_allclose(P[tip[lb]], spine.axes[lb][t, -1], atol=1e-9)
        np.testing.assert_allclose(P[0], spine.junctions[t, 0], atol=1e-9)
    # rotations are unit quaternions; rest frame is the identity
    np.testing.assert_allclose(np.linalg.norm(rig.rotations, axis=2), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(rig.rotations[rig.reference, 1:, 3]), 1.0, atol=1e-9)


def test_null_limb_holds_the_neighbouring_pose():
    _, poses = creature_take("starfish", 12)
    spine = true_spine("starfish", poses, hide={"arm2": [8, 9]})
    rig = armature_from_spine(spine)
    assert rig.reference == 6
    arm = [j for j, e in enumerate(rig.element) if e == "arm2"]
    for t in (8, 9):  # hold frame 7's local pose (the neighbour nearer the reference)
        np.testing.assert_allclose(rig.rotations[t, arm], rig.rotations[7, arm])
        np.testing.assert_allclose(rig.translations[t, arm], rig.translations[7, arm])
    other = [j for j, e in enumerate(rig.element) if e == "arm1"]
    assert not np.allclose(rig.rotations[9, other], rig.rotations[7, other])


def test_invalid_input():
    v, f, _ = _grid(4)
    A, B = np.zeros((1, 3)), np.ones((1, 3))
    with pytest.raises(ValueError, match="vertices"):
        cotangent_laplacian(np.zeros((4, 2)), f)
    with pytest.raises(ValueError, match="faces"):
        cotangent_laplacian(v, f + 100)
    with pytest.raises(ValueError, match="faces"):
        cotangent_laplacian(v, f + 0.5)
    with pytest.raises(ValueError, match="faces"):
        bone_heat_weights(v, np.zeros((0, 3), int), A, B)
    with pytest.raises(ValueError, match="points"):
        segment_distances(np.zeros(3), A, B)
    with pytest.raises(ValueError, match="seg_a"):
        segment_distances(v, A, np.ones((2, 3)))
    with pytest.raises(ValueError, match="max_influences"):
        limit_influences(np.ones((3, 2)), max_influences=0)
    with pytest.raises(SkinningError):
        limit_influences(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="seg_a"):
        bone_heat_weights(v, f, np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="seg_b"):
        bone_heat_weights(v, f, A, np.ones((2, 3)))
    with pytest.raises(ValueError, match="heat"):
        bone_heat_weights(v, f, A, B, heat=0)
    with pytest.raises(SkinningError):
        bone_heat_weights(np.zeros((3, 3)), np.array([[0, 1, 2]]), A, B)
    _, poses = creature_take("starfish", 4)
    spine = true_spine("starfish", poses)
    with pytest.raises(ValueError, match="spine"):
        armature_from_spine({"format": "x"})
    with pytest.raises(ValueError, match="segments"):
        armature_from_spine(spine, segments=0)
    with pytest.raises(ValueError, match="reference"):
        armature_from_spine(spine, reference=99)
    with pytest.raises(ValueError, match="max_influences"):
        rigged_model(spine, v, f, max_influences=5)
    hidden = true_spine("starfish", poses, hide={"arm0": range(4)})
    with pytest.raises(NoCompleteFrameError):
        armature_from_spine(hidden)
