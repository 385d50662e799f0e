"""Synthetic footage for the import tests: per-camera images and an aniposelib calibration TOML."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

W, H = 160, 120


def img(cam: int, k: int) -> np.ndarray:
    a = np.zeros((H, W, 3), np.uint8)
    a[..., 0] = 60 * cam
    a[..., 1] = 20 * k
    cv2.circle(a, (40 + 10 * k, 60), 15, (255, 255, 255), -1)
    return a


CAMS = [
    # name, rvec, tvec, fx, dist
    ("left", [0.1, -0.2, 0.05], [10.0, 20.0, 900.0], 210.0, [-0.1, 0.01, 0.001, -0.002, 0.0]),
    ("right", [-0.3, 0.4, 0.0], [-150.0, 5.0, 1000.0], 190.0, [0.05, 0.0, 0.0, 0.0, -0.01]),
    ("top", [1.2, 0.0, 0.0], [0.0, 0.0, 1200.0], 200.0, [0.0, 0.0, 0.0, 0.0, 0.0]),
]


def write_anipose_toml(path: Path, cams=CAMS, size=(W, H)) -> None:
    lines = []
    for i, (name, r, t, f, d) in enumerate(cams):
        lines += [
            f"[cam_{i}]",
            f'name = "{name}"',
            f"size = [ {size[0]}, {size[1]},]",
            f"matrix = [ [ {f}, 0.0, {size[0] / 2}], [ 0.0, {f}, {size[1] / 2}], [ 0.0, 0.0, 1.0]]",
            f"distortions = [ {', '.join(str(x) for x in d)},]",
            f"rotation = [ {', '.join(str(x) for x in r)},]",
            f"translation = [ {', '.join(str(x) for x in t)},]",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.5", ""]
    path.write_text("\n".join(lines))
