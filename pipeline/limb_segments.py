"""Rigid parts of a tracked template cut along its limb axes: every limb a chain of intervals.

A motion segmentation over the surface (Tzionas & Gall 2016, :mod:`pipeline.motion_segmentation`) reads
a tracking's non-rigid noise as bending and cuts it into segments. But a limb is a chain: its rigid parts
are intervals along its axis. :func:`limb_segments` therefore

1. keeps the body (label :data:`pipeline.template_labels.BODY`) one segment;
2. orders every limb's vertices by the arc length of their nearest point on the limb's axis (junction to
   tip, at the template's frame) and puts candidate cuts at ``candidates`` positions evenly along it (a
   candidate interval holds at least :data:`MIN_VERTICES` vertices: a rigid motion needs three points
   off a line);
3. gives an interval the rigid residual of its vertices over the frames (squared distance of every
   vertex from the best rigid motion of the interval's vertices from the template's frame: Kabsch /
   Umeyama from the interval's moment sums, so every one of the ``O(candidates**2)`` intervals costs
   one 3x3 SVD a frame), and finds the best cut into ``k`` intervals for every ``k`` by dynamic
   programming (Bellman 1961, the optimal segmentation of a sequence);
4. keeps a cut only when it lowers the residual by more than the tracking's noise lets one cut of a rigid
   piece lower it: the noise ratio ``rho`` is measured on the body, one rigid part, as the largest
   fraction of its residual that the best single cut along any of its principal axes removes (with the
   same number of candidate positions). A limb keeps cutting while the next cut (or the next two
   together) removes more than ``rho`` (``1 - (1 - rho)**2``) of the remaining residual.

``rho="limb"`` measures the noise on every limb itself instead: its DP's cuts far beyond any limb's joints
(the 7th to the 16th, :data:`LIMB_TAIL`) remove noise alone, and a cut is kept while it removes more than
:data:`LIMB_FACTOR` times their mean fraction. It follows the tracking's noise where the limb is and the
limb's own size (the body's noise is another's when the body is tracked as one patch and the limbs on a
grid); the factor is one of the two (5 and 6) that cut a synthetic chain of 0, 1, 2 and 4 joints (rigid
jitter per patch, noise per vertex) into its parts but once (docs/armature-format.md). Its limit: a limb of
more than six joints (a tail, a tentacle) has real joints among those far cuts and is cut too little; a
limb whose far cuts remove nothing (a noiseless tracking) has noise 0 and keeps every cut.

Given the parts a tracking held rigid (``seams``: the segments of the armature its kept round tracked with,
``tracked/rig_segments.npy``), the candidate cuts keep off where two of them meet along a limb: the round's
skinned pose moves every vertex rigidly with its segment, so the tracked surface is stretched in a band at every
such boundary, and the cut search would slice that band out as a sliver one candidate wide. Every candidate
cut within half a candidate spacing of a seam (the median position of the limb's vertices on the mesh edges
between the two parts) is moved to half a spacing from it, seam by seam: of two seams less than a spacing apart,
a candidate moved off one may end within half a spacing of the other (docs/armature-format.md has the figures).

With ``centres`` a cut is kept only where a joint can be: at a joint the two neighbouring parts' rigid motions carry
one point (the centre of rotation) to the same place in every frame, and that point lies inside the limb, near its
axis at the cut. A cut whose centre of rotation (:func:`pipeline.armature_skeleton.joint_residual` of the rigid
motions of the intervals on its two sides, drawn towards the axis at the cut only where the motions leave it free)
lies farther from the limb's axis, across it, than the limb's radius (the median distance of the limb's vertices
from its axis) by more than twice its uncertainty (the pivot's residual over the relative rotation's second
singular value, as the placement measures it) is dropped, its two intervals merged, the worst such cut first, until
every cut passes: across a sliver or a stretched band the relative motion is a stretch or a shear, and its centre
lies outside the limb (docs/armature-format.md has the figures).

Otherwise no length or count is set for a creature: the cut positions follow the limb's own extent, the
threshold the take's own noise. Written by hand: an interval segmentation of a chain by rigid residual is no
library's (scipy has the SVDs).
"""

from __future__ import annotations

import numpy as np

__all__ = ["LIMB_FACTOR", "LIMB_TAIL", "MIN_VERTICES", "limb_segments", "chain_cuts", "limb_noise", "noise_ratio",
           "seam_positions"]

#: the fewest vertices of a candidate interval
MIN_VERTICES = 4
#: ``rho="limb"``: the cuts (1-based, first and last) whose mean removed fraction is a limb's noise
LIMB_TAIL = (7, 16)
#: ``rho="limb"``: a cut is kept while it removes more than this many times the limb's noise
LIMB_FACTOR = 6.0


def limb_segments(vertices, labels, axes, *, reference: int = 0, candidates: int = 32,
                  rho: float | str | None = None, faces=None, seams=None, centres: bool = False) -> np.ndarray:
    """The rigid part of every template vertex: the body one segment, every limb a chain of intervals.

    Parameters
    ----------
    vertices : (T, V, 3) float array_like
        The tracked template (shared connectivity), T >= 2.
    labels : (V,) int array_like
        Limb of every vertex (index into ``axes``) or -1 for the body
        (:func:`pipeline.template_labels.template_labels`).
    axes : sequence of (n_k, 3) float array_like
        Every limb's axis, a polyline from its junction to its tip, at frame ``reference``.
    reference : int
        The frame of ``axes`` (the template's frame), ``0 .. T-1``.
    candidates : int
        Candidate cut positions along a limb (evenly along the extent of its vertices), >= 2.
    rho : float or "limb", optional
        The fraction of a rigid piece's residual one cut removes by noise alone, in [0, 1). Default:
        measured on the body (:func:`noise_ratio`), which must then hold at least ``2 * MIN_VERTICES``
        vertices. ``"limb"``: measured on every limb itself (:func:`limb_noise`).
    faces : (F, 3) int array_like, optional
        The template's triangles (indices into the V vertices); needed with ``seams``.
    seams : (V,) int array_like, optional
        The parts the tracking moved rigidly (the segments of its armature round): a candidate cut within half a
        candidate spacing of where two of them meet along a limb (:func:`seam_positions`) is moved to half a spacing
        from it, seam by seam (:func:`chain_cuts`' ``avoid``; the module docstring says why).
    centres : bool
        Drop every cut whose two intervals' centre of rotation lies off the limb's axis by more than the limb's
        radius beyond twice its uncertainty, the worst first, merging its intervals (the module docstring says
        how and why).

    Returns
    -------
    (V,) int64 ndarray
        Segment of every vertex: 0 the body (when it has vertices), then every limb's intervals from
        its junction to its tip, limb by limb.

    Raises
    ------
    ValueError
        Naming the parameter: shapes, a label outside ``-1 .. len(axes)-1``, an axis that is not a finite
        polyline, ``reference`` outside the frames, ``candidates < 2``, ``rho`` outside [0, 1), a body
        too small to measure the noise on, ``seams`` not one integer a vertex or without ``faces``, ``faces`` not
        triangles of the vertices, ``centres`` not a bool.
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 3 or V.shape[2] != 3 or V.shape[0] < 2 or V.shape[1] == 0 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be a finite (T, V, 3) array with T >= 2, got shape {V.shape}")
    lab = np.asarray(labels)
    if lab.shape != (V.shape[1],) or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"labels must be ({V.shape[1]},) integers, got {lab.dtype} shape {lab.shape}")
    ax = [np.asarray(a, dtype=np.float64) for a in axes]
    for a in ax:
        if a.ndim != 2 or a.shape[1] != 3 or len(a) < 2 or not np.isfinite(a).all():
            raise ValueError(f"axes must be finite (n, 3) polylines of at least 2 points, got shape {a.shape}")
    if len(lab) and (lab.min() < -1 or lab.max() >= len(ax)):
        raise ValueError(f"labels must be in -1 .. {len(ax) - 1}, got {lab.min()} .. {lab.max()}")
    if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or not 0 <= reference < len(V):
        raise ValueError(f"reference must be a frame in 0 .. {len(V) - 1}, got {reference!r}")
    if isinstance(candidates, bool) or not isinstance(candidates, (int, np.integer)) or candidates < 2:
        raise ValueError(f"candidates must be an int >= 2, got {candidates!r}")
    tri, parts = _check_seams(faces, seams, V.shape[1])
    if not isinstance(centres, (bool, np.bool_)):
        raise ValueError(f"centres must be True or False, got {centres!r}")
    body = np.flatnonzero(lab == -1)
    rho = _noise(rho, V, body, int(reference), int(candidates))
    out = np.full(V.shape[1], -1, dtype=np.int64)
    nxt = 0
    if len(body):
        out[body] = 0
        nxt = 1
    for k, a in enumerate(ax):
        idx = np.flatnonzero(lab == k)
        if len(idx) == 0:
            continue
        s = _arc_length(V[reference, idx], a)
        avoid = None
        if parts is not None:
            position = np.full(V.shape[1], np.nan)
            position[idx] = s
            avoid = seam_positions(tri, parts, position)
        piece = chain_cuts(V[:, idx], s, reference=int(reference), candidates=int(candidates), rho=rho, avoid=avoid)
        if centres:
            piece = _centred_cuts(V[:, idx], s, piece, a, int(reference))
        out[idx] = nxt + piece
        nxt += int(piece.max()) + 1
    return out


def _axis_points(axis: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points of the polyline ``axis`` at arc lengths ``s`` (clamped to its ends) and its unit direction there."""
    d = np.diff(axis, axis=0)
    L = np.linalg.norm(d, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    i = np.clip(np.searchsorted(cum, s) - 1, 0, len(L) - 1)
    u = d[i] / np.maximum(L[i], 1e-300)[:, None]
    return axis[i] + (np.asarray(s) - cum[i])[:, None] * u, u


def _centred_cuts(X: np.ndarray, s: np.ndarray, piece: np.ndarray, axis: np.ndarray, reference: int) -> np.ndarray:
    """``centres`` of :func:`limb_segments` on one limb: its intervals ``piece`` (0 .. at the lowest ``s``) with every
    cut whose centre of rotation lies off the axis by more than the radius beyond twice its uncertainty merged away,
    the worst first; intervals renumbered 0 .. from the lowest ``s``."""
    from pipeline.armature_skeleton import joint_residual
    from pipeline.rigid_parts import rigid_motions

    near, _ = _axis_points(axis, s)
    radius = float(np.median(np.linalg.norm(X[reference] - near, axis=1)))
    piece = piece.copy()
    motion: dict = {}  # interval -> its rigid motions; a merge changes only the merged interval's
    while True:
        groups = np.unique(piece)  # ascending = along the limb (chain_cuts' order; merging keeps it)
        if len(groups) < 2:
            break
        for g in groups:
            if g not in motion:
                motion[g] = rigid_motions(X[:, piece == g], reference=reference)
        motions = [motion[g] for g in groups]
        off = np.empty(len(groups) - 1)
        for i in range(len(groups) - 1):
            cut = 0.5 * (float(s[piece == groups[i]].max()) + float(s[piece == groups[i + 1]].min()))
            p, u = _axis_points(axis, np.array([cut]))
            res, c = joint_residual(motions[i], motions[i + 1], p[0])
            M = motions[i][0] - motions[i + 1][0]
            e = np.linalg.eigvalsh(np.einsum("tji,tjk->ik", M, M) / len(M))  # ascending; e[0] ~ 0 along a hinge
            sigma = res / np.sqrt(max(float(e[1]), 1e-300))
            d = c - p[0]
            off[i] = float(np.linalg.norm(d - (d @ u[0]) * u[0])) - 2.0 * sigma
        worst = int(np.argmax(off))
        if off[worst] <= radius:
            break
        piece[piece == groups[worst + 1]] = groups[worst]
        del motion[groups[worst]], motion[groups[worst + 1]]
    return np.unique(piece, return_inverse=True)[1].astype(np.int64)


def _check_seams(faces, seams, n: int):
    """``faces`` and ``seams`` of :func:`limb_segments` checked: (triangles, parts), or (None, None) without seams."""
    if seams is None:
        return None, None
    if faces is None:
        raise ValueError("faces must be given with seams (the mesh edges where two parts meet)")
    parts = np.asarray(seams)
    if parts.shape != (n,) or not np.issubdtype(parts.dtype, np.integer):
        raise ValueError(f"seams must be ({n},) integers, got {parts.dtype} shape {parts.shape}")
    tri = np.asarray(faces)
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer) or (
            tri.size and (tri.min() < 0 or tri.max() >= n)):
        raise ValueError(f"faces must be (F, 3) integers in 0 .. {n - 1}, got {tri.dtype} shape {tri.shape}")
    return tri.astype(np.int64), parts.astype(np.int64)


def seam_positions(faces, parts, position) -> np.ndarray:
    """Where two parts meet along a chain: per pair of ``parts`` that share a mesh edge with an end on the chain,
    the median ``position`` of the chain's vertices on such edges.

    Parameters
    ----------
    faces : (F, 3) int ndarray
        The template's triangles.
    parts : (V,) int ndarray
        Part of every vertex.
    position : (V,) float ndarray
        Every vertex's position along the chain, NaN off the chain.

    Returns
    -------
    (m,) float ndarray
        The seams' positions, ascending.

    Raises
    ------
    ValueError
        Naming the parameter: ``faces`` not (F, 3), ``parts`` and ``position`` not one value for every vertex
        the faces name.
    """
    f = np.asarray(faces, dtype=np.int64)
    p = np.asarray(parts, dtype=np.int64)
    s = np.asarray(position, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got shape {f.shape}")
    if p.ndim != 1 or s.shape != p.shape or (f.size and f.max() >= len(p)):
        raise ValueError(f"parts and position must be (V,) for the faces' vertices, got {p.shape} and {s.shape}")
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    e = e[p[e[:, 0]] != p[e[:, 1]]]
    pair = np.sort(p[e], axis=1)
    ends = np.concatenate([e[:, 0], e[:, 1]])
    keys = np.concatenate([pair, pair])
    on = np.isfinite(s[ends])
    if not on.any():
        return np.zeros(0)
    ends, keys = ends[on], keys[on]
    _, which = np.unique(keys, axis=0, return_inverse=True)
    which = which.ravel()
    out = []
    for g in range(int(which.max()) + 1):
        mine = np.unique(ends[which == g])  # a vertex on two edges of the seam counts once
        out.append(float(np.median(s[mine])))
    return np.sort(np.asarray(out))


def _noise(rho, V: np.ndarray, body: np.ndarray, reference: int, candidates: int) -> float | str:
    """``rho`` of :func:`limb_segments` checked: a float, ``"limb"``, or None measured on the body."""
    if isinstance(rho, str):
        if rho != "limb":
            raise ValueError(f"rho must be a float in [0, 1), None or 'limb', got {rho!r}")
        return rho
    if rho is None:
        if len(body) < 2 * MIN_VERTICES:
            raise ValueError(f"labels: the body has {len(body)} vertices, too few to measure the noise on; give rho")
        return noise_ratio(V[:, body], reference=reference, candidates=candidates)
    if not (0 <= rho < 1):
        raise ValueError(f"rho must be in [0, 1), got {rho!r}")
    return float(rho)


def chain_cuts(vertices, position, *, reference: int = 0, candidates: int = 32, rho: float | str,
               avoid=None) -> np.ndarray:
    """Cut a chain of vertices into intervals of ``position``: the best cut for every count, the count kept
    while a cut removes more than ``rho`` of the residual (see the module docstring).

    Parameters
    ----------
    vertices : (T, n, 3) float ndarray
    position : (n,) float ndarray
        Every vertex's position along the chain.
    reference, candidates : int
        As :func:`limb_segments`.
    rho : float or "limb"
        The noise ratio, in [0, 1), or ``"limb"``: :func:`limb_noise` of this chain's own cuts.
    avoid : (m,) float array_like, optional
        Positions the candidate cuts keep off (:func:`seam_positions`): a candidate within half a candidate spacing
        of one is moved to half a spacing from it, on its own side, one position after the other; of two positions
        less than a spacing apart, a candidate moved off one may end within half a spacing of the other.

    Returns
    -------
    (n,) int64 ndarray
        Interval of every vertex, 0 at the lowest positions.
    """
    if isinstance(rho, str) and rho != "limb" or not isinstance(rho, str) and not (
            isinstance(rho, (int, float, np.floating)) and 0 <= rho < 1):
        raise ValueError(f"rho must be a float in [0, 1) or 'limb', got {rho!r}")
    avoid = np.zeros(0) if avoid is None else np.asarray(avoid, dtype=np.float64).ravel()
    if not np.isfinite(avoid).all():
        raise ValueError("avoid must be finite positions")
    E, bounds, order, starts = _dp(vertices, position, reference, candidates, avoid=avoid)
    k = _choose(E, limb_noise(E) if isinstance(rho, str) else rho)
    out = np.empty(len(position), dtype=np.int64)
    for p, (i, j) in enumerate(bounds[k]):
        out[order[starts[i]:starts[j]]] = p
    return out


def noise_ratio(vertices, *, reference: int = 0, candidates: int = 32) -> float:
    """The largest fraction of a rigid piece's residual that its best single cut removes, over cuts along its
    three principal axes at frame ``reference``.

    Parameters
    ----------
    vertices : (T, n, 3) float ndarray
        One rigid part's tracked vertices (the body), n >= ``2 * MIN_VERTICES``.
    reference, candidates : int
        As :func:`limb_segments`.

    Returns
    -------
    float
        In [0, 1).
    """
    X = np.asarray(vertices, dtype=np.float64)
    P = X[reference] - X[reference].mean(0)
    _, _, Vt = np.linalg.svd(P, full_matrices=False)
    best = 0.0
    for d in Vt:
        E, _, _, _ = _dp(X, P @ d, reference, candidates, k_max=2)
        if len(E) > 1 and E[0] > 0:
            best = max(best, (E[0] - E[1]) / E[0])
    return float(min(best, 1.0 - 1e-9))


def limb_noise(E) -> float:
    """``rho="limb"``: :data:`LIMB_FACTOR` times the mean fraction of the residual that the chain's cuts
    :data:`LIMB_TAIL` remove (the last half of its cuts when it has fewer), at most 1 - 1e-9.

    Parameters
    ----------
    E : (K,) float array_like
        The chain's best residual with ``0 .. K-1`` cuts (non-increasing).

    Returns
    -------
    float
        In [0, 1); 0 for a chain of one candidate interval (no cut to make). A chain of two has its one cut as
        its own noise: it is not cut.
    """
    E = np.asarray(E, dtype=np.float64)
    if E.ndim != 1 or len(E) == 0 or not np.isfinite(E).all() or (E < 0).any():
        raise ValueError(f"E must be a non-empty (K,) array of finite residuals >= 0, got shape {E.shape}")
    r = 1.0 - E[1:] / np.maximum(E[:-1], 1e-300)
    lo, hi = LIMB_TAIL
    tail = r[lo - 1:hi] if len(r) >= lo else r[len(r) // 2:]
    if len(tail) == 0:
        return 0.0
    return float(min(LIMB_FACTOR * max(float(tail.mean()), 0.0), 1.0 - 1e-9))


def _choose(E: np.ndarray, rho: float) -> int:
    """The number of cuts: stop where neither the next cut nor the next two remove enough."""
    k = 0
    while k + 1 < len(E):
        one = E[k + 1] < (1 - rho) * E[k]
        two = k + 2 < len(E) and E[k + 2] < (1 - rho) ** 2 * E[k]
        if not (one or two):
            break
        k += 2 if (two and not one) else 1
    return k


def _bins(position: np.ndarray, candidates: int, avoid=()):
    """Vertices sorted by position, and the start of every candidate interval (each >= MIN_VERTICES); a candidate
    edge within half a spacing of a position in ``avoid`` is moved to half a spacing from it, one position after
    the other (of two less than a spacing apart, the second can move it back near the first)."""
    order = np.argsort(position, kind="stable")
    s = position[order]
    n = len(s)
    edges = np.linspace(s[0], s[-1], candidates + 1)[1:-1]
    half = 0.5 * (s[-1] - s[0]) / candidates
    for c in avoid:
        d = edges - c
        near = np.abs(d) < half
        edges[near] = c + np.where(d[near] >= 0, half, -half)
    edges = np.sort(edges)
    cut = np.searchsorted(s, edges, side="right")
    starts = [0]
    for c in cut:
        if c - starts[-1] >= MIN_VERTICES and n - c >= MIN_VERTICES:
            starts.append(int(c))
    starts.append(n)
    return order, np.asarray(starts)


def _dp(vertices, position, reference: int, candidates: int, k_max: int | None = None, avoid=()):
    """Best residual with 1.. pieces (E[k] = k cuts), the pieces' bin bounds, the order and bin starts."""
    X = np.asarray(vertices, dtype=np.float64)
    order, starts = _bins(np.asarray(position, dtype=np.float64), candidates, avoid)
    C = _interval_costs(X[:, order], starts, reference)
    B = len(starts) - 1
    K = B if k_max is None else min(B, k_max)
    D = np.full((K, B + 1), np.inf)
    arg = np.zeros((K, B + 1), dtype=np.int64)
    D[0, 1:] = C[0, 1:]
    for k in range(1, K):
        for j in range(k + 1, B + 1):
            cand = D[k - 1, k:j] + C[k:j, j]
            i = int(np.argmin(cand))
            D[k, j], arg[k, j] = cand[i], k + i
    E = D[:, B]
    bounds = []
    for k in range(K):
        b, j = [], B
        for kk in range(k, 0, -1):
            i = int(arg[kk, j])
            b.append((i, j))
            j = i
        b.append((0, j))
        bounds.append(b[::-1])
    return E, bounds, order, starts


def _interval_costs(X: np.ndarray, starts: np.ndarray, reference: int) -> np.ndarray:
    """C[i, j]: the rigid residual over frames of bins i .. j-1 (sum of squared distances)."""
    P = X[reference]
    cs = lambda a: np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])[starts]  # noqa: E731
    n = starts.astype(np.float64)
    sP = cs(P)                                              # (B+1, 3)
    sPP = cs((P * P).sum(1))                                # (B+1,)
    Q = np.moveaxis(X, 1, 0)                                # (n, T, 3)
    sQ = cs(Q)                                              # (B+1, T, 3)
    sQQ = cs((Q * Q).sum(2))                                # (B+1, T)
    sPQ = cs(P[:, None, :, None] * Q[:, :, None, :])        # (B+1, T, 3, 3)
    B = len(starts) - 1
    i, j = np.triu_indices(B + 1, k=1)
    m = (n[j] - n[i])[:, None]
    dP = sP[j] - sP[i]
    dQ = sQ[j] - sQ[i]
    ssP = (sPP[j] - sPP[i])[:, None] - (dP * dP).sum(1)[:, None] / m
    ssQ = (sQQ[j] - sQQ[i]) - (dQ * dQ).sum(2) / m
    M = (sPQ[j] - sPQ[i]) - dP[:, None, :, None] * dQ[:, :, None, :] / m[:, :, None, None]
    sv = np.linalg.svd(M, compute_uv=False)                 # (pairs, T, 3)
    sign = np.sign(np.linalg.det(M))
    sign[sign == 0] = 1
    fit = sv[..., 0] + sv[..., 1] + sign * sv[..., 2]
    res = np.clip(ssP + ssQ - 2 * fit, 0, None)
    res[:, reference] = 0.0
    C = np.zeros((B + 1, B + 1))
    C[i, j] = res.sum(1)
    return C


def _arc_length(X: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Arc length along ``axis`` of every point's nearest point on it."""
    a, b = axis[:-1], axis[1:]
    d = b - a
    L = np.linalg.norm(d, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    t = np.einsum("nsk,sk->ns", X[:, None, :] - a[None], d) / np.maximum(L * L, 1e-300)
    t = np.clip(t, 0, 1)
    near = a[None] + t[..., None] * d[None]
    dist = np.linalg.norm(X[:, None, :] - near, axis=2)
    s = np.argmin(dist, axis=1)
    return cum[s] + t[np.arange(len(X)), s] * L[s]
