"""Edge-graph geodesics, components, base points."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from pipeline.geodesic import (
    EmptyMeshError,
    average_geodesic_distance,
    edge_graph,
    farthest_point_sampling,
    geodesic_distance,
    largest_component,
    mesh_edges,
    validate_mesh,
    vertex_areas,
)


def capsule(height=3.0):
    """A capsule with roughly uniform edges (trimesh's has only end rings on the cylinder)."""
    m = trimesh.creation.capsule(height=height, radius=0.5, count=[16, 16])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.2)
    return trimesh.Trimesh(v, f)


def grid(n=6):
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


def test_edges_and_distances_match_exact_formula():
    v, f = grid(6)
    e = mesh_edges(f)
    # grid edges + one diagonal per square
    assert len(e) == 2 * 6 * 5 + 25
    g = edge_graph(v, e)
    d = geodesic_distance(g, 0)
    # on this triangulation, shortest path = diagonal steps then axis steps
    i, j = v[:, 0], v[:, 1]
    exact = np.minimum(i, j) * np.sqrt(2) + np.abs(i - j)
    np.testing.assert_allclose(d, exact, atol=1e-12)
    np.testing.assert_allclose(vertex_areas(v, f).sum(), 25.0)


def test_largest_component_keeps_biggest_and_warns(caplog):
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=1)
    v = np.vstack([b.vertices + 5, a.vertices])
    f = np.vstack([b.faces, a.faces + len(b.vertices)])
    with caplog.at_level(logging.WARNING):
        v2, f2, kept = largest_component(v, f)
    assert "2 connected parts" in caplog.text
    assert len(f2) == len(a.faces)
    np.testing.assert_allclose(v2, a.vertices)
    np.testing.assert_array_equal(kept, np.arange(len(b.vertices), len(v)))


def test_farthest_points_and_agd():
    m = capsule(4.0)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    g = edge_graph(v, mesh_edges(f))
    base, dist = farthest_point_sampling(g, 2, vertices=v)
    # the two first base points are the capsule's two ends
    assert abs(abs(v[base[0], 2] - v[base[1], 2]) - 5.0) < 0.05
    np.testing.assert_allclose(dist[1], geodesic_distance(g, base[1]))
    agd, _ = average_geodesic_distance(g, n_base=16, vertices=v)
    # AGD is largest at the ends of the capsule, smallest in the middle
    assert abs(v[np.argmax(agd), 2]) > 2.4
    assert abs(v[np.argmin(agd), 2]) < 0.6


def test_invalid_input():
    v, f = grid(3)
    with pytest.raises(ValueError, match="vertices"):
        validate_mesh(v[:, :2], f)
    with pytest.raises(ValueError, match="vertices"):
        validate_mesh(np.full_like(v, np.nan), f)
    with pytest.raises(ValueError, match="faces"):
        validate_mesh(v, f[:, :2])
    with pytest.raises(ValueError, match="faces"):
        validate_mesh(v, f + 100)
    with pytest.raises(EmptyMeshError):
        validate_mesh(v, np.zeros((0, 3), int))
    g = edge_graph(v, mesh_edges(f))
    with pytest.raises(ValueError, match="sources"):
        geodesic_distance(g, [100])
    with pytest.raises(ValueError, match="n"):
        farthest_point_sampling(g, 0)
    with pytest.raises(EmptyMeshError):
        largest_component(v, np.zeros((0, 3), int))
