"""Rigid patches of a tracked template: their motions, the previous frame's shape and the prediction.

The template tracker (:mod:`pipeline.tracking`, Tzionas & Gall 2016, section 3.2) cuts the template
into patches and works with their rigid motions where the paper works with single vertices (the
reasons: :mod:`pipeline.tracking`'s docstring and docs/tracking.md, "Where the tracker departs from
the paper"):

* :func:`surface_patches`, :func:`farthest_seeds`: patches of about a given size, seeded by
  farthest-point sampling on the surface, never across two connected parts (nor, given the
  template's limb/body labels, across two of them: the body one patch);
* :func:`patch_rigid_motion`: each patch's rigid motion onto its pairs (point-to-plane), only in the
  directions the pairs constrain;
* :func:`patch_align`, :func:`blended_patches`, :func:`blended_align`: the previous frame's shape
  placed patch by patch onto the round's start (overlapping, smoothly weighted patches: no free
  hinge at a patch boundary);
* :func:`patch_constraints`, :func:`predict_motion`: the next frame's start, every patch repeating
  the motion of the two frames before along the directions the data constrained.

The underscored variants take the summing matrices and smoother that
:class:`pipeline.tracking.TemplateTracker` builds once per take (the same sums, bit for bit); they
are the tracker's fast paths, not an API. Hand-written: no maintained package offers patch-wise
constrained point-to-plane motion; the sums are numpy/scipy. Farthest-point sampling is a dozen
lines here because the packages that offer it sample a given number of points, where the patches
need a covering radius, and break ties by rounding, where the patches must not change when the
template is moved.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from pipeline.mesh_primitives import check_mesh, check_points, mesh_components
from pipeline.mesh_primitives import scatter_add as _scatter_add
from pipeline.mesh_primitives import sum_by as _sum_by
from pipeline.mesh_primitives import summing_matrix as _summing

__all__ = [
    "surface_patches",
    "farthest_seeds",
    "grid_seeds",
    "patch_rigid_motion",
    "patch_align",
    "blended_patches",
    "blended_align",
    "patch_constraints",
    "predict_motion",
]


def surface_patches(vertices, faces, size: float, *, labels=None) -> tuple[np.ndarray, np.ndarray]:
    """Patches of about ``size`` across, never spanning two connected components (nor two labels).

    The seeds follow the surface, not a grid of the world: per connected component,
    farthest-point sampling (:func:`farthest_seeds`) from the vertex farthest from the component's
    centroid, until every vertex is within ``SEED_RADIUS * size`` of a seed; every vertex joins
    its nearest seed (the earlier seed among equally near ones). The patches do not change when
    the template is moved or turned, also where its shape is symmetric: distances equal to within
    rounding count as equal (docs/tracking.md, "Patches that follow the surface").

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    size : float
        Patch diameter, mm.
    labels : (V,) int ndarray, optional
        The template's parts: a limb (``0, 1, ...``) or the body (``-1``) of every vertex.
        No patch spans two parts; the body of each connected component is one rigid patch, and
        every limb is cut on a ``size`` grid of its own, its cells counted from the limb's own
        corner, not seeded on the surface (docs/tracking.md, "Patches that follow the surface",
        says why).

    Returns
    -------
    patch : (V,) int ndarray
        Patch of every vertex (numbered by component, then seed order; with labels, by component
        and part, a limb's seeds one per cell, every vertex with its part's nearest seed).
    component : (n_patches,) int ndarray
        Connected component of every patch.
    """
    v, f = check_mesh(vertices, faces)
    if isinstance(size, bool) or not (isinstance(size, (int, float, np.integer, np.floating)) and math.isfinite(size)
                                      and size > 0):
        raise ValueError(f"size must be a positive number (mm), got {size!r}")
    n = len(v)
    comp = mesh_components(f, n)
    if labels is not None:
        return _labelled_patches(v, comp, _check_labels(labels, n), size)
    patch = np.empty(n, np.int64)
    component = []
    radius = SEED_RADIUS * float(size)
    for c in range(int(comp.max()) + 1 if n else 0):
        mine = np.flatnonzero(comp == c)
        seeds = mine[farthest_seeds(v[mine], radius)]
        patch[mine] = len(component) + _nearest_seed(v[seeds], v[mine])
        component.extend([c] * len(seeds))
    return patch, np.asarray(component, dtype=np.int64)


SEED_RADIUS = 0.6
"""The seeds' covering radius, in patch sizes: about as many patches as a ``size`` grid's cells hold
(docs/tracking.md, "Patches that follow the surface", says how it was chosen)."""

_TIE = 1e-9
"""Relative difference under which two distances count as equal (rounding, not shape)."""


def _first_max(d: np.ndarray) -> int:
    """Index of the largest value, the lowest index among values equal to it within rounding."""
    return int(np.flatnonzero(d >= d.max() * (1.0 - _TIE))[0])


def _nearest_seed(seeds: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Every point's nearest seed (index into ``seeds``), the earlier seed among equally near ones."""
    if len(seeds) == 1:
        return np.zeros(len(points), np.int64)
    d, i = cKDTree(seeds).query(points, k=min(8, len(seeds)))  # a vertex equally near more (a cap's centre)
    tie = d <= d[:, :1] * (1.0 + _TIE) + 1e-12
    return np.where(tie, i, len(seeds)).min(1).astype(np.int64)


def farthest_seeds(points, radius: float) -> np.ndarray:
    """Farthest-point sampling: indices of seeds such that every point is within ``radius`` of one.

    The first seed is the point farthest from the points' centroid; each next one the point
    farthest from all seeds so far, until none is further than ``radius``; among points equally
    far (within rounding), the lowest index. The seeds depend on the points' shape only, not on
    where they lie or how they are turned, and are at least ``radius`` apart.

    Parameters
    ----------
    points : (N >= 1, 3) float ndarray
    radius : float
        Covering radius (> 0), in the points' unit.

    Returns
    -------
    (S,) int ndarray
        Seed indices into ``points``, in the order chosen.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 1:
        raise ValueError(f"points must have shape (N >= 1, 3), got {p.shape}")
    if isinstance(radius, bool) or not (isinstance(radius, (int, float, np.integer, np.floating))
                                        and math.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive number, got {radius!r}")
    seeds = [_first_max(np.linalg.norm(p - p.mean(0), axis=1))]
    d = np.linalg.norm(p - p[seeds[0]], axis=1)
    while d.max() > radius:
        seeds.append(_first_max(d))
        d = np.minimum(d, np.linalg.norm(p - p[seeds[-1]], axis=1))
    return np.asarray(seeds, dtype=np.int64)


def _check_labels(labels, n: int, name: str = "labels") -> np.ndarray:
    """``labels`` as (n,) int64 (-1 the body, 0.. a limb), or a ValueError naming ``name``."""
    lab = np.asarray(labels)
    if lab.shape != (n,) or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"{name} must give one integer per template vertex (-1 the body, 0, 1, ... a limb), "
                         f"shape ({n},), got shape {lab.shape} of {lab.dtype}")
    if n and lab.min() < -1:
        raise ValueError(f"{name} must give one integer per template vertex (-1 the body, 0, 1, ... a limb), "
                         f"got {int(lab.min())}")
    return lab.astype(np.int64)


def _labelled_patches(v: np.ndarray, comp: np.ndarray, lab: np.ndarray, size: float):
    """:func:`surface_patches` with labels: per (component, part), the body one patch, a limb cut on its own grid."""
    _, group = np.unique(np.stack([comp, lab], 1), axis=0, return_inverse=True)
    group = group.ravel()
    patch = np.empty(len(v), np.int64)
    component = []
    for g in range(int(group.max()) + 1 if len(v) else 0):
        mine = np.flatnonzero(group == g)
        if lab[mine[0]] < 0:  # the body: rigid as a whole
            patch[mine] = len(component)
            component.append(comp[mine[0]])
            continue
        seeds, nearest = grid_seeds(v[mine], size)
        patch[mine] = len(component) + nearest
        component.extend([comp[mine[0]]] * len(seeds))
    return patch, np.asarray(component, dtype=np.int64)


def grid_seeds(points, size: float, *, offset: float = 0.0, corner=None) -> tuple[np.ndarray, np.ndarray]:
    """The grid rule of a limb's patches (``--labels``): one seed per cell of a world grid.

    Cells of ``size`` are counted from ``corner`` (default: the points' lowest corner), moved by ``offset``
    cells along every axis; the first point in each cell is a seed, and every point joins its nearest seed.
    Unlike :func:`farthest_seeds`, the seeds depend on where the points lie.

    Parameters
    ----------
    points : (N >= 1, 3) float ndarray
    size : float
        The cells' edge (> 0), in the points' unit.
    offset : float
        The grid's shift, in cells (finite).
    corner : (3,) float array-like, optional
        Where the cells are counted from.

    Returns
    -------
    seeds : (S,) int ndarray
        Indices into ``points``, ascending.
    nearest : (N,) int ndarray
        Every point's nearest seed, an index into ``seeds``.
    """
    p = check_points(points, min_points=1)
    for name, value, low in (("size", size, 0.0), ("offset", offset, None)):
        if isinstance(value, bool) or not (isinstance(value, (int, float, np.integer, np.floating))
                                           and math.isfinite(value) and (low is None or value > low)):
            raise ValueError(f"{name} must be a {'positive' if low is not None else 'finite'} number, got {value!r}")
    lo = p.min(0) if corner is None else np.asarray(corner, dtype=np.float64)
    if lo.shape != (3,) or not np.all(np.isfinite(lo)):
        raise ValueError(f"corner must be a finite point (3,), got {corner!r}")
    cell = np.floor((p - lo + offset * size) / size).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    seeds = np.sort(first)
    return seeds, cKDTree(p[seeds]).query(p)[1]


def patch_rigid_motion(V, pv, px, pn, patches, *, fallback, component=None, min_pairs: int = 12,
                       damping: float = 1e-6, cutoff: float = 1e-2) -> np.ndarray:
    """Every vertex moved by its patch's rigid motion onto the pairs (point-to-plane, one step).

    Per patch, the small rigid motion ``(omega, t)`` minimising
    ``sum (n_k . (a_k + omega x a_k + t - x_k))^2`` over the patch's pairs (vertex ``a_k``, data
    point ``x_k`` with normal ``n_k``; Chen & Medioni's linearised point-to-plane ICP), about
    the patch centroid, restricted to the motions the pairs constrain: with the rotation
    scaled by the patch's radius, eigen-directions of the 6x6 normal matrix weaker than
    ``cutoff`` times its strongest get none (a cylindrical patch's twist about its own axis,
    which point-to-plane pairs cannot see: left free, noise twisted thin parts by up to 15
    degrees a frame on the simulated pipe). Patches with fewer than ``min_pairs`` pairs take the motion of the
    nearest patch of the same connected component (``component``, per patch) that has enough;
    vertices of components without any such patch keep ``fallback``.

    Returns
    -------
    (V, 3) float ndarray
    """
    return _patch_rigid_motion(V, pv, px, pn, patches, _summing(patches, int(patches.max()) + 1), fallback=fallback,
                               component=component, min_pairs=min_pairs, damping=damping, cutoff=cutoff)


_UPPER6 = np.triu_indices(6)


def _pair_normal_matrices(lab, J, r, a, n_p):
    """Per patch, ``J^T J`` (6, 6), ``J^T r`` (6,) and the pairs' ``sum |a|^2``: the 21 distinct products of
    ``J^T J`` (the matrix is symmetric) and the rest summed in one sparse product (:func:`_summing`)."""
    iu, ju = _UPPER6
    sums = _sum_by(_summing(lab, n_p), np.concatenate([J[:, iu] * J[:, ju], J * r[:, None], (a ** 2).sum(1)[:, None]], 1))
    JtJ = np.empty((n_p, 6, 6))
    JtJ[:, iu, ju] = sums[:, :21]
    JtJ[:, ju, iu] = sums[:, :21]
    return JtJ, sums[:, 21:27], sums[:, 27]


def _patch_rigid_motion(V, pv, px, pn, patches, patch_sum, *, fallback, component=None, min_pairs: int = 12,
                        damping: float = 1e-6, cutoff: float = 1e-2):
    """:func:`patch_rigid_motion` with the patches' summing matrix (``_summing(patches, n_patches)``) given."""
    n_p = patch_sum.shape[0]
    comp = np.zeros(n_p, np.int64) if component is None else np.asarray(component)
    lab = patches[pv]
    cnt = np.bincount(lab, minlength=n_p)
    ok = cnt >= min_pairs
    if not ok.any():
        return np.asarray(fallback, dtype=np.float64).copy()
    sizes = np.maximum(np.bincount(patches, minlength=n_p), 1)
    cen = _sum_by(patch_sum, V) / sizes[:, None]
    a = V[pv] - cen[lab]
    J = np.concatenate([np.cross(a, pn), pn], axis=1)  # (P, 6)
    r = np.einsum("ij,ij->i", px - V[pv], pn)
    JtJ, Jtr, spread = _pair_normal_matrices(lab, J, r, a, n_p)
    x = _truncated_solve(JtJ[ok], Jtr[ok], spread[ok] / cnt[ok], damping, cutoff)
    sol = np.zeros((n_p, 6))
    sol[ok] = x
    still = np.zeros(n_p, bool)
    for c in np.unique(comp[~ok]):  # patches without enough pairs move like the nearest one that has them
        dst = np.flatnonzero(~ok & (comp == c))
        src = np.flatnonzero(ok & (comp == c))
        if len(src) == 0:
            still[dst] = True
            continue
        sol[dst] = sol[src[cKDTree(cen[src]).query(cen[dst])[1]]]
    w, t = sol[:, :3], sol[:, 3:]
    theta = np.linalg.norm(w, axis=1)
    k = w / np.maximum(theta, 1e-12)[:, None]
    K = np.zeros((n_p, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    R = np.eye(3) + np.sin(theta)[:, None, None] * K + (1 - np.cos(theta))[:, None, None] * (K @ K)
    A = V - cen[patches]
    out = np.einsum("vij,vj->vi", R[patches], A) + cen[patches] + t[patches]
    keep = still[patches]
    out[keep] = np.asarray(fallback, dtype=np.float64)[keep]
    return out


def patch_align(source, target, patches) -> np.ndarray:
    """``source`` moved patch by patch by the rigid motion that best maps it onto ``target`` (Kabsch).

    Parameters
    ----------
    source, target : (V, 3) float ndarray
    patches : (V,) int ndarray

    Returns
    -------
    (V, 3) float ndarray
        Every patch of ``source`` keeps its shape and takes ``target``'s place.
    """
    S = np.asarray(source, dtype=np.float64)
    T = np.asarray(target, dtype=np.float64)
    return _patch_align(S, T, patches, _summing(patches, int(patches.max()) + 1))


def _patch_align(S, T, patches, patch_sum) -> np.ndarray:
    """:func:`patch_align` with the patches' summing matrix (``_summing(patches, n_patches)``) given."""
    n_p = patch_sum.shape[0]
    cnt = np.maximum(np.bincount(patches, minlength=n_p), 1)[:, None]
    cs = _sum_by(patch_sum, S) / cnt
    ct = _sum_by(patch_sum, T) / cnt
    a, b = S - cs[patches], T - ct[patches]
    H = _sum_by(patch_sum, a[:, :, None] * b[:, None, :])  # (n_p, 3, 3)
    U, _, Wt = np.linalg.svd(H)
    D = np.ones((n_p, 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("pij,pjk->pik", U, Wt)))
    R = np.einsum("pji,pj,pkj->pik", Wt, D, U)  # R = W diag(D) U^T maps a onto b
    return np.einsum("vij,vj->vi", R[patches], a) + ct[patches]


def blended_patches(vertices, faces, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping patches with smooth weights: every vertex belongs to several, no boundary is shared by all.

    The patches of :func:`surface_patches` (``size`` across), each grown to the vertices of
    its connected component within ``r = R + size / 2`` of its centroid (``R``: its farthest
    own vertex), weighted ``(1 - (d / r)^2)^2``: across every boundary of the partition
    (edges shorter than ``size / 2``) both vertices are in both patches.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        The surface the patches cover (the template at rest), mm.
    faces : (F, 3) int ndarray
        Its triangles (they give the connected components no patch spans).
    size : float
        Diameter of the patches before they are grown, mm (> 0).

    Returns
    -------
    patch, vertex : (K,) int ndarray
        The (patch, vertex) pairs covered; patches are numbered ``0 .. n_patches - 1`` as in
        :func:`surface_patches`, every vertex is covered at least by its own.
    weight : (K,) float ndarray
        Their weights, summing to 1 over each vertex's patches.

    Notes
    -----
    The support of the previous-shape prior of :class:`pipeline.tracking.TemplateTracker` (``prior="previous"``).
    Tzionas & Gall 2016 (§3) compensate the under-constrained single-view data terms by the
    smoothness term towards the previous frame alone (eq. 4); the rigid patches of this prior
    are the project's addition (see the module docstring).
    """
    v, f = check_mesh(vertices, faces, min_vertices=4, min_faces=1)
    if isinstance(size, bool) or not (isinstance(size, (int, float, np.integer, np.floating)) and math.isfinite(size) and size > 0):
        raise ValueError(f"size must be a positive number (mm), got {size!r}")
    return _blended_patches(v, f, float(size))


def _blended_patches(v, f, size):
    """:func:`blended_patches` on checked input."""
    part, comp_p = surface_patches(v, f, size)
    n_p = int(part.max()) + 1
    cnt = np.maximum(np.bincount(part, minlength=n_p), 1)[:, None]
    centre = _scatter_add(part, v, n_p) / cnt
    comp_v = comp_p[part]
    own = np.linalg.norm(v - centre[part], axis=1)
    radius = np.array([own[part == p].max() for p in range(n_p)]) + 0.5 * float(size)
    pp, vv = [], []
    tree = cKDTree(v)
    for p in range(n_p):
        near = np.asarray(tree.query_ball_point(centre[p], r=radius[p]), dtype=np.int64)
        near = np.union1d(near[comp_v[near] == comp_p[p]], np.flatnonzero(part == p))
        pp.append(np.full(len(near), p)), vv.append(near)
    pp, vv = np.concatenate(pp), np.concatenate(vv)
    d = np.linalg.norm(v[vv] - centre[pp], axis=1) / radius[pp]
    w = np.clip(1.0 - d * d, 0.0, None) ** 2
    w = np.where(part[vv] == pp, np.maximum(w, 1e-3), w)
    w /= np.bincount(vv, weights=w, minlength=len(v))[vv]
    return pp, vv, w


def blended_align(source, target, cover) -> np.ndarray:
    """``source`` placed onto ``target`` by overlapping rigid patches, blended (weighted Kabsch per patch).

    Like :func:`patch_align`, but with the patches of :func:`blended_patches`: a vertex takes
    the weighted mean of the placements of the patches covering it, so no patch boundary is
    a free hinge of the placed shape.

    Parameters
    ----------
    source : (V, 3) float ndarray
        The shape to keep (the previous frame's vertices), mm.
    target : (V, 3) float ndarray
        Where it goes (the round's start), mm; same vertex order as ``source``.
    cover : ((K,) int, (K,) int, (K,) float) ndarrays
        ``(patch, vertex, weight)`` of :func:`blended_patches` on a surface of ``V`` vertices:
        vertex indices in ``0 .. V - 1``, weights finite and >= 0.

    Returns
    -------
    (V, 3) float ndarray
        Every vertex at ``sum_p w_p (R_p (s - c_p) + d_p)`` over the patches ``p`` covering it,
        ``(R_p, c_p, d_p)`` the rotation and the weighted centroids of ``source`` and ``target``
        of the weighted Kabsch fit of patch ``p``: ``target`` itself wherever it is a rigid
        motion of ``source`` over every patch covering the vertex.

    Notes
    -----
    The previous-shape prior of :class:`pipeline.tracking.TemplateTracker` (``prior="previous"``, ``blend=True``):
    it keeps what Tzionas & Gall 2016 (§3, eq. 4) keep through the Laplacian only, the previous
    frame's shape, rigidly per patch (see the module docstring).
    """
    S = np.asarray(source, dtype=np.float64)
    T = np.asarray(target, dtype=np.float64)
    if S.ndim != 2 or S.shape[1] != 3 or S.shape[0] < 1:
        raise ValueError(f"source must have shape (V >= 1, 3), got {S.shape}")
    if T.shape != S.shape:
        raise ValueError(f"target must have the shape of source {S.shape}, got {T.shape}")
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(T))):
        raise ValueError("source and target must be finite")
    return _blended_align(S, T, _check_cover(cover, len(S)))


def _check_cover(cover, n: int):
    """``cover`` (:func:`blended_patches`) as (int64, int64, float64) arrays, checked against ``n`` vertices."""
    if not (isinstance(cover, (tuple, list)) and len(cover) == 3):
        raise ValueError("cover must be the (patch, vertex, weight) arrays of blended_patches")
    pp, vv, w = (np.asarray(c) for c in cover)
    if pp.ndim != 1 or len(pp) < 1 or vv.shape != pp.shape or w.shape != pp.shape:
        raise ValueError(f"cover's patch, vertex and weight must have one shape (K >= 1,), got {pp.shape}, {vv.shape}, {w.shape}")
    if not (np.issubdtype(pp.dtype, np.integer) and np.issubdtype(vv.dtype, np.integer)):
        raise ValueError(f"cover's patch and vertex must be integer arrays, got {pp.dtype} and {vv.dtype}")
    if pp.min() < 0:
        raise ValueError("cover's patch indices must be >= 0")
    if vv.min() < 0 or vv.max() >= n:
        raise ValueError(f"cover's vertex indices must be in 0 .. {n - 1} (source has {n} vertices)")
    w = w.astype(np.float64)
    if not (np.all(np.isfinite(w)) and w.min() >= 0):
        raise ValueError("cover's weights must be finite and >= 0")
    return pp.astype(np.int64), vv.astype(np.int64), w


def _cover_sums(cover, n: int):
    """What :func:`_blended_align` sums over a fixed ``cover`` of ``n`` vertices, built once per
    take: the summing matrices of its patches and of its vertices (:func:`_summing`, the same
    sums as ``bincount``'s, bit for bit) and every patch's total weight."""
    pp, vv, w = cover
    n_p = int(pp.max()) + 1
    sw = np.maximum(np.bincount(pp, weights=w, minlength=n_p), 1e-300)[:, None]
    return _summing(pp, n_p), _summing(vv, n), sw


def _blended_align(S, T, cover, sums=None) -> np.ndarray:
    """:func:`blended_align` on checked input; ``sums``: :func:`_cover_sums` of ``cover`` (default: built here)."""
    pp, vv, w = cover
    by_patch, by_vertex, sw = _cover_sums(cover, len(S)) if sums is None else sums
    n_p = by_patch.shape[0]
    cs = _sum_by(by_patch, w[:, None] * S[vv]) / sw
    ct = _sum_by(by_patch, w[:, None] * T[vv]) / sw
    a = S[vv] - cs[pp]
    H = _sum_by(by_patch, (w[:, None] * a)[:, :, None] * (T[vv] - ct[pp])[:, None, :])
    U, _, Wt = np.linalg.svd(H)
    D = np.ones((n_p, 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("pij,pjk->pik", U, Wt)))
    R = np.einsum("pji,pj,pkj->pik", Wt, D, U)
    placed = np.einsum("kij,kj->ki", R[pp], a) + ct[pp]
    return _sum_by(by_vertex, w[:, None] * placed)


def _truncated_solve(JtJ, Jtr, spread, damping, cutoff):
    """Per patch, the 6-vector minimising ``|J x - r|`` restricted to the directions the pairs
    constrain: rotations are scaled by the patch's radius (so all six are in mm), and
    eigen-directions of ``J^T J`` weaker than ``cutoff`` of the strongest get no motion (a
    cylinder's twist about its own axis, a plane's sliding, which point-to-plane pairs do not see)."""
    r = np.sqrt(np.maximum(spread, 1e-12))
    S = np.concatenate([1.0 / r[:, None] * np.ones((1, 3)), np.ones((len(r), 3))], axis=1)  # x = S * y
    A = JtJ * S[:, :, None] * S[:, None, :]
    b = Jtr * S
    w, U = np.linalg.eigh(A)
    keep = w >= np.maximum(cutoff * w[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.maximum(w + damping * w[:, -1:], 1e-300), 0.0)
    y = np.einsum("pij,pj,pkj,pk->pi", U, inv, U, b)
    return y * S


def _umbrella(faces, n):
    f = np.asarray(faces, dtype=np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    A = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    A.data[:] = 1.0
    A = A + sp.eye(n, format="csr")
    return sp.diags(1.0 / np.asarray(A.sum(1)).ravel()) @ A


def patch_constraints(V, pv, pn, patches, *, min_pairs: int = 12, cutoff: float = 1e-2) -> np.ndarray:
    """Per patch, the projector onto the rigid motions its point-to-plane pairs constrain.

    The same directions :func:`patch_rigid_motion` solves in: eigen-directions of the patch's
    6x6 point-to-plane normal matrix (rotations scaled by the patch's radius, about its
    centroid) no weaker than ``cutoff`` of the strongest. Patches with fewer than
    ``min_pairs`` pairs constrain nothing (a zero projector).

    Returns
    -------
    (n_patches, 6, 6) float ndarray
        Per patch, the (oblique) projector ``Q`` of a small motion ``(omega, t)`` about the
        patch's centroid onto those directions: ``Q @ (omega, t)``.
    """
    n_p = int(patches.max()) + 1
    lab = patches[pv]
    cnt = np.bincount(lab, minlength=n_p)
    sizes = np.maximum(np.bincount(patches, minlength=n_p), 1)
    cen = _scatter_add(patches, V, n_p) / sizes[:, None]
    a = V[pv] - cen[lab]
    J = np.concatenate([np.cross(a, pn), pn], axis=1)
    r = np.sqrt(np.maximum(_scatter_add(lab, (a ** 2).sum(1), n_p) / np.maximum(cnt, 1), 1e-12))
    S = np.concatenate([1.0 / r[:, None] * np.ones((1, 3)), np.ones((n_p, 3))], axis=1)
    A = _scatter_add(lab, J[:, :, None] * J[:, None, :], n_p) * S[:, :, None] * S[:, None, :]
    w, U = np.linalg.eigh(A)
    keep = (w >= np.maximum(cutoff * w[:, -1:], 1e-300)) & (cnt >= min_pairs)[:, None]
    Q = np.einsum("pij,pj,pkj->pik", U, keep.astype(float), U)  # in y = x / S
    return S[:, :, None] * Q / S[:, None, :]


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _rodrigues(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def _shape_of(a) -> str:
    """How an argument that should be a sparse matrix is described in an error."""
    kind = "sparse" if sp.issparse(a) else type(a).__name__
    return f"{kind} {getattr(a, 'shape', '')}".strip()


def predict_motion(previous, before, faces, patches, *, constrained=None, smoothing: int = 10, smoother=None,
                   patch_sum=None) -> np.ndarray:
    """Constant-velocity prediction of the next frame from the two tracked frames before it.

    Every patch repeats the rigid motion that took it from ``before`` to ``previous``
    (Kabsch per patch), restricted to the motions the data constrained on the previous
    frame (``constrained``, :func:`patch_constraints`): along directions the data cannot
    see (a cylinder sliding along or twisting about its own axis) a tracking error would be
    repeated and grow, frame after frame, with nothing to correct it. The per-vertex
    displacements are then averaged over ``smoothing`` rings of neighbours, so patch
    borders do not tear.

    Parameters
    ----------
    previous, before : (V, 3) float ndarray
        The template on the two frames before (``previous`` the nearer).
    faces : (F, 3) int ndarray
    patches : (V,) int ndarray
    constrained : (n_patches, 6, 6) float ndarray, optional
        Default: every motion (plain constant velocity per patch).
    smoothing : int
    smoother : (V, V) sparse matrix, optional
        One ring of the averaging (each vertex and its neighbours on ``faces``, equal
        weights): :attr:`pipeline.tracking.TemplateTracker.smoother`, built once per take. Default: built here.
    patch_sum : (n_patches, V) sparse matrix, optional
        The summing matrix of ``patches`` (:attr:`pipeline.tracking.TemplateTracker.patch_sum`, the same sums
        bit for bit). Default: sums by ``bincount``.

    Returns
    -------
    (V, 3) float ndarray
    """
    P = np.asarray(previous, float)
    B = np.asarray(before, float)
    n = len(P)
    n_p = int(patches.max()) + 1
    if smoother is None:
        smoother = _umbrella(faces, n)
    elif not sp.issparse(smoother) or smoother.shape != (n, n):
        raise ValueError(f"smoother must be a sparse matrix of shape {(n, n)}, got {_shape_of(smoother)}")
    if patch_sum is not None and (not sp.issparse(patch_sum) or patch_sum.shape != (n_p, n)):
        raise ValueError(f"patch_sum must be a sparse matrix of shape {(n_p, n)}, got {_shape_of(patch_sum)}")

    def by_patch(values):
        return _scatter_add(patches, values, n_p) if patch_sum is None else _sum_by(patch_sum, values)

    cnt = np.maximum(np.bincount(patches, minlength=n_p), 1)[:, None]
    cb = by_patch(B) / cnt
    cp = by_patch(P) / cnt
    a, b = B - cb[patches], P - cp[patches]
    H = by_patch(a[:, :, None] * b[:, None, :])
    U, _, Wt = np.linalg.svd(H)
    D = np.ones((n_p, 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("pij,pjk->pik", U, Wt)))
    R = np.einsum("pji,pj,pkj->pik", Wt, D, U)  # before -> previous, about the centroids
    omega = _rotvec(R)
    t = cp - cb  # the centroid's step; repeated about the previous centroid
    if constrained is not None:
        x = np.einsum("pij,pj->pi", np.asarray(constrained, float), np.concatenate([omega, t], axis=1))
        omega, t = x[:, :3], x[:, 3:]
    Rn = _rodrigues(omega)
    moved = np.einsum("vij,vj->vi", Rn[patches], b) + cp[patches] + t[patches]
    step = moved - P
    for _ in range(int(smoothing)):
        step = smoother @ step
    return P + step
