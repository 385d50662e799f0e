"""Calibrations the calibration-file tests share."""

from __future__ import annotations

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera, rodrigues_to_matrix


def random_calibration(n=12, seed=0):
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        K = [[500 + rng.random() * 100, 0.0, 320 + rng.random()], [0, 510 + rng.random() * 100, 240 + rng.random()],
             [0, 0, 1]]
        cams.append(Camera(f"cam{i:02d}", K=K, dist=rng.normal(0, 0.05, 5), R=rodrigues_to_matrix(rng.normal(size=3)),
                           t=rng.normal(0, 1000, 3), size=(640, 480)))
    return Calibration(tuple(cams), units="mm", meta={"rms_px": 0.31, "per_camera_rms_px": {"cam00": 0.3}})
