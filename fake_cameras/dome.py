"""A dome of simulated cameras around the capture volume.

The cameras sit on two or three rings at different elevations around the
volume (z up, floor at z = 0, millimetres), all aimed at the volume centre,
each with its own focal length, principal point, distance and mild lens
distortion, like a hand-built rig. The focal length of every camera is chosen
so that the corners of the volume just fit the image (4% margin): the
whole volume is seen by every camera and fills most of the frame.
"""

from __future__ import annotations

import math

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from stage.rig import Volume

__all__ = ["make_dome", "look_at", "MIN_CAMERAS", "MAX_CAMERAS"]

MIN_CAMERAS = 4
MAX_CAMERAS = 24


def look_at(center: np.ndarray, target: np.ndarray, *, up: np.ndarray = (0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """World -> camera rotation of a camera at ``center`` looking at ``target``.

    Camera axes follow OpenCV: x right, y down, z forward.

    Parameters
    ----------
    center, target : (3,) float ndarray
    up : (3,) float ndarray, optional
        World up direction (image "up"). Must not be parallel to the viewing direction.
    roll : float, optional
        Extra rotation about the optical axis, radians.

    Returns
    -------
    (3, 3) float ndarray
        ``R`` such that ``Xc = R @ (X - center)``.
    """
    c = np.asarray(center, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - c
    n = np.linalg.norm(fwd)
    if n < 1e-9:
        raise ValueError("target must differ from center")
    fwd /= n
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    rn = np.linalg.norm(right)
    if rn < 1e-9:
        raise ValueError("up must not be parallel to the viewing direction")
    right /= rn
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    if roll:
        cr, sr = math.cos(roll), math.sin(roll)
        Rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
        R = Rz @ R
    return R


def _ring_layout(n: int) -> list[tuple[float, int]]:
    """(elevation in degrees, number of cameras) per ring."""
    if n < 8:
        top = n // 2
        return [(15.0, n - top), (50.0, top)]
    top = max(2, round(n * 0.25))
    mid = round(n * 0.35)
    return [(10.0, n - top - mid), (35.0, mid), (62.0, top)]


def _fit_focal(R, t, corners, size, cx, cy, margin=0.04) -> float:
    """Largest focal length that keeps every volume corner inside the image."""
    w, h = size
    pc = corners @ R.T + t
    x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    mx, my = margin * w, margin * h
    lims = []
    for v, c, hi, m in ((x, cx, w - 1, mx), (y, cy, h - 1, my)):
        pos, neg = v[v > 1e-9], -v[v < -1e-9]
        if pos.size:
            lims.append((hi - m - c) / pos.max())
        if neg.size:
            lims.append((c - m) / neg.max())
    return float(min(lims))


def make_dome(
    n_cameras: int = 12,
    *,
    size: tuple[int, int] = (640, 480),
    volume: Volume | None = None,
    seed: int = 0,
    distortion: bool = True,
    distance: float | None = None,
) -> Calibration:
    """True calibration of a simulated dome of cameras.

    Parameters
    ----------
    n_cameras : int, optional
        Number of cameras, 4..24. Fewer than 8 cameras sit on two rings
        (15 and 50 degrees elevation), more on three (10, 35, 62 degrees).
    size : (int, int), optional
        Image ``(width, height)`` of every camera.
    volume : stage.rig.Volume, optional
        Capture volume (default ``Volume()``: centre (0, 0, 375), 750 mm cube).
    seed : int, optional
        Seed of the per-camera variations (focal length, principal point,
        distance, azimuth jitter, roll, distortion).
    distortion : bool, optional
        Give every camera mild lens distortion (``k1, k2`` within +-0.05,
        +-0.02 and tangential terms within +-0.001); zero when False.
    distance : float, optional
        Mean distance of the cameras from the volume centre; default 2.4x the
        volume's bounding-sphere radius (about 1.56 m for the default volume).

    Returns
    -------
    calib.Calibration
        Cameras ``cam00``, ``cam01``... (world frame: mm, z up, floor z = 0),
        ``meta`` records how the dome was made.
    """
    if isinstance(n_cameras, bool) or not isinstance(n_cameras, (int, np.integer)):
        raise ValueError(f"n_cameras must be an integer, got {n_cameras!r}")
    if not MIN_CAMERAS <= n_cameras <= MAX_CAMERAS:
        raise ValueError(f"n_cameras must be within {MIN_CAMERAS}..{MAX_CAMERAS}, got {n_cameras}")
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height), got {size!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise ValueError(f"size must be (width, height) within 16..8192 pixels, got {size!r}")
    vol = Volume() if volume is None else volume
    if not isinstance(vol, Volume):
        raise ValueError(f"volume must be a stage.rig.Volume, got {type(vol).__name__}")
    rng = np.random.default_rng(seed)
    center = np.asarray(vol.center, dtype=np.float64)
    half = np.asarray(vol.size, dtype=np.float64) / 2.0
    radius = float(np.linalg.norm(half))  # bounding sphere of the volume
    if distance is None:
        distance = 2.4 * radius
    if not distance > radius * 1.05:
        raise ValueError(f"distance must exceed the volume's bounding radius ({radius:.0f}), got {distance}")

    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half + center
    cams: list[Camera] = []
    k = 0
    for ring, (elev_deg, count) in enumerate(_ring_layout(int(n_cameras))):
        az0 = ring * math.pi / max(count, 1) * 0.5 + 0.3
        for j in range(count):
            az = az0 + 2 * math.pi * j / count + rng.uniform(-0.08, 0.08)
            el = math.radians(elev_deg + rng.uniform(-3.0, 3.0))
            d = distance * rng.uniform(0.95, 1.05)
            pos = center + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            target = center + rng.uniform(-0.03, 0.03, size=3) * half
            R = look_at(pos, target, roll=math.radians(rng.uniform(-3.0, 3.0)))
            t = -R @ pos
            cx = (w - 1) / 2.0 + rng.uniform(-0.02, 0.02) * w
            cy = (h - 1) / 2.0 + rng.uniform(-0.02, 0.02) * h
            f = _fit_focal(R, t, corners, (w, h), cx, cy) * rng.uniform(0.96, 1.0)
            aspect = rng.uniform(0.998, 1.002)
            K = np.array([[f, 0.0, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])
            if distortion:
                dist = np.array(
                    [
                        rng.uniform(-0.05, 0.05),
                        rng.uniform(-0.02, 0.02),
                        rng.uniform(-0.001, 0.001),
                        rng.uniform(-0.001, 0.001),
                        0.0,
                    ]
                )
            else:
                dist = np.zeros(5)
            cams.append(Camera(name=f"cam{k:02d}", K=K, dist=dist, R=R, t=t, size=(w, h)))
            k += 1
    meta = {
        "source": "fake_cameras.dome",
        "seed": int(seed),
        "volume": {"center": list(vol.center), "size": list(vol.size)},
        "distortion": bool(distortion),
        "exact": True,  # the cameras the images are rendered through (Calibration.reprojection_error_px: 0)
    }
    return Calibration(cameras=tuple(cams), units="mm", meta=meta)
