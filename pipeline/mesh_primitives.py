"""Mesh primitives the tracker, the motion segmentation, the exporter and the simulator share:
the one check of a mesh's arrays, vertex normals, enclosed volume, triangle areas, the sums
over a mesh's face corners behind them, and the rigid motion that best carries one point set onto
another (:func:`rigid_fit`), the connected components of a mesh or of an edge list
(:func:`mesh_components`, :func:`edge_components`), and whether a point lies inside a surface (:func:`winding_number`).

A vertex in no face (an isolated vertex) has **no normal: zero**, not an arbitrary direction. Every
user of a normal then treats it as "no surface here": the tracker's normal gate never pairs it,
the renderer's shading ignores it. A format that demands unit normals (glTF) fills them itself
(:mod:`pipeline.gltf_export`).

The sums go through one sparse matrix per mesh (:func:`summing_matrix`) rather than
``np.add.at``: the same sums bit for bit as ``np.bincount`` adds them, built once and reused
for every frame of a take (:class:`pipeline.tracking.TemplateTracker`). trimesh computes normals
too, but per ``Trimesh`` object with its caches; the tracker needs them for a fixed connectivity
and thousands of vertex arrays.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["check_mesh", "check_points", "summing_matrix", "sum_by", "scatter_add", "triangle_areas", "vertex_normals", "mesh_volume",
           "outward_normals", "winding_number", "rigid_fit", "edge_components", "mesh_components"]


def check_points(points, *, name: str = "points", min_points: int = 0) -> np.ndarray:
    """``points`` as a finite float64 (N, 3) array of at least ``min_points`` rows, or a ValueError naming it
    ``name``."""
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) < min_points or not np.isfinite(X).all():
        least = f" of at least {min_points} points" if min_points else ""
        raise ValueError(f"{name} must be a finite (N, 3) array{least}, got shape {X.shape}")
    return X


def check_mesh(vertices, faces, *, min_vertices: int = 0, min_faces: int = 0,
               integral_faces: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A mesh's arrays checked and converted to ``(float64 (V, 3), int64 (F, 3))``.

    Parameters
    ----------
    vertices : (V, 3) array-like
        Finite, at least ``min_vertices`` of them.
    faces : (F, 3) int array-like
        At least ``min_faces`` triangles indexing ``vertices``; an empty array is ``(0, 3)``.
    integral_faces : bool
        Also accept a float array holding whole numbers (what some mesh readers return).

    Raises
    ------
    ValueError
        Naming ``vertices`` or ``faces``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < min_vertices:
        raise ValueError(f"vertices must have shape (V >= {min_vertices}, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite")
    f = np.asarray(faces)
    if f.size == 0:
        f = f.reshape(0, 3)
    whole = np.issubdtype(f.dtype, np.integer) or (
        integral_faces and np.issubdtype(f.dtype, np.number) and bool(np.all(np.mod(f, 1) == 0)))
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < min_faces or not whole:
        raise ValueError(f"faces must be an integer array of shape (F >= {min_faces}, 3), got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside 0..{len(v) - 1}")
    return v, f


def summing_matrix(index, n: int) -> sp.csr_matrix:
    """(n, K) sparse ``S`` with ``S @ values`` equal, bit for bit, to
    ``np.bincount(index, weights=values, minlength=n)`` per column: each row holds ones at its
    values' positions in order, so it adds them in the order bincount does. Built once, it serves
    every sum over the same ``index`` (e.g. ``faces.ravel()``: the corners' sums per vertex)."""
    index = np.asarray(index, dtype=np.int64).reshape(-1)
    k = len(index)
    return sp.csr_matrix((np.ones(k), (index, np.arange(k))), shape=(int(n), k))


def sum_by(S: sp.csr_matrix, values) -> np.ndarray:
    """``S @ values`` for (K,) or (K, d...) values (:func:`summing_matrix`)."""
    vals = np.asarray(values, dtype=np.float64)
    return (S @ vals.reshape(len(vals), -1)).reshape((S.shape[0],) + vals.shape[1:])


def scatter_add(index: np.ndarray, values, n: int) -> np.ndarray:
    """``out[index[k]] += values[k]`` for (K,) or (K, d...) values, by ``np.bincount`` (much faster than
    ``np.add.at``; :func:`summing_matrix` gives the same sums when one index serves many calls)."""
    vals = np.asarray(values, dtype=np.float64)
    flat = vals.reshape(len(vals), -1)
    out = np.stack([np.bincount(index, weights=flat[:, c], minlength=n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n,) + vals.shape[1:])


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) areas of a mesh's triangles (checked arrays: :func:`check_mesh`)."""
    v, f = vertices, faces
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def _unit_normals(v: np.ndarray, f: np.ndarray, corners: sp.csr_matrix) -> np.ndarray:
    """Unit area-weighted normals of one (V, 3) frame, ``corners = summing_matrix(f.ravel(), V)``."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = sum_by(corners, np.repeat(fn, 3, axis=0))
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(nn > 0, nn, 1.0)


def vertex_normals(vertices, faces, *, corners: sp.spmatrix | None = None) -> np.ndarray:
    """Unit area-weighted vertex normals, zero for a vertex in no face (or whose faces cancel).

    Parameters
    ----------
    vertices : (V, 3) or (T, V, 3) float ndarray
        One mesh, or the frames of a mesh sequence of one connectivity.
    faces : (F, 3) int ndarray
    corners : (V, 3F) sparse matrix, optional
        ``summing_matrix(faces.ravel(), V)`` (:attr:`pipeline.tracking.TemplateTracker.corner_sum`),
        reused instead of built on every call: the same normals, bit for bit.

    Returns
    -------
    ndarray, the shape of ``vertices``
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim not in (2, 3) or v.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (V, 3) or (T, V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.shape} {f.dtype}")
    n_v = v.shape[-2]
    if f.size and (f.min() < 0 or f.max() >= n_v):
        raise ValueError("faces index vertices that do not exist")
    if corners is None:
        corners = summing_matrix(f.ravel(), n_v)
    elif not sp.issparse(corners) or corners.shape != (n_v, f.size):
        raise ValueError(f"corners must be a sparse ({n_v}, {f.size}) matrix (the faces' corner sums), "
                         f"got {type(corners).__name__} of shape {getattr(corners, 'shape', None)}")
    if v.ndim == 2:
        return _unit_normals(v, f, corners)
    return np.stack([_unit_normals(frame, f, corners) for frame in v]) if len(v) else np.zeros_like(v)


def mesh_volume(vertices, faces, *, signed: bool = False) -> float:
    """Enclosed volume (divergence theorem; exact for closed, consistently oriented meshes); ``signed``: positive
    when the triangles wind with their normals out of the surface, negative when they wind into it."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    return float(volume if signed else abs(volume))


def outward_normals(vertices, faces) -> np.ndarray:
    """:func:`vertex_normals` of a closed surface turned out of it, whichever way its triangles wind (all the same
    way): negated when its signed volume (:func:`mesh_volume`) is negative.

    Parameters
    ----------
    vertices : (V, 3) float array_like
    faces : (F, 3) int array_like

    Returns
    -------
    (V, 3) float64 ndarray

    Raises
    ------
    ValueError
        As :func:`check_mesh`.
    """
    v, f = check_mesh(vertices, faces)
    return vertex_normals(v, f) * (1.0 if mesh_volume(v, f, signed=True) >= 0 else -1.0)


def winding_number(point, vertices, faces) -> float:
    """The generalized winding number of a mesh about ``point`` (Jacobson et al. 2013): the triangles' signed solid
    angles at ``point`` (van Oosterom & Strackee 1983) summed over ``4 pi``.

    About a closed surface it is 1 inside and 0 outside (-1 inside when the faces wind inwards); a hole lowers it by
    the solid angle it leaves open, and a sheet of the surface pushed through another part (a tracked limb pressed
    into the body) adds its own turns only about the points it encloses, where the nearest vertices' normals face the
    point beside it.

    Parameters
    ----------
    point : (3,) float array_like
    vertices : (V, 3) float array_like
    faces : (F, 3) int array_like

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Naming ``point`` (not three finite coordinates), or as :func:`check_mesh`.
    """
    p = np.asarray(point, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"point must be three finite coordinates, got shape {p.shape}")
    v, f = check_mesh(vertices, faces)
    a, b, c = v[f[:, 0]] - p, v[f[:, 1]] - p, v[f[:, 2]] - p
    la, lb, lc = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1), np.linalg.norm(c, axis=1)
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
           + np.einsum("ij,ij->i", c, a) * lb)
    return float(np.arctan2(num, den).sum() / (2.0 * np.pi))


def rigid_fit(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising ``sum ||R a + t - b||^2`` over paired points (Kabsch / Arun et al. 1987; no reflection).

    Parameters
    ----------
    A, B : (n, 3) float ndarray
        Paired points.

    Returns
    -------
    R : (3, 3) ndarray
    t : (3,) ndarray
    """
    ca, cb = A.mean(0), B.mean(0)
    H = (A - ca).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])  # (a degenerate set: no reflection either)
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def _vertex_count(n) -> int:
    """``n`` as an int, or a ValueError naming ``n``."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be a whole number >= 0 (the number of vertices), got {n!r}")
    return int(n)


def edge_components(edges, n) -> np.ndarray:
    """Connected component of every vertex of an undirected graph given by its edges.

    Parameters
    ----------
    edges : (E, 2) int array-like
        Vertex pairs within ``0..n-1``; an edge's direction, repeated edges and loops do not matter.
    n : int
        Number of vertices (>= 0); a vertex in no edge is a component of its own.

    Returns
    -------
    (n,) int64 ndarray
        Component of every vertex, ``0..C-1``, numbered by their lowest vertex: vertex 0's component
        is 0, the component of the lowest vertex not in it 1, and so on (the labels of
        ``scipy.sparse.csgraph.connected_components``).

    Raises
    ------
    ValueError
        Naming ``edges`` or ``n``.
    """
    from scipy.sparse.csgraph import connected_components

    n = _vertex_count(n)
    e = np.asarray(edges)
    if e.size == 0:  # any empty input, an empty list too (a float array)
        e = np.zeros((0, 2), np.int64)
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
        raise ValueError(f"edges must be an integer array of shape (E, 2), got {e.shape} {e.dtype}")
    if e.size and (e.min() < 0 or e.max() >= n):
        raise ValueError(f"edges index vertices outside 0..{n - 1}")
    if n == 0:
        return np.zeros(0, np.int64)
    graph = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def mesh_components(faces, n) -> np.ndarray:
    """Connected component of every vertex of a triangle mesh: vertices joined by a face's edges.

    Parameters
    ----------
    faces : (F, 3) int array-like
        Triangles indexing ``0..n-1``.
    n : int
        Number of vertices (>= 0); a vertex in no face is a component of its own.

    Returns
    -------
    (n,) int64 ndarray
        Component of every vertex, numbered by their lowest vertex (:func:`edge_components`).

    Raises
    ------
    ValueError
        Naming ``faces`` or ``n``.
    """
    f = np.asarray(faces)
    if f.size == 0:
        f = np.zeros((0, 3), np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.shape} {f.dtype}")
    n = _vertex_count(n)
    if f.size and (f.min() < 0 or f.max() >= n):
        raise ValueError(f"faces index vertices outside 0..{n - 1}")
    return edge_components(np.stack([f.ravel(), np.roll(f, 1, axis=1).ravel()], axis=1), n)
