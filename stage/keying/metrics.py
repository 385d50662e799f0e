"""Mask quality measures: IoU and the boundary F-score.

The boundary F-score (Martin, Fowlkes & Malik 2004; the "F" of the DAVIS benchmark,
Perazzi et al. 2016) matches boundary pixels of the prediction and of the ground
truth within a distance tolerance: precision is the fraction of predicted boundary
pixels within ``tol`` pixels (Euclidean) of a true boundary pixel, recall the
converse, F their harmonic mean. It is sensitive to thin structures (a lost limb
tip removes its whole outline) where IoU barely moves.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["iou", "mask_boundary", "boundary_f_score"]


def _check_pair(pred: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pred)
    t = np.asarray(truth)
    if p.ndim != 2 or p.shape != t.shape:
        raise ValueError(f"pred and truth must be (H, W) masks of the same shape, got {p.shape} and {t.shape}")
    if p.dtype != bool or t.dtype != bool:
        raise ValueError(f"pred and truth must be bool arrays, got {p.dtype} and {t.dtype}")
    return p, t


def iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks (1.0 when both are empty)."""
    p, t = _check_pair(pred, truth)
    union = np.count_nonzero(p | t)
    return 1.0 if union == 0 else np.count_nonzero(p & t) / union


def mask_boundary(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: mask pixels with a 4-neighbour outside the mask (the image edge does not count)."""
    m = np.asarray(mask)
    if m.ndim != 2 or m.dtype != bool:
        raise ValueError(f"mask must be an (H, W) bool array, got {m.dtype} {m.shape}")
    m8 = m.view(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    er = cv2.erode(m8, cross, borderType=cv2.BORDER_REPLICATE)
    return m & (er == 0)


def _within(src: np.ndarray, dst: np.ndarray, tol: float) -> int:
    """How many ``src`` boundary pixels lie within ``tol`` of a ``dst`` boundary pixel."""
    if not dst.any():
        return 0
    dist = cv2.distanceTransform((~dst).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return int(np.count_nonzero(dist[src] <= tol))


def boundary_f_score(pred: np.ndarray, truth: np.ndarray, *, tol: float = 2.0) -> float:
    """Boundary F-score of ``pred`` against ``truth`` at a tolerance of ``tol`` pixels.

    Parameters
    ----------
    pred, truth : (H, W) bool ndarray
    tol : float
        Match distance in pixels (Euclidean, between pixel centres).

    Returns
    -------
    float
        In [0, 1]; 1.0 when neither mask has a boundary, 0.0 when only one has.
    """
    p, t = _check_pair(pred, truth)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a non-negative number, got {tol!r}")
    bp, bt = mask_boundary(p), mask_boundary(t)
    n_p, n_t = int(bp.sum()), int(bt.sum())
    if n_p == 0 and n_t == 0:
        return 1.0
    if n_p == 0 or n_t == 0:
        return 0.0
    precision = _within(bp, bt, tol) / n_p
    recall = _within(bt, bp, tol) / n_t
    if precision + recall == 0:
        return 0.0
    return 2 * precision * recall / (precision + recall)
