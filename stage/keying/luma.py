"""Luma keying for dark (or bright) backdrops, e.g. the black cloth of the Middlebury dino.

The luma histogram of a dark backdrop is a sharp peak with a long tail (cloth
folds, stray light), so neither a Gaussian backdrop model nor Otsu's threshold
(biased towards the larger class, and cutting dark shading on the subject) fits.
The threshold is the minimum of the smoothed log-histogram between the backdrop
peak and the subject's peak (the intermodes/minimum method, Prewitt & Mendelsohn
1966), with Otsu's threshold (Otsu 1979) only used to separate the two peaks. The
backdrop distance of a pixel is its luma beyond the backdrop peak, in units
chosen so that the mid-point of the soft-matte thresholds falls on that valley.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from stage.keying._color import M_Y
from stage.keying.params import KeyingError

__all__ = ["estimate_luma_model", "luma_distance", "otsu_threshold"]


def otsu_threshold(hist: np.ndarray) -> float:
    """Otsu's threshold of a 256-bin histogram (first bin of the upper class)."""
    h = np.asarray(hist, float)
    p = h / max(h.sum(), 1e-12)
    omega = np.cumsum(p)
    mu = np.cumsum(p * np.arange(h.size))
    mu_t = mu[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        sb = (mu_t * omega - mu) ** 2 / (omega * (1 - omega))
    sb = np.nan_to_num(sb, nan=-1.0, posinf=-1.0)
    return float(np.argmax(sb) + 1)


def estimate_luma_model(
    samples: np.ndarray, *, polarity: str | None = None, border: np.ndarray | None = None, t_mid: float
) -> dict[str, Any]:
    """Fit the luma backdrop model.

    Parameters
    ----------
    samples : (K, 3) float ndarray
        BGR samples of the frames.
    polarity : {"dark", "bright"} or None
        Backdrop darker or brighter than the subject; ``None``: the class most of
        ``border`` falls into (else "dark").
    border : (B, 3) float ndarray or None
        BGR samples from the image border, used to pick the polarity.
    t_mid : float
        Mid-point of the soft-matte thresholds (the valley maps to it).

    Returns
    -------
    dict
        ``polarity``, ``peak`` (backdrop luma mode), ``valley`` (threshold, luma),
        ``otsu``, ``sigma`` (luma per distance unit).
    """
    s = np.asarray(samples, dtype=np.float64)
    y = np.clip(s @ M_Y, 0, 255)
    hist = np.bincount(y.astype(int), minlength=256)[:256].astype(float)
    t_otsu = otsu_threshold(hist)
    if polarity is None:
        if border is not None and len(border):
            yb = np.asarray(border, float) @ M_Y
            polarity = "dark" if np.mean(yb < t_otsu) >= 0.5 else "bright"
        else:
            polarity = "dark"
    if polarity == "bright":
        hist = hist[::-1]
        t_otsu = 256.0 - t_otsu
    lo_end = int(t_otsu)
    if lo_end < 1 or lo_end > 255 or hist[:lo_end].sum() == 0 or hist[lo_end:].sum() == 0:
        raise KeyingError("luma histogram has a single class: no backdrop/subject contrast")
    peak = int(np.argmax(hist[:lo_end]))
    fg_peak = lo_end + int(np.argmax(hist[lo_end:]))
    smooth = gaussian_filter1d(np.log1p(hist), 3.0)
    valley = peak + int(np.argmin(smooth[peak : fg_peak + 1]))
    if valley <= peak:
        valley = lo_end
    sigma = (valley - peak) / t_mid
    if polarity == "bright":
        peak, valley, t_otsu, fg_peak = 255 - peak, 255 - valley, 255 - t_otsu, 255 - fg_peak
    return {
        "polarity": polarity,
        "peak": float(peak),
        "valley": float(valley),
        "otsu": float(t_otsu),
        "subject_peak": float(fg_peak),
        "sigma": float(sigma),
    }


def luma_distance(image: np.ndarray, model: dict[str, Any]) -> np.ndarray:
    """(H, W) float32 backdrop distance: luma beyond the backdrop peak in ``sigma`` units."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    sign = 1.0 if model["polarity"] == "dark" else -1.0
    scale = sign / model["sigma"]
    d = cv2.addWeighted(gray, scale, gray, 0.0, -model["peak"] * scale, dtype=cv2.CV_32F)
    return cv2.max(d, 0.0)
