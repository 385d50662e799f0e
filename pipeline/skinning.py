"""Skinning weights by bone heat diffusion (Baran & Popović 2007, "Pinocchio").

Tzionas & Gall 2016 (section 4.2) rig their watertight meshes this way: every
bone ``i`` gets a weight field ``w_i`` on the surface that solves the
screened heat equation

    (-Δ + H) w_i = H p_i

where ``Δ`` is the cotangent Laplace-Beltrami operator, ``H`` is diagonal with
``H_jj = c / d_j**2`` (``d_j``: distance from vertex ``j`` to its nearest
bone) and ``p_i`` is 1 where bone ``i`` is the nearest bone of a vertex, else 0
(shared equally among ties). With the lumped mass matrix ``M`` (barycentric vertex areas,
:func:`pipeline.geodesic.vertex_areas`) and the
stiffness matrix ``L`` (``Δ = -M^-1 L``) the system reads
``(L + M H) w_i = M H p_i``: one sparse factorisation, one solve per bone.

Pinocchio only lets a bone heat a vertex that "sees" it through the inside of
the mesh; this module uses the plain nearest bone (no visibility test), which
is right for limbs that are apart and what a spine's bones (which run inside
the limbs) give on the creatures we film.

Functions here are pure: arrays in, arrays out.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pipeline.geodesic import validate_mesh, vertex_areas

__all__ = [
    "cotangent_laplacian",
    "segment_distances",
    "bone_heat_weights",
    "limit_influences",
    "SkinningError",
]

log = logging.getLogger(__name__)


class SkinningError(ValueError):
    """A valid input that yields no weights (degenerate mesh, no bones)."""


def cotangent_laplacian(vertices, faces) -> sp.csr_matrix:
    """Cotangent stiffness matrix ``L`` (positive semi-definite, rows sum to 0).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray

    Returns
    -------
    (V, V) scipy.sparse.csr_matrix
        ``L_ij = -(cot a_ij + cot b_ij) / 2`` for an edge, ``L_ii = -sum_j L_ij``.
        Cotangents are clamped to ``[-1e3, 1e3]`` (slivers from marching cubes).
    """
    v, f = validate_mesh(vertices, faces)
    n = len(v)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        a = v[i] - v[o]
        b = v[j] - v[o]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        dot = (a * b).sum(1)
        cot = np.clip(dot / np.maximum(cross, 1e-300), -1e3, 1e3)
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    W.sum_duplicates()
    d = -np.asarray(W.sum(axis=1)).ravel()
    return (W + sp.diags(d)).tocsr()


def segment_distances(points, seg_a, seg_b, *, chunk: int = 16384) -> np.ndarray:
    """Euclidean distance from every point to every segment.

    Parameters
    ----------
    points : (N, 3) float ndarray
    seg_a, seg_b : (B, 3) float ndarray
        Segment end points.

    Returns
    -------
    (N, B) float ndarray
    """
    P = np.asarray(points, dtype=np.float64)
    A = np.asarray(seg_a, dtype=np.float64)
    Bp = np.asarray(seg_b, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {P.shape}")
    if A.ndim != 2 or A.shape[1] != 3 or A.shape != Bp.shape:
        raise ValueError("seg_a and seg_b must both have shape (B, 3)")
    ab = Bp - A
    l2 = np.maximum((ab * ab).sum(1), 1e-300)
    out = np.empty((len(P), len(A)))
    for s in range(0, len(P), chunk):
        ap = P[s : s + chunk, None, :] - A[None]
        t = np.clip((ap * ab[None]).sum(-1) / l2[None], 0.0, 1.0)
        d = ap - t[..., None] * ab[None]
        out[s : s + chunk] = np.sqrt((d * d).sum(-1))
    return out


def limit_influences(weights, *, max_influences: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Keep the largest ``max_influences`` weights per vertex, renormalised.

    Parameters
    ----------
    weights : (V, B) float ndarray
        Non-negative; every row must have a positive entry.
    max_influences : int

    Returns
    -------
    joints : (V, k) int ndarray
        Column ids, by decreasing weight (``k = min(max_influences, B)``).
    w : (V, k) float ndarray
        Their weights; rows sum to 1.
    """
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2 or W.shape[1] == 0:
        raise ValueError(f"weights must have shape (V, B) with B > 0, got {W.shape}")
    if int(max_influences) < 1:
        raise ValueError(f"max_influences must be >= 1, got {max_influences}")
    k = min(int(max_influences), W.shape[1])
    W = np.clip(W, 0.0, None)
    idx = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, idx, axis=1)
    s = w.sum(1, keepdims=True)
    if np.any(s <= 0):
        raise SkinningError("some vertices have no positive weight")
    return idx.astype(np.int64), w / s


def bone_heat_weights(
    vertices,
    faces,
    seg_a,
    seg_b,
    *,
    heat: float = 1.0,
    tie_tolerance: float = 1e-3,
    min_distance: float | None = None,
) -> np.ndarray:
    """Bone heat skinning weights of every vertex for every bone (Baran & Popović 2007).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
        A triangle mesh (closed meshes give the best weights).
    seg_a, seg_b : (B, 3) float ndarray
        Bones as segments.
    heat : float
        The constant ``c`` of ``H_jj = c / d_j**2`` (Pinocchio: 1).
    tie_tolerance : float
        Bones within ``(1 + tie_tolerance) * d_j`` of a vertex share its
        ``p_i`` equally.
    min_distance : float, optional
        Lower bound of ``d_j`` (default: 1e-3 x the mesh's bounding-box
        diagonal), so that a bone touching the surface does not blow up ``H``.

    Returns
    -------
    (V, B) float ndarray
        Weights in ``[0, 1]``; rows sum to 1.

    Raises
    ------
    SkinningError
        When the mesh has no area.
    """
    v, f = validate_mesh(vertices, faces)
    A = np.asarray(seg_a, dtype=np.float64)
    Bp = np.asarray(seg_b, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or len(A) == 0:
        raise ValueError(f"seg_a must have shape (B, 3) with B > 0, got {A.shape}")
    if Bp.shape != A.shape:
        raise ValueError(f"seg_b must have the shape of seg_a {A.shape}, got {Bp.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(Bp))):
        raise ValueError("seg_a and seg_b must be finite")
    if not (heat > 0 and np.isfinite(heat)):
        raise ValueError(f"heat must be > 0, got {heat}")
    if not tie_tolerance >= 0:
        raise ValueError(f"tie_tolerance must be >= 0, got {tie_tolerance}")
    m = vertex_areas(v, f)
    if m.sum() <= 0:
        raise SkinningError("mesh has no surface area")
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    dmin = 1e-3 * diag if min_distance is None else float(min_distance)
    if not dmin > 0:
        raise ValueError(f"min_distance must be > 0, got {min_distance}")
    D = segment_distances(v, A, Bp)
    d = np.maximum(D.min(1), dmin)
    P = (D <= d[:, None] * (1.0 + tie_tolerance)).astype(np.float64)
    P /= P.sum(1, keepdims=True)
    # vertices that belong to no triangle get a tiny mass so the system stays regular
    m = np.where(m > 0, m, m[m > 0].min())
    h = m * heat / d**2
    L = cotangent_laplacian(v, f)
    S = (L + sp.diags(h)).tocsc()
    solve = spla.factorized(S)
    rhs = h[:, None] * P
    W = np.empty_like(P)
    for i in range(P.shape[1]):
        W[:, i] = solve(rhs[:, i]) if rhs[:, i].any() else 0.0
    W = np.clip(W, 0.0, 1.0)
    s = W.sum(1, keepdims=True)
    bad = s[:, 0] <= 1e-12
    if np.any(bad):  # fall back to the nearest bone
        W[bad] = P[bad]
        s[bad] = 1.0
    return W / s
