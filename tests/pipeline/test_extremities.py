"""Tips: protruding AGD maxima."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.extremities import CLEAR, find_extremities, local_maxima, protrudes
from pipeline.geodesic import mesh_edges
from tests.pipeline.shapes import capsule, forked_capsule


def star(arms=4, length=2.0):
    """A ball with ``arms`` capsules sticking out of it (one watertight mesh)."""
    parts = [trimesh.creation.icosphere(subdivisions=3, radius=1.0)]
    dirs = []
    for k in range(arms):
        a = 2 * np.pi * k / arms
        d = np.array([np.cos(a), np.sin(a), 0.3 * (k % 2)])
        d /= np.linalg.norm(d)
        c = trimesh.creation.capsule(height=length, radius=0.3, count=[12, 12])
        z = np.array([0, 0, 1.0])
        R = trimesh.geometry.align_vectors(z, d)
        c.apply_transform(R)
        c.apply_translation(d * (0.6 + length / 2))
        parts.append(c)
        dirs.append(d)
    m = trimesh.boolean.union(parts) if False else trimesh.util.concatenate(parts)
    return m, np.array(dirs)


def test_local_maxima_vs_bruteforce():
    rng = np.random.default_rng(1)
    m = trimesh.creation.icosphere(subdivisions=2)
    e = mesh_edges(np.asarray(m.faces))
    vals = rng.normal(size=len(m.vertices))
    vals[5] = vals[6] = vals.max() + 1  # a tie between neighbours (or not) is broken by index
    got = set(local_maxima(vals, e).tolist())
    ref = set()
    for i in range(len(vals)):
        nb = np.concatenate([e[e[:, 0] == i, 1], e[e[:, 1] == i, 0]])
        if all((vals[i], i) > (vals[j], j) for j in nb):
            ref.add(i)
    assert got == ref


def test_fast_tests_agree_with_persistence_definition():
    """Every tip passes the slow exact test; every 1-ring maximum rejected fails it."""
    m = capsule()
    # bend it into a 'V' with a short bump: 2 real tips + noise
    v = np.asarray(m.vertices).copy()
    v[:, 0] += 0.3 * np.abs(v[:, 2])
    f = np.asarray(m.faces)
    ext = find_extremities(v, f, min_protrusion=0.1)
    e = mesh_edges(f)
    for t in ext.vertices:
        assert protrudes(ext.agd, e, int(t), ext.threshold)
    for c in local_maxima(ext.agd, e):
        if c not in set(ext.vertices.tolist()):
            assert not protrudes(ext.agd, e, int(c), ext.threshold)
    assert len(ext) == 2


def test_clear_tips_match_the_persistence_definition_at_1_5_h():
    """``clear`` = the slow exact persistence test at ``CLEAR * h``; a bump on a capsule's side
    that passes ``h`` but not ``1.5 h`` is a tip that is not clear, the capsule's ends are."""
    m = capsule()
    v, f = np.asarray(m.vertices).copy(), np.asarray(m.faces)
    v[:, 0] += 0.8 * (v[:, 0] > 0) * np.exp(-(v[:, 2] ** 2 + v[:, 1] ** 2) / 0.25**2)
    e = mesh_edges(f)
    for mp in (0.04, 0.07, 0.1, 0.15):
        ext = find_extremities(v, f, min_protrusion=mp)
        assert ext.clear.shape == (len(ext),) and ext.clear.dtype == bool
        ref = [protrudes(ext.agd, e, int(t), CLEAR * ext.threshold) for t in ext.vertices]
        assert ext.clear.tolist() == ref, mp
    ext = find_extremities(v, f, min_protrusion=0.07)
    bump = np.abs(ext.points[:, 2]) < 0.5
    assert bump.sum() == 1 and not ext.clear[bump].any() and ext.clear[~bump].all()


def test_sphere_has_no_tips_capsule_two():
    s = trimesh.creation.icosphere(subdivisions=3)
    assert len(find_extremities(s.vertices, s.faces)) == 0
    c = capsule()
    ext = find_extremities(c.vertices, c.faces)
    assert len(ext) == 2
    np.testing.assert_allclose(np.sort(np.abs(ext.points[:, 2])), [2.0, 2.0], atol=0.05)


def test_threshold_is_scale_free():
    c = capsule()
    a = find_extremities(c.vertices, c.faces)
    b = find_extremities(c.vertices * 1000.0, c.faces)
    assert len(a) == len(b) == 2
    # symmetric ties may fall on another vertex of the same cap: compare heights
    np.testing.assert_allclose(np.sort(b.points[:, 2]) / 1000.0, np.sort(a.points[:, 2]), atol=0.05)
    np.testing.assert_allclose(b.threshold, 1000.0 * a.threshold, rtol=1e-9)


def test_alternates_are_the_limbs_other_ball_maxima():
    """Each alternate fails persistence, is the maximum of its own geodesic h-ball (slow Dijkstra
    check) and lies in its tip's h-superlevel component; a limb with one end has none."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components, dijkstra

    from pipeline.geodesic import edge_graph

    v, f = forked_capsule()
    ext = find_extremities(v, f)
    assert len(ext) == 2 and len(ext.alternates) == 2
    top = int(np.argmax(ext.points[:, 2]))
    assert len(ext.alternates[top]) == 1 and len(ext.alternates[1 - top]) == 0
    a = int(ext.alternates[top][0])
    np.testing.assert_allclose(v[a], [-0.28, 0.0, 2.35], atol=0.05)  # the other bump of the fork
    e = mesh_edges(f)
    agd, h, tip = ext.agd, ext.threshold, int(ext.vertices[top])
    assert not protrudes(agd, e, a, h) and agd[a] < agd[tip]
    d = dijkstra(edge_graph(v, e), indices=a)
    assert agd[d < h].max() == agd[a]
    keep = agd >= agd[tip] - h
    ee = e[keep[e[:, 0]] & keep[e[:, 1]]]
    _, lab = connected_components(sp.csr_matrix((np.ones(len(ee)), (ee[:, 0], ee[:, 1])), shape=(len(v),) * 2))
    assert lab[a] == lab[tip]
    c = capsule()
    assert [len(x) for x in find_extremities(c.vertices, c.faces).alternates] == [0, 0]


def test_invalid_input():
    c = capsule()
    with pytest.raises(ValueError, match="n_base"):
        find_extremities(c.vertices, c.faces, n_base=1)
    with pytest.raises(ValueError, match="min_protrusion"):
        find_extremities(c.vertices, c.faces, min_protrusion=0)
    with pytest.raises(ValueError, match="protrusion"):
        find_extremities(c.vertices, c.faces, protrusion=-1.0)
    with pytest.raises(ValueError, match="faces"):
        find_extremities(c.vertices, np.zeros((0, 3), int))
