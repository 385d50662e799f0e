"""Mesh contraction curve skeleton (Au et al. 2008), against shapes with a known axis."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.contraction_skeleton import contract_mesh, contraction_skeleton, cotangent_laplacian


def _bent_tube(R=100.0, r=12.0, degrees=150.0, voxel=3.0):
    """A capsule bent along a circular arc (marching cubes of its distance field); the arc is its axis."""
    from skimage.measure import marching_cubes

    s = np.linspace(0.0, np.radians(degrees), 600)
    arc = np.c_[R * np.cos(s), R * np.sin(s), np.zeros_like(s)]
    lo, hi = arc.min(0) - 2 * r, arc.max(0) + 2 * r
    axes = [np.arange(lo[k], hi[k] + voxel, voxel) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d, _ = cKDTree(arc).query(grid)
    v, f, _, _ = marching_cubes((d - r).reshape([len(a) for a in axes]), 0.0, spacing=(voxel,) * 3)
    return v + lo, f[:, ::-1].astype(np.int64), arc, r


def _polyline_points(P, E, n=20):
    return np.concatenate([np.linspace(P[a], P[b], n) for a, b in E])


def test_cotangent_laplacian_matches_the_per_triangle_formula():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1)
    v = np.asarray(m.vertices) * [2.0, 1.0, 1.0]
    f = np.asarray(m.faces)
    L, areas = cotangent_laplacian(v, f)
    ref = np.zeros((len(v), len(v)))
    for tri in f:
        for k in range(3):
            i, j, o = tri[(k + 1) % 3], tri[(k + 2) % 3], tri[k]
            a, b = v[i] - v[o], v[j] - v[o]
            c = 0.5 * max(0.0, (a @ b) / np.linalg.norm(np.cross(a, b)))
            ref[i, j] += c
            ref[j, i] += c
    ref -= np.diag(ref.sum(1))
    np.testing.assert_allclose(L.toarray(), ref, atol=1e-12)
    assert np.isclose(areas.sum(), trimesh.Trimesh(v, f, process=False).area)
    np.testing.assert_allclose(L @ np.ones(len(v)), 0.0, atol=1e-12)


def test_bent_tube_skeleton_follows_its_axis():
    v, f, arc, r = _bent_tube()
    P, E = contraction_skeleton(v, f)
    deg = np.bincount(E.ravel(), minlength=len(P))
    assert (deg == 1).sum() == 2 and (deg >= 3).sum() == 0  # one chain
    # measured: nodes at most 3.2 mm (0.27 of the 12 mm radius) from the arc, 1.2 mm on average
    d, _ = cKDTree(arc).query(P)
    assert d.max() <= 0.4 * r
    # the arc, away from its caps (one radius and a group), is covered: measured 1.9 mm at most
    s = np.linalg.norm(np.diff(arc, axis=0), axis=1).cumsum()
    inner = arc[1:][(s > 1.5 * r) & (s < s[-1] - 1.5 * r)]
    d2, _ = cKDTree(_polyline_points(P, E)).query(inner)
    assert d2.max() <= 0.3 * r


def test_contraction_reaches_the_axis_without_collapsing_the_length():
    v, f, arc, r = _bent_tube()
    c = contract_mesh(v, f)
    d, _ = cKDTree(arc).query(c)
    assert np.median(d) <= 0.15 * r  # was r on the surface
    ang = np.degrees(np.arctan2(c[:, 1], c[:, 0]))
    assert ang.min() < 5.0 and ang.max() > 145.0  # the 150-degree arc keeps its length


def test_curve_skeleton_without_a_spine_uses_the_contraction(caplog):
    """An ellipsoid shows no tips (no spine): its curve skeleton runs along the major axis."""
    import trimesh

    from pipeline.armature_skeleton import curve_skeleton

    m = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(m.vertices) * [60.0, 25.0, 25.0]
    with caplog.at_level(logging.WARNING):
        cs = curve_skeleton(v, np.asarray(m.faces))
    assert "contraction" in caplog.text
    assert len(cs.edges) >= 2
    off = np.linalg.norm(cs.points[:, 1:], axis=1)
    # measured: 0.5 mm off the axis at most; 74 mm of the 120 mm axis (the contraction ends
    # about a minor radius short of either pole: 120 - 2 x 25 = 70)
    assert off.max() <= 0.1 * 25.0
    assert np.ptp(cs.points[:, 0]) >= 0.5 * 120.0


def test_invalid_input():
    v, f, _, _ = _bent_tube(voxel=6.0)
    with pytest.raises(ValueError, match="vertices"):
        contraction_skeleton(v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        contraction_skeleton(v, f + len(v))
    with pytest.raises(ValueError, match="spacing"):
        contraction_skeleton(v, f, spacing=0.0)
    with pytest.raises(ValueError, match="min_branch"):
        contraction_skeleton(v, f, min_branch=-1.0)
    with pytest.raises(ValueError, match="iterations"):
        contract_mesh(v, f, iterations=0)
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        contract_mesh(bad, f)
