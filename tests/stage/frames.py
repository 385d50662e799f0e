"""Deterministic frames and a calibration for the take-store tests (also imported by the child
processes those tests start)."""

from __future__ import annotations

import cv2
import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from stage.frame import Frame

W, H = 160, 120


def make_image(cam: int, k: int) -> np.ndarray:
    """Deterministic, distinct image per (camera, frame)."""
    rng = np.random.default_rng(1000 * cam + k)
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = (np.arange(W)[None, :] * 1.5).astype(np.uint8)
    img[..., 1] = 40 * cam
    img[..., 2] = (k * 7) % 256
    img[rng.integers(0, H, 20), rng.integers(0, W, 20)] = 255
    return img


def make_frame(cam_id: str, cam: int, k: int, *, jpeg=False, depth=False) -> Frame:
    img = make_image(cam, k)
    enc = cv2.imencode(".jpg", img)[1].tobytes() if jpeg else None
    d = np.full((H, W), 1000 + k, np.uint16) if depth else None
    return Frame(img, cam_id, k, 10**12 * (cam + 1) + k * 33_333_333, 5 * 10**9 + k * 33_333_333 + cam * 1000, depth=d, encoded=enc)


def calibration(names) -> Calibration:
    cams = []
    for i, n in enumerate(names):
        K = np.array([[200.0, 0, W / 2], [0, 200.0, H / 2], [0, 0, 1]])
        cams.append(Camera(n, K, np.zeros(5), np.eye(3), np.array([10.0 * i, 0, 1000]), (W, H)))
    return Calibration(tuple(cams))
