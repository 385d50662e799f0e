"""Accuracy of a spine against the simulated rig's ground truth.

The spine's limbs are matched to the true limbs once for the whole take (Hungarian
assignment on the mean tip distance), then measured frame by frame:

- ``tip_error``: distance from each spine tip to its matched true tip, as a fraction
  of the creature's size (the diagonal of the bounding box of its limb axes over the
  take);
- ``identity``: a frame is consistent when the frame's own best assignment of seen
  spine tips to true tips agrees with the take-level match;
- ``axis_error``: mean distance from the points of each spine axis to the matched
  true limb axis (a polyline), as a fraction of the size, over the whole spine axis;
- ``limb_axis_error`` (when the true poses are given): the same comparison restricted
  to the *limbs*, i.e. to the parts of both axes that lie outside the creature's body.

Why the limb axis error leaves the body out
-------------------------------------------
In Brostow et al. (2004, §4.1 and §4.3) a spine is a graph whose limbs are chains of
ring centroids running from a *junction* to a tip, and the junctions (metanodes where
the limbs of the merged per-tip skeletons meet) lie *inside* the body: on a starfish
or a quadruped every limb's chain continues through the torso to the common junction
near the body's centre. The simulator's ground truth (:attr:`Pose.axes
<fake_cameras.creatures.Pose>`) instead starts each limb axis at the limb's
attachment point on the body and has no axis inside the body at all (the body is a
few fat capsules, not a chain). Measured over the whole spine axis, the stretch from
the junction to where the limb leaves the body is therefore scored against the
attachment end of the true axis: an error by construction that says nothing about
the limb (several times the error of the same axes outside the body).

``limb_axis_error`` therefore compares, per frame and matched limb, only the points
outside every body capsule (``Pose.limb == -1``, signed distance > 0): both polylines
are resampled densely along their length (step ``size / 400``), the points inside the
body are dropped, and the score is the symmetric mean

    0.5 * (mean over spine-limb points of their distance to the true axis
           + mean over true-limb points of their distance to the spine axis),

so a spine limb that stops short of the true one (or runs off elsewhere) is penalised
as much as one that strays. A (frame, limb) pair with no point outside the body on
either side is skipped (and counted in ``limb_axis_skipped``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["evaluate_spine", "point_polyline_distance", "resample_polyline", "limb_axis_distance"]


def point_polyline_distance(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance from each point to a polyline.

    Parameters
    ----------
    points : (N, 3) float ndarray
    polyline : (K, 3) float ndarray, K >= 1

    Returns
    -------
    (N,) float ndarray
    """
    p = np.asarray(points, float).reshape(-1, 3)
    q = np.asarray(polyline, float).reshape(-1, 3)
    if q.shape[0] == 0:
        raise ValueError("polyline must have at least one point")
    if q.shape[0] == 1:
        return np.linalg.norm(p - q[0], axis=1)
    a, b = q[:-1], q[1:]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(1), 1e-30)
    t = np.clip(((p[:, None, :] - a[None]) * ab[None]).sum(2) / L2[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(p[:, None, :] - closest, axis=2).min(axis=1)


def resample_polyline(polyline: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline at most ``step`` apart, vertices included.

    Parameters
    ----------
    polyline : (K, 3) float ndarray, K >= 1
    step : float
        Largest spacing (same units as the polyline), > 0.

    Returns
    -------
    (N, 3) float ndarray
    """
    q = np.asarray(polyline, float).reshape(-1, 3)
    if q.shape[0] == 0:
        raise ValueError("polyline must have at least one point")
    if not step > 0:
        raise ValueError(f"step must be positive, got {step}")
    out = [q[:1]]
    for a, b in zip(q[:-1], q[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def limb_axis_distance(spine_axis: np.ndarray, true_axis: np.ndarray, pose, *, step: float) -> float | None:
    """Symmetric mean distance between a spine limb and a true limb outside the body.

    Both polylines are resampled (:func:`resample_polyline`), points inside any body
    capsule of ``pose`` (limb label -1) are dropped, and the result is the mean of the
    two directed mean point-to-polyline distances (module docstring).

    Parameters
    ----------
    spine_axis, true_axis : (K, 3) float ndarray
        Junction-to-tip polylines.
    pose : fake_cameras.creatures.Pose
        The true pose of that frame (its body capsules).
    step : float
        Resampling step, > 0.

    Returns
    -------
    float or None
        ``None`` when either limb has no point outside the body.
    """
    S = resample_polyline(spine_axis, step)
    T = resample_polyline(true_axis, step)
    body = np.asarray(pose.limb) == -1
    if body.any():
        S = S[pose.capsule_sdf(S)[:, body].min(axis=1) > 0]
        T = T[pose.capsule_sdf(T)[:, body].min(axis=1) > 0]
    if len(S) < 2 or len(T) < 2:
        return None
    # distances to the *whole* other polyline (not only its outside part): where a limb
    # leaves the body is a property of the surface, not of either axis
    d_st = point_polyline_distance(S, np.asarray(true_axis, float)).mean()
    d_ts = point_polyline_distance(T, np.asarray(spine_axis, float)).mean()
    return float(0.5 * (d_st + d_ts))


def evaluate_spine(
    spine: Mapping,
    true_tips: np.ndarray,
    true_axes: Mapping[str, np.ndarray],
    limb_names: Sequence[str],
    *,
    tip_tolerance: float = 0.03,
    poses: Sequence | None = None,
) -> dict:
    """Compare a ``capture-stage/spine@1`` dictionary with the ground truth.

    Parameters
    ----------
    spine : dict
        As written to ``spine.json`` (``Spine.to_dict()``).
    true_tips : (F, L, 3) float ndarray
        True limb tips per frame, in ``limb_names`` order.
    true_axes : dict limb -> (F, K, 3) float ndarray
        True limb axes (junction to tip) per frame; a limb without one (a mesh subject's named
        tips) is scored on its tip only.
    limb_names : sequence of str
    tip_tolerance : float
        A tip counts as found within this fraction of the creature's size.
    poses : sequence of fake_cameras.creatures.Pose, optional
        The true pose of every frame; when given, ``limb_axis_error_mean`` is measured
        on the limbs outside the body (module docstring).

    Returns
    -------
    dict
        ``K``, ``true_limbs``, ``size``, ``match`` (spine limb -> true limb),
        ``tip_within_tol`` (fraction of (frame, true limb) with a matched spine tip within
        tolerance), ``tip_error_median``/``tip_error_p95`` (fractions of size),
        ``identity_consistent`` (fraction of frames), ``axis_error_mean`` (fraction of size),
        ``seen`` (fraction of (frame, limb) where the spine has a tip);
        with ``poses``: ``limb_axis_error_mean`` (fraction of size, symmetric, outside the
        body) and ``limb_axis_skipped`` (number of (frame, limb) pairs with no limb outside
        the body), otherwise both ``None``.
    """
    tips = np.asarray(true_tips, float)
    if tips.ndim != 3 or tips.shape[2] != 3:
        raise ValueError(f"true_tips must be (F, L, 3), got {tips.shape}")
    F, L, _ = tips.shape
    if len(limb_names) != L:
        raise ValueError("limb_names must name every true limb")
    frames = spine.get("frames", [])
    if len(frames) != F:
        raise ValueError(f"spine has {len(frames)} frames, the ground truth {F}")
    if poses is not None and len(poses) != F:
        raise ValueError(f"poses must give one pose per frame ({F}), got {len(poses)}")
    limbs = list(spine["graph"]["limbs"])
    K = len(limbs)
    allpts = np.concatenate([np.asarray(true_axes[n], float).reshape(-1, 3) for n in limb_names if n in true_axes]
                            + [tips.reshape(-1, 3)])
    size = float(np.linalg.norm(allpts.max(0) - allpts.min(0)))
    S = _spine_tips(frames, limbs)
    rows, cols = _take_match(S, tips)
    match = {limbs[r]: limb_names[c] for r, c in zip(rows, cols)}
    pairs = [(limbs[r], limb_names[c]) for r, c in zip(rows, cols)]
    errs, within = _tip_errors(S, tips, rows, cols, size=size, tip_tolerance=tip_tolerance)
    consistent = _consistent_frames(S, tips, limbs, limb_names, match)
    axis_errs = [e / size for e in _axis_distances(frames, pairs, true_axes)]
    limb_errs: list[float] = []
    skipped = 0
    if poses is not None:
        limb_errs, skipped = _limb_axis_errors(frames, pairs, true_axes, poses, size=size)
    errs_a = np.asarray(errs) if errs else np.asarray([np.inf])
    return {
        "K": K,
        "true_limbs": L,
        "size": size,
        "match": match,
        "tip_within_tol": within / max(1, F * min(K, L)),
        "tip_error_median": float(np.median(errs_a)),
        "tip_error_p95": float(np.percentile(errs_a, 95)),
        "identity_consistent": consistent / max(1, F),
        "axis_error_mean": float(np.mean(axis_errs)) if axis_errs else float("inf"),
        "seen": float(np.isfinite(S[..., 0]).mean()) if K else 0.0,
        "limb_axis_error_mean": (float(np.mean(limb_errs)) if limb_errs else float("inf")) if poses is not None else None,
        "limb_axis_skipped": skipped if poses is not None else None,
    }


# --------------------------------------------------------------------------- evaluate_spine, step by step


def _spine_tips(frames: Sequence[Mapping], limbs: Sequence[str]) -> np.ndarray:
    """(F, K, 3) spine tips per frame, nan where a limb has no tip."""
    S = np.full((len(frames), len(limbs), 3), np.nan)
    for f, fr in enumerate(frames):
        for j, limb in enumerate(limbs):
            t = fr["tips"].get(limb)
            if t is not None:
                S[f, j] = t
    return S


def _take_match(S: np.ndarray, tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One assignment of spine limbs to true limbs for the whole take (mean tip distance, Hungarian)."""
    K, L = S.shape[1], tips.shape[1]
    cost = np.zeros((K, L))
    for j in range(K):
        d = np.linalg.norm(S[:, j, None, :] - tips, axis=2)  # (F, L)
        with np.errstate(invalid="ignore"):
            cost[j] = np.nanmean(np.where(np.isnan(d), np.nan, d), axis=0) if np.isfinite(d).any() else 1e9
    cost = np.nan_to_num(cost, nan=1e9)
    return linear_sum_assignment(cost) if K and L else (np.zeros(0, int), np.zeros(0, int))


def _tip_errors(S, tips, rows, cols, *, size: float, tip_tolerance: float) -> tuple[list[float], int]:
    """Tip errors (fractions of size) of the matched limbs where seen, and how many are within tolerance."""
    errs, within = [], 0
    for f in range(len(S)):
        for r, c in zip(rows, cols):
            if np.isfinite(S[f, r]).all():
                e = np.linalg.norm(S[f, r] - tips[f, c]) / size
                errs.append(e)
                within += e <= tip_tolerance
    return errs, within


def _consistent_frames(S, tips, limbs, limb_names, match: dict) -> int:
    """Frames whose own best assignment agrees with the take's (frames with no tip count as consistent)."""
    consistent = 0
    for f in range(len(S)):
        seen = [j for j in range(len(limbs)) if np.isfinite(S[f, j]).all()]
        if not seen:
            consistent += 1
            continue
        d = np.linalg.norm(S[f, seen][:, None, :] - tips[f][None], axis=2)
        rr, cc = linear_sum_assignment(d)
        frame_match = {limbs[seen[a]]: limb_names[b] for a, b in zip(rr, cc)}
        consistent += all(match.get(k) == v for k, v in frame_match.items())
    return consistent


def _axis_distances(frames, pairs, true_axes) -> list[float]:
    """Mean distance of every matched spine axis to its true axis, per (frame, limb) with an axis."""
    out = []
    for f, fr in enumerate(frames):
        for limb, true_limb in pairs:
            ax = fr.get("axes", {}).get(limb)
            if ax and true_limb in true_axes:
                d = point_polyline_distance(np.asarray(ax, float), np.asarray(true_axes[true_limb][f], float))
                out.append(d.mean())
    return out


def _limb_axis_errors(frames, pairs, true_axes, poses, *, size: float) -> tuple[list[float], int]:
    """:func:`limb_axis_distance` (fractions of size) per (frame, limb), and the pairs with nothing outside."""
    errs, skipped = [], 0
    step = size / 400
    for f, fr in enumerate(frames):
        for limb, true_limb in pairs:
            ax = fr.get("axes", {}).get(limb)
            if not ax or true_limb not in true_axes:
                continue
            e = limb_axis_distance(np.asarray(ax, float), np.asarray(true_axes[true_limb][f], float), poses[f], step=step)
            if e is None:
                skipped += 1
            else:
                errs.append(e / size)
    return errs, skipped
