"""Spill suppression: remove the backdrop's hue from foreground colours.

Light bounced off a green screen tints the subject's edges green. For the
foreground colour, the chroma component along the backdrop hue is clamped to
zero where it is positive (the generalization of the classic ``G' = min(G,
max(R, B))`` despill to any backdrop hue), keeping the luma.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from stage.keying._color import M_C, M_Y

__all__ = ["despill"]


def despill(image: np.ndarray, model: dict[str, Any]) -> np.ndarray:
    """Spill-suppressed copy of a BGR image.

    Parameters
    ----------
    image : (H, W, 3) or (N, H, W, 3) uint8 ndarray
    model : dict
        Chroma backdrop model (``n0`` or ``hue``).

    Returns
    -------
    uint8 ndarray, same shape
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape[-1] != 3 or image.ndim not in (3, 4):
        raise ValueError(f"image must be an (H, W, 3) or (N, H, W, 3) uint8 array, got {getattr(image, 'shape', None)}")
    if image.ndim == 4:
        return np.stack([despill(im, model) for im in image])
    hue = float(model["hue"])
    u = np.array([np.cos(hue), np.sin(hue)])
    # chroma along the backdrop hue, a = u . (M_C @ bgr); remove max(a, 0) * u in chroma, keep Y.
    ycc_to_bgr = np.linalg.inv(np.vstack([M_Y, M_C]))  # (3, 3): (Y, Cr', Cb') -> BGR
    along = (u @ M_C).astype(np.float32)[None, :]
    f = image.astype(np.float32)
    a = np.maximum(cv2.transform(f, along), 0.0)
    delta = (ycc_to_bgr[:, 1:] @ u).astype(np.float32)  # BGR change per unit of chroma along u
    out = f - a[..., None] * delta
    return np.clip(out, 0, 255).round().astype(np.uint8)
