"""Depth path: fuse depth frames into a truncated signed distance volume, then a surface.

RGB-D cameras (depthai, or the simulated rig with ``depth=True``) measure the camera-frame
``Z`` of the first surface behind every pixel. Each voxel centre is projected into each depth
image with the same rule as the visual hull (:func:`pipeline.volume.grid_pixel_index`, lens
distortion included; tables computed once per calibration and grid by :class:`TSDFFusion`),
and the projective signed distance ``sdf = depth - z`` is truncated to ``[-T, T]`` and
averaged over the cameras (Curless & Levoy 1996; Newcombe et al. 2011, KinectFusion).
Voxels more than ``T`` behind a measured surface are occluded for that camera and not updated.

Voxels no camera measured within the band (deep inside the subject, or never seen) take
their sign from carving: inside when every camera that sees them sees them behind the
surface (at least ``min_views`` of them), else outside. When silhouettes exist the field is
intersected with the visual hull (outside the hull is outside). Marching cubes at level 0
gives the surface (:func:`pipeline.surface.surface_from_field`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.calibration import Calibration
from pipeline.hull import _memory_limit
from pipeline.surface import EmptySurfaceError, surface_from_field
from pipeline.volume import Grid, grid_pixel_index

__all__ = ["TSDFResult", "TSDFFusion", "fuse_tsdf", "tsdf_memory_bytes"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TSDFResult:
    """A fused volume.

    Attributes
    ----------
    tsdf : (nx, ny, nz) float32 ndarray
        Truncated signed distance in units of the truncation, in [-1, 1], negative inside;
        every voxel has a value (unobserved ones get -1 or +1, see the module notes).
    weight : (nx, ny, nz) uint8 ndarray
        Cameras that measured the voxel within the truncation band.
    grid : Grid
    truncation : float
        World units.
    """

    tsdf: np.ndarray
    weight: np.ndarray
    grid: Grid
    truncation: float

    def surface(self, **options: Any):
        """Zero level set as a cleaned ``trimesh.Trimesh``; options as :func:`pipeline.surface.surface_from_field`."""
        return surface_from_field(self.tsdf, self.grid, level=0.0, inside="below", **options)


def tsdf_memory_bytes(grid: Grid, calibration: Calibration) -> int:
    """Memory (bytes) of the :class:`TSDFFusion` tables: pixel index and depth per voxel and camera."""
    return int(grid.n_voxels * (8 * len(calibration) + 16))


class TSDFFusion:
    """Fuses depth frames on one grid for one calibration, reusing its projection tables.

    Parameters
    ----------
    calibration : Calibration
        The depth cameras (depth registered to these intrinsics).
    grid : Grid
    truncation : float, optional
        Truncation distance ``T`` in world units; default 3 voxels.
    depth_scale : float, optional
        World units per depth unit (1.0 for uint16 millimetres in a millimetre world,
        0.001 for a metre world).
    memory_limit : int, optional
        Bytes the tables may take (default half the physical memory); more is refused up
        front with the GiB figure.
    """

    def __init__(
        self,
        calibration: Calibration,
        grid: Grid,
        *,
        truncation: float | None = None,
        depth_scale: float = 1.0,
        memory_limit: int | None = None,
    ) -> None:
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
        if not isinstance(grid, Grid):
            raise ValueError(f"grid must be a Grid, got {type(grid).__name__}")
        T = 3.0 * grid.voxel if truncation is None else float(truncation)
        if not (T > 0 and np.isfinite(T)):
            raise ValueError(f"truncation must be a positive distance, got {truncation!r}")
        if not (float(depth_scale) > 0):
            raise ValueError(f"depth_scale must be positive, got {depth_scale!r}")
        need = tsdf_memory_bytes(grid, calibration)
        limit = _memory_limit() if memory_limit is None else int(memory_limit)
        if need > limit:
            raise ValueError(
                f"grid {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} with {len(calibration)} cameras needs "
                f"{need / 1024**3:.2f} GiB for its depth tables, more than the {limit / 1024**3:.2f} GiB allowed; "
                "lower the resolution or shrink the volume"
            )
        self.calibration = calibration
        self.grid = grid
        self.truncation = T
        self.depth_scale = float(depth_scale)
        self._flat = []
        self._z = []
        for cam in calibration:
            flat, z = grid_pixel_index(cam, grid, with_depth=True)
            self._flat.append(flat)
            self._z.append(z)

    def fuse(
        self,
        depths: Any,
        *,
        hull: np.ndarray | None = None,
        min_views: int = 2,
        zero_depth: str = "unknown",
    ) -> TSDFResult:
        """Fuse one frame of depth images.

        Parameters
        ----------
        depths : (C, H, W) uint16 ndarray or list of (H, W) arrays
            Camera-frame Z per pixel in depth units; 0 = no measurement.
        hull : (nx, ny, nz) bool ndarray, optional
            Visual hull on the same grid; outside it is outside.
        min_views : int, optional
            Cameras that must see an unmeasured voxel for carving to call it inside.
        zero_depth : {"unknown", "free"}, optional
            What a 0 pixel means: no information (real sensors: dropouts), or nothing in
            range along that ray (a rig whose background returns no depth).

        Returns
        -------
        TSDFResult

        Raises
        ------
        EmptySurfaceError
            No valid depth in any camera.
        """
        ds = self._check_depths(depths)
        if hull is not None:
            hull = np.asarray(hull)
            if hull.shape != self.grid.shape or hull.dtype != bool:
                raise ValueError(f"hull must be a bool array of the grid's shape {self.grid.shape}")
        if isinstance(min_views, bool) or not isinstance(min_views, (int, np.integer)) or min_views < 1:
            raise ValueError(f"min_views must be a positive integer, got {min_views!r}")
        if zero_depth not in ("unknown", "free"):
            raise ValueError(f"zero_depth must be 'unknown' or 'free', got {zero_depth!r}")
        if not any(np.any(d) for d in ds):
            raise EmptySurfaceError("no valid depth in any camera: the frame is empty")
        n = self.grid.n_voxels
        T = np.float32(self.truncation)
        acc = np.zeros(n, dtype=np.float32)
        weight = np.zeros(n, dtype=np.uint8)
        free = np.zeros(n, dtype=np.uint8)
        seen = np.zeros(n, dtype=np.uint8)
        for flat, z, d in zip(self._flat, self._z, ds):
            vis = flat >= 0
            dv = d.ravel()[np.where(vis, flat, 0)].astype(np.float32) * np.float32(self.depth_scale)
            valid = vis & (dv > 0)
            sdf = dv - z
            upd = valid & (sdf >= -T)
            acc += np.where(upd, np.clip(sdf / T, -1.0, 1.0), np.float32(0))
            weight += upd
            is_free = valid & (sdf > T)
            if zero_depth == "free":
                is_free |= vis & (dv <= 0)
            free += is_free
            seen += vis
        mv = min(int(min_views), len(ds))
        inside = (seen >= mv) & (free == 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            field = np.where(weight > 0, acc / np.maximum(weight, 1), np.where(inside, -1.0, 1.0)).astype(np.float32)
        field = field.reshape(self.grid.shape)
        if hull is not None:
            field = np.where(hull, field, np.float32(1.0))
        return TSDFResult(tsdf=field, weight=weight.reshape(self.grid.shape), grid=self.grid, truncation=float(T))

    def _check_depths(self, depths: Any) -> list[np.ndarray]:
        if isinstance(depths, np.ndarray):
            if depths.ndim != 3:
                raise ValueError(f"depths must have shape (C, H, W), got {depths.shape}")
            items = [depths[i] for i in range(depths.shape[0])]
        elif isinstance(depths, (list, tuple)):
            items = [np.asarray(d) for d in depths]
        else:
            raise ValueError(f"depths must be a (C, H, W) array or a list of (H, W) arrays, got {type(depths).__name__}")
        if len(items) != len(self.calibration):
            raise ValueError(f"depths: expected one depth image per camera ({len(self.calibration)}), got {len(items)}")
        out = []
        for cam, d in zip(self.calibration, items):
            w, h = cam.size
            if d.shape != (h, w):
                raise ValueError(f"depths: camera {cam.name!r} is {w}x{h}, its depth image has shape {d.shape}")
            if not (np.issubdtype(d.dtype, np.integer) or np.issubdtype(d.dtype, np.floating)) or d.dtype == bool:
                raise ValueError(f"depths must be numeric (uint16 depth units), got {d.dtype}")
            out.append(np.where(np.isfinite(d), d, 0) if np.issubdtype(d.dtype, np.floating) else d)
        return out


def fuse_tsdf(
    depths: Any,
    calibration: Calibration,
    grid: Grid,
    *,
    hull: np.ndarray | None = None,
    truncation: float | None = None,
    depth_scale: float = 1.0,
    min_views: int = 2,
    zero_depth: str = "unknown",
) -> TSDFResult:
    """One-off :meth:`TSDFFusion.fuse` (builds the tables for a single frame)."""
    return TSDFFusion(calibration, grid, truncation=truncation, depth_scale=depth_scale).fuse(
        depths, hull=hull, min_views=min_views, zero_depth=zero_depth
    )
