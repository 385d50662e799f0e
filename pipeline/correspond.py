"""Tip correspondence over time (Brostow et al. 2004, section 4.2).

The per-frame tips ``E_t`` are noisy: limbs merge, bumps appear for a frame.
Assuming the creature grows no new limbs, the number of limbs is
``K = mode |E_t|``. The reference frame is the middle of the longest run of
``K``-tip frames; every possible mapping of a frame's tips onto the
reference's is scored by the residual of Arun et al.'s least-squares rigid
alignment (eqs. 6-8) and the best one kept. Frames with another tip count are
matched against both the reference and the nearest ``K``-tip frame; their
superfluous tips are culled, and limbs they lack stay empty.

Choices the paper leaves open, made here:

* ``K``-tip frames are visited outward from the reference and scored against
  the nearest reference (Arun residual, weight ``reference_weight``) *and*
  the previous visited frame (centroid-aligned residual, weight 1: between
  neighbouring frames the creature barely turns, and a free rotation would
  let a near-symmetric body swap head and tail at no cost). This is the
  paper's "align each exploratory skeleton with respect to its temporal
  neighbors"; tips alone against one reference mislabel 36 of the 48
  horse-gallop frames, this labels all 48 correctly.
* Whole skeletons are aligned, not only tips: ``features`` adds points along
  each tip's own limb (at 1/4, 1/2, 3/4 of its length), which separates
  left from right legs whose hooves swing past each other.
* Long takes get several references, one per ``reference_span`` frames (the
  middle of the longest ``K``-run inside each window); a reference's own tips
  are assigned like any ``K``-tip frame, so all share the same limb ids.
* Permutations are enumerated exhaustively and scored in one vectorised batch
  (only the singular values of each 3x3 ``H`` are needed: the residual is
  ``|A|^2 + |B|^2 - 2 (s1 + s2 + sign(det H) s3)`` for centred sets). Above
  ``max_permutations`` candidates (K > 8) the Hungarian assignment on
  centred tip positions is refined by a local search of pairwise swaps and
  replacements (unweighted sum over the anchors).
* Every frame with tips is visited outward from the reference and anchored to the
  last seen position of every limb, so a limb missing from some frames (hidden,
  merged, too thin to survive) keeps its slot and never makes the others swap.
* A borderline count (``K + 1`` tips found in 40-60 % of the frames with tips, ``K``
  in the others, whichever of the two is the mode) is decided for ``K + 1`` when the
  extra limb is the same limb throughout, for ``K`` when it is not: aligned onto the
  reference by the other limbs, its tip stays within ``0.4`` x the RMS radius of the
  reference tips of its mean position, or it moves continuously (over at least 5 pairs of
  consecutive frames its RMS step is at most 0.35 of what positions drawn independently
  would give: an arm swinging by the body, fused with it in some frames, spreads farther
  than 0.4 radii but moves a little each frame; a bump at a random place jumps). The step
  is taken on the tip the other limbs leave in each frame with ``K + 1`` tips, not on the
  extra limb's assigned tips, which the correspondence and the gate chose for continuity.
* Hidden limbs: a limb fused with the body in some frames (arms at the sides of a
  standing person filmed by few cameras, legs together) is hidden there, not absent,
  and its tip is missing from those frames' counts; when such frames are many, the
  mode undercounts. A frame's *clear* tips (those that protrude by at least 1.5 times
  the tip threshold, :data:`pipeline.extremities.CLEAR`) are limbs for sure, so their
  count is a lower bound of ``K`` in that frame. When the clear tips are given, ``K``
  is raised above the mode (never lowered) to the largest clear count that at least
  ``HIDDEN_SHARE`` (a tenth) of the frames with tips reach, a frame with that many
  tips being there to serve as the reference: one frame's phantom does not add a limb,
  a limb seen clearly in a tenth of the take does. Tips that barely protrude (a ragged
  hand split in two, a fold of the hull) still take part in the correspondence but
  never raise ``K``.
  :attr:`Correspondence.count_rule` says which rule chose ``K``.
* A tip whose residual after alignment to its temporal neighbour exceeds
  ``gate`` times the RMS radius of the reference tips is dropped (its limb
  is empty in that frame) rather than given to a limb it is far from.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from functools import lru_cache
from itertools import permutations

import numpy as np
from scipy.optimize import linear_sum_assignment

from pipeline.mesh_primitives import rigid_fit

__all__ = [
    "NoLimbsError",
    "arun_alignment",
    "alignment_errors",
    "limb_count",
    "reference_frames",
    "Correspondence",
    "correspond_tips",
]


class NoLimbsError(ValueError):
    """No frame of the take has a limb tip (e.g. a take of spheres)."""


def arun_alignment(A, B):
    """Least-squares rigid motion taking points ``A`` onto ``B`` (Arun et al. 1987; eqs. 6-8).

    Parameters
    ----------
    A, B : (k, 3) float ndarray
        Corresponding points.

    Returns
    -------
    R : (3, 3) float ndarray
        Rotation (``det = +1``; the reflection case is corrected).
    T : (3,) float ndarray
    error : float
        ``sum_k |B_k - R A_k - T|^2`` (eq. 6).
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or A.shape != B.shape:
        raise ValueError(f"A and B must both have shape (k, 3), got {A.shape} and {B.shape}")
    if len(A) == 0:
        raise ValueError("A and B must not be empty")
    R, T = rigid_fit(A, B)  # eqs. 7-8, with the reflection fix of Arun et al., section IV
    err = float(np.sum((B - A @ R.T - T) ** 2))
    return R, T, err


def alignment_errors(A, B) -> np.ndarray:
    """Residual of eq. 6 for many candidate point sets at once.

    Parameters
    ----------
    A : (k, 3) or (M, k, 3) float ndarray
    B : (M, k, 3) float ndarray

    Returns
    -------
    (M,) float ndarray
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if B.ndim != 3 or B.shape[2] != 3:
        raise ValueError(f"B must have shape (M, k, 3), got {B.shape}")
    if A.ndim == 2:
        A = A[None]
    Ac = A - A.mean(axis=1, keepdims=True)
    Bc = B - B.mean(axis=1, keepdims=True)
    H = np.einsum("mki,mkj->mij", np.broadcast_to(Ac, Bc.shape), Bc)
    s = np.linalg.svd(H, compute_uv=False)
    d = np.sign(np.linalg.det(H))
    d[d == 0] = 1.0
    tr = s[:, 0] + s[:, 1] + d * s[:, 2]
    err = np.sum(Ac**2, axis=(1, 2)) + np.sum(Bc**2, axis=(1, 2)) - 2 * tr
    return np.maximum(err, 0.0)


def limb_count(counts) -> int:
    """``K = mode |E_t|``; ties go to the count with the longest run of frames, then the larger."""
    c = [int(x) for x in counts]
    if not c:
        raise ValueError("counts must not be empty")
    freq = Counter(c)
    best = max(freq.values())
    tied = [k for k, v in freq.items() if v == best]
    return max(tied, key=lambda k: (_longest_run(c, k)[1], k))


def _runs(counts, K):
    runs, start = [], None
    for i, c in enumerate(list(counts) + [None]):
        if c == K and start is None:
            start = i
        elif c != K and start is not None:
            runs.append((start, i))
            start = None
    return runs


def _longest_run(counts, K):
    runs = _runs(counts, K)
    if not runs:
        return None, 0
    s, e = max(runs, key=lambda r: (r[1] - r[0], -r[0]))
    return (s, e), e - s


def reference_frames(counts, K: int, *, span: int = 150) -> list[int]:
    """Reference frames: the middle of the longest ``K``-run, plus one per further ``span`` frames.

    The first element is the primary reference (middle of the longest run of
    the whole take); each other window of ``span`` frames (tiling the take
    around the primary) contributes the middle of its own longest ``K``-run.
    """
    c = [int(x) for x in counts]
    if span < 1:
        raise ValueError(f"span must be >= 1, got {span}")
    run, length = _longest_run(c, K)
    if not length:
        raise ValueError(f"no frame has {K} tips")
    primary = (run[0] + run[1] - 1) // 2
    refs = [primary]
    T = len(c)
    if T <= span:
        return refs
    # windows tiling the take, centred on the primary
    starts = set()
    s = primary - span // 2
    while s > -span:
        starts.add(s)
        s -= span
    s = primary - span // 2 + span
    while s < T:
        starts.add(s)
        s += span
    for s in sorted(starts):
        lo, hi = max(0, s), min(T, s + span)
        if lo <= primary < hi or hi - lo < span // 4:
            continue
        sub = c[lo:hi]
        r, L = _longest_run(sub, K)
        if L:
            refs.append(lo + (r[0] + r[1] - 1) // 2)
    return refs


@lru_cache(maxsize=64)
def _perms(n: int, k: int) -> np.ndarray:
    return np.array(list(permutations(range(n), k)), dtype=np.int64).reshape(-1, k)


@dataclass(frozen=True)
class Correspondence:
    """Which tip of each frame is which limb.

    Attributes
    ----------
    K : int
        Number of limbs (mode of the tip counts).
    assignment : (T, K) int ndarray
        Index into frame ``t``'s tips of limb ``k``; ``-1`` = not seen.
    references : list of int
        Reference frames, primary first.
    error : (T,) float ndarray
        Alignment residual of the chosen mapping (nan for frames without tips).
    count_rule : str
        How ``K`` was chosen: ``"given"``, ``"mode"``, the borderline decision or the hidden limbs.
    """

    K: int
    assignment: np.ndarray
    references: list
    error: np.ndarray
    count_rule: str = "given"


#: A count of clear tips that at least this share of the frames with tips reach raises ``K`` to it
#: (module docstring: hidden limbs).
HIDDEN_SHARE = 0.1
#: A count seen in this share of the frames with tips (beside the mode) is borderline.
BORDERLINE = (0.4, 0.6)
#: The extra limb of a borderline count is "the same limb" when its aligned tip stays
#: within this many RMS radii of the reference tips of its mean position.
SAME_LIMB_SPREAD = 0.4
#: ... or when it moves continuously: over at least ``SMOOTH_PAIRS`` pairs of consecutive frames,
#: its RMS step is at most ``SMOOTH`` times what positions drawn independently would give
#: (``sqrt(2)`` times its spread). A bump at a random place each frame scores about 1, an arm
#: swinging by the body about 0.2 at 30 frames a second; a few bumps score as low as an arm, more
#: of them over few pairs (docs/notes/tracking-decisions.md, "The spine's borderline count at 10
#: frames a second", has the figures).
SMOOTH = 0.35
SMOOTH_PAIRS = 5


def _extra_limb_track(frames, corr: "Correspondence") -> tuple[float, float, int]:
    """The least-seen limb's tip, aligned onto the reference by the other limbs: its spread over
    the frames where every limb is seen (RMS distance to its mean / RMS tip radius), and its
    smoothness over the frames with ``K`` tips where the other limbs are seen (RMS step between
    consecutive ones / (sqrt(2) x RMS distance to its mean): the tip the others leave, whether the
    gate kept it or not, so the correspondence's own choices do not make a random bump look
    continuous) with the number of consecutive pairs."""
    A = corr.assignment
    K = corr.K
    extra = int(np.argmin((A >= 0).sum(axis=0)))
    others = [k for k in range(K) if k != extra]
    r0 = corr.references[0]
    ref = frames[r0][A[r0]]
    radius = _rms_spread(ref) or 1.0
    seen, left = {}, {}
    for t in np.flatnonzero(np.all(A[:, others] >= 0, axis=1)):
        if len(frames[t]) != K and A[t, extra] < 0:
            continue
        P = frames[t][A[t, others]]
        R, T, _ = arun_alignment(P, ref[others])
        rest = np.setdiff1d(np.arange(len(frames[t])), A[t, others])
        if A[t, extra] >= 0:
            seen[int(t)] = R @ frames[t][A[t, extra]] + T
        if len(frames[t]) == K and len(rest) == 1:
            left[int(t)] = R @ frames[t][rest[0]] + T
    spread = _rms_spread(list(seen.values())) / radius if len(seen) >= 2 else float("inf")
    steps = [float(np.sum((left[t + 1] - left[t]) ** 2)) for t in left if t + 1 in left]
    rms = _rms_spread(list(left.values())) if len(left) >= 2 else 0.0
    smooth = float(np.sqrt(np.mean(steps)) / (math.sqrt(2) * rms)) if steps and rms > 0 else float("inf")
    return spread, smooth, len(steps)


def _rms_spread(points) -> float:
    """RMS distance of ``points`` (n, 3) to their mean."""
    X = np.asarray(points)
    return float(np.sqrt(np.mean(np.sum((X - X.mean(0)) ** 2, axis=1))))


def _errors(A, B, rigid=True):
    """Eq. 6 residuals (rigid for >= 3 points, translation-only below or when not ``rigid``)."""
    if rigid and B.shape[1] >= 3:
        return alignment_errors(A, B)
    A = np.asarray(A)
    if A.ndim == 2:
        A = A[None]
    Ac = A - A.mean(axis=1, keepdims=True)
    Bc = B - B.mean(axis=1, keepdims=True)
    return np.sum((Bc - Ac) ** 2, axis=(1, 2))


def _best_mapping(
    pts: np.ndarray, anchors: list[np.ndarray], K: int, max_perms: int, weights=None
) -> tuple[np.ndarray, float]:
    """Best injective mapping limb slot -> frame tip (``-1`` for empty slots).

    pts : (n, m, 3) tip plus limb points of each frame tip.
    anchors : (K, m, 3) arrays with nan for limbs unknown in that anchor.
    """
    n, m = pts.shape[:2]
    weights = [1.0] * len(anchors) if weights is None else list(weights)
    # a negative weight marks a temporal neighbour: translation-only residual
    rigid = [w >= 0 for w in weights]
    weights = [abs(w) for w in weights]
    known = np.ones(K, dtype=bool)
    for a in anchors:
        known &= np.all(np.isfinite(a.reshape(K, -1)), axis=1)
    if n >= K:
        if math.perm(n, K) > max_perms:
            return _local_search(pts, anchors, K)
        P = _perms(n, K)
        slots = np.flatnonzero(known)
        if len(slots) == 0:
            return P[0].copy(), float("nan")
        B = pts[P[:, slots]].reshape(len(P), -1, 3)
        err = np.zeros(len(P))
        for a, w, rg in zip(anchors, weights, rigid):
            err += w * _errors(a[slots].reshape(-1, 3), B, rg)
        # candidates differing only in unknown slots tie: keep the first
        i = int(np.argmin(err))
        return P[i].copy(), float(err[i])
    if math.perm(K, n) > max_perms:
        return _local_search(pts, anchors, K)
    P = _perms(K, n)  # P[i, j] = slot of tip j
    if known.sum() >= n:
        P = P[np.all(known[P], axis=1)]
    B = np.broadcast_to(pts.reshape(1, -1, 3), (len(P), n * m, 3))
    err = np.zeros(len(P))
    for a, w, rg in zip(anchors, weights, rigid):
        A = np.nan_to_num(a[P].reshape(len(P), -1, 3))
        err += w * _errors(A, B, rg)
    i = int(np.argmin(err))
    out = np.full(K, -1, dtype=np.int64)
    out[P[i]] = np.arange(n)
    return out, float(err[i])


def _mapping_error(pts, anchors, mapping):
    sl = np.flatnonzero(mapping >= 0)
    B = pts[mapping[sl]].reshape(1, -1, 3)
    e = 0.0
    for a in anchors:
        A = a[sl].reshape(-1, 3)
        ok = np.all(np.isfinite(A), axis=1)
        if ok.any():
            e += float(_errors(A[ok], B[:, ok])[0])
    return e


def _local_search(pts, anchors, K):
    """Hungarian on centred tip positions, then greedy swaps and replacements (very large K)."""
    n = len(pts)
    tips = pts[:, 0]
    a = anchors[0][:, 0]
    okA = np.all(np.isfinite(a), axis=1)
    ca = a[okA].mean(0)
    cb = tips.mean(0)
    cost = np.linalg.norm((a - ca)[:, None, :] - (tips - cb)[None], axis=2)
    cost = np.where(np.isfinite(cost), cost, 1e9)
    r, c = linear_sum_assignment(cost)
    mapping = np.full(K, -1, dtype=np.int64)
    mapping[r] = c
    best = _mapping_error(pts, anchors, mapping)
    improved = True
    while improved:
        improved = False
        for i in range(K):
            cands = []
            for j in range(i + 1, K):
                m2 = mapping.copy()
                m2[i], m2[j] = m2[j], m2[i]
                cands.append(m2)
            used = set(mapping[mapping >= 0].tolist())
            for u in range(n):
                if u not in used:
                    m2 = mapping.copy()
                    m2[i] = u
                    cands.append(m2)
            for m2 in cands:
                e = _mapping_error(pts, anchors, m2)
                if e < best - 1e-12:
                    best, mapping, improved = e, m2, True
    return mapping, best


def correspond_tips(
    tips,
    *,
    features=None,
    clear=None,
    K: int | None = None,
    reference_span: int = 150,
    max_permutations: int = 40320,
    gate: float = 1.0,
    reference_weight: float = 0.1,
) -> Correspondence:
    """Assign every frame's tips to ``K`` limbs consistently over a take (section 4.2).

    Parameters
    ----------
    tips : sequence of (n_t, 3) float ndarray
        Tips of each frame, in take order (``n_t`` may be 0).
    features : sequence of (n_t, m, 3) float ndarray, optional
        Further points that move with each tip (points along its limb, see
        :func:`pipeline.skeleton.limb_points`); aligned together with the
        tips, so whole skeletons are aligned rather than tips alone.
    clear : sequence of (n_t,) bool array-like, optional
        Which tips of each frame protrude clearly
        (:attr:`pipeline.extremities.Extremities.clear`); lets hidden limbs count
        (module docstring).
    K : int, optional
        Number of limbs; default ``mode n_t`` (raised by the clear tips, when given).
    reference_span : int
        One reference frame per this many frames.
    max_permutations : int
        Exhaustive search up to this many mappings per frame.
    gate : float
        Drop a tip farther than ``gate`` x (RMS radius of the reference tips)
        from its limb's position in the aligned temporal neighbour.

    reference_weight : float
        Weight of the reference frame's residual against the temporal
        neighbour's (1.0) when both anchor a frame.

    Returns
    -------
    Correspondence

    Raises
    ------
    NoLimbsError
        When no frame has a tip (or ``K`` would be 0).
    """
    frames = _check_tips(tips)
    if max_permutations < 1:
        raise ValueError(f"max_permutations must be >= 1, got {max_permutations}")
    if not gate > 0:
        raise ValueError(f"gate must be > 0, got {gate}")
    pts = _tip_points(frames, features)
    clear_counts = _clear_counts(frames, clear)
    opts = dict(reference_span=reference_span, max_permutations=max_permutations, gate=gate,
                reference_weight=reference_weight)
    if K is None:
        corr = _with_counted_K(frames, pts, opts)
        hidden = _hidden_limbs(frames, clear_counts, corr.K)
        if hidden is None:
            return corr
        return _correspond(frames, pts, hidden[0], hidden[1], **opts)
    return _correspond(frames, pts, int(K), "given", **opts)


def _check_tips(tips) -> list[np.ndarray]:
    frames = []
    for i, t in enumerate(tips):
        a = np.asarray(t, dtype=np.float64)
        if a.size == 0:
            a = a.reshape(0, 3)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"tips[{i}] must have shape (n, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"tips[{i}] must be finite")
        frames.append(a)
    if not frames:
        raise ValueError("tips must hold at least one frame")
    return frames


def _clear_counts(frames: list[np.ndarray], clear) -> np.ndarray | None:
    """Clear tips per frame, or None when ``clear`` is not given."""
    if clear is None:
        return None
    clear = list(clear)
    if len(clear) != len(frames):
        raise ValueError(f"clear must have one entry per frame ({len(frames)}), got {len(clear)}")
    out = []
    for i, (a, c) in enumerate(zip(frames, clear)):
        c = np.asarray(c)
        if c.shape != (len(a),) or not (c.dtype == bool or np.isin(c, (0, 1)).all()):
            raise ValueError(f"clear[{i}] must hold one bool per tip ({len(a)}), got shape {c.shape}")
        out.append(int(np.count_nonzero(c)))
    return np.asarray(out, dtype=np.int64)


def _hidden_limbs(frames, clear_counts, K: int) -> tuple[int, str] | None:
    """``(K, rule)`` raised by the clear tips (module docstring: hidden limbs), or None to keep ``K``."""
    if clear_counts is None:
        return None
    counts = np.asarray([len(a) for a in frames])
    with_tips = counts > 0
    if not with_tips.any():
        return None
    cc = clear_counts[with_tips]
    for n in range(int(cc.max()), K, -1):
        share = float(np.mean(cc >= n))
        if share >= HIDDEN_SHARE and n in counts:
            rule = (f"hidden limbs: {n} clear tips in {100 * share:.0f} % of the frames with tips (at least "
                    f"{100 * HIDDEN_SHARE:.0f} %); the mode count {K} misses limbs fused with the body elsewhere")
            return n, rule
    return None


def _tip_points(frames: list[np.ndarray], features) -> list[np.ndarray]:
    """(n_t, m, 3) per frame: each tip followed by the points along its limb."""
    if features is None:
        return [a[:, None, :] for a in frames]
    features = list(features)
    if len(features) != len(frames):
        raise ValueError(f"features must have one entry per frame ({len(frames)}), got {len(features)}")
    pts = []
    for i, (a, fe) in enumerate(zip(frames, features)):
        fe = np.asarray(fe, dtype=np.float64)
        if len(a) == 0:
            pts.append(None)
            continue
        if fe.size == 0:
            fe = fe.reshape(len(a), 0, 3)
        if fe.ndim != 3 or fe.shape[0] != len(a) or fe.shape[2] != 3 or not np.all(np.isfinite(fe)):
            raise ValueError(f"features[{i}] must be finite with shape ({len(a)}, m, 3), got {fe.shape}")
        pts.append(np.concatenate([a[:, None, :], fe], axis=1))
    widths = {p.shape[1] for p in pts if p is not None}
    if len(widths) > 1:
        raise ValueError("features must have the same number of points per tip in every frame")
    w = widths.pop() if widths else 1
    return [np.zeros((0, w, 3)) if p is None else p for p in pts]


def _with_counted_K(frames, pts, opts) -> Correspondence:
    """``K`` = the mode of the tip counts, unless the count is borderline: the larger of two
    neighbouring counts is found in 40-60 % of the frames with tips (whether it is the mode
    or not); then the larger count when the extra limb is the same limb throughout, else the
    smaller (module docstring)."""
    counts = [len(a) for a in frames]
    K = limb_count(counts)
    with_tips = np.asarray([c for c in counts if c > 0])

    def share(n: int) -> float:
        return float(np.mean(with_tips >= n)) if with_tips.size else 0.0

    lo, hi = BORDERLINE
    if lo <= share(K + 1) <= hi and (K + 1) in counts:
        small, large = K, K + 1
    elif K > 1 and lo <= share(K) <= hi and (K - 1) in counts:
        small, large = K - 1, K
    else:
        return _correspond(frames, pts, K, "mode", **opts)
    wider = _correspond(frames, pts, large, "", **opts)
    spread, smooth, pairs = _extra_limb_track(frames, wider)
    moves = pairs >= SMOOTH_PAIRS and smooth <= SMOOTH
    same = spread <= SAME_LIMB_SPREAD or moves
    why = (f"spread {spread:.2f} of the tip radius, limit {SAME_LIMB_SPREAD}; step {smooth:.2f} of a random "
           f"place's over {pairs} pairs of consecutive frames, limit {SMOOTH} over {SMOOTH_PAIRS}")
    rule = (
        f"borderline: {large} tips in {100 * share(large):.0f} % of the frames; the extra limb "
        f"{'is' if same else 'is not'} the same limb throughout ({why}): K = {large if same else small}"
    )
    if same:
        return Correspondence(K=wider.K, assignment=wider.assignment, references=wider.references,
                              error=wider.error, count_rule=rule)
    return _correspond(frames, pts, small, rule, **opts)


def _correspond(frames, pts, K: int, rule: str, *, reference_span, max_permutations, gate, reference_weight):
    counts = [len(a) for a in frames]
    if K < 1:
        raise NoLimbsError("no limb tips found in any frame (K = 0): nothing protrudes")
    if K not in counts:
        raise ValueError(f"K={K} but no frame has {K} tips")
    refs = reference_frames(counts, K, span=reference_span)
    assign = np.full((len(frames), K), -1, dtype=np.int64)
    err = np.full(len(frames), np.nan)
    assign[refs[0]] = np.arange(K)
    err[refs[0]] = 0.0
    _sweep(pts, counts, refs, assign, err, max_permutations=max_permutations, reference_weight=reference_weight)
    ref_tips = frames[refs[0]]
    radius = _rms_spread(ref_tips)
    _gate(frames, counts, refs[0], assign, gate * max(radius, 1e-12))
    return Correspondence(K=K, assignment=assign, references=list(refs), error=err, count_rule=rule)


def _limb_rows(values: np.ndarray, mapping: np.ndarray, K: int) -> np.ndarray:
    """Per limb slot, the frame's row it is mapped to (nan for an empty slot)."""
    out = np.full((K,) + values.shape[1:], np.nan)
    ok = mapping >= 0
    out[ok] = values[mapping[ok]]
    return out


def _sweep(pts, counts, refs, assign, err, *, max_permutations, reference_weight) -> None:
    """Every frame with tips, outward from the primary reference, against the nearest
    reference and the last seen position of every limb (a limb missing from some frames
    keeps its place, so the others never have to take it)."""
    T, K = assign.shape
    r0 = refs[0]
    assigned_refs = {r0}
    for direction in (1, -1):
        last = _limb_rows(pts[r0], assign[r0], K)
        t = r0 + direction
        while 0 <= t < T:
            if counts[t] > 0:
                near_ref = min(assigned_refs, key=lambda r, t=t: abs(r - t))
                # the temporal neighbour always anchors too (translation only): a rigid fit
                # alone, even to the adjacent reference, may turn a near-symmetric body half
                # round (a quadruped's front legs onto its hind legs, head onto tail)
                anchors = [_limb_rows(pts[near_ref], assign[near_ref], K), last]
                w = [reference_weight, -1.0]
                m, e = _best_mapping(pts[t], anchors, K, max_permutations, w)
                assign[t] = m
                err[t] = e
                seen = m >= 0
                last = last.copy()
                last[seen] = pts[t][m[seen]]
                if t in refs and counts[t] == K:
                    assigned_refs.add(t)
            t += direction


def _gate(frames, counts, r0: int, assign, gate_d: float) -> None:
    """Drop tips farther than ``gate_d`` from their limb in the aligned nearest K-tip neighbour."""
    T, K = assign.shape
    kframes = np.flatnonzero(np.asarray(counts) == K)
    for t in range(T):
        if counts[t] == 0 or t == r0:
            continue
        others = kframes[kframes != t]
        if len(others) == 0:
            continue
        nb = int(others[np.argmin(np.abs(others - t))])
        A = _limb_rows(frames[nb], assign[nb], K)
        B = _limb_rows(frames[t], assign[t], K)
        ok = np.all(np.isfinite(A), axis=1) & np.all(np.isfinite(B), axis=1)
        if ok.sum() < 3:
            continue
        resid = _robust_residuals(A[ok], B[ok])
        bad = np.flatnonzero(ok)[resid > gate_d]
        assign[t, bad] = -1


def _robust_residuals(A, B):
    """Per-point residual after a rigid fit, refit without the worst point (one outlier)."""
    R, T, _ = arun_alignment(A, B)
    r = np.linalg.norm(B - A @ R.T - T, axis=1)
    if len(A) >= 4:
        keep = np.ones(len(A), dtype=bool)
        keep[int(np.argmax(r))] = False
        R, T, _ = arun_alignment(A[keep], B[keep])
        r = np.linalg.norm(B - A @ R.T - T, axis=1)
    return r
