"""Plate keying: difference from a clean background plate, shadow-aware.

Each pixel is compared with the plate's colour ``E`` at that pixel as in
Horprasert, Harwood & Davis 1999 ("A statistical approach for real-time robust
background subtraction and shadow detection"): the brightness distortion
``beta = <I, E> / <E, E>`` and the chromaticity distortion ``|I - beta E|``. A
shadow (``shadow_floor <= beta <= 1``) with the plate's chromaticity is backdrop;
colour change, darkening below the floor or brightening are foreground. Distances
are in units of the camera noise: per pixel when the plate comes with a noise map
(measured on the plate itself, :func:`stage.keying.background.take_plate`), else one
level estimated robustly from the frame-plate differences (most pixels are backdrop).
A slow lighting drift scales the whole image: each frame's gain is the median
brightness distortion over the pixels of a well-lit plate, and brightness is compared
with the plate times that gain (the chromaticity distortion needs no correction).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

__all__ = ["median_plate", "estimate_plate_model", "plate_distance"]


def median_plate(frames: np.ndarray, *, max_frames: int = 25) -> np.ndarray:
    """(H, W, 3) uint8 per-pixel temporal median of up to ``max_frames`` evenly spaced frames.

    A background plate estimated from the take itself: correct wherever the
    subject covers a pixel in less than half of the frames.
    """
    n = frames.shape[0]
    idx = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))
    return np.median(frames[idx], axis=0).round().astype(np.uint8)


def estimate_plate_model(frames: np.ndarray, plate: np.ndarray, *, stride: int, shadow_floor: float) -> dict[str, Any]:
    """Robust noise level of the frames against the plate.

    Returns
    -------
    dict
        ``sigma`` (per-channel noise, grey levels), ``shadow_floor``, ``plate_source``
        is added by the caller.
    """
    n = frames.shape[0]
    idx = np.unique(np.linspace(0, n - 1, min(n, 8)).round().astype(int))
    d = frames[idx, ::stride, ::stride].astype(np.float32) - plate[None, ::stride, ::stride].astype(np.float32)
    med = np.median(d)
    sigma = float(1.4826 * np.median(np.abs(d - med)))
    return {"sigma": max(sigma, 0.5), "shadow_floor": float(shadow_floor)}


def frame_gain(beta: np.ndarray, ee: np.ndarray) -> float:
    """A frame's global gain against the plate: the median brightness distortion over every
    7th pixel of the plate that is not dark (most pixels are backdrop), within [0.5, 2]."""
    b = beta[::7, ::7]
    lit = ee[::7, ::7] > 3 * 40.0**2
    vals = b[lit] if lit.sum() > 100 else b.ravel()
    return float(np.clip(np.median(vals), 0.5, 2.0)) if vals.size else 1.0


def plate_distance(image: np.ndarray, plate: np.ndarray, model: dict[str, Any]) -> np.ndarray:
    """(H, W) float32 backdrop distance in noise units (see module docstring).

    ``model`` holds ``sigma`` (grey levels) and ``shadow_floor``; an optional ``_noise``
    (H, W) float32 map replaces ``sigma`` pixel by pixel.
    """
    noise = model.get("_noise")
    sigma = noise if noise is not None else float(model["sigma"])
    floor = float(model["shadow_floor"])
    i = image.astype(np.float32)
    e = plate.astype(np.float32)
    ones = np.ones((1, 3), np.float32)
    ee = cv2.transform(e * e, ones) + 1.0
    ie = cv2.transform(i * e, ones)
    beta = ie / ee
    g = frame_gain(beta, ee)
    norm_e = np.sqrt(ee)
    diff = i - beta[..., None] * e
    cd = np.sqrt(cv2.transform(diff * diff, ones)) / sigma
    # brightness beyond [floor, 1] times the frame's gain along the plate colour, in noise units
    dark = (floor * g - beta) * norm_e / sigma
    bright = (beta - g) * norm_e / sigma
    return np.maximum(np.maximum(cd, dark), bright).astype(np.float32, copy=False)
