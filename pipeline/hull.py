"""Visual hull by voxel carving with cached lookup tables, coarse to fine.

The visual hull (Laurentini 1994) is the largest solid consistent with the silhouettes: a
voxel is kept when its centre projects into the foreground of every camera that sees it.
Brostow et al. 2004 (section 4) carve it at about 12 minutes per frame; here the geometry
that does not change between frames -- which pixel every voxel projects to, lens
distortion included -- is computed once per calibration and grid (:class:`HullCarver`) and
every frame is carved by table look-ups:

* **Lookup tables.** Per camera, the flat index of the pixel each voxel centre projects to
  (``row * width + col``, or ``-1`` when the camera does not see the voxel), from
  :func:`pipeline.volume.pixel_index`.
* **Coarse to fine.** Voxels are grouped in blocks (e.g. 16^3, then 4^3). For every block
  and camera the tables give the exact bounding rectangle of the pixels its voxels project
  to; with a summed-area table of the mask the number of foreground pixels in that
  rectangle says, per camera, whether *all* the block's voxels fall on background (the
  camera carves the whole block), all on foreground (it keeps it) or neither. Only blocks
  whose fate is undecided are split, down to single voxels at the finest level, where the
  tables are gathered. The test is conservative in the right direction, so the result
  equals full-resolution carving **exactly** (tested).
* **Visibility and tolerance.** A camera only carves voxels it sees; a voxel seen by fewer
  than ``min_views`` cameras is dropped (nothing constrains it); with ``tolerance=k`` a
  voxel survives up to ``k`` cameras that disagree, so one bad mask does not amputate a
  limb.
* **Bad masks.** A camera whose mask is all foreground carries no information (a keying
  failure); it is ignored with a warning naming it. No foreground anywhere raises
  :class:`EmptyHullError` (the frame is empty).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from calib.calibration import Calibration
from pipeline.volume import Grid, above_plane, check_plane, grid_pixel_index, pixel_index

__all__ = [
    "EmptyHullError",
    "HullResult",
    "HullCarver",
    "carve_direct",
    "hull_memory_bytes",
    "default_levels",
    "check_masks",
]

log = logging.getLogger(__name__)

_GIB = 1024.0**3


class EmptyHullError(ValueError):
    """The silhouettes leave nothing: no foreground in any camera, or every voxel carved."""


#: Every voxel carved: the cameras' silhouettes meet nowhere inside the grid (a subject beyond the capture volume
#: meets them outside it).
NO_AGREEMENT = ("every voxel was carved: the silhouettes do not agree on any region of the grid (a subject outside "
                "the capture volume, or masks that miss it)")


@dataclass(frozen=True)
class HullResult:
    """A carved frame.

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool ndarray
        True inside the visual hull, on ``grid``.
    grid : Grid
    ignored : tuple of str
        Cameras left out of this frame (mask all foreground).
    stats : dict
        ``voxels`` kept, ``refined`` voxels tested one by one, ``blocks`` tested per level.
    """

    occupancy: np.ndarray
    grid: Grid
    ignored: tuple[str, ...] = ()
    stats: dict = field(default_factory=dict)


def default_levels(shape: Sequence[int]) -> tuple[int, ...]:
    """Block sizes (coarse to fine) used by :class:`HullCarver` for a grid ``shape``.

    Powers of two from 2 up to about a quarter of the longest axis (at most 32): each level
    halves the block edge, so only the blocks that straddle the silhouette boundary are split.
    """
    n = max(int(s) for s in shape)
    sizes = []
    b = 2
    while b <= min(32, n // 4):
        sizes.append(b)
        b *= 2
    return tuple(reversed(sizes))


def hull_memory_bytes(grid: Grid, calibration: Calibration, *, levels: Sequence[int] | None = None) -> int:
    """Memory the :class:`HullCarver` tables of ``grid`` need (bytes), before building them."""
    lv = tuple(levels) if levels is not None else default_levels(grid.shape)
    top = lv[0] if lv else 1
    npad = grid.padded(top).n_voxels
    c = len(calibration)
    lut = npad * 4 * c  # int32 per voxel per camera
    fp = sum(npad // (b**3) * 10 * c for b in lv)  # i00 int32, du/dv int16, vis flags
    build = npad * 16  # per-camera temporaries while building (col, row, flat, reordered copy)
    frame = npad * 2  # per-frame occupancy and counters (worst case: everything refined)
    return int(lut + fp + build + frame)


def _memory_limit() -> int:
    try:
        phys = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        phys = 8 * 1024**3
    return int(phys // 2)


def check_masks(masks: Any, calibration: Calibration, name: str = "masks") -> list[np.ndarray]:
    """Validate one frame of masks: one (H, W) array per camera, of that camera's size.

    In a list, ``None`` stands for a camera that has no frame in this frame set (a drop):
    it neither carves nor counts as a view. Returns a list of C-contiguous bool arrays
    (and those ``None`` entries).
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    if isinstance(masks, np.ndarray):
        if masks.ndim != 3:
            raise ValueError(f"{name} must have shape (C, H, W), got {masks.shape}")
        items = [masks[i] for i in range(masks.shape[0])]
    elif isinstance(masks, (list, tuple)):
        items = [None if m is None else np.asarray(m) for m in masks]
    else:
        raise ValueError(f"{name} must be a (C, H, W) array or a list of (H, W) arrays, got {type(masks).__name__}")
    if len(items) != len(calibration):
        raise ValueError(f"{name}: expected one mask per camera ({len(calibration)}), got {len(items)}")
    out = []
    for cam, m in zip(calibration, items):
        if m is None or (isinstance(m, np.ndarray) and m.dtype == object and m.ndim == 0 and m.item() is None):
            out.append(None)
            continue
        w, h = cam.size
        if m.shape != (h, w):
            raise ValueError(f"{name}: camera {cam.name!r} is {w}x{h}, its mask has shape {m.shape}")
        if m.dtype != bool:
            if not (np.issubdtype(m.dtype, np.integer) or np.issubdtype(m.dtype, np.floating)):
                raise ValueError(f"{name} must be bool (or numbers, nonzero = foreground), got {m.dtype}")
            m = m != 0
        else:
            # bool arrays made by viewing OpenCV's 0/255 output hold 255 bytes; the tables
            # below read raw bytes, so make every byte 0 or 1
            m = np.ascontiguousarray(m).view(np.uint8) != 0
        out.append(np.ascontiguousarray(m))
    return out


def _usable(masks: list[np.ndarray], calibration: Calibration) -> tuple[list[int], tuple[str, ...]]:
    """Indices of cameras to carve with, names of cameras ignored; raises when nothing is there."""
    use, ignored = [], []
    any_fg = False
    for i, (cam, m) in enumerate(zip(calibration, masks)):
        if m is None:  # no frame from this camera in this set
            ignored.append(cam.name)
            continue
        n = int(np.count_nonzero(m))
        if n == m.size:
            log.warning("camera %s: mask is all foreground (keying failed?); ignored for this frame", cam.name)
            ignored.append(cam.name)
            continue
        any_fg |= n > 0
        use.append(i)
    if not any_fg:
        raise EmptyHullError("no foreground in any camera's mask: the frame is empty")
    return use, tuple(ignored)


def _check_options(tolerance: Any, min_views: Any, n_use: int) -> tuple[int, int]:
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, np.integer)) or tolerance < 0:
        raise ValueError(f"tolerance must be a non-negative integer, got {tolerance!r}")
    if isinstance(min_views, bool) or not isinstance(min_views, (int, np.integer)) or min_views < 1:
        raise ValueError(f"min_views must be a positive integer, got {min_views!r}")
    if tolerance >= max(n_use, 1):
        raise ValueError(f"tolerance={tolerance} must be smaller than the number of cameras carving ({n_use})")
    return int(tolerance), min(int(min_views), n_use)


def _block_reduce(a: np.ndarray, r: int, op) -> np.ndarray:
    """Reduce a 3-D array over ``r x r x r`` blocks with a binary ufunc (strided, fast)."""
    if r == 1:
        return a
    for axis in (2, 1, 0):
        sl = [slice(None)] * 3
        parts = []
        for i in range(r):
            sl[axis] = slice(i, None, r)
            parts.append(a[tuple(sl)])
        out = parts[0].copy()
        for p_ in parts[1:]:
            op(out, p_, out=out)
        a = out
    return a


def carve_direct(
    masks: Any,
    calibration: Calibration,
    grid: Grid,
    *,
    tolerance: int = 0,
    min_views: int = 2,
) -> np.ndarray:
    """Visual hull by projecting every voxel centre in every frame (no tables, no hierarchy).

    Projects with :meth:`calib.camera.Camera.project` (through :func:`pipeline.volume.pixel_index`),
    independently of the tables' :func:`pipeline.volume.grid_pixel_index`.

    The plain baseline that :class:`HullCarver` is compared with, for speed (``stage bench
    reconstruct``) and for exactness (tests). Same rules as :meth:`HullCarver.carve`.

    Parameters
    ----------
    masks : (C, H, W) bool ndarray or list of (H, W) bool ndarrays
        One silhouette per camera of ``calibration``, foreground True.
    calibration : Calibration
    grid : Grid
    tolerance : int, optional
        Number of cameras allowed to disagree before a voxel is carved.
    min_views : int, optional
        Cameras that must see a voxel for it to be kept (clipped to the cameras in use).

    Returns
    -------
    (nx, ny, nz) bool ndarray

    Raises
    ------
    EmptyHullError
        No foreground anywhere, or nothing left after carving.
    """
    ms = check_masks(masks, calibration)
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a Grid, got {type(grid).__name__}")
    use, _ = _usable(ms, calibration)
    k, mv = _check_options(tolerance, min_views, len(use))
    carve = np.zeros(grid.n_voxels, dtype=np.uint8)
    seen = np.zeros(grid.n_voxels, dtype=np.uint8)
    nx, ny, nz = grid.shape
    ax, ay, az = grid.axes()
    step = max(1, (1 << 20) // (ny * nz))
    for i0 in range(0, nx, step):
        i1 = min(nx, i0 + step)
        X, Y, Z = np.meshgrid(ax[i0:i1], ay, az, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        sl = slice(i0 * ny * nz, i1 * ny * nz)
        for i in use:
            flat, _ = pixel_index(calibration[i], pts)
            vis = flat >= 0
            fg = ms[i].ravel()[np.where(vis, flat, 0)]
            seen[sl] += vis
            carve[sl] += vis & ~fg
    occ = (carve <= k) & (seen >= mv)
    if not occ.any():
        raise EmptyHullError(NO_AGREEMENT)
    return occ.reshape(grid.shape)


@dataclass
class _Level:
    """Per-camera footprints of the blocks of one level (arrays are (C, n_blocks))."""

    block: int
    dims: tuple[int, int, int]  # blocks per axis
    i00: np.ndarray  # int32 flat index into the (H+1, W+1) integral image of the rectangle's corner
    du: np.ndarray  # int16 rectangle width (0 when the camera sees no voxel of the block)
    dv: np.ndarray  # int16 rectangle height
    vis_all: np.ndarray  # bool: the camera sees every voxel of the block
    vis_any: np.ndarray  # bool: the camera sees at least one voxel


class HullCarver:
    """Carves visual hulls on one grid for one calibration, reusing its lookup tables.

    Parameters
    ----------
    calibration : Calibration
        Cameras (world units = grid units).
    grid : Grid
    levels : sequence of int, optional
        Block edge lengths of the coarse levels, coarse to fine, each a multiple of the next
        (e.g. ``(16, 4)``); ``()`` carves every voxel from the tables (no hierarchy). Default
        :func:`default_levels`.
    memory_limit : int, optional
        Bytes the tables may take; default half the physical memory. A grid that needs more
        is refused up front (``ValueError`` with the GiB it would need).

    Notes
    -----
    Building the tables projects every voxel of the grid (padded to a multiple of the top
    block) into every camera once; carving a frame then costs a few look-ups per boundary
    block and one gather per boundary voxel and camera.
    """

    def __init__(
        self,
        calibration: Calibration,
        grid: Grid,
        *,
        levels: Sequence[int] | None = None,
        memory_limit: int | None = None,
    ) -> None:
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
        if not isinstance(grid, Grid):
            raise ValueError(f"grid must be a Grid, got {type(grid).__name__}")
        lv = tuple(int(b) for b in (levels if levels is not None else default_levels(grid.shape)))
        for a, b in zip(lv, lv[1:]):
            if b < 1 or a % b or a <= b:
                raise ValueError(f"levels must decrease, each a multiple of the next, got {lv}")
        if lv and lv[-1] < 2:
            raise ValueError(f"levels: the finest block must be at least 2 voxels, got {lv}")
        need = hull_memory_bytes(grid, calibration, levels=lv)
        limit = _memory_limit() if memory_limit is None else int(memory_limit)
        if need > limit:
            raise ValueError(
                f"grid {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} with {len(calibration)} cameras needs "
                f"{need / _GIB:.2f} GiB for its lookup tables, more than the {limit / _GIB:.2f} GiB allowed; "
                "lower the resolution or shrink the volume"
            )
        self.calibration = calibration
        self.grid = grid
        self.levels = lv
        self.memory_bytes = need
        self._above_cache: tuple[tuple[float, ...], np.ndarray] | None = None
        t0 = time.perf_counter()
        self._build()
        self.build_seconds = time.perf_counter() - t0
        log.info("hull tables for %r, %d cameras, levels %s: %.2f s", grid, len(calibration), lv, self.build_seconds)

    # -- tables ---------------------------------------------------------------------------------
    def _build(self) -> None:
        lv = self.levels
        top = lv[0] if lv else 1
        fine = lv[-1] if lv else 1
        pg = self.grid.padded(top)
        self._pgrid = pg
        P = pg.shape
        C = len(self.calibration)
        fdims = tuple(p // fine for p in P)
        nfb = int(np.prod(fdims))
        self._fine = fine
        self._fdims = fdims
        self._lut = np.empty((C, nfb, fine**3), dtype=np.int32)
        self._sentinel = np.empty(C, dtype=np.int64)
        level_arrays: dict[int, dict[str, list]] = {b: {k: [] for k in ("i00", "du", "dv", "all", "any")} for b in lv}
        for c, cam in enumerate(self.calibration):
            w, h = cam.size
            flat = grid_pixel_index(cam, pg)
            vis = flat >= 0
            self._sentinel[c] = w * h
            blk = np.where(vis, flat, w * h).reshape(fdims[0], fine, fdims[1], fine, fdims[2], fine)
            self._lut[c] = blk.transpose(0, 2, 4, 1, 3, 5).reshape(nfb, fine**3)
            if not lv:
                continue
            vis3 = vis.reshape(P)
            col = np.where(vis, flat % w, 0).astype(np.int16).reshape(P)
            row = np.where(vis, flat // w, 0).astype(np.int16).reshape(P)
            big = np.int16(32767)
            # finest-level block extrema from the voxels, coarser levels from their children
            b = lv[-1]
            stats = (
                _block_reduce(np.where(vis3, col, big), b, np.minimum),
                _block_reduce(np.where(vis3, row, big), b, np.minimum),
                _block_reduce(np.where(vis3, col, np.int16(-1)), b, np.maximum),
                _block_reduce(np.where(vis3, row, np.int16(-1)), b, np.maximum),
                _block_reduce(vis3, b, np.logical_and),
                _block_reduce(vis3, b, np.logical_or),
            )
            stats_by_block = {b: stats}
            for hi_b, lo_b in zip(reversed(lv[:-1]), reversed(lv[1:])):
                r = hi_b // lo_b
                ops = (np.minimum, np.minimum, np.maximum, np.maximum, np.logical_and, np.logical_or)
                stats_by_block[hi_b] = tuple(_block_reduce(a_, r, op) for a_, op in zip(stats_by_block[lo_b], ops))
            for b in lv:
                cmin, rmin, cmax, rmax, vall, vany = (a.ravel() for a in stats_by_block[b])
                i00 = np.where(vany, rmin.astype(np.int32) * (w + 1) + cmin, 0).astype(np.int32)
                du = np.where(vany, cmax - cmin + 1, 0).astype(np.int16)
                dv = np.where(vany, rmax - rmin + 1, 0).astype(np.int16)
                la = level_arrays[b]
                la["i00"].append(i00)
                la["du"].append(du)
                la["dv"].append(dv)
                la["all"].append(vall)
                la["any"].append(vany)
        self._levels: list[_Level] = []
        for b in lv:
            la = level_arrays[b]
            self._levels.append(
                _Level(
                    block=b,
                    dims=tuple(p // b for p in P),  # type: ignore[arg-type]
                    i00=np.stack(la["i00"]),
                    du=np.stack(la["du"]),
                    dv=np.stack(la["dv"]),
                    vis_all=np.stack(la["all"]),
                    vis_any=np.stack(la["any"]),
                )
            )

    def lut(self, camera: int | str) -> np.ndarray:
        """Lookup table of one camera: (nx, ny, nz) int32 flat pixel index, -1 where unseen."""
        c = self.calibration.names.index(camera) if isinstance(camera, str) else int(camera)
        f, fd = self._fine, self._fdims
        t = self._lut[c].reshape(fd[0], fd[1], fd[2], f, f, f).transpose(0, 3, 1, 4, 2, 5)
        t = t.reshape(self._pgrid.shape)
        nx, ny, nz = self.grid.shape
        t = t[:nx, :ny, :nz]
        return np.where(t == self._sentinel[c], -1, t).astype(np.int32)

    # -- carving --------------------------------------------------------------------------------
    def carve(
        self,
        masks: Any,
        *,
        tolerance: int = 0,
        min_views: int = 2,
        coarse_to_fine: bool = True,
        support_plane: Any = None,
        margin: int = 0,
    ) -> HullResult:
        """Carve one frame.

        Parameters
        ----------
        masks : (C, H, W) bool ndarray or list of (H, W) bool ndarrays
            One silhouette per camera, in calibration order, foreground True.
        tolerance : int, optional
            A voxel survives up to ``tolerance`` cameras that see it on background.
        min_views : int, optional
            Cameras that must see a voxel for it to be kept (clipped to the cameras in use).
        coarse_to_fine : bool, optional
            Use the block hierarchy (same result, much faster); False gathers every voxel.
        support_plane : (4,) float array-like, optional
            ``(a, b, c, d)``: the plane the subject stands on; voxels whose centre lies
            below it (``a x + b y + c z + d < 0``) are carved. Cameras that all look
            down on the subject cannot carve the cone under its base
            (:func:`pipeline.volume.above_plane`).
        margin : int, optional
            Grow every silhouette by this many pixels before carving (a conservative
            hull, Laurentini 1994): with calibration and keying both off by a fraction
            of a pixel, the intersection of many exact silhouettes shaves thin parts
            (spikes, limb tips) that every camera only just sees.

        Returns
        -------
        HullResult

        Raises
        ------
        EmptyHullError
            No foreground in any mask, or nothing left after carving.
        ValueError
            Masks of the wrong number, size or type; bad options.
        """
        ms = check_masks(masks, self.calibration)
        if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or margin < 0:
            raise ValueError(f"margin must be a non-negative integer (pixels), got {margin!r}")
        if margin > 0:
            import cv2

            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
            ms = [None if m is None else cv2.dilate(m.view(np.uint8), disk).view(bool) for m in ms]
        above = None if support_plane is None else self._above(support_plane)
        use, ignored = _usable(ms, self.calibration)
        k, mv = _check_options(tolerance, min_views, len(use))
        stats: dict[str, Any] = {"blocks": []}
        if coarse_to_fine and self._levels:
            full_blocks, fine_blocks = self._sort_blocks(ms, use, k, mv, stats)
        else:
            full_blocks, fine_blocks = [], np.arange(self._lut.shape[1], dtype=np.int64)
        stats["refined"] = int(fine_blocks.size * self._fine**3)
        occ = self._occupancy(ms, use, k, mv, full_blocks, fine_blocks)
        if above is not None:
            occ &= above
        n = int(np.count_nonzero(occ))
        stats["voxels"] = n
        if n == 0:
            raise EmptyHullError(NO_AGREEMENT)
        return HullResult(occupancy=occ, grid=self.grid, ignored=ignored, stats=stats)

    def _sort_blocks(self, ms, use, k: int, mv: int, stats: dict) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
        """Coarse to fine: every block that all its pixels' counts say is empty is dropped, one they say
        is full is kept whole (``(level, blocks)`` pairs), the rest are refined; -> those and the finest
        blocks left to carve voxel by voxel."""
        import cv2

        integ = [cv2.integral(ms[i].view(np.uint8)).ravel() for i in use]
        widths = [self.calibration[i].size[0] + 1 for i in use]
        active = np.arange(int(np.prod(self._levels[0].dims)), dtype=np.int64)
        full_blocks: list[tuple[int, np.ndarray]] = []
        for li, L in enumerate(self._levels):
            stats["blocks"].append(int(active.size))
            if active.size == 0:
                break
            n_lo = np.zeros(active.size, dtype=np.int16)
            n_hi = np.zeros(active.size, dtype=np.int16)
            s_lo = np.zeros(active.size, dtype=np.int16)
            s_hi = np.zeros(active.size, dtype=np.int16)
            for j, i in enumerate(use):
                S = integ[j]
                i00 = L.i00[i, active]
                du = L.du[i, active].astype(np.int32)
                dv = L.dv[i, active].astype(np.int32) * widths[j]
                cnt = S[i00 + dv + du] - S[i00 + du] - S[i00 + dv] + S[i00]
                area = du * (dv // widths[j])
                va = L.vis_all[i, active]
                n_lo += va & (cnt == 0)
                n_hi += cnt < area
                s_lo += va
                s_hi += L.vis_any[i, active]
            empty = (n_lo > k) | (s_hi < mv)
            full = ~empty & (n_hi <= k) & (s_lo >= mv)
            amb = ~(empty | full)
            full_blocks.append((li, active[full]))
            nxt = active[amb]
            active = self._children(nxt, li)
        return full_blocks, active

    def _occupancy(self, ms, use, k: int, mv: int, full_blocks, fine_blocks: np.ndarray) -> np.ndarray:
        """The grid's occupancy: the whole blocks, and the finest blocks carved voxel by voxel."""
        P = self._pgrid.shape
        occ = np.zeros(P, dtype=bool)
        for li, blocks in full_blocks:  # whole blocks, written at their own level
            if blocks.size:
                L = self._levels[li]
                bx, by, bz = np.unravel_index(blocks, L.dims)
                occ.reshape(L.dims[0], L.block, L.dims[1], L.block, L.dims[2], L.block)[bx, :, by, :, bz, :] = True
        if fine_blocks.size:
            f3 = self._fine**3
            carve = np.zeros((fine_blocks.size, f3), dtype=np.uint8)
            seen = np.zeros((fine_blocks.size, f3), dtype=np.uint8)
            for i in use:
                e = np.empty(ms[i].size + 1, dtype=np.uint8)
                e[:-1] = ms[i].ravel()
                e[-1] = 2  # sentinel: voxel not seen by this camera
                v = e[self._lut[i][fine_blocks]]
                carve += v == 0
                seen += v != 2
            keep = (carve <= k) & (seen >= mv)
            rows, cols = np.nonzero(keep)
            f = self._fine
            bx, by, bz = np.unravel_index(fine_blocks[rows], self._fdims)
            lx, ly, lz = np.unravel_index(cols, (f, f, f))
            occ.reshape(-1)[((bx * f + lx) * P[1] + (by * f + ly)) * P[2] + (bz * f + lz)] = True
        nx, ny, nz = self.grid.shape
        if (nx, ny, nz) != P:
            occ = np.ascontiguousarray(occ[:nx, :ny, :nz])
        return occ

    def _above(self, plane: Any) -> np.ndarray:
        key = tuple(check_plane(plane).tolist())
        cached = self._above_cache
        if cached is None or cached[0] != key:
            cached = (key, above_plane(self.grid, key))
            self._above_cache = cached
        return cached[1]

    def _children(self, blocks: np.ndarray, li: int) -> np.ndarray:
        """Ids of the children (next level, or fine blocks after the last level) of ``blocks``."""
        L = self._levels[li]
        if li + 1 < len(self._levels):
            nb = self._levels[li + 1]
            r = L.block // nb.block
            cd = nb.dims
        else:
            r = L.block // self._fine
            cd = self._fdims
        if r == 1:
            return blocks
        x, y, z = np.unravel_index(blocks, L.dims)
        o = np.arange(r)
        cx = (x[:, None] * r + o)[:, :, None, None]
        cy = (y[:, None] * r + o)[:, None, :, None]
        cz = (z[:, None] * r + o)[:, None, None, :]
        return ((cx * cd[1] + cy) * cd[2] + cz).reshape(-1)
