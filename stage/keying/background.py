"""A clean background plate from the take itself (no empty-room recording needed).

Over frames spread across the take, a pixel's background is the value it holds most of
the time. The per-pixel temporal median gives it wherever the subject covers the pixel in
less than half of the frames (Cucchiara et al. 2003 use the median of a frame buffer the
same way). Where the samples do not agree with their median (fewer than half within the
noise tolerance: the subject covers the pixel more often than not), the plate is the
temporal *mode*: the sample with most others within the tolerance, averaged with them
(a moving subject's colours vary, the background's do not). A pixel where no value holds
in a quarter of the samples is one the subject (or something else that moves) never
leaves: it is flagged, and the keyer treats it as uncertain rather than as background.

The camera noise is measured on the plate itself: per pixel, the robust spread (MAD) of
the samples that agree with it, smoothed over a small window, so the plate keyer's
distances are in units of the noise where they are measured (sensor noise, compression,
flicker of a monitor all differ across the image).

Written by hand: OpenCV's background subtractors (MOG2, KNN) learn online frame by frame
and give no plate of a whole take nor a noise map; a median over a few dozen frames
and a mode where it fails are a few array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PlateEstimate", "take_plate", "sample_indices"]

#: Samples agreeing with the median below which the mode is sought instead.
_MEDIAN_SUPPORT = 0.5
#: Samples agreeing with the mode below which a pixel is flagged (the background never holds).
_STUCK_SUPPORT = 0.25
#: Tolerance of "agreeing", in units of the global noise (per-channel max norm).
_AGREE_SIGMAS = 5.0


@dataclass(frozen=True, eq=False)
class PlateEstimate:
    """A background plate estimated from a take.

    Attributes
    ----------
    plate : (H, W, 3) uint8 ndarray
    noise : (H, W) float32 ndarray
        Per-pixel noise (standard deviation per channel, grey levels).
    support : (H, W) float32 ndarray
        Share of the samples that agree with the plate.
    stuck : (H, W) bool ndarray
        Pixels where no value held in a quarter of the samples (see module docstring).
    sigma : float
        The global noise (median of ``noise``).
    samples : int
        Frames used.
    """

    plate: np.ndarray
    noise: np.ndarray
    support: np.ndarray
    stuck: np.ndarray
    sigma: float
    samples: int

    @property
    def stuck_fraction(self) -> float:
        return float(self.stuck.mean())


def sample_indices(n: int, k: int) -> np.ndarray:
    """Up to ``k`` frame indices spread evenly across ``n`` frames (first and last included)."""
    if n < 1 or k < 1:
        raise ValueError(f"n and k must be positive, got n={n}, k={k}")
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int))


def _global_sigma(frames: np.ndarray, med: np.ndarray) -> float:
    sub = (slice(None), slice(None, None, 4), slice(None, None, 4))
    d = np.abs(frames[sub].astype(np.int16) - med[None, ::4, ::4].astype(np.int16))
    return max(0.5, 1.4826 * float(np.median(d)))


def _mode_of(samples: np.ndarray, tol: float, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``samples`` (N, M, 3) uint8: the mean of the largest set of samples within
    ``tol`` (max norm) of one of them, and that set's share of N."""
    n, m = samples.shape[:2]
    t = int(np.floor(tol))
    plate = np.empty((m, 3), np.float32)
    support = np.empty(m, np.float32)
    for s in range(0, m, chunk):
        x = samples[:, s : s + chunk].astype(np.int16)  # (N, c, 3)
        c = x.shape[1]
        close = np.ones((n, n, c), bool)
        for ch in range(3):  # per channel: int16 differences, no (N, N, c, 3) array
            a = x[..., ch]
            close &= np.abs(a[:, None] - a[None]) <= t
        counts = close.sum(axis=1)  # (N, c): samples near each sample
        best = counts.argmax(axis=0)  # (c,)
        sel = close[best, :, np.arange(c)].T[..., None]  # (N, c, 1) members of the best set
        plate[s : s + chunk] = (x * sel).sum(axis=0) / np.maximum(sel.sum(axis=0), 1)
        support[s : s + chunk] = counts[best, np.arange(c)] / n
    return plate, support


def take_plate(frames: np.ndarray, *, band: int = 48) -> PlateEstimate:
    """The background plate, noise map and flagged pixels from frames spread across a take.

    Parameters
    ----------
    frames : (N, H, W, 3) uint8 ndarray
        BGR frames of one camera, N >= 3 (spread across the take, see :func:`sample_indices`).
    band : int
        Rows processed at a time (memory stays at a few N x band x W arrays).

    Returns
    -------
    PlateEstimate

    Raises
    ------
    ValueError
        Wrong shape or dtype, fewer than 3 frames.
    """
    if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be a (N, H, W, 3) uint8 array, got {getattr(frames, 'dtype', type(frames))} "
                         f"{getattr(frames, 'shape', '')}")
    n, h, w = frames.shape[:3]
    if n < 3:
        raise ValueError(f"frames: a plate from the take needs at least 3 frames, got {n}")
    sub = frames[:, ::4, ::4]
    sigma0 = _global_sigma(sub, np.median(sub, axis=0).round().astype(np.uint8))
    tol = _AGREE_SIGMAS * sigma0
    plate = np.empty((h, w, 3), np.float32)
    support = np.empty((h, w), np.float32)
    spread = np.empty((h, w), np.float32)
    for r in range(0, h, band):
        plate[r : r + band], support[r : r + band], spread[r : r + band] = _band(frames[:, r : r + band], tol, sigma0)
    noise = np.maximum(cv2.blur(spread, (7, 7)), 0.5 * sigma0).astype(np.float32)
    plate8 = np.clip(plate.round(), 0, 255).astype(np.uint8)
    stuck = support < _STUCK_SUPPORT
    return PlateEstimate(plate=plate8, noise=noise, support=support, stuck=stuck,
                         sigma=float(np.median(noise)), samples=int(n))


def _chanmax(d: np.ndarray) -> np.ndarray:
    """Max over the last axis of size 3 (faster than ``max(axis=-1)``)."""
    return np.maximum(np.maximum(d[..., 0], d[..., 1]), d[..., 2])


def _band(frames: np.ndarray, tol: float, sigma0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plate, support and noise of a band of rows (see module docstring)."""
    n = frames.shape[0]
    k = n // 2
    part = np.partition(frames, (k - 1, k) if n % 2 == 0 else k, axis=0)  # uint8: fast
    plate = part[k].astype(np.float32) if n % 2 else (part[k - 1].astype(np.float32) + part[k]) / 2
    x = frames.astype(np.float32)  # (N, b, W, 3)
    support = (_chanmax(np.abs(x - plate[None])) <= tol).mean(axis=0)
    weak = support < _MEDIAN_SUPPORT
    if weak.any():
        mode, sup = _mode_of(frames[:, weak], tol)
        better = sup > support[weak]
        rows, cols = np.nonzero(weak)
        plate[rows[better], cols[better]] = mode[better]
        support[rows[better], cols[better]] = sup[better]
    d = np.abs(x - plate[None])  # (N, b, W, 3)
    agree = (_chanmax(d) <= tol)[..., None]
    cnt = agree.sum(axis=0)
    # mean absolute deviation of the agreeing samples: 0.7979 sigma for Gaussian noise
    dsum = (d * agree).sum(axis=0)
    mad = np.where(cnt > 0, dsum / np.maximum(cnt, 1), sigma0 / 1.2533)
    return plate, support.astype(np.float32), (1.2533 * mad.mean(axis=-1)).astype(np.float32)
