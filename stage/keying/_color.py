"""Shared colour functions: the linear BGR -> (Y, Cr, Cb) map and chi quantiles."""

from __future__ import annotations

import numpy as np
from scipy.special import gammainc, gammaincinv  # chi2 from scipy.special: importing scipy.stats costs 0.4 s

# OpenCV's full-range BGR -> YCrCb (cv2.COLOR_BGR2YCrCb) without the +128 chroma offset:
# rows are Y, Cr - 128, Cb - 128 as functions of (B, G, R). Linear and offset-free, so
# scaling the BGR colour by k (a shadow, a vignette) scales Y and the chroma by k.
M_Y = np.array([0.114, 0.587, 0.299])
M_C = np.array(
    [
        0.713 * np.array([-0.114, -0.587, 0.701]),  # Cr - 128
        0.564 * np.array([0.886, -0.587, -0.299]),  # Cb - 128
    ]
)

NAMED_COLORS_BGR = {
    "green": (0, 255, 0),
    "blue": (255, 0, 0),
    "red": (0, 0, 255),
    "black": (0, 0, 0),
    "white": (255, 255, 255),
}


def chi_radius(p_outside: float, dof: int) -> float:
    """Radius holding all but ``p_outside`` of a standard Gaussian in ``dof`` dimensions."""
    return float(np.sqrt(chi2_ppf(1.0 - p_outside, dof)))


def chi2_ppf(q: float, dof: int) -> float:
    """Quantile of the chi-squared distribution (as ``scipy.stats.chi2.ppf``)."""
    return float(2.0 * gammaincinv(dof / 2.0, q))


def chi2_cdf(x: float, dof: int) -> float:
    """Distribution function of the chi-squared distribution (as ``scipy.stats.chi2.cdf``)."""
    return float(gammainc(dof / 2.0, x / 2.0))


def default_thresholds(dof: int) -> tuple[float, float]:
    """Soft-matte thresholds in units of the backdrop spread: 1e-3 and 1e-6 tail radii."""
    return chi_radius(1e-3, dof), chi_radius(1e-6, dof)


def validate_frames(frames: object, name: str = "frames") -> np.ndarray:
    """Check an (N, H, W, 3) uint8 stack (a single (H, W, 3) image is promoted)."""
    if not isinstance(frames, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(frames).__name__}")
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (N, H, W, 3), got {frames.shape}")
    if frames.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got {frames.dtype}")
    if frames.shape[0] == 0 or frames.shape[1] < 8 or frames.shape[2] < 8:
        raise ValueError(f"{name} must hold at least one frame of at least 8x8 pixels, got {frames.shape}")
    return frames


def sample_pixels(frames: np.ndarray, *, stride: int, max_frames: int = 16) -> np.ndarray:
    """(K, 3) float64 BGR samples: every ``stride``-th pixel of up to ``max_frames`` evenly spaced frames."""
    n = frames.shape[0]
    idx = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))
    s = frames[idx, ::stride, ::stride].reshape(-1, 3)
    return s.astype(np.float64)
