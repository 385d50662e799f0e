"""Fast paths of the per-frame spine step against their exact references.

* the proxy average geodesic distance (:func:`pipeline.geodesic.proxy_average_geodesic_distance`,
  used by :func:`pipeline.extremities.find_extremities` with ``agd_proxy``) against the exact
  24-base-point AGD: same tips, each within 3 % of ``sqrt(area)`` of the exact one;
* the k-hop max-dilation pre-filter of ``find_extremities`` (exact by construction) against the
  persistence definition on a bumpy surface with many local maxima.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.extremities import find_extremities, local_maxima, protrudes
from pipeline.frame_skeleton import SpineParams, frame_skeleton
from pipeline.geodesic import (
    average_geodesic_distance,
    cluster_vertices,
    edge_graph,
    mesh_edges,
    proxy_average_geodesic_distance,
    vertex_areas,
)
from tests.conftest import shared_dataset

TIP_TOL = 0.03  # tip shift, fraction of sqrt(surface area)
AGD_TOL = 0.06  # pointwise AGD difference, fraction of the AGD maximum


@pytest.fixture(scope="module")
def horse():
    from pipeline.meshio import load_mesh

    v, f = load_mesh(shared_dataset("horse_gallop") / "0001.obj")
    return np.asarray(v, dtype=np.float64), np.asarray(f)


def test_cluster_vertices_patches_are_connected():
    m = trimesh.creation.icosphere(subdivisions=4)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    e = mesh_edges(f)
    lab = cluster_vertices(v, e, 200)
    P = lab.max() + 1
    assert 100 <= P <= 400
    assert set(np.unique(lab)) == set(range(P))
    # every patch is edge-connected (a patch never spans two sheets)
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    same = e[lab[e[:, 0]] == lab[e[:, 1]]]
    n = len(v)
    _, cc = connected_components(sp.csr_matrix((np.ones(len(same)), (same[:, 0], same[:, 1])), shape=(n, n)), directed=False)
    assert len(np.unique(cc)) == P


def test_proxy_agd_matches_exact_on_horse(horse):
    v, f = horse
    e = mesh_edges(f)
    exact, _ = average_geodesic_distance(edge_graph(v, e), n_base=24, vertices=v)
    fast, base = proxy_average_geodesic_distance(v, e, n_base=24, n_proxy=1500)
    assert len(base) == 24 and np.all((base >= 0) & (base < len(v)))
    assert np.max(np.abs(fast - exact)) <= AGD_TOL * exact.max()


def test_proxy_tips_match_exact_on_horse(horse):
    v, f = horse
    size = float(np.sqrt(vertex_areas(v, f).sum()))
    exact = find_extremities(v, f)
    fast = find_extremities(v, f, agd_proxy=1500)  # 8431 vertices > 3 * 1500: proxy used
    assert len(exact) == 6
    assert len(fast) == len(exact)
    d = np.linalg.norm(exact.points[:, None] - fast.points[None], axis=2)
    assert d.min(axis=1).max() <= TIP_TOL * size
    assert d.min(axis=0).max() <= TIP_TOL * size


def test_frame_skeleton_proxy_vs_exact(horse):
    v, f = horse
    size = float(np.sqrt(vertex_areas(v, f).sum()))
    a = frame_skeleton(v, f, params=SpineParams(agd_proxy=None))
    b = frame_skeleton(v, f, params=SpineParams(agd_proxy=1500))
    assert a.n_tips == b.n_tips == 6
    d = np.linalg.norm(a.limb_points[:, None] - b.limb_points[None], axis=3).max(axis=2)
    # limbs pair up one to one, and whole limbs (not only tips) agree
    assert d.min(axis=1).max() <= 2 * TIP_TOL * size
    assert len(set(np.argmin(d, axis=1).tolist())) == 6


def test_prefilter_keeps_exact_definition_on_bumpy_surface():
    """Many small bumps (the dilation pre-filter runs): tips equal the slow persistence definition."""
    m = trimesh.creation.capsule(height=3.0, radius=0.5, count=[24, 24])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.08)
    v = np.asarray(v).copy()
    f = np.asarray(f)
    v[:, 0] += 0.3 * np.abs(v[:, 2])
    rng = np.random.default_rng(3)
    v += rng.normal(scale=0.004, size=v.shape)
    e = mesh_edges(f)
    h = 0.1 * np.sqrt(vertex_areas(v, f).sum())
    ext = find_extremities(v, f, protrusion=h)
    agd, _ = average_geodesic_distance(edge_graph(v, e), n_base=24, vertices=v)
    cand = local_maxima(agd, e)
    assert len(cand) > 8  # the pre-filter is exercised
    ref = [int(m_) for m_ in cand if protrudes(agd, e, int(m_), h)]
    assert sorted(ext.vertices.tolist()) == sorted(ref)
    assert len(ref) == 2


def test_invalid_input():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    with pytest.raises(ValueError, match="agd_proxy"):
        find_extremities(v, f, agd_proxy=0)
    with pytest.raises(ValueError, match="n_target"):
        cluster_vertices(v, mesh_edges(f), 0)
    with pytest.raises(ValueError):
        SpineParams(agd_proxy=10)
