"""Motion segmentation (Tzionas & Gall 2016, section 4.1): formulas against slow references, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.motion_segmentation import (
    check_sequence,
    interval_length,
    motion_segmentation,
    rigid_residual,
    spectral_clusters,
    trajectory_distances,
)


def _slow_distances(X, N, dt):
    T, n, _ = X.shape
    dv = np.zeros((n, n))
    dn = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            d = [np.linalg.norm(X[t, i] - X[t, j]) for t in range(T)]
            a = [np.arccos(np.clip(N[t, i] @ N[t, j], -1, 1)) for t in range(T)]
            for t in range(T):
                for s in range(t, min(T, t + dt + 1)):
                    dv[i, j] = max(dv[i, j], abs(d[s] - d[t]))
                    dn[i, j] = max(dn[i, j], abs(a[s] - a[t]))
    return dv, dn


@pytest.mark.parametrize("T, dt", [(9, 1), (9, 3), (9, 20), (40, 16), (41, 13)])
def test_trajectory_distances_match_the_definition(T, dt):
    rng = np.random.default_rng(3)
    X = rng.normal(size=(T, 7, 3)) * 50
    N = rng.normal(size=(T, 7, 3))
    N /= np.linalg.norm(N, axis=2, keepdims=True)
    dv, dn = trajectory_distances(X, N, interval=dt, block_elements=100)  # several row blocks
    rv, rn = _slow_distances(X, N, dt)
    np.testing.assert_allclose(dv, rv, atol=2e-3 * 50)
    np.testing.assert_allclose(dn, rn, atol=2e-3)


def test_interval_length_is_twice_the_largest_step():
    v = np.zeros((5, 4, 3))
    v[3, 2, 0] = 4.0  # one vertex steps 4 then back 4
    assert interval_length(v) == 4  # 2 * 4 = 8, capped at T - 1 = 4
    assert interval_length(v, to_reference=0.25) == 2


def test_spectral_clusters_find_blocks():
    lab = np.repeat([0, 1, 2], [30, 20, 10])
    A = np.where(lab[:, None] == lab[None, :], 1.0, 0.02)
    got, eig, k = spectral_clusters(A)
    assert k == 3
    assert eig[:3].max() < 0.7 < eig[3]
    # same partition up to renaming
    assert len({(a, b) for a, b in zip(lab, got)}) == 3


def test_rigid_residual_is_zero_for_a_rigid_motion():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    X = rng.normal(size=(50, 3))
    R = Rotation.random(6, random_state=2).as_matrix()
    Y = np.einsum("tij,nj->tni", R, X) + rng.normal(size=(6, 1, 3))
    assert rigid_residual(Y) < 1e-9
    Y[3, :25] *= 1.5
    assert rigid_residual(Y) > 0.1


def _two_bars(T=12):
    """A bar hinged at its middle (the origin); the right half turns by up to 60 degrees (mm)."""
    import trimesh

    m = trimesh.creation.box(extents=(200, 20, 20))
    for _ in range(4):
        m = m.subdivide()
    v0 = np.asarray(m.vertices)
    right = v0[:, 0] > 0
    frames = []
    for ang in np.linspace(0, np.pi / 3, T):
        c, s = np.cos(ang), np.sin(ang)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        v = v0.copy()
        v[right] = v0[right] @ R.T
        frames.append(v)
    return np.asarray(frames), np.asarray(m.faces), right


def test_two_hinged_parts_are_two_segments():
    V, F, right = _two_bars()
    seg = motion_segmentation(V, F, n_samples=300)
    assert seg.n_segments == 2
    # every vertex away from the hinge carries its part's label
    far = np.abs(V[0][:, 0]) > 10
    lab_r = np.bincount(seg.labels[far & right]).argmax()
    assert (seg.labels[far & right] == lab_r).all() and (seg.labels[far & ~right] != lab_r).all()


def test_rigid_sequence_is_one_segment(caplog):
    V, F, _ = _two_bars(8)
    Vr = np.repeat(V[:1], 8, axis=0) + np.linspace(0, 80, 8)[:, None, None]  # translates, nothing bends
    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(Vr, F, n_samples=200)
    assert seg.n_segments == 1 and seg.k == 1
    assert "nothing bends" in caplog.text


def test_one_frame_is_one_segment(caplog):
    V, F, _ = _two_bars(3)
    with caplog.at_level(logging.WARNING):
        seg = motion_segmentation(V[:1], F)
    assert seg.n_segments == 1
    assert "one frame" in caplog.text


def test_invalid_input():
    V, F, _ = _two_bars(3)
    with pytest.raises(ValueError, match="track"):
        check_sequence([V[0], V[1][:-5]], F)
    with pytest.raises(ValueError, match="vertices"):
        motion_segmentation(V[0], F)
    with pytest.raises(ValueError, match="faces"):
        motion_segmentation(V, F + len(V[0]))
    with pytest.raises(ValueError, match="lambda_thr"):
        motion_segmentation(V, F, lambda_thr=3.0)
    with pytest.raises(ValueError, match="lam"):
        motion_segmentation(V, F, lam=-1)
    with pytest.raises(ValueError, match="n_samples"):
        motion_segmentation(V, F, n_samples=1)
    bad = V.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        motion_segmentation(bad, F)
