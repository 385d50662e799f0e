"""Accuracy of a spine against the simulated rig's ground truth.

The spine's limbs are matched to the true limbs once for the whole take (Hungarian
assignment on the mean tip distance), then measured frame by frame:

- ``tip_error``: distance from each spine tip to its matched true tip, as a fraction
  of the creature's size (the diagonal of the bounding box of its limb axes over the
  take);
- ``identity``: a frame is consistent when the frame's own best assignment of seen
  spine tips to true tips agrees with the take-level match;
- ``axis_error``: mean distance from the points of each spine axis to the matched
  true limb axis (a polyline), as a fraction of the size.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["evaluate_spine", "point_polyline_distance"]


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


def evaluate_spine(
    spine: Mapping,
    true_tips: np.ndarray,
    true_axes: Mapping[str, np.ndarray],
    limb_names: Sequence[str],
    *,
    tip_tolerance: float = 0.03,
) -> dict:
    """Compare a ``capture-stage/spine@1`` dictionary with the ground truth.

    Parameters
    ----------
    spine : dict
        As written to ``spine.json`` (``Spine.to_dict()``).
    true_tips : (F, L, 3) float ndarray
        True limb tips per frame, in ``limb_names`` order.
    true_axes : dict limb -> (F, K, 3) float ndarray
        True limb axes (junction to tip) per frame.
    limb_names : sequence of str
    tip_tolerance : float
        A tip counts as found within this fraction of the creature's size.

    Returns
    -------
    dict
        ``K``, ``true_limbs``, ``size``, ``match`` (spine limb -> true limb),
        ``tip_within_tol`` (fraction of (frame, true limb) with a matched spine tip within
        tolerance), ``tip_error_median``/``tip_error_p95`` (fractions of size),
        ``identity_consistent`` (fraction of frames), ``axis_error_mean`` (fraction of size),
        ``seen`` (fraction of (frame, limb) where the spine has a tip).
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
    limbs = list(spine["graph"]["limbs"])
    K = len(limbs)
    allpts = np.concatenate([np.asarray(true_axes[n], float).reshape(-1, 3) for n in limb_names] + [tips.reshape(-1, 3)])
    size = float(np.linalg.norm(allpts.max(0) - allpts.min(0)))

    S = np.full((F, K, 3), np.nan)
    for f, fr in enumerate(frames):
        for j, limb in enumerate(limbs):
            t = fr["tips"].get(limb)
            if t is not None:
                S[f, j] = t
    # take-level match
    cost = np.zeros((K, L))
    for j in range(K):
        d = np.linalg.norm(S[:, j, None, :] - tips, axis=2)  # (F, L)
        with np.errstate(invalid="ignore"):
            cost[j] = np.nanmean(np.where(np.isnan(d), np.nan, d), axis=0) if np.isfinite(d).any() else 1e9
    cost = np.nan_to_num(cost, nan=1e9)
    rows, cols = linear_sum_assignment(cost) if K and L else (np.zeros(0, int), np.zeros(0, int))
    match = {limbs[r]: limb_names[c] for r, c in zip(rows, cols)}

    errs = []
    within = 0
    consistent = 0
    for f in range(F):
        seen = [j for j in range(K) if np.isfinite(S[f, j]).all()]
        for r, c in zip(rows, cols):
            if np.isfinite(S[f, r]).all():
                e = np.linalg.norm(S[f, r] - tips[f, c]) / size
                errs.append(e)
                within += e <= tip_tolerance
        if seen:
            d = np.linalg.norm(S[f, seen][:, None, :] - tips[f][None], axis=2)
            rr, cc = linear_sum_assignment(d)
            frame_match = {limbs[seen[a]]: limb_names[b] for a, b in zip(rr, cc)}
            consistent += all(match.get(k) == v for k, v in frame_match.items())
        else:
            consistent += 1
    axis_errs = []
    for f, fr in enumerate(frames):
        for r, c in zip(rows, cols):
            ax = fr.get("axes", {}).get(limbs[r])
            if ax:
                d = point_polyline_distance(np.asarray(ax, float), np.asarray(true_axes[limb_names[c]][f], float))
                axis_errs.append(d.mean() / size)
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
    }
