"""Level-set rings, node costs (eq. 4), skeleton trees, limb quality (eq. 5)."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
import trimesh

from pipeline.geodesic import edge_graph, geodesic_distance, mesh_edges, vertex_areas
from pipeline.skeleton import grow_skeleton, level_set_rings, limb_end, limb_points, limb_quality, ring_statistics


def capsule(height=4.0, r=0.5):
    m = trimesh.creation.capsule(height=height, radius=r, count=[24, 24])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.15)
    return np.asarray(v), np.asarray(f)


def rings_bfs(d, edges, n_bins, width):
    """Slow reference: BFS over (vertex, band) nodes linked by edges crossing the band."""
    n = len(d)
    b = np.minimum((d / width).astype(int), n_bins - 1)
    adj = {}
    for u, v in edges:
        for k in range(min(b[u], b[v]), max(b[u], b[v]) + 1):
            adj.setdefault((u, k), []).append((v, k))
            adj.setdefault((v, k), []).append((u, k))
    comp = {}
    c = 0
    for s in adj:
        if s in comp:
            continue
        comp[s] = c
        q = deque([s])
        while q:
            x = q.popleft()
            for y in adj[x]:
                if y not in comp:
                    comp[y] = c
                    q.append(y)
        c += 1
    return np.array([comp[(i, b[i])] for i in range(n)]), b


def test_rings_match_bfs_reference():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices) * [1, 1, 3], np.asarray(m.faces)
    e = mesh_edges(f)
    d = geodesic_distance(edge_graph(v, e), 0)
    ring, level, width = level_set_rings(d, e, n_bins=12)
    ref, b = rings_bfs(d, e, 12, width)
    # same partition of the vertices (up to labels), and the level is the bin
    pairs = set(zip(ring.tolist(), ref.tolist()))
    assert len(pairs) == len(set(ring.tolist())) == len(set(ref.tolist()))
    np.testing.assert_array_equal(level[ring], b)
    assert np.all(np.diff(level) >= 0)


def test_ring_statistics_match_per_ring_svd():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(300, 3)) * [3, 1, 0.2]
    ring = rng.integers(-1, 7, size=300)
    c, cost, frame, count = ring_statistics(p, ring, 7)
    for r in range(7):
        q = p[ring == r]
        qc = q - q.mean(0)
        _, s, vt = np.linalg.svd(qc, full_matrices=False)
        assert count[r] == len(q)
        np.testing.assert_allclose(c[r], q.mean(0), atol=1e-12)
        np.testing.assert_allclose(cost[r], np.sum(s**2) / len(q), rtol=1e-10)  # eq. 4
        np.testing.assert_allclose(abs(frame[r, 0] @ vt[0]), 1.0, atol=1e-8)
        np.testing.assert_allclose(abs(frame[r, 1] @ vt[1]), 1.0, atol=1e-8)
        np.testing.assert_allclose(frame[r, 2], np.cross(frame[r, 0], frame[r, 1]), atol=1e-12)


def test_capsule_skeleton_is_its_axis():
    v, f = capsule()
    e = mesh_edges(f)
    g = edge_graph(v, e)
    top = int(np.argmax(v[:, 2]))
    bottom = int(np.argmin(v[:, 2]))
    sk = grow_skeleton(v, e, g, top, tips=np.array([top, bottom]), n_bins=40, weights=vertex_areas(v, f))
    # a chain: no branching, root at the seed, nodes on the z axis
    assert sk.parent[0] == -1 and np.sum(sk.parent == -1) == 1
    assert np.all(np.bincount(sk.parent[sk.parent >= 0]) <= 1)
    assert sk.tip_nodes[0] == 0
    mid = np.abs(sk.nodes[:, 2]) < 1.5
    assert np.max(np.linalg.norm(sk.nodes[mid, :2], axis=1)) < 0.02
    # cylinder rings: C = r^2 (points on a circle of radius 0.5), frame axis 3 = z
    np.testing.assert_allclose(sk.cost[mid], 0.25, rtol=0.05)
    assert np.all(np.abs(sk.frame[mid, 2, 2]) > 0.99)
    lp = limb_points(sk, v[top], (0.0, 1.0))
    np.testing.assert_allclose(lp[0], v[top])
    assert lp[1, 2] < -1.5
    # a chain with one other tip: the limb ends at that tip's ring, where the limb points end
    assert limb_end(sk) == sk.tip_nodes[1]
    np.testing.assert_array_equal(lp[1], sk.nodes[limb_end(sk)])


def test_limb_quality_eq5():
    assert limb_quality([0.5, 1.0, 0.25], 2.0) == pytest.approx(3 - 1.75 / 2.0)
    assert limb_quality([], 1.0) == 0.0


def test_invalid_input():
    v, f = capsule()
    e = mesh_edges(f)
    g = edge_graph(v, e)
    with pytest.raises(ValueError, match="n_bins"):
        level_set_rings(np.zeros(len(v)), e, n_bins=0)
    with pytest.raises(ValueError, match="seed_vertex"):
        grow_skeleton(v, e, g, len(v) + 3)
    with pytest.raises(ValueError, match="norm"):
        limb_quality([1.0], 0.0)
