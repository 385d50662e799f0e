"""The frame every driver returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Frame"]


@dataclass(frozen=True, eq=False)
class Frame:
    """One image from one camera.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        BGR image (OpenCV's channel order), decoded.
    camera_id : str
        Id of the camera in the rig.
    index : int
        The device's own frame sequence number (gaps mean the device dropped frames).
    timestamp_ns : int
        Device timestamp in nanoseconds, on the device's clock.
    host_timestamp_ns : int
        Host ``time.monotonic_ns()`` when the frame was received.
    depth : (H, W) uint16 ndarray or None
        Depth in millimetres aligned to ``image`` (0 = no measurement), for RGB-D cameras.
    encoded : bytes or None
        The camera's own JPEG/MJPEG bytes when it delivered compressed frames; the
        take store keeps these as they arrived instead of re-encoding.
    exposure_ms : float or None
        The exposure time of this frame in milliseconds, where the device reports it.
    gain : float or None
        The sensor's gain for this frame where the device reports it, in the device's units
        (``Granted.extra["gain_unit"]``: ISO sensitivity for OAK cameras, the V4L2 gain control).
    """

    image: np.ndarray
    camera_id: str
    index: int
    timestamp_ns: int
    host_timestamp_ns: int
    depth: np.ndarray | None = None
    encoded: bytes | None = None
    exposure_ms: float | None = None
    gain: float | None = None

    def __post_init__(self) -> None:
        img = self.image
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(
                f"image must be an (H, W, 3) uint8 array, got {getattr(img, 'dtype', type(img))} {getattr(img, 'shape', '')}"
            )
        if self.depth is not None:
            d = self.depth
            if not isinstance(d, np.ndarray) or d.dtype != np.uint16 or d.shape != img.shape[:2]:
                raise ValueError("depth must be an (H, W) uint16 array matching image")

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return self.image.shape[:2]
