"""Pairwise trajectory distances of a mesh sequence's vertices (Tzionas & Gall 2016, eqs. 8-9).

``d^v_ij``: the largest change of the distance between vertices ``i`` and ``j`` between two frames at
most ``dt`` apart (eq. 8); ``d^n_ij``: the same for the angle between their normals (eq. 9, radians).
The motion segmentation (:mod:`pipeline.motion_segmentation`) builds its affinities from them.

Hand-written because no library computes a sliding-window range of pairwise distances; the windows'
extremes are taken whole frames at a time (:func:`_window_extreme`), the distances by batched BLAS.
"""

from __future__ import annotations

import numpy as np

__all__ = ["trajectory_distances"]


def _window_extreme(x: np.ndarray, width: int, op) -> np.ndarray:
    """``op`` (np.maximum or np.minimum) over every window ``x[t : t + width]``, t = 0 .. T - width.

    Whole frames at a time (contiguous memory): a running loop for short windows, doubling
    (extremes over 1, 2, 4, .. frames, then two overlapping spans) for medium ones, and the van
    Herk / Gil-Werman decomposition for long ones (running prefix and suffix extremes within blocks
    of ``width`` frames, one frame of every block per step: three passes whatever the width).
    """
    T = x.shape[0]
    n_win = T - width + 1
    if width <= 8:
        out = x[:n_win].copy()
        for k in range(1, width):
            op(out, x[k : k + n_win], out=out)
        return out
    if width <= 16:
        cur = op(x[:-1], x[1:])  # extremes over 2 frames (the first doubling, no copy of x)
        span = 2
        while 2 * span <= width:
            n = T - 2 * span + 1
            op(cur[:n], cur[span : span + n], out=cur[:n])
            span *= 2
        # cur[t] = extreme of x[t : t + span]; a window of ``width`` is two such spans
        return op(cur[:n_win], cur[width - span : width - span + n_win])
    pre = np.empty_like(x)
    suf = np.empty_like(x)
    for start in range(0, T, width):
        end = min(T, start + width)
        pre[start] = x[start]
        for k in range(start + 1, end):
            op(pre[k - 1], x[k], out=pre[k])
        suf[end - 1] = x[end - 1]
        for k in range(end - 2, start - 1, -1):
            op(suf[k + 1], x[k], out=suf[k])
    # a window starting at t spans the suffix of t's block and the prefix of the next up to t + width - 1
    return op(suf[:n_win], pre[width - 1 : width - 1 + n_win], out=suf[:n_win])


def _window_range(x: np.ndarray, width: int) -> np.ndarray:
    """max over t of (max - min of x[t .. t+width-1]) along axis 0."""
    T = x.shape[0]
    if width >= T:
        return x.max(0) - x.min(0)
    hi = _window_extreme(x, width, np.maximum)
    hi -= _window_extreme(x, width, np.minimum)
    return hi.max(0)


def trajectory_distances(
    trajectories, normals=None, *, interval: int, block_elements: int = 12_000_000
) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise trajectory distances ``d^v`` and ``d^n`` (Tzionas & Gall eqs. 8, 9).

    ``d^v_ij`` is the largest change of the distance between vertices ``i``
    and ``j`` between two frames at most ``interval`` frames apart; ``d^n_ij``
    the same for the angle between their normals.

    Parameters
    ----------
    trajectories : (T, n, 3) float ndarray
    normals : (T, n, 3) float ndarray, optional
        Unit normals; ``d^n`` is zero when omitted.
    interval : int
        ``dt`` in frames (>= 1).
    block_elements : int
        Working-set size (elements) of one block of rows.

    Returns
    -------
    dv, dn : (n, n) float32 ndarray
        Symmetric, zero diagonal.
    """
    X = np.asarray(trajectories, dtype=np.float32)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"trajectories must have shape (T, n, 3), got {X.shape}")
    T, n, _ = X.shape
    if int(interval) < 1:
        raise ValueError(f"interval must be >= 1, got {interval}")
    width = int(interval) + 1
    X = X - X.mean(1, keepdims=True)
    sq = (X * X).sum(2)  # (T, n)
    N = None
    if normals is not None:
        N = np.asarray(normals, dtype=np.float32)
        if N.shape != X.shape:
            raise ValueError(f"normals must have the shape of trajectories {X.shape}, got {N.shape}")
    dv = np.zeros((n, n), dtype=np.float32)
    dn = np.zeros((n, n), dtype=np.float32)
    rows = max(1, int(block_elements) // max(T * n, 1))
    for a in range(0, n, rows):
        b = min(n, a + rows)
        cols = slice(a, n)  # upper triangle only
        G = np.matmul(X[:, a:b], X[:, cols].transpose(0, 2, 1))  # batched BLAS, not einsum's loop
        D = sq[:, a:b, None] + sq[:, None, cols] - 2.0 * G
        np.maximum(D, 0.0, out=D)
        np.sqrt(D, out=D)
        dv[a:b, cols] = _window_range(D, width)
        if N is not None:
            C = np.matmul(N[:, a:b], N[:, cols].transpose(0, 2, 1))
            np.clip(C, -1.0, 1.0, out=C)
            if width >= T:  # one window: arccos is monotonic, take it after the range
                dn[a:b, cols] = np.arccos(C.min(0)) - np.arccos(C.max(0))
            else:
                np.arccos(C, out=C)
                dn[a:b, cols] = _window_range(C, width)
    iu = np.triu_indices(n, 1)
    dv[iu[1], iu[0]] = dv[iu]
    dn[iu[1], iu[0]] = dn[iu]
    np.fill_diagonal(dv, 0.0)
    np.fill_diagonal(dn, 0.0)
    return dv, dn
