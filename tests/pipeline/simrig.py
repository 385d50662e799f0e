"""A tiny analytic rig for the reconstruction tests: cameras on a dome, a capsule creature given
by its signed distance function, silhouettes and depth ray-marched per pixel (lens distortion
included, through ``Camera.pixel_grid_rays``). Independent of ``fake_cameras`` on purpose: the
ground truth here is the SDF itself."""

from __future__ import annotations

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera


def look_at(name: str, centre, target, *, size=(160, 120), f=None, dist=(0, 0, 0, 0, 0)) -> Camera:
    centre = np.asarray(centre, float)
    fwd = np.asarray(target, float) - centre
    fwd /= np.linalg.norm(fwd)
    up = np.array([0.0, 0.0, 1.0])
    if abs(fwd @ up) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    w, h = size
    f = f if f is not None else 1.1 * w
    K = np.array([[f, 0, (w - 1) / 2 + 0.3], [0, f, (h - 1) / 2 - 0.2], [0, 0, 1]])
    return Camera(name, K, np.asarray(dist, float), R, -R @ centre, size)


def dome(n: int = 8, *, size=(160, 120), radius=2000.0, target=(0, 0, 300), distortion=True, seed=0) -> Calibration:
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n + rng.uniform(-0.1, 0.1)
        el = np.deg2rad([15, 45][i % 2] + rng.uniform(-5, 5))
        c = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)]) * radius + np.asarray(target)
        d = (-0.08, 0.02, 0.0005, -0.0003, 0.0) if distortion else (0, 0, 0, 0, 0)
        cams.append(look_at(f"cam{i:02d}", c, target, size=size, f=0.9 * size[0], dist=d))
    return Calibration(tuple(cams))


def _capsule_sdf(p, a, b, r):
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - r


class Creature:
    """A starfish-like union of capsules around (0, 0, 300) mm (body + 4 limbs + a neck)."""

    def __init__(self, scale: float = 1.0):
        c = np.array([0.0, 0.0, 300.0])
        s = scale
        self.capsules = [
            (c + s * np.array([-60, 0, 0]), c + s * np.array([60, 0, 0]), 70 * s),
            (c + s * np.array([40, 40, -20]), c + s * np.array([150, 170, -160]), 22 * s),
            (c + s * np.array([40, -40, -20]), c + s * np.array([170, -150, -170]), 22 * s),
            (c + s * np.array([-40, 40, -20]), c + s * np.array([-170, 150, -170]), 22 * s),
            (c + s * np.array([-40, -40, -20]), c + s * np.array([-140, -180, -160]), 22 * s),
            (c + s * np.array([60, 0, 30]), c + s * np.array([200, 0, 160]), 28 * s),
        ]

    def sdf(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 3)
        return np.min([_capsule_sdf(p, a, b, r) for a, b, r in self.capsules], axis=0)

    def bounds(self) -> np.ndarray:
        lo = np.min([np.minimum(a, b) - r for a, b, r in self.capsules], axis=0)
        hi = np.max([np.maximum(a, b) + r for a, b, r in self.capsules], axis=0)
        return np.stack([lo, hi])


def render(calibration: Calibration, sdf, *, far=6000.0, eps=0.05, steps=200):
    """Silhouettes (C, H, W) bool and depth (C, H, W) uint16 mm (0 = no return) by sphere tracing."""
    masks, depths = [], []
    for cam in calibration:
        o, d = cam.pixel_grid_rays()
        h, w = d.shape[:2]
        d = d.reshape(-1, 3)
        t = np.zeros(len(d))
        alive = np.ones(len(d), bool)
        hit = np.zeros(len(d), bool)
        for _ in range(steps):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            dist = sdf(o + d[idx] * t[idx, None])
            h_ = dist < eps
            hit[idx[h_]] = True
            t[idx] += np.maximum(dist, 0)
            alive[idx[h_ | (t[idx] > far)]] = False
        z = t * (d @ cam.R[2])
        depth = np.where(hit, np.round(z), 0).astype(np.uint16)
        masks.append(hit.reshape(h, w))
        depths.append(depth.reshape(h, w))
    return np.stack(masks), np.stack(depths)
