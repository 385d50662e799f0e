"""JPEG frames of a take: encode a decoded frame for storage, decode stored bytes (OpenCV)."""

from __future__ import annotations

import numpy as np

from stage.store._format import TakeError

__all__ = ["encode_jpeg", "decode_jpeg"]


def encode_jpeg(image: np.ndarray, quality: int = 95) -> bytes:
    """(H, W, 3) uint8 BGR -> JPEG bytes."""
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:  # pragma: no cover
        raise ValueError("could not encode frame as JPEG")
    return buf.tobytes()


def decode_jpeg(data: np.ndarray, where: str) -> np.ndarray:
    """JPEG bytes (uint8 array) -> (H, W, 3) uint8 BGR; :class:`TakeError` naming ``where`` when corrupt."""
    import cv2

    img = cv2.imdecode(np.ascontiguousarray(data), cv2.IMREAD_COLOR)
    if img is None:
        raise TakeError(f"{where}: stored JPEG bytes cannot be decoded (corrupt frame)")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img
