"""The capture volume as a keying prior: a pixel whose viewing ray misses the volume is background.

Whatever a camera sees there (walls, lights, people outside the stage) cannot be the
subject, so the keyer's distance is set to zero outside the volume's image. The image of
an axis-aligned box is the convex hull of its projected surface (a pinhole camera maps the
convex box, clipped to the half-space in front of it, to a convex region); the surface is
sampled densely so that lens distortion bends the outline as it should, and the region is
grown by ``margin`` pixels. A camera inside the box sees it everywhere.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib.camera import Camera

__all__ = ["volume_image"]


def _box_surface(lo: np.ndarray, hi: np.ndarray, n: int) -> np.ndarray:
    """(6 n^2, 3) points on the six faces of the box."""
    t = np.linspace(0.0, 1.0, n)
    a, b = np.meshgrid(t, t)
    a, b = a.ravel(), b.ravel()
    pts = []
    for axis in range(3):
        u, v = [i for i in range(3) if i != axis]
        for side in (lo[axis], hi[axis]):
            p = np.empty((a.size, 3))
            p[:, axis] = side
            p[:, u] = lo[u] + a * (hi[u] - lo[u])
            p[:, v] = lo[v] + b * (hi[v] - lo[v])
            pts.append(p)
    return np.concatenate(pts)


def volume_image(camera: Camera, bounds: np.ndarray, *, margin: int = 4, samples: int = 24) -> np.ndarray:
    """Pixels of ``camera`` whose viewing rays meet the box ``bounds``.

    Parameters
    ----------
    camera : Camera
    bounds : (6,) or (2, 3) float array-like
        ``[xmin, ymin, zmin, xmax, ymax, zmax]`` in the calibration's units.
    margin : int
        Pixels the region grows by (calibration error, a subject touching the box).
    samples : int
        Points per edge of every face sampled.

    Returns
    -------
    (H, W) bool ndarray

    Raises
    ------
    ValueError
        ``bounds`` not six finite numbers with ``lo < hi``; ``margin`` negative.
    """
    b = np.asarray(bounds, float).reshape(-1)
    if b.shape != (6,) or not np.all(np.isfinite(b)) or np.any(b[3:] <= b[:3]):
        raise ValueError(f"bounds must be [xmin, ymin, zmin, xmax, ymax, zmax] with min < max, got {bounds!r}")
    if not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be a non-negative integer, got {margin!r}")
    lo, hi = b[:3], b[3:]
    w, h = camera.size
    c = camera.center
    if np.all(c > lo) and np.all(c < hi):
        return np.ones((h, w), bool)
    pts = _box_surface(lo, hi, samples)
    z = camera.world_to_camera(pts)[:, 2]
    near = 1e-3 * float(np.linalg.norm(hi - lo))
    front = z > near
    if not front.any():
        return np.zeros((h, w), bool)
    pc = camera.world_to_camera(pts[front])
    xy = pc[:, :2] / pc[:, 2:3]
    K = camera.K
    uv = xy @ K[:2, :2].T + K[:2, 2]  # pinhole
    # the lens model only where it holds (inside the image and a little beyond): far outside,
    # the distortion polynomial folds back
    corners = (np.array([[0, 0], [w, 0], [0, h], [w, h]], float) - K[:2, 2]) / np.diag(K)[:2]
    inner = np.hypot(xy[:, 0], xy[:, 1]) <= 1.2 * np.hypot(corners[:, 0], corners[:, 1]).max()
    if inner.any():
        uv[inner] = camera.project(pts[front][inner])
    # clip far-away projections (points just in front of the camera) to keep the polygon finite
    lim = 2.0 * max(w, h)  # within int32 at 4 fractional bits
    uv = np.clip(uv, -lim, w + lim)
    hull = cv2.convexHull(np.round(uv * 16).astype(np.int32))  # 4 fractional bits
    out = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    if margin:
        out = cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1)))
    return out.view(bool)
