"""The one camera model of capture-stage.

Pinhole projection with OpenCV's five-parameter distortion (k1, k2, p1, p2, k3),
world -> camera rotation ``R`` and translation ``t``, lengths in millimetres
(or whatever unit the calibration was made in; every package keeps it).

A world point ``X`` maps to camera coordinates ``Xc = R @ X + t``, to normalized
coordinates ``(x, y) = Xc[:2] / Xc[2]``, is distorted as in OpenCV
(``cv2.projectPoints``) and mapped to pixels by ``K``. Pixel centres sit at
integer coordinates, as in OpenCV.

The math lives in free functions (arrays in, arrays out); :class:`Camera` is a
small immutable value object that wraps them and serializes with
``to_dict`` / ``from_dict``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "Camera",
    "cached_pixel_grid_rays",
    "cached_pixel_ray_depths",
    "distort_normalized",
    "undistort_normalized",
    "project_points",
    "pixel_rays",
    "rodrigues_to_matrix",
    "matrix_to_rodrigues",
]


def _as_points(points: Any, name: str, dim: int) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {np.shape(points)}")
    return arr


def _check_dist(dist: Any) -> np.ndarray:
    d = np.zeros(5, dtype=np.float64)
    arr = np.asarray(dist, dtype=np.float64).ravel()
    if arr.size > 5 and np.any(arr[5:] != 0):
        raise ValueError("dist: only k1, k2, p1, p2, k3 are supported; higher terms must be zero")
    if arr.size not in (0, 4, 5) and arr.size <= 5:
        raise ValueError(f"dist must have 4 or 5 coefficients, got {arr.size}")
    d[: min(arr.size, 5)] = arr[:5]
    return d


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's radial-tangential distortion to normalized coordinates.

    Parameters
    ----------
    xy : (N, 2) float ndarray
        Undistorted normalized image coordinates ``X/Z, Y/Z``.
    dist : (5,) float ndarray
        ``k1, k2, p1, p2, k3``.

    Returns
    -------
    (N, 2) float ndarray
        Distorted normalized coordinates.
    """
    xy = _as_points(xy, "xy", 2)
    k1, k2, p1, p2, k3 = _check_dist(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, *, iterations: int = 20) -> np.ndarray:
    """Invert :func:`distort_normalized` by Newton's method (vectorized).

    Parameters
    ----------
    xy_d : (N, 2) float ndarray
        Distorted normalized coordinates.
    dist : (5,) float ndarray
        ``k1, k2, p1, p2, k3``.
    iterations : int, optional
        Newton steps; the default reaches machine precision for the mild
        distortion of real lenses.

    Returns
    -------
    (N, 2) float ndarray
        Undistorted normalized coordinates.
    """
    xy_d = _as_points(xy_d, "xy_d", 2)
    k1, k2, p1, p2, k3 = _check_dist(dist)
    if not np.any([k1, k2, p1, p2, k3]):
        return xy_d.copy()
    x = xy_d[:, 0].copy()
    y = xy_d[:, 1].copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xy_d[:, 0]
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - xy_d[:, 1]
        j11 = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        dx = (j22 * fx - j12 * fy) / det
        dy = (-j21 * fx + j11 * fy) / det
        x -= dx
        y -= dy
        if np.max(np.abs(dx) + np.abs(dy), initial=0.0) < 1e-14:
            break
    return np.stack([x, y], axis=1)


def project_points(
    points: np.ndarray,
    *,
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    return_depth: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Project world points to pixels (same result as ``cv2.projectPoints``).

    Parameters
    ----------
    points : (N, 3) float ndarray
        World points.
    K : (3, 3) float ndarray
        Intrinsic matrix.
    dist : (5,) float ndarray
        ``k1, k2, p1, p2, k3``.
    R : (3, 3) float ndarray
        World -> camera rotation.
    t : (3,) float ndarray
        World -> camera translation.
    return_depth : bool, optional
        Also return the camera-frame depth ``Z`` of every point.

    Returns
    -------
    pixels : (N, 2) float ndarray
    depth : (N,) float ndarray, only with ``return_depth``
        Points with ``depth <= 0`` lie behind the camera; their pixels are
        meaningless.
    """
    pts = _as_points(points, "points", 3)
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    pc = pts @ R.T + t
    z = pc[:, 2]
    safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xy = pc[:, :2] / safe[:, None]
    xy_d = distort_normalized(xy, dist)
    u = K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2]
    v = K[1, 1] * xy_d[:, 1] + K[1, 2]
    pix = np.stack([u, v], axis=1)
    if return_depth:
        return pix, z
    return pix


def pixel_rays(
    pixels: np.ndarray, *, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through pixels (lens distortion removed).

    Parameters
    ----------
    pixels : (N, 2) float ndarray
        Pixel coordinates (integer = pixel centre).
    K, dist, R, t
        As in :func:`project_points`.

    Returns
    -------
    origin : (3,) float ndarray
        The camera centre in world coordinates.
    directions : (N, 3) float ndarray
        Unit ray directions in world coordinates.
    """
    pix = _as_points(pixels, "pixels", 2)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    yd = (pix[:, 1] - K[1, 2]) / K[1, 1]
    xd = (pix[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    xy = undistort_normalized(np.stack([xd, yd], axis=1), dist)
    dirs_c = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    dirs_w = dirs_c @ R  # R.T @ d for each row
    dirs_w /= np.linalg.norm(dirs_w, axis=1, keepdims=True)
    origin = -R.T @ t
    return origin, dirs_w


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) -> (3, 3) rotation matrix."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * (Kx @ Kx)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray | float:
    """Rotation angle (degrees, in [0, 180]) of one or many rotation matrices.

    Computed as ``atan2(|axial(R - R^T)| / 2, (trace(R) - 1) / 2)``: ``arccos`` of the trace alone
    loses half the digits near 0 (an identity off by 1e-16 in the trace reads as 1e-6 degrees).

    Parameters
    ----------
    R : (..., 3, 3) float ndarray
        Rotation matrices.

    Returns
    -------
    float or (...) float ndarray
        A float for one (3, 3) matrix, else one angle per matrix.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    axial = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(axial, axis=-1)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    ang = np.degrees(np.arctan2(sin, cos))
    return float(ang) if R.ndim == 2 else ang


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> rotation vector (axis * angle)."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return rvec.ravel()


#: the keys of :meth:`Camera.to_dict` (what :meth:`Camera.from_dict` accepts)
_CAMERA_KEYS = frozenset({"name", "K", "dist", "R", "t", "size", "meta"})


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera: intrinsics, distortion, world -> camera pose.

    Parameters
    ----------
    name : str
        Camera id, unique within a rig.
    K : (3, 3) float ndarray
    dist : (5,) float ndarray
        ``k1, k2, p1, p2, k3``.
    R : (3, 3) float ndarray
        World -> camera rotation.
    t : (3,) float ndarray
        World -> camera translation (same unit as the world, mm for our rigs).
    size : (int, int)
        Image ``(width, height)`` in pixels.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("name must be a non-empty string")
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("K: focal lengths must be positive")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0, atol=1e-9) or abs(K[1, 0]) > 1e-9:
            raise ValueError(f"K must be an intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got rows "
                             f"{K[1].tolist()} and {K[2].tolist()}")
        R = np.asarray(self.R, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"R must be 3x3, got shape {R.shape}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("R must be a proper rotation matrix")
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if t.shape != (3,):
            raise ValueError(f"t must have 3 elements, got {t.shape}")
        size = tuple(int(s) for s in self.size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"size must be (width, height) > 0, got {self.size}")
        dist = _check_dist(self.dist)
        for label, a in (("K", K), ("dist", dist), ("t", t)):
            if not np.isfinite(a).all():
                raise ValueError(f"camera {self.name}: {label} must be finite, got {a.ravel().tolist()}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "size", size)
        for a in (self.K, self.dist, self.R, self.t):
            a.setflags(write=False)

    # -- geometry -----------------------------------------------------------
    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,)."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        return matrix_to_rodrigues(self.R)

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``K [R | t]`` (ignores distortion)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        pts = _as_points(points, "points", 3)
        return pts @ self.R.T + self.t

    def project(self, points: np.ndarray, *, return_depth: bool = False):
        """Project world points; see :func:`project_points`."""
        return project_points(points, K=self.K, dist=self.dist, R=self.R, t=self.t, return_depth=return_depth)

    def rays(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixels; see :func:`pixel_rays`."""
        return pixel_rays(pixels, K=self.K, dist=self.dist, R=self.R, t=self.t)

    def unproject(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """World points at camera-frame depth ``Z`` behind pixels.

        Parameters
        ----------
        pixels : (N, 2) float ndarray
        depth : (N,) float ndarray
            Camera-frame ``Z`` (as in depth images), not distance along the ray.
        """
        pix = _as_points(pixels, "pixels", 2)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        if z.shape[0] != pix.shape[0]:
            raise ValueError("depth must have one value per pixel")
        origin, d = self.rays(pix)
        dz = d @ self.R[2]  # z component of direction in camera frame
        return origin + d * (z / dz)[:, None]

    def in_image(self, pixels: np.ndarray, *, margin: float = 0.0) -> np.ndarray:
        pix = _as_points(pixels, "pixels", 2)
        w, h = self.size
        return (
            (pix[:, 0] >= -0.5 + margin)
            & (pix[:, 0] < w - 0.5 - margin)
            & (pix[:, 1] >= -0.5 + margin)
            & (pix[:, 1] < h - 0.5 - margin)
        )

    def pixel_grid_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every pixel centre: origin (3,), directions (H, W, 3)."""
        w, h = self.size
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        origin, d = self.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
        return origin, d.reshape(h, w, 3)

    def replace(self, **changes: Any) -> "Camera":
        data = dict(name=self.name, K=self.K, dist=self.dist, R=self.R, t=self.t, size=self.size, meta=dict(self.meta))
        data.update(changes)
        return Camera(**data)

    # -- serialization ------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "size": [int(self.size[0]), int(self.size[1])],
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            **({"meta": dict(self.meta)} if self.meta else {}),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Camera":
        if not isinstance(data, dict):
            raise ValueError(f"camera must be a dictionary, got {type(data).__name__}")
        unknown = sorted(set(data) - _CAMERA_KEYS)
        if unknown:  # a misspelt key would silently fall back to a default
            raise ValueError(f"camera {data.get('name', '?')!r}: unknown keys {unknown} (known: {sorted(_CAMERA_KEYS)})")
        try:
            return cls(
                name=str(data["name"]),
                K=np.asarray(data["K"], dtype=np.float64),
                dist=np.asarray(data.get("dist", [0, 0, 0, 0, 0]), dtype=np.float64),
                R=np.asarray(data["R"], dtype=np.float64),
                t=np.asarray(data["t"], dtype=np.float64),
                size=tuple(data["size"]),
                meta=dict(data.get("meta", {})),
            )
        except KeyError as exc:
            raise ValueError(f"camera dictionary is missing the key {exc.args[0]!r}") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.name == other.name
            and self.size == other.size
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.dist, other.dist)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
        )

    def __hash__(self) -> int:
        return hash((self.name, self.size, self.K.tobytes(), self.t.tobytes()))

    def __repr__(self) -> str:
        c = self.center
        return (
            f"Camera({self.name!r}, {self.width}x{self.height}, f=({self.K[0, 0]:.1f}, {self.K[1, 1]:.1f}), "
            f"centre=({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}))"
        )


_RAY_CACHE: OrderedDict = OrderedDict()  # camera -> [origin, directions, ray depths or None]
_RAY_LOCK = threading.Lock()
_RAY_CACHE_SIZE = 32


def _cached_rays(camera: Camera) -> list:
    """The ray cache's entry of ``camera`` (computed on a miss), marked as the latest used."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    with _RAY_LOCK:
        hit = _RAY_CACHE.get(camera)
        if hit is not None:
            _RAY_CACHE.move_to_end(camera)
            return hit
    origin, dirs = camera.pixel_grid_rays()
    origin.setflags(write=False)
    dirs.setflags(write=False)
    with _RAY_LOCK:
        entry = _RAY_CACHE.setdefault(camera, [origin, dirs, None])  # another thread's, if it came first
        _RAY_CACHE.move_to_end(camera)
        while len(_RAY_CACHE) > _RAY_CACHE_SIZE:
            _RAY_CACHE.popitem(last=False)
    return entry


def cached_pixel_grid_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`Camera.pixel_grid_rays`, kept for the last 32 cameras asked for.

    Every frame of a camera uses the same rays (rendering, depth back-projection), and
    computing them undistorts every pixel. Thread-safe; the directions are read-only.

    Returns
    -------
    origin : (3,) ndarray
    directions : (H, W, 3) ndarray, read-only
    """
    entry = _cached_rays(camera)
    return entry[0], entry[1]


def cached_pixel_ray_depths(camera: Camera) -> np.ndarray:
    """(H, W) camera-frame Z of every pixel's unit ray (:func:`cached_pixel_grid_rays`), read-only.

    A depth image (camera-frame Z per pixel, what RGB-D sensors give) back-projects as
    ``origin + directions * (depth / ray_depths)[..., None]``. Kept with the rays, in the same
    cache of the last 32 cameras; thread-safe.
    """
    entry = _cached_rays(camera)
    if entry[2] is None:  # two threads may both compute it: the same array
        dz = entry[1] @ camera.R[2]
        dz.setflags(write=False)
        entry[2] = dz
    return entry[2]
