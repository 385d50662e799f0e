"""Mesh primitives the tracker, the motion segmentation, the exporter and the simulator share:
vertex normals, enclosed volume, and the sparse sums over a mesh's face corners behind them.

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

__all__ = ["summing_matrix", "sum_by", "vertex_normals", "mesh_volume"]


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


def mesh_volume(vertices, faces) -> float:
    """Enclosed volume (divergence theorem; exact for closed, consistently oriented meshes)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return float(abs(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()) / 6.0)
