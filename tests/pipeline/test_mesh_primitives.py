"""pipeline.mesh_primitives: vertex normals (zero for a vertex in no face), volume, corner sums, connected components."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.gltf_export import _unit_normals
from pipeline.mesh_primitives import (
    edge_components,
    mesh_components,
    mesh_volume,
    outward_normals,
    sum_by,
    summing_matrix,
    vertex_normals,
    winding_number,
)


def _slow_normals(v, f):
    """Vertex by vertex: the normalized sum of the cross products of its faces (their doubled areas)."""
    out = np.zeros_like(v)
    for i in range(len(v)):
        s = np.zeros(3)
        for a, b, c in f:
            if i in (a, b, c):
                s += np.cross(v[b] - v[a], v[c] - v[a])
        out[i] = s / np.linalg.norm(s) if np.linalg.norm(s) > 0 else 0.0
    return out


def _mesh_with_an_isolated_vertex():
    m = trimesh.creation.icosphere(subdivisions=1, radius=2.0)
    v = np.vstack([m.vertices, [[5.0, 5.0, 5.0]]])  # the last vertex is in no face
    return v, np.asarray(m.faces)


def test_normals_equal_the_per_vertex_reference_and_an_isolated_vertex_has_none():
    v, f = _mesh_with_an_isolated_vertex()
    n = vertex_normals(v, f)
    np.testing.assert_allclose(n, _slow_normals(v, f), atol=1e-12)
    assert np.all(n[-1] == 0.0)  # one answer for a vertex in no face: zero
    np.testing.assert_allclose(np.linalg.norm(n[:-1], axis=1), 1.0, atol=1e-12)
    # outward on a sphere
    assert np.all(np.einsum("ij,ij->i", n[:-1], v[:-1]) > 0)


def test_frames_at_once_and_reused_corner_sums_give_the_same_normals_bit_for_bit():
    v, f = _mesh_with_an_isolated_vertex()
    rng = np.random.default_rng(0)
    frames = v[None] + rng.normal(scale=0.05, size=(4,) + v.shape)
    corners = summing_matrix(f.ravel(), len(v))
    batched = vertex_normals(frames, f)
    for t in range(4):
        one = vertex_normals(frames[t], f)
        assert np.array_equal(batched[t], one) and np.array_equal(vertex_normals(frames[t], f, corners=corners), one)


def test_corner_sums_equal_bincount_bit_for_bit():
    rng = np.random.default_rng(1)
    index = rng.integers(0, 7, 50)
    values = rng.normal(size=(50, 3))
    S = summing_matrix(index, 7)
    ref = np.stack([np.bincount(index, weights=values[:, c], minlength=7) for c in range(3)], axis=1)
    assert np.array_equal(sum_by(S, values), ref)


def test_volume_of_a_sphere_and_the_exporter_gets_unit_normals():
    m = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    assert mesh_volume(m.vertices, m.faces) == pytest.approx(m.volume, rel=1e-12)
    v, f = _mesh_with_an_isolated_vertex()
    n = _unit_normals(v, f)  # glTF wants every NORMAL of unit length: the isolated vertex gets +z
    assert n.dtype == np.float32 and np.array_equal(n[-1], [0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)


def test_signed_volume_and_outward_normals_whichever_way_the_faces_wind():
    """The signed volume is trimesh's volume with the faces wound outward and its negative wound inward; the outward
    normals are the outward-wound mesh's vertex normals both ways (exact)."""
    m = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    assert mesh_volume(v, f, signed=True) == pytest.approx(m.volume, rel=1e-12)
    assert mesh_volume(v, f[:, ::-1], signed=True) == pytest.approx(-m.volume, rel=1e-12)
    assert mesh_volume(v, f[:, ::-1]) == mesh_volume(v, f)
    assert np.array_equal(outward_normals(v, f), vertex_normals(v, f))
    assert np.array_equal(outward_normals(v, f[:, ::-1]), -vertex_normals(v, f[:, ::-1]))
    np.testing.assert_allclose(outward_normals(v, f[:, ::-1]), vertex_normals(v, f), atol=1e-12)
    assert (np.einsum("ij,ij->i", outward_normals(v, f[:, ::-1]), v) > 0).all()  # out of the sphere


def test_invalid_input():
    from pipeline.mesh_primitives import check_points

    v, f = _mesh_with_an_isolated_vertex()
    assert check_points(v.tolist()).dtype == np.float64 and np.array_equal(check_points(v), v)
    for bad in (v[:, :2], v[0], np.where(np.arange(len(v))[:, None] == 1, np.inf, v)):
        with pytest.raises(ValueError, match="^corners must be a finite"):
            check_points(bad, name="corners")
    with pytest.raises(ValueError, match=f"^corners must be a finite .* at least {len(v) + 1} points"):
        check_points(v, name="corners", min_points=len(v) + 1)
    assert len(check_points(v, min_points=len(v))) == len(v)
    with pytest.raises(ValueError, match="vertices"):
        vertex_normals(v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        vertex_normals(v, f.astype(float))
    with pytest.raises(ValueError, match="do not exist"):
        vertex_normals(v[:5], f)
    with pytest.raises(ValueError, match="corners"):
        vertex_normals(v, f, corners=np.eye(3))
    with pytest.raises(ValueError, match="vertices"):
        outward_normals(np.stack([v, v]), f)  # one mesh, not frames
    with pytest.raises(ValueError, match="faces"):
        outward_normals(v, f[:, :2])
    with pytest.raises(ValueError, match="faces"):
        outward_normals(v[:5], f)
    for bad in (np.zeros(2), [0.0, np.nan, 0.0], np.zeros((1, 3))):
        with pytest.raises(ValueError, match="^point must be three finite"):
            winding_number(bad, v, f)
    with pytest.raises(ValueError, match="faces"):
        winding_number(np.zeros(3), v, f[:, :2])
    with pytest.raises(ValueError, match="vertices"):
        winding_number(np.zeros(3), v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        mesh_components(f[:, :2], len(v))
    with pytest.raises(ValueError, match="faces"):
        mesh_components(f, 5)
    with pytest.raises(ValueError, match="n must"):
        mesh_components(f, -1)
    with pytest.raises(ValueError, match="edges"):
        edge_components(f, len(v))
    with pytest.raises(ValueError, match="edges"):
        edge_components(np.array([[0, 1.5]]), 3)
    with pytest.raises(ValueError, match="edges"):
        edge_components(np.array([[0, 3]]), 3)
    with pytest.raises(ValueError, match="n must"):
        edge_components(np.array([[0, 1]]), 2.0)


def test_rigid_fit_recovers_a_known_motion_and_never_a_reflection():
    """``rigid_fit``: the exact rotation and translation of paired points (to 1e-9), and a proper rotation
    (det +1) for points that a mirror would pair better."""
    from scipy.spatial.transform import Rotation

    from pipeline.mesh_primitives import rigid_fit

    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    t = np.array([5.0, -2.0, 0.5])
    R2, t2 = rigid_fit(A, A @ R.T + t)
    assert np.allclose(R2, R, atol=1e-9) and np.allclose(t2, t, atol=1e-9)
    Rm, _ = rigid_fit(A, A * [-1.0, 1.0, 1.0])
    assert np.isclose(np.linalg.det(Rm), 1.0)


def _slow_components(edges, n):
    """Breadth-first search from every vertex not reached yet, in vertex order: the components numbered
    by their lowest vertex."""
    nbrs = [set() for _ in range(n)]
    for a, b in edges:
        nbrs[a].add(b)
        nbrs[b].add(a)
    lab = np.full(n, -1)
    for s in range(n):
        if lab[s] >= 0:
            continue
        lab[s] = c = lab.max() + 1
        todo = [s]
        while todo:
            for w in nbrs[todo.pop()]:
                if lab[w] < 0:
                    lab[w] = c
                    todo.append(w)
    return lab


@pytest.mark.parametrize("seed", range(6))
def test_components_equal_a_breadth_first_search_label_for_label(seed):
    """On random meshes and edge lists of many pieces, with vertices in no face or edge: the same labels
    exactly (not only the same partition), numbered by their lowest vertex."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 80))
    f = rng.integers(0, n, (int(rng.integers(0, n // 2 + 1)), 3))
    f_edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    got = mesh_components(f, n)
    assert got.dtype == np.int64 and np.array_equal(got, _slow_components(f_edges, n))
    e = rng.integers(0, n, (int(rng.integers(0, n)), 2))
    assert np.array_equal(edge_components(e, n), _slow_components(e, n))
    assert np.array_equal(edge_components(e[:, ::-1], n), edge_components(e, n))  # direction does not matter


def test_components_of_empty_and_separate_meshes():
    a = trimesh.creation.icosphere(subdivisions=1)
    n = len(a.vertices)
    f = np.concatenate([a.faces + n, a.faces])  # the second sphere's faces first: numbering by lowest vertex
    lab = mesh_components(f, 2 * n + 1)
    assert np.array_equal(lab, np.r_[np.zeros(n), np.ones(n), 2])
    assert mesh_components(np.zeros((0, 3), np.int64), 0).shape == (0,)
    assert np.array_equal(edge_components(np.zeros((0, 2), np.int64), 3), [0, 1, 2])
    assert np.array_equal(edge_components([], 2), [0, 1]) and np.array_equal(mesh_components([], 2), [0, 1])


def test_winding_number_against_the_solid_angles_of_a_cube():
    """The winding number of a closed cube (Jacobson et al. 2013) is 1 about points inside, 0 about points outside and
    -1 with its faces reversed; one face's triangles subtend a sixth of the sphere at the centre, so their winding
    number there is exactly 1/6 (all to 1e-12)."""
    m = trimesh.creation.box(extents=(2.0, 2.0, 2.0)).subdivide()
    v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)
    for point in ([0.0, 0.0, 0.0], [0.9, -0.8, 0.95], [-0.99, 0.0, 0.3]):
        assert winding_number(point, v, f) == pytest.approx(1.0, abs=1e-12)
        assert winding_number(point, v, f[:, ::-1]) == pytest.approx(-1.0, abs=1e-12)
    for point in ([1.01, 0.0, 0.0], [3.0, 2.0, -1.0], [0.0, 0.0, -1.5]):
        assert winding_number(point, v, f) == pytest.approx(0.0, abs=1e-12)
    top = f[v[f].mean(1)[:, 2] > 0.999]  # the face z = 1, in its triangles
    assert winding_number(np.zeros(3), v, top) == pytest.approx(1.0 / 6.0, abs=1e-12)
