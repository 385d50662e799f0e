"""Trajectory distances (Tzionas & Gall 2016, eqs. 8-9) against the definition, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.trajectory_distances import trajectory_distances


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


def test_invalid_input():
    X = np.zeros((4, 5, 3))
    with pytest.raises(ValueError, match="trajectories"):
        trajectory_distances(X[..., :2], interval=1)
    with pytest.raises(ValueError, match="interval"):
        trajectory_distances(X, interval=0)
    with pytest.raises(ValueError, match="normals"):
        trajectory_distances(X, np.zeros((4, 4, 3)), interval=1)
