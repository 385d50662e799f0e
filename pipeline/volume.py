"""Voxel grids over the capture volume, and the voxel -> pixel rule shared by every carver.

A :class:`Grid` is an axis-aligned block of cubic voxels in the calibration's world frame
(millimetres for our rigs). Voxel ``(i, j, k)`` has its centre at
``lo + (i + 0.5, j + 0.5, k + 0.5) * voxel``.

A voxel *projects to* the pixel that contains the projection of its centre (lens distortion
included, via :meth:`calib.camera.Camera.project`): ``(floor(u + 0.5), floor(v + 0.5))``, pixel
centres at integer coordinates as in OpenCV. A camera *sees* a voxel when that pixel lies in
the image and the centre is in front of the camera (``Z > 0``). Every carver in ``pipeline``
(visual hull, TSDF) uses :func:`pixel_index` so they agree to the voxel.

Footage imported from another rig has no capture volume; :func:`volume_from_cameras` derives
one from the cameras (the region most of them see), optionally narrowed by the masks'
bounding boxes (a conservative visual hull of the bounding boxes, Laurentini 1994).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from stage.rig import check_plane  # the one rule for planes; re-exported here for the pipeline

__all__ = [
    "Grid",
    "grid_from_volume",
    "volume_from_cameras",
    "pixel_index",
    "grid_pixel_index",
    "check_bounds",
    "check_plane",
    "above_plane",
    "view_elevation",
    "pixel_footprint",
]

log = logging.getLogger(__name__)


def check_bounds(bounds: Any, name: str = "volume_bounds") -> np.ndarray:
    """Validate axis-aligned bounds and return them as a (2, 3) float array ``[lo, hi]``."""
    try:
        b = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair of 3-vectors (lo, hi)") from None
    if b.shape != (2, 3):
        raise ValueError(f"{name} must have shape (2, 3) = (lo, hi), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{name} must be finite")
    if np.any(b[1] <= b[0]):
        raise ValueError(f"{name}: hi must exceed lo in every axis, got lo={b[0].tolist()} hi={b[1].tolist()}")
    return b


def above_plane(grid: "Grid", plane: Any) -> np.ndarray:
    """Voxels whose centre lies on or above a plane (the side its normal points to).

    A subject standing on a support (floor, turntable, pedestal) has nothing below it,
    but when every camera looks down on it no silhouette can carve the cone under its
    base: a visual hull from cameras at elevation ``theta`` reaches about
    ``r * tan(theta)`` below a base of radius ``r``. The support plane removes it.

    Parameters
    ----------
    grid : Grid
    plane : (4,) float array-like
        ``(a, b, c, d)``: kept where ``a x + b y + c z + d >= 0`` (world units).

    Returns
    -------
    (nx, ny, nz) bool ndarray
    """
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a Grid, got {type(grid).__name__}")
    p = check_plane(plane)
    ax, ay, az = grid.axes()
    s = (p[0] * ax)[:, None, None] + (p[1] * ay)[None, :, None] + (p[2] * az)[None, None, :] + p[3]
    return s >= 0


def view_elevation(calibration: Calibration, point: Any) -> tuple[np.ndarray, float]:
    """How far above the subject every camera sits: the blind side under a ring of cameras.

    Parameters
    ----------
    calibration : Calibration
    point : (3,) float array-like
        The subject's centre, world units.

    Returns
    -------
    up : (3,) float ndarray
        Unit direction of the mean viewing position (the cameras' side).
    elevation : float
        Smallest angle, in degrees, between a camera's direction from ``point`` and the plane
        perpendicular to ``up``. Positive when every camera looks down on the subject: then
        no silhouette can carve the cone under its base, which reaches about
        ``tan(elevation)`` times the base's half-width below it (see :func:`above_plane`).
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    p = np.asarray(point, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"point must be a finite 3-vector, got {point!r}")
    d = np.stack([c.center - p for c in calibration])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = d.mean(axis=0)
    if np.linalg.norm(m) < 1e-9:  # cameras all around: no blind side
        return np.array([0.0, 0.0, 1.0]), -90.0
    from scipy.optimize import minimize

    def unit(a: np.ndarray) -> np.ndarray:
        return np.array([np.sin(a[0]) * np.cos(a[1]), np.sin(a[0]) * np.sin(a[1]), np.cos(a[0])])

    # the direction whose lowest camera is highest (start: the mean viewing direction)
    m = m / np.linalg.norm(m)
    a0 = np.array([np.arccos(np.clip(m[2], -1, 1)), np.arctan2(m[1], m[0])])
    res = minimize(lambda a: -float((d @ unit(a)).min()), a0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9})
    up = unit(res.x) if -res.fun >= float((d @ m).min()) else m
    return up, float(np.degrees(np.arcsin(np.clip(d @ up, -1.0, 1.0)).min()))


@dataclass(frozen=True, eq=False)
class Grid:
    """A block of cubic voxels.

    Parameters
    ----------
    lo : (3,) float ndarray
        Corner of the grid (minimum x, y, z) in world units.
    shape : (int, int, int)
        Number of voxels along x, y, z.
    voxel : float
        Edge length of a voxel in world units.
    """

    lo: np.ndarray
    shape: tuple[int, int, int]
    voxel: float

    def __post_init__(self) -> None:
        lo = np.asarray(self.lo, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or not np.all(np.isfinite(lo)):
            raise ValueError(f"lo must be a finite 3-vector, got {self.lo!r}")
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"shape must be three positive integers, got {self.shape!r}")
        voxel = float(self.voxel)
        if not (voxel > 0 and math.isfinite(voxel)):
            raise ValueError(f"voxel must be a positive number, got {self.voxel!r}")
        lo.setflags(write=False)
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "voxel", voxel)

    @property
    def hi(self) -> np.ndarray:
        """(3,) far corner."""
        return self.lo + np.asarray(self.shape, dtype=np.float64) * self.voxel

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) ``[lo, hi]``."""
        return np.stack([self.lo, self.hi])

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y and z: three 1-D arrays."""
        return tuple(self.lo[a] + (np.arange(self.shape[a]) + 0.5) * self.voxel for a in range(3))  # type: ignore[return-value]

    def centers(self) -> np.ndarray:
        """(N, 3) voxel centres in C order of ``shape`` (x slowest)."""
        ax, ay, az = self.axes()
        X, Y, Z = np.meshgrid(ax, ay, az, indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) continuous voxel indices -> world points (index ``i`` is the centre of voxel ``i``)."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return self.lo + (ijk + 0.5) * self.voxel

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> continuous voxel indices (inverse of :meth:`index_to_world`)."""
        pts = np.asarray(points, dtype=np.float64)
        return (pts - self.lo) / self.voxel - 0.5

    def padded(self, multiple: int) -> "Grid":
        """The same grid with every dimension rounded up to a multiple of ``multiple`` (grown at ``hi``)."""
        m = int(multiple)
        if m < 1:
            raise ValueError("multiple must be >= 1")
        shape = tuple(int(-(-s // m) * m) for s in self.shape)
        return Grid(self.lo, shape, self.voxel)

    def to_dict(self) -> dict:
        return {"lo": self.lo.tolist(), "shape": list(self.shape), "voxel": self.voxel}

    @classmethod
    def from_dict(cls, data: dict) -> "Grid":
        try:
            return cls(np.asarray(data["lo"], dtype=np.float64), tuple(data["shape"]), float(data["voxel"]))
        except KeyError as exc:
            raise ValueError(f"grid dictionary is missing the key {exc.args[0]!r}") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Grid):
            return NotImplemented
        return self.shape == other.shape and self.voxel == other.voxel and np.array_equal(self.lo, other.lo)

    def __hash__(self) -> int:
        return hash((self.shape, self.voxel, self.lo.tobytes()))

    def __repr__(self) -> str:
        lo, hi = self.lo, self.hi
        return (
            f"Grid({self.shape[0]}x{self.shape[1]}x{self.shape[2]}, voxel={self.voxel:.4g}, "
            f"lo=({lo[0]:.4g}, {lo[1]:.4g}, {lo[2]:.4g}), hi=({hi[0]:.4g}, {hi[1]:.4g}, {hi[2]:.4g}))"
        )


def grid_from_volume(volume_bounds: Any, resolution: int) -> Grid:
    """A grid of cubic voxels covering an axis-aligned volume.

    Parameters
    ----------
    volume_bounds : (2, 3) float array-like
        ``(lo, hi)`` corners of the volume, world units. A ``stage.rig.Volume`` works too
        (its ``bounds``).
    resolution : int
        Number of voxels along the longest axis; the other axes get as many voxels of the
        same size as needed to cover them. The grid is centred on the volume.

    Returns
    -------
    Grid
    """
    if hasattr(volume_bounds, "bounds") and not isinstance(volume_bounds, np.ndarray):
        volume_bounds = volume_bounds.bounds
    b = check_bounds(volume_bounds)
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    ext = b[1] - b[0]
    voxel = float(ext.max()) / int(resolution)
    shape = tuple(max(1, int(math.ceil(e / voxel - 1e-9))) for e in ext)
    centre = (b[0] + b[1]) / 2
    lo = centre - np.asarray(shape, dtype=np.float64) * voxel / 2
    return Grid(lo, shape, voxel)  # type: ignore[arg-type]


def pixel_index(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel each point projects to, as a flat index into the camera's image.

    Parameters
    ----------
    camera : Camera
    points : (N, 3) float ndarray
        World points (voxel centres).

    Returns
    -------
    flat : (N,) int32 ndarray
        ``row * width + column`` of the pixel containing the projection (rounded to the
        nearest pixel centre), or ``-1`` when the point projects outside the image or lies
        behind the camera.
    depth : (N,) float64 ndarray
        Camera-frame ``Z`` of every point.
    """
    pix, z = camera.project(points, return_depth=True)
    w, h = camera.size
    with np.errstate(invalid="ignore"):
        col = np.floor(pix[:, 0] + 0.5)
        row = np.floor(pix[:, 1] + 0.5)
        ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = np.full(points.shape[0] if points.ndim == 2 else 1, -1, dtype=np.int32)
    flat[ok] = (row[ok] * w + col[ok]).astype(np.int32)
    return flat, z


def grid_pixel_index(
    camera: Camera, grid: Grid, *, with_depth: bool = False, chunk_voxels: int = 1 << 17
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """:func:`pixel_index` of every voxel centre of ``grid``, computed slab by slab.

    Same formula as :func:`calib.camera.project_points`, evaluated with the grid's separable
    structure (``R @ X + t`` as a sum of three per-axis terms) in cache-sized chunks; it
    agrees with :func:`pixel_index` except for floating-point ties exactly on a pixel border.

    Parameters
    ----------
    camera : Camera
    grid : Grid
    with_depth : bool, optional
        Also return the camera-frame ``Z`` of every voxel centre (float32).
    chunk_voxels : int, optional
        Voxels per chunk.

    Returns
    -------
    flat : (nx * ny * nz,) int32 ndarray
        Flat pixel index per voxel in C order of ``grid.shape``, ``-1`` where unseen.
    depth : (nx * ny * nz,) float32 ndarray, only with ``with_depth``
    """
    nx, ny, nz = grid.shape
    ax, ay, az = grid.axes()
    R, t, K = camera.R, camera.t, camera.K
    k1, k2, p1, p2, k3 = camera.dist
    has_dist = bool(np.any(camera.dist))
    w, h = camera.size
    A = [np.outer(ax, R[:, 0]), np.outer(ay, R[:, 1]), np.outer(az, R[:, 2])]
    flat_out = np.empty(grid.n_voxels, dtype=np.int32)
    z_out = np.empty(grid.n_voxels, dtype=np.float32) if with_depth else None
    step = max(1, int(chunk_voxels) // (ny * nz))
    for i0 in range(0, nx, step):
        i1 = min(nx, i0 + step)
        pc = [
            A[0][i0:i1, m][:, None, None] + A[1][:, m][None, :, None] + A[2][:, m][None, None, :] + t[m]
            for m in range(3)
        ]
        z = pc[2].reshape(-1)
        safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
        x = pc[0].reshape(-1) / safe
        y = pc[1].reshape(-1) / safe
        if has_dist:
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        else:
            xd, yd = x, y
        u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        v = K[1, 1] * yd + K[1, 2]
        with np.errstate(invalid="ignore"):
            col = np.floor(u + 0.5)
            row = np.floor(v + 0.5)
            ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        f = np.where(ok, row * w + col, -1.0)
        sl = slice(i0 * ny * nz, i1 * ny * nz)
        flat_out[sl] = f
        if z_out is not None:
            z_out[sl] = z
    if z_out is not None:
        return flat_out, z_out
    return flat_out


# -- capture volume from the cameras -------------------------------------------------------------


def _look_at_point(cams: Sequence[Camera]) -> np.ndarray:
    """Least-squares point closest to every optical axis."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.R[2]  # optical axis in world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e8:  # parallel axes: fall back to a point in front of the cameras
        return np.mean([c.center + c.R[2] * 1.0 for c in cams], axis=0)
    return np.linalg.solve(A, b)


def _mask_boxes(masks: Any, calibration: Calibration, pad: int) -> list[tuple[int, int, int, int] | None]:
    """Per camera (col0, row0, col1, row1) inclusive box of foreground over all frames, or None."""
    arr = masks
    if isinstance(arr, np.ndarray):
        if arr.ndim == 3:
            arr = arr[None]
        if arr.ndim != 4:
            raise ValueError(f"masks must have shape (C, H, W) or (F, C, H, W), got {np.shape(masks)}")
        per_cam = [arr[:, c] for c in range(arr.shape[1])]
    else:
        per_cam = [np.asarray(m) for m in arr]
        per_cam = [m[None] if m.ndim == 2 else m for m in per_cam]
    if len(per_cam) != len(calibration):
        raise ValueError(f"masks: expected one mask per camera ({len(calibration)}), got {len(per_cam)}")
    boxes: list[tuple[int, int, int, int] | None] = []
    for cam, m in zip(calibration, per_cam):
        w, h = cam.size
        if m.ndim != 3 or m.shape[1:] != (h, w):
            raise ValueError(f"masks: camera {cam.name!r} expects {h}x{w} masks, got shape {m.shape[1:]}")
        fg = np.asarray(m, dtype=bool).any(axis=0)
        if fg.all():
            log.warning("camera %s: mask is all foreground; not used to bound the volume", cam.name)
            boxes.append(None)
            continue
        rows = np.flatnonzero(fg.any(axis=1))
        cols = np.flatnonzero(fg.any(axis=0))
        if rows.size == 0:
            boxes.append((1, 1, 0, 0))  # empty box: nothing in this camera
            continue
        boxes.append((max(cols[0] - pad, 0), max(rows[0] - pad, 0), min(cols[-1] + pad, w - 1), min(rows[-1] + pad, h - 1)))
    return boxes


def pixel_footprint(calibration: Calibration, points: Any) -> np.ndarray:
    """Size of one pixel at some points, per camera (world units per pixel).

    A pixel of focal length ``f`` (pixels) covers ``Z / f`` world units at depth ``Z``
    along the optical axis (pinhole; distortion changes it by well under a percent near
    the image centre, where a subject is filmed).

    Parameters
    ----------
    calibration : Calibration
    points : (3,) or (N, 3) float array-like
        World points, e.g. the subject's centre.

    Returns
    -------
    (C, N) float ndarray
        NaN where the camera does not see the point (behind it or outside its image).
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(P).all():
        raise ValueError("points must be finite")
    out = np.full((len(calibration), len(P)), np.nan)
    for i, cam in enumerate(calibration):
        flat, _ = pixel_index(cam, P)
        z = cam.world_to_camera(P)[:, 2]
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        seen = flat >= 0
        out[i, seen] = z[seen] / f
    return out


def volume_from_cameras(
    calibration: Calibration,
    masks: Any = None,
    *,
    min_fraction: float = 0.5,
    margin: float = 0.05,
    samples: int = 48,
    iterations: int = 4,
    box_pad: int = 4,
) -> np.ndarray:
    """Derive a capture volume from the cameras (for footage without a rig volume).

    The volume is the bounding box of the region that at least ``min_fraction`` of the
    cameras see (at least two); with masks, only points that fall inside the foreground
    bounding box of every camera that sees them count (a conservative visual hull of the
    boxes). It is found by sampling a cube around the point closest to all optical axes and
    shrinking the cube onto the kept samples a few times.

    Parameters
    ----------
    calibration : Calibration
    masks : (C, H, W) or (F, C, H, W) bool ndarray, or a list of per-camera masks, optional
        Silhouettes; several frames make the union of their boxes.
    min_fraction : float, optional
        Fraction of the cameras that must see a point, in (0, 1].
    margin : float, optional
        Relative margin added on every side of the box found.
    samples : int, optional
        Samples per axis of each refinement pass.
    iterations : int, optional
        Refinement passes.
    box_pad : int, optional
        Pixels added around every mask bounding box.

    Returns
    -------
    (2, 3) float ndarray
        ``[lo, hi]`` in world units.

    Raises
    ------
    ValueError
        Bad arguments, or no region that enough cameras see (or no foreground at all).
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    if not (0 < float(min_fraction) <= 1):
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction!r}")
    if not (float(margin) >= 0):
        raise ValueError(f"margin must be >= 0, got {margin!r}")
    if int(samples) < 4 or int(iterations) < 1:
        raise ValueError("samples must be >= 4 and iterations >= 1")
    cams = list(calibration)
    need = max(min(2, len(cams)), int(math.ceil(min_fraction * len(cams))))
    boxes = _mask_boxes(masks, calibration, int(box_pad)) if masks is not None else [None] * len(cams)
    if masks is not None and all(b is not None and b[0] > b[2] for b in boxes):
        raise ValueError("masks: no foreground in any camera; cannot bound the subject")

    centre = _look_at_point(cams)
    dist = np.median([np.linalg.norm(c.center - centre) for c in cams])
    lo, hi = centre - dist, centre + dist
    kept_lo = kept_hi = kept_step = None
    for _ in range(int(iterations)):
        axes = [np.linspace(lo[a], hi[a], int(samples)) for a in range(3)]
        step = (hi - lo) / (int(samples) - 1)
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        seen = np.zeros(len(pts), dtype=np.int32)
        inside = np.ones(len(pts), dtype=bool)
        for cam, box in zip(cams, boxes):
            flat, _ = pixel_index(cam, pts)
            vis = flat >= 0
            seen += vis
            if box is not None:
                w = cam.size[0]
                col, row = flat % w, flat // w
                inb = (col >= box[0]) & (col <= box[2]) & (row >= box[1]) & (row <= box[3])
                inside &= ~vis | inb
        keep = (seen >= need) & inside
        if not keep.any():
            if kept_lo is None:
                raise ValueError(
                    f"no region is seen by {need} of the {len(cams)} cameras"
                    + (" inside the masks' bounding boxes" if masks is not None else "")
                    + "; pass the volume explicitly"
                )
            break
        kp = pts[keep]
        kept_lo, kept_hi, kept_step = kp.min(axis=0), kp.max(axis=0), step
        lo, hi = kept_lo - 1.5 * step, kept_hi + 1.5 * step
    assert kept_lo is not None and kept_hi is not None and kept_step is not None
    # the true region reaches at most one sample step beyond the outermost kept sample
    lo, hi = kept_lo - kept_step, kept_hi + kept_step
    ext = hi - lo
    out = np.stack([lo - margin * ext, hi + margin * ext])
    log.info("capture volume from %d cameras: lo=%s hi=%s", len(cams), out[0].round(4), out[1].round(4))
    return out
