"""Rigid parts of a mesh sequence: rigid motions of vertex groups, and a segmentation refined into rigid parts.

:func:`rigid_motions` gives a group of vertices' best rigid motion (Kabsch) from a reference frame to
every frame, :func:`rigid_residual` how far the group is from moving rigidly, :func:`relative_bend`
how far two groups turn against each other. The motion segmentation (:mod:`pipeline.motion_segmentation`,
Tzionas & Gall 2016, section 4.1) refines its spectral clusters with them, in steps the paper is
silent on (the reasons: that module's docstring): segments that move as one rigid body are merged
(``_merge_rigid``), a segment that does not move rigidly is cut by the normalised cut of its samples
(``_split_nonrigid``), what does not move with a segment's rigid core is peeled off
(``_peel_nonrigid``), and a segment that is the blend zone of a skinned joint is dissolved
into its neighbours (``_dissolve_blends``); those four are the segmentation's steps, not an API.
"""

from __future__ import annotations

import hashlib

import numpy as np

from pipeline.mesh_primitives import edge_components

__all__ = ["rigid_motions", "rigid_residual", "relative_bend"]

def rigid_motions(points, *, reference: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The best rigid motion of a point set from one frame to every frame, all frames at once.

    Least squares (Arun et al. 1987; the reflection case corrected), batched over frames:
    one SVD of a 3x3 matrix per frame.

    Parameters
    ----------
    points : (T, n, 3) float array_like
        The same ``n`` points in ``T`` frames.
    reference : int
        The frame the motions start from.

    Returns
    -------
    R : (T, 3, 3) float ndarray
        Rotations (det +1).
    t : (T, 3) float ndarray
        ``points[k] ~ points[reference] @ R[k].T + t[k]``.
    """
    Y = np.asarray(points, dtype=np.float64)
    if Y.ndim != 3 or Y.shape[2] != 3 or Y.shape[1] == 0:
        raise ValueError(f"points must have shape (T, n, 3) with n >= 1, got {Y.shape}")
    if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or not 0 <= reference < len(Y):
        raise ValueError(f"reference must be a frame index within 0..{len(Y) - 1}, got {reference!r}")
    c = Y.mean(1)
    Rt = _rotations_from(Y - c[:, None], int(reference))
    R = Rt.transpose(0, 2, 1)
    return R, c - np.einsum("tij,j->ti", R, c[reference])


def _rotations_from(Yc: np.ndarray, reference: int) -> np.ndarray:
    """(T, 3, 3) ``Q`` with ``Yc[reference] @ Q[k] ~ Yc[k]`` for centred point sets ``Yc`` (T, n, 3)."""
    H = np.matmul(Yc[reference].T[None], Yc)  # (T, 3, 3)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.matmul(U, Vt)))
    U[:, :, 2] *= d[:, None]
    return np.matmul(U, Vt)


def rigid_residual(points, groups=None) -> float:
    """How far a set of trajectories is from one rigid motion.

    Parameters
    ----------
    points : (T, n, 3) float ndarray
    groups : (n,) int array_like, optional
        Group of every point: the result is the largest over the groups of
        their median residual, so a few stray points (labels propagated
        across a boundary) do not hide a rigid union, and a small group that
        moves on its own is not outvoted by a large one.

    Returns
    -------
    float
        The largest (over frames) RMS distance (median per group when
        ``groups`` is given) after the best rigid transform from frame 0
        (:func:`rigid_motions`).
    """
    Y = np.asarray(points, dtype=np.float64)
    Y = Y - Y.mean(1, keepdims=True)
    X = Y[0]
    res = np.sqrt(((np.matmul(X[None], _rotations_from(Y, 0)) - Y) ** 2).sum(2))  # (T, n)
    if groups is None:
        return float(np.sqrt((res**2).mean(1)).max())
    g = np.asarray(groups)
    return float(max(np.median(res[:, g == k], axis=1).max() for k in np.unique(g)))


def _some_frames(T: int, most: int = 120) -> np.ndarray:
    """At most ``most`` evenly spaced frame positions (rigidity of smooth motion, checked on long sequences)."""
    return np.unique(np.linspace(0, T - 1, min(int(T), most)).round().astype(np.int64))


def _max_min(F: np.ndarray, m: int, first: int | None = None) -> np.ndarray:
    """``m`` rows of ``F`` spread out: ``first`` (default: the row farthest from their mean), then each time
    the row farthest from those chosen (for unit rows: the one most nearly orthogonal to them)."""
    first = int(np.argmax(((F - F.mean(0)) ** 2).sum(1))) if first is None else int(first)
    out = [first]
    dmin = ((F - F[first]) ** 2).sum(1)
    for _ in range(1, int(m)):
        out.append(int(np.argmax(dmin)))
        np.minimum(dmin, ((F - F[out[-1]]) ** 2).sum(1), out=dmin)
    return np.asarray(out, dtype=np.int64)


def _spread(ids: np.ndarray, most: int) -> np.ndarray:
    """At most ``most`` of ``ids``, evenly spread over them (every k-th): a deterministic subset."""
    return ids if len(ids) <= most else ids[np.linspace(0, len(ids) - 1, most).round().astype(np.int64)]


def _merge_rigid(labels: np.ndarray, v: np.ndarray, edges: np.ndarray, tol: float, *, per_segment: int = 400,
                 min_edges: int = 3) -> np.ndarray:
    """Merge adjacent segments whose union still moves rigidly (residual below ``tol``)."""
    rng = np.random.default_rng(0)
    lab = labels.copy()
    vf = v[_some_frames(len(v))]  # gathered once: the rows of a segment are then one take
    members = {int(s): np.flatnonzero(lab == s) for s in np.unique(lab)}
    pick = {s: (m if len(m) <= per_segment else rng.choice(m, per_segment, replace=False)) for s, m in members.items()}

    def adjacent_pairs():
        la, lb = lab[edges[:, 0]], lab[edges[:, 1]]
        c = la != lb
        lo, hi = np.minimum(la[c], lb[c]), np.maximum(la[c], lb[c])
        m = int(lab.max()) + 1
        keys, counts = np.unique(lo * m + hi, return_counts=True)  # one integer per pair: a 1-D unique
        return {(int(k // m), int(k % m)) for k, n in zip(keys, counts) if n >= min_edges}

    cache: dict = {}
    while True:
        pairs = adjacent_pairs()
        if not pairs:
            break
        for pr in pairs:
            if pr not in cache:
                ids = np.r_[pick[pr[0]], pick[pr[1]]]
                grp = np.r_[np.zeros(len(pick[pr[0]])), np.ones(len(pick[pr[1]]))]
                cache[pr] = rigid_residual(vf[:, ids], grp)
        best = min(pairs, key=lambda pr: cache[pr])
        if cache[best] >= tol:
            break
        a, b = best
        lab[lab == b] = a
        both = np.r_[pick[a], pick[b]]
        pick[a] = both if len(both) <= per_segment else rng.choice(both, per_segment, replace=False)
        pick.pop(b)
        cache = {pr: r for pr, r in cache.items() if a not in pr and b not in pr}
    return lab


def _best_cut(A: np.ndarray, near: np.ndarray, ids: np.ndarray, residual, min_size: int, cuts: int = 19):
    """The normalised cut of a segment's samples (a sweep of the Fiedler vector, Shi & Malik 2000) whose
    halves move most rigidly; ``None`` when no cut leaves both halves ``min_size`` vertices.

    Returns (len(ids),) 0/1 side of every vertex (its nearest sample's).
    """
    d = A.sum(1)
    s = 1.0 / np.sqrt(np.maximum(d, 1e-300))
    _, U = np.linalg.eigh(np.eye(len(A)) - s[:, None] * A * s[None, :])
    fiedler = U[:, 1] * s  # the generalised eigenvector of (D - A, D)
    best, best_res = None, np.inf
    for q in np.linspace(0.05, 0.95, int(cuts)):
        side = (fiedler > np.quantile(fiedler, q)).astype(np.int64)[near]
        if min(int((side == 0).sum()), int((side == 1).sum())) < min_size:
            continue
        r = max(residual(ids[side == 0]), residual(ids[side == 1]))
        if r < best_res:
            best, best_res = side, r
    return best


def _memoised(memo: dict, kind: str, ids: np.ndarray, compute):
    """``memo``'s value for ``kind`` of the vertex set ``ids``, ``compute()`` when it has none."""
    k = kind, hashlib.blake2b(np.ascontiguousarray(ids, dtype=np.int64).tobytes(), digest_size=16).digest()
    if k not in memo:
        memo[k] = compute()
    return memo[k]


def _split_nonrigid(labels: np.ndarray, v: np.ndarray, samples: np.ndarray, A: np.ndarray, tol: float, *,
                    min_size: int, gain: float = 0.5, per_segment: int = 400, depth: int = 6,
                    ahead: int = 1, memo: dict | None = None) -> np.ndarray:
    """Split segments that do not move rigidly, recursively (the spectral cuts of their own samples).

    The eigenvalue count ``k`` spends clusters on large parts and can leave a
    small part fused to its neighbour (a tail on a body); a segment whose
    rigid residual exceeds ``tol`` is cut in two along the Fiedler vector of
    its samples' affinities (:func:`_best_cut`) when that leaves both halves
    at most ``gain`` of its residual -- a joint inside it, not a
    smooth deformation. With ``ahead`` > 1, when neither half is within that (parts on both
    sides of the cut: a segment of several, the count short by one), the halves are cut
    again, at most ``ahead`` cuts deep, and the segment is cut when every piece is within it;
    a cut that leaves one half within and the other not is beside a joint, and is not made.
    Pieces below ``min_size`` vertices are not made. ``memo``: residuals and cuts by vertex set, kept
    between calls on the same sequence, samples and affinities (a second call redoes no cut of the first).
    """
    from scipy.spatial import cKDTree

    lab = labels.copy()
    vf = v[_some_frames(len(v))]
    inside = np.zeros(len(lab), dtype=bool)
    memo = {} if memo is None else memo

    def residual(ids):  # on evenly spread members (every k-th): the same answer whatever the seed
        return _memoised(memo, "residual", ids, lambda: rigid_residual(vf[:, _spread(ids, per_segment)]))

    def cut_of(ids):
        inside[:] = False
        inside[ids] = True
        sub = np.flatnonzero(inside[samples])
        if len(sub) < 8 or len(ids) < 2 * min_size:
            return None
        _, near = cKDTree(v[0, samples[sub]]).query(v[0, ids])
        return _best_cut(A[np.ix_(sub, sub)], near, ids, residual, min_size)

    def cut(ids):
        return _memoised(memo, "cut", ids, lambda: cut_of(ids))

    def pieces(ids, bound, levels):  # ids cut until every piece is within bound; None if not so in levels
        side = cut(ids) if levels > 0 else None
        if side is None:
            return None
        halves = [ids[side == 0], ids[side == 1]]
        res = [residual(h) for h in halves]
        within = [r <= bound for r in res]
        if all(within):
            return halves
        if any(within) or min(res) <= tol:
            return None  # a half is within or rigid: no parts on both sides (a cut beside a joint, a smooth bend)
        a = pieces(halves[0], bound, levels - 1)
        b = None if a is None else pieces(halves[1], bound, levels - 1)
        return None if b is None else a + b

    todo = [(int(x), 0) for x in np.unique(lab)]
    while todo:
        sgm, level = todo.pop()
        ids = np.flatnonzero(lab == sgm)
        if level >= depth or len(ids) < 2 * min_size:
            continue
        parent = residual(ids)
        if parent <= tol:
            continue
        got = pieces(ids, gain * parent, int(ahead))
        if got is None or len(got) < 2:
            continue
        todo.append((sgm, level + 1))
        for piece in got[1:]:
            new = int(lab.max()) + 1
            lab[piece] = new
            todo.append((new, level + 1))
    return lab


def relative_bend(motion_a, motion_b, *, most: int = 60) -> float:
    """Degrees two parts turn against each other: the largest angle between their relative rotations
    in any two frames (at most ``most`` evenly spaced frames).

    Parameters
    ----------
    motion_a, motion_b : tuple of (T, 3, 3) and (T, 3) float ndarray
        ``x_t = R_t x + t_t`` of each part.
    """
    Ra, Rb = np.asarray(motion_a[0], dtype=np.float64), np.asarray(motion_b[0], dtype=np.float64)
    if Ra.shape != Rb.shape or Ra.ndim != 3 or Ra.shape[1:] != (3, 3):
        raise ValueError(f"motions must hold (T, 3, 3) rotations of one length, got {Ra.shape} and {Rb.shape}")
    sel = np.unique(np.linspace(0, len(Ra) - 1, min(len(Ra), int(most))).round().astype(np.int64))
    Rr = np.matmul(Ra[sel].transpose(0, 2, 1), Rb[sel])
    cos = (np.einsum("aij,bij->ab", Rr, Rr) - 1.0) / 2.0  # trace(Rr_a^T Rr_b)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)).max()))


def _gaps(motion, Y0: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """(F, n) distances of trajectories ``Y`` (F, n, 3) from where ``motion`` carries their first positions."""
    R, t = motion
    d = np.matmul(Y0[None], R.transpose(0, 2, 1))  # batched BLAS: R_t y for every frame
    d += t[:, None]
    d -= Y
    return np.sqrt(np.einsum("tvi,tvi->tv", d, d))


def _core_motion(Y: np.ndarray, *, keep: float = 0.5, rounds: int = 3):
    """The rigid motion of the most rigid ``keep`` of a point set's trajectories (trimmed least squares:
    refit on the points the last fit explains best), from frame 0; (R (T, 3, 3), t (T, 3))."""
    R, t = rigid_motions(Y)
    for _ in range(rounds):
        r = _gaps((R, t), Y[0], Y).max(0)
        R, t = rigid_motions(Y[:, np.argsort(r)[: max(3, int(keep * len(r)))]])
    return R, t


def _consensus_motion(Y: np.ndarray, tol: float, patch: int, *, hypotheses: int = 24, most: int = 1000,
                      rounds: int = 3):
    """The rigid motion the most trajectories of ``Y`` (F, n, 3) follow within ``tol`` in every frame (maximum
    consensus): hypotheses are the rigid motions of the ``patch`` points nearest to each of ``hypotheses``
    farthest-point seeds of the first frame (:func:`_max_min`), counted on at most ``most`` evenly spread
    points; the best is refitted on the points it carries within ``tol``, ``rounds`` times. No random draw."""
    from scipy.spatial import cKDTree

    n = Y.shape[1]
    sub = _spread(np.arange(n), most)
    tree = cKDTree(Y[0])
    best, best_count = None, -1
    for s in _max_min(Y[0], min(int(hypotheses), n)):
        _, nb = tree.query(Y[0, s], k=min(max(4, int(patch)), n))
        motion = rigid_motions(Y[:, np.atleast_1d(nb)])
        count = int((_gaps(motion, Y[0, sub], Y[:, sub]).max(0) <= tol).sum())
        if count > best_count:
            best, best_count = motion, count
    for _ in range(int(rounds)):
        inliers = _gaps(best, Y[0], Y).max(0) <= tol
        if inliers.sum() < 4:
            break
        best = rigid_motions(Y[:, inliers])
    return best


def _peel_nonrigid(labels: np.ndarray, v: np.ndarray, edges: np.ndarray, tol: float, *, min_size: int,
                   depth: int = 4, gain: float = 0.5, settled: set | None = None) -> np.ndarray:
    """Parts fused to a segment peeled off: the vertices its core motion (:func:`_core_motion`) leaves
    more than ``tol`` away in some frame, as surface-connected patches of at least ``min_size`` vertices
    that have a motion of their own (their own rigid residual at most ``gain`` of their residual under
    the core's motion, the rule of :func:`_split_nonrigid`): a leg or a tail fused to the body moves
    with its own motion, the body's core with the body's; a smooth bend is no part. When the trimmed core
    leaves fewer than ``min_size`` vertices within ``tol`` (a segment of several parts, none of them half
    of it: the trimmed fit mixes them and fits none), the core is the motion most of its vertices follow
    (:func:`_consensus_motion`). Tracking noise can look like such a part (``peel_parts`` of
    :func:`motion_segmentation`). Segments in ``settled`` are not looked at (peeled already)."""
    lab = labels.copy()
    vf = v[_some_frames(len(v))]
    V = len(lab)
    settled = set() if settled is None else set(settled)  # segments looked at and left as they were
    for _ in range(int(depth)):
        changed = False
        for sgm in np.unique(lab):
            ids = np.flatnonzero(lab == sgm)
            if len(ids) < 2 * min_size or int(sgm) in settled:
                continue
            settled.add(int(sgm))
            Y = vf[:, ids].astype(np.float64)
            R, t = _core_motion(Y)
            gap = _gaps((R, t), Y[0], Y)  # (frames, vertices)
            off = gap.max(0) > tol
            if (~off).sum() < min_size:  # the trimmed core fits no part (none holds half the segment)
                R, t = _consensus_motion(Y, tol, min_size)
                gap = _gaps((R, t), Y[0], Y)
                off = gap.max(0) > tol
            where = np.full(V, -1)
            where[ids] = np.arange(len(ids))
            if off.sum() < min_size or (~off).sum() < min_size:
                continue
            mask = np.zeros(V, bool)
            mask[ids[off]] = True
            e = edges[mask[edges[:, 0]] & mask[edges[:, 1]]]
            comp = edge_components(e, V)
            sizes = np.bincount(comp[mask], minlength=comp.max() + 1)
            for c in np.flatnonzero(sizes >= min_size):
                patch = np.flatnonzero(mask & (comp == c))
                some = patch[:: max(1, len(patch) // 400)]
                under_core = float(np.sqrt((gap[:, where[some]] ** 2).mean(1)).max())
                if rigid_residual(vf[:, some]) > gain * under_core:
                    continue  # no motion of its own (a smooth bend, a blend between two parts)
                lab[patch] = int(lab.max()) + 1
                settled.discard(int(sgm))
                changed = True
        if not changed:
            break
    return lab


def _blend_gaps(Y: np.ndarray, Pa: np.ndarray, Pb: np.ndarray) -> np.ndarray:
    """(n,) RMS over the frames of the distance of trajectories ``Y`` (F, n, 3) from their best blend of two
    predictions, ``min over w in [0, 1] of |w Pa + (1 - w) Pb - Y|`` per point (closed form): the linear blend
    skinning of a point between two bones, one weight per point."""
    d = Pa - Pb  # Y ~ Pb + w (Pa - Pb)
    e = Y - Pb
    w = np.clip(np.einsum("fni,fni->n", d, e) / np.maximum(np.einsum("fni,fni->n", d, d), 1e-300), 0.0, 1.0)
    r = e - w[None, :, None] * d
    return np.sqrt(np.einsum("fni,fni->n", r, r) / len(Y))


def _dissolve_blends(labels: np.ndarray, v: np.ndarray, edges: np.ndarray, *, min_edges: int = 3,
                     per_segment: int = 400) -> np.ndarray:
    """Segments that are a joint's blend zone, not a part, dissolved into the parts they join.

    Skinned surfaces bend smoothly: near a joint every vertex follows a blend of the two bones' motions, in
    proportions that change along the surface, so it follows neither bone rigidly, and the spectral step can
    cut such a zone off as a segment of its own (a sliver whose boundaries all become joints). A segment
    smaller than each of its neighbours (a band round a joint is narrower than the parts it joins) whose
    vertices follow a per-vertex blend of two neighbouring segments' motions (:func:`_blend_gaps`, their core
    motions, :func:`_core_motion`, the best pair per vertex) more closely than any one rigid motion of their
    own (median over its vertices of the RMS distance over the frames) is such a zone: each of its vertices
    joins the neighbour whose core motion carries it closest. A rigid part between others (a finger's middle
    phalanx, a limb segment) follows its own rigid motion exactly and stays; a segment with a smaller
    neighbour is a part that carries others (a hub) and stays. The zone furthest from rigid against its
    blend goes first, and the motions are looked at again.
    """
    rng = np.random.default_rng(0)
    lab = labels.copy()
    vf = v[_some_frames(len(v))].astype(np.float64)
    cores: dict = {}
    samples: dict = {}

    def sample(s):
        if s not in samples:
            ids = np.flatnonzero(lab == s)
            samples[s] = ids if len(ids) <= per_segment else np.sort(rng.choice(ids, per_segment, replace=False))
        return samples[s]

    def core(s):
        if s not in cores:
            cores[s] = _core_motion(vf[:, sample(s)])
        return cores[s]

    def predict(s, X0):
        R, t = core(s)
        return np.matmul(X0[None], R.transpose(0, 2, 1)) + t[:, None]

    for _ in range(int(lab.max()) + 1):
        la, lb = lab[edges[:, 0]], lab[edges[:, 1]]
        c = la != lb
        keys, counts = np.unique(np.c_[np.minimum(la[c], lb[c]), np.maximum(la[c], lb[c])], axis=0,
                                 return_counts=True)
        keys = keys[counts >= min_edges]
        sizes = np.bincount(lab)
        worst, worst_ratio = None, 1.0
        for s in np.unique(lab):
            s = int(s)
            nb = sorted({int(b) for a, b in keys if a == s} | {int(a) for a, b in keys if b == s})
            if len(nb) < 2 or sizes[s] >= sizes[nb].min():
                continue
            Y = vf[:, sample(s)]
            own = float(np.median(np.sqrt((_gaps(rigid_motions(Y), Y[0], Y) ** 2).mean(0))))
            P = [predict(n, Y[0]) for n in nb]
            blend = float(np.median(np.min([_blend_gaps(Y, P[i], P[j]) for i in range(len(P))
                                            for j in range(i + 1, len(P))], axis=0)))
            if own > worst_ratio * blend:
                worst, worst_ratio, pair = s, own / max(blend, 1e-300), nb
        if worst is None:
            break
        ids = np.flatnonzero(lab == worst)
        Y = vf[:, ids]
        near = np.stack([np.sqrt((_gaps(core(n), Y[0], Y) ** 2).mean(0)) for n in pair]).argmin(0)
        lab[ids] = np.asarray(pair)[near]
        for s in (worst, *pair):  # their members changed: sampled and fitted again when next asked
            samples.pop(s, None)
            cores.pop(s, None)
    return lab
