"""The subject's box: where the subject is over the whole take, found coarse to fine from the silhouettes.

The processing grid (:mod:`pipeline.process`) must hold the subject in every frame set and be no
larger than it needs to be: its voxel follows the cameras' pixel footprint within a voxel budget, so
a box several times the subject's costs resolution. :func:`find_subject_box` finds the box from
every frame set of the take in one pass:

1. **Conservative carving, coarse to fine.** The search volume is cut into cubes, 16 along its
   longest side at the top level, each level halving the cube edge down to the finest voxel
   (default :data:`FOOTPRINT_PIXELS` pixel footprints at the volume's centre). A cube is tested
   against the *whole rectangle* its corners project to (one pixel wider on every side), not
   against the pixel of its centre: a camera that sees the whole cube and finds no silhouette
   pixel in that rectangle carves it (Laurentini 1994: a conservative hull, which holds the
   subject whatever the cube size, thin limbs included). Only the children of the cubes kept at
   one level are tested at the next, on silhouettes max-pooled to the finest level's scale
   (a pooled pixel is foreground when any of its pixels is), so a frame set costs about the
   subject's surface in cubes.
2. **Cameras that find it.** A camera *finds* a cube when it sees some of the cube and a
   silhouette pixel lies in the part of the cube's rectangle inside its image. A cube is kept
   only when at least half the cameras that see most of the volume (at least two) find it
   (:func:`find_subject_box`'s ``min_share``), and at least as many as find the best-found cube
   of its frame set and level, less ``view_slack`` (default one). Every camera that sees a
   point of the subject finds the cubes around it, so the subject's cubes are found by all the
   cameras that see it; a phantom crossing of a few silhouette cones is found only by those few
   (two opposite cameras' cones cross along the whole line between them, out to where the
   other cameras no longer see). The slack keeps a limb that leaves one camera's image, or
   falls in a hole of one camera's silhouette, where the body is found by all.
3. **The silhouettes explain every piece.** The kept cubes form connected pieces. A piece is the
   subject's when its projection *uniquely* explains silhouette pixels (pixels no other piece
   covers) in at least ``min_support`` cameras, at least ``support_share`` of the silhouette it
   covers there. A phantom crossing of cones lies inside silhouettes that the subject's own piece
   already covers, so it explains nothing alone; a spurious blob in one camera's silhouettes
   explains its pixels in that one camera only. Neither is the subject, whatever its size
   (ghost removal in the spirit of Franco & Boyer 2009 and Guan et al. 2008).

The box is the union of the pieces kept at the finest level over all frame sets, grown by one
finest voxel on every side (the margin), within the search volume.

Written here rather than with :class:`pipeline.hull.HullCarver`: the carver tests voxel centres
on one fixed grid (exact at its own resolution, not conservative across levels), and no library
carves with rectangle footprints or sorts the pieces of a hull by the silhouette pixels they
alone explain.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.calibration import Calibration
from pipeline.volume import check_bounds, check_plane, pixel_footprint, pixel_index

__all__ = ["SubjectBox", "find_subject_box", "TOP_VOXELS", "FOOTPRINT_PIXELS"]

log = logging.getLogger(__name__)

#: Cubes along the search volume's longest side at the top level.
TOP_VOXELS = 16
#: Default finest cube edge, in pixel footprints at the search volume's centre (median camera).
FOOTPRINT_PIXELS = 4.0
#: Levels at most (the finest is then 16 * 2**7 = 2048 cubes along the volume's longest side).
MAX_LEVELS = 8
#: Pooled pixels along the finest cube's projection, at least (the masks are pooled to this scale).
POOLED_PIXELS = 2.0

_OFFSETS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)  # cube corners


@dataclass(frozen=True)
class SubjectBox:
    """Where the subject is over a take (:func:`find_subject_box`).

    Attributes
    ----------
    bounds : (2, 3) float ndarray
        ``[lo, hi]`` of the box (the pieces' union grown by ``margin``, within the search volume).
    frame_boxes : (S, 2, 3) float ndarray
        The subject's box in every frame set (the cubes kept at the finest level), NaN where
        no subject was found.
    centres : (S, 3) float ndarray
        Centre of the kept cubes per frame set (NaN where none): where the subject is, for the
        pixel footprint at the subject.
    voxels : tuple of float
        Cube edge of every level, coarse to fine.
    margin : float
        Grown on every side of the union (one finest cube).
    min_views : int
        Cameras that must find a cube at least (``min_share`` of the most cameras seeing any point).
    view_slack : int
        A cube is found by at least the most cameras finding any cube of its frame set less this.
    pooling : tuple of int
        Per camera, the silhouettes' pooling factor.
    stats : dict
        ``frame_sets`` searched, ``with_subject``, ``pieces_kept`` and ``pieces_rejected`` (at the
        finest level, summed over the frame sets), ``phantoms_rejected`` (at any level).
    """

    bounds: np.ndarray
    frame_boxes: np.ndarray
    centres: np.ndarray
    voxels: tuple[float, ...]
    margin: float
    min_views: int
    pooling: tuple[int, ...]
    stats: dict = field(default_factory=dict)
    view_slack: int = 1

    def to_dict(self) -> dict:
        """The box and why (for ``process.json``): JSON types only."""
        lo, hi = self.bounds
        return {
            "lo": lo.tolist(), "hi": hi.tolist(), "size": (hi - lo).tolist(),
            "level_voxels": [float(v) for v in self.voxels], "margin": float(self.margin),
            "min_views": int(self.min_views), "view_slack": int(self.view_slack),
            "pooling": [int(s) for s in self.pooling], **self.stats,
        }


# ----------------------------------------------------------------------------- geometry of the cubes


def _cube_rects(cam, lo: np.ndarray, voxel: float, ijk: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per cube: seen whole, seen in part, and the pixel rectangle (c0, r0, c1, r1, inclusive,
    clipped, one pixel wider on every side) its eight corners project to."""
    # corner first (8, M): the reductions over the eight corners run along whole rows
    corners = lo + (ijk[None, :, :] + _OFFSETS[:, None, :]) * voxel
    pix, z = cam.project(corners.reshape(-1, 3), return_depth=True)
    m = len(ijk)
    z = z.reshape(8, m)
    u = np.floor(pix[:, 0].reshape(8, m) + 0.5)
    v = np.floor(pix[:, 1].reshape(8, m) + 0.5)
    front = np.logical_and.reduce(z > 0, axis=0)
    w, h = cam.size
    with np.errstate(invalid="ignore"):
        c0, c1 = np.minimum.reduce(u, axis=0), np.maximum.reduce(u, axis=0)
        r0, r1 = np.minimum.reduce(v, axis=0), np.maximum.reduce(v, axis=0)
        front &= np.isfinite(c0) & np.isfinite(c1) & np.isfinite(r0) & np.isfinite(r1)
        whole = front & (c0 >= 0) & (c1 <= w - 1) & (r0 >= 0) & (r1 <= h - 1)
        part = front & (c1 >= 0) & (c0 <= w - 1) & (r1 >= 0) & (r0 <= h - 1)
    rect = np.zeros((m, 4), dtype=np.int64)
    rect[part, 0] = np.clip(c0[part] - 1, 0, w - 1)
    rect[part, 1] = np.clip(r0[part] - 1, 0, h - 1)
    rect[part, 2] = np.clip(c1[part] + 1, 0, w - 1)
    rect[part, 3] = np.clip(r1[part] + 1, 0, h - 1)
    return whole, part, rect


@dataclass
class _Level:
    """Cubes of one level: edge ``voxel``; ``cache`` holds the top level's rectangles."""

    voxel: float
    cache: dict | None = None


def _rects(cams: Sequence, lo: np.ndarray, level: _Level, ijk: np.ndarray, pooling: Sequence[int]) -> list:
    """Per camera ``(whole, part, pooled rect)`` of the cubes ``ijk`` of a level (the top level's cached)."""
    if level.cache is not None and "rects" in level.cache:
        return level.cache["rects"]
    out = []
    for cam, s in zip(cams, pooling):
        whole, part, rect = _cube_rects(cam, lo, level.voxel, ijk)
        out.append((whole, part, rect // s))
    if level.cache is not None:
        level.cache["rects"] = out
    return out


# ----------------------------------------------------------------------------- one frame set


def _pool(mask: np.ndarray, s: int) -> np.ndarray:
    """A silhouette max-pooled by ``s`` (a pooled pixel is foreground when any of its pixels is), uint8."""
    import cv2

    m = mask.view(np.uint8) if mask.dtype == bool else (mask != 0).view(np.uint8)
    if s == 1:
        return np.ascontiguousarray(m)
    h, w = m.shape
    hp, wp = -(-h // s), -(-w // s)
    if (hp * s, wp * s) != (h, w):
        padded = np.zeros((hp * s, wp * s), np.uint8)
        padded[:h, :w] = m
        m = padded
    return (cv2.resize(m, (wp, hp), interpolation=cv2.INTER_AREA) > 0).view(np.uint8)


def _carve(ijk: np.ndarray, rects: list, usable: list[int], integrals: dict, *, tolerance: int,
           min_views: int, view_slack: int | None = None) -> np.ndarray:
    """Cubes kept: found (a silhouette pixel in the visible part of the rectangle) by ``min_views``
    usable cameras and by the most cameras that find any of the cubes less ``view_slack`` (None:
    no such bound), and at most ``tolerance`` cameras that see them whole find no silhouette pixel
    in their rectangle."""
    found = np.zeros(len(ijk), np.int32)
    misses = np.zeros(len(ijk), np.int32)
    for c in usable:
        whole, part, rect = rects[c]
        idx = np.flatnonzero(part)
        if idx.size == 0:
            continue
        S = integrals[c]
        c0, r0, c1, r1 = rect[idx].T
        hit = (S[r1 + 1, c1 + 1] - S[r0, c1 + 1] - S[r1 + 1, c0] + S[r0, c0]) > 0
        found[idx[hit]] += 1
        misses[idx[~hit & whole[idx]]] += 1
    keep = (misses <= tolerance) & (found >= min_views)
    if keep.any() and view_slack is not None:
        keep &= found >= found[keep].max() - view_slack
    return keep


def _pieces(ijk: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected pieces (26-neighbourhood) of a set of cubes: a label 0..n-1 per cube, and n."""
    from scipy import ndimage

    lo = ijk.min(axis=0)
    shape = tuple(ijk.max(axis=0) - lo + 1)
    occ = np.zeros(shape, bool)
    rel = ijk - lo
    occ[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    return lab[rel[:, 0], rel[:, 1], rel[:, 2]] - 1, int(n)


def _cover(rect: np.ndarray, shape: tuple[int, int]) -> tuple[tuple[slice, slice], np.ndarray]:
    """The union of pixel rectangles (c0, r0, c1, r1 inclusive) within their bounding box: (slices, bool image)."""
    c_lo, r_lo = int(rect[:, 0].min()), int(rect[:, 1].min())
    c_hi, r_hi = int(rect[:, 2].max()), int(rect[:, 3].max())
    d = np.zeros((r_hi - r_lo + 2, c_hi - c_lo + 2), np.int32)
    c0, r0 = rect[:, 0] - c_lo, rect[:, 1] - r_lo
    c1, r1 = rect[:, 2] - c_lo + 1, rect[:, 3] - r_lo + 1
    np.add.at(d, (r0, c0), 1)
    np.add.at(d, (r0, c1), -1)
    np.add.at(d, (r1, c0), -1)
    np.add.at(d, (r1, c1), 1)
    cov = np.cumsum(np.cumsum(d, axis=0), axis=1)[:-1, :-1] > 0
    return (slice(r_lo, r_hi + 1), slice(c_lo, c_hi + 1)), cov


def _explained(labels: np.ndarray, n: int, rects: list, usable: list[int], pooled: dict, *, min_support: int,
               support_share: float) -> np.ndarray:
    """Per piece, whether its projection alone explains silhouette pixels in ``min_support`` cameras."""
    support = np.zeros(n, np.int32)
    for c in usable:
        whole, part, rect = rects[c]
        fg = pooled[c]
        covers = []
        count = np.zeros(fg.shape, np.int16)
        for k in range(n):
            sel = (labels == k) & part
            if not sel.any():
                covers.append(None)
                continue
            sl, cov = _cover(rect[sel], fg.shape)
            count[sl] += cov
            covers.append((sl, cov))
        for k, item in enumerate(covers):
            if item is None:
                continue
            sl, cov = item
            under = cov & (fg[sl] != 0)
            total = int(np.count_nonzero(under))
            alone = int(np.count_nonzero(under & (count[sl] == 1)))
            if alone >= 2 and alone >= support_share * total:
                support[k] += 1
    return support >= min_support


def _children(ijk: np.ndarray) -> np.ndarray:
    """The eight half-size cubes of every cube (indices on the next level)."""
    return (2 * ijk[:, None, :] + _OFFSETS[None]).reshape(-1, 3)


def _above(lo: np.ndarray, voxel: float, ijk: np.ndarray, plane: np.ndarray | None) -> np.ndarray:
    """Cubes with a corner on or above the support plane (all when there is none)."""
    if plane is None:
        return np.ones(len(ijk), bool)
    corners = lo + (ijk[None, :, :] + _OFFSETS[:, None, :]) * voxel
    return np.logical_or.reduce((corners @ plane[:3] + plane[3]) >= 0, axis=0)


def _frame_subject(masks: Sequence, cams: Sequence, lo: np.ndarray, levels: list[_Level], top: np.ndarray,
                   opts: dict, stats: dict) -> np.ndarray | None:
    """The cubes (finest level indices) of the subject in one frame set, or None."""
    import cv2

    pooling = opts["pooling"]
    usable = [c for c, m in enumerate(masks) if m is not None and m.any() and not m.all()]
    if len(usable) < 2:
        return None
    pooled = {c: _pool(masks[c], pooling[c]) for c in usable}
    integrals = {c: cv2.integral(pooled[c]) for c in usable}
    min_views = min(opts["min_views"], len(usable))
    support = min(opts["min_support"], len(usable))
    ijk = top
    for li, level in enumerate(levels):
        if li > 0:
            ijk = _children(ijk)
        rects = _rects(cams, lo, level, ijk, pooling)
        keep = _carve(ijk, rects, usable, integrals, tolerance=opts["tolerance"], min_views=min_views,
                      view_slack=opts["view_slack"])
        keep &= _above(lo, level.voxel, ijk, opts["plane"])
        if not keep.any():
            return None
        ijk = ijk[keep]
        rects = [(w[keep], p[keep], r[keep]) for w, p, r in rects]
        labels, n = _pieces(ijk)
        ok = _explained(labels, n, rects, usable, pooled, min_support=support, support_share=opts["support_share"])
        stats["phantoms_rejected"] += int(n - ok.sum())
        if li == len(levels) - 1:
            stats["pieces_kept"] += int(ok.sum())
            stats["pieces_rejected"] += int(n - ok.sum())
        if not ok.any():
            return None
        ijk = ijk[ok[labels]]
    return ijk


# ----------------------------------------------------------------------------- entry point


def _check_masks_source(masks: Any) -> int:
    if not (hasattr(masks, "__len__") and hasattr(masks, "__getitem__")):
        raise ValueError(f"masks must be a sequence of frame sets (len and indexing), got {type(masks).__name__}")
    n = len(masks)
    if n < 1:
        raise ValueError("masks: no frame sets")
    return n


def _set_masks(masks: Any, k: int, cams: Sequence) -> list:
    """The masks of frame set ``k``, checked: one (H, W) array (or None) per camera."""
    ms = masks[k]
    if len(ms) != len(cams):
        raise ValueError(f"masks[{k}]: expected one mask per camera ({len(cams)}), got {len(ms)}")
    out = []
    for cam, m in zip(cams, ms):
        if m is None:
            out.append(None)
            continue
        m = np.asarray(m)
        w, h = cam.size
        if m.shape != (h, w):
            raise ValueError(f"masks[{k}]: camera {cam.name!r} is {w}x{h}, its mask has shape {m.shape}")
        out.append(m if m.dtype == bool else m != 0)
    return out


def _most_views(cams: Sequence, bounds: np.ndarray) -> int:
    """The most cameras that see any point of a 24^3 lattice over the volume (centre projections)."""
    axes = [np.linspace(bounds[0, a], bounds[1, a], 24) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    seen = sum((pixel_index(cam, pts)[0] >= 0).astype(np.int32) for cam in cams)
    return int(np.max(seen))


def _levels(bounds: np.ndarray, finest: float) -> list[float]:
    """Cube edges coarse to fine: the volume's longest side over :data:`TOP_VOXELS`, halved down to ``finest``."""
    v = float((bounds[1] - bounds[0]).max()) / TOP_VOXELS
    out = [v]
    while out[-1] / 2 >= finest * 0.99 and len(out) < MAX_LEVELS:
        out.append(out[-1] / 2)
    return out


def _pooling(cams: Sequence, bounds: np.ndarray, voxel: float) -> tuple[int, ...]:
    """Per camera, the factor the silhouettes are pooled by: the finest cube stays
    :data:`POOLED_PIXELS` pooled pixels across wherever in the volume the camera sees it."""
    lo, hi = bounds
    pts = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
                   + [list((lo + hi) / 2)])
    fp = pixel_footprint(Calibration(tuple(cams)), pts)
    out = []
    for row in fp:
        seen = row[np.isfinite(row)]
        px = voxel / float(seen.max()) if seen.size else 1.0
        out.append(max(1, int(px / POOLED_PIXELS)))
    return tuple(out)


def find_subject_box(
    masks: Any,
    calibration: Calibration,
    volume_bounds: Any,
    *,
    tolerance: int = 0,
    finest_voxel: float | None = None,
    min_share: float = 0.5,
    view_slack: int = 1,
    min_support: int = 2,
    support_share: float = 0.2,
    support_plane: Any = None,
    progress: Callable[[int, int], None] | None = None,
) -> SubjectBox:
    """The box that holds the subject in every frame set of a take, from its silhouettes.

    Parameters
    ----------
    masks : sequence
        ``masks[k]`` is frame set ``k``: one (H, W) bool silhouette per camera of
        ``calibration`` (``None`` for a camera without a valid mask there). A (S, C, H, W)
        array works; so does a lazy sequence that reads each set from a take.
    calibration : Calibration
    volume_bounds : (2, 3) float array-like
        ``[lo, hi]`` of the search volume (the rig's capture volume, or the cameras' shared view).
    tolerance : int, optional
        Cameras that may find no silhouette on a cube before it is carved.
    finest_voxel : float, optional
        The finest cube edge wanted (world units); default :data:`FOOTPRINT_PIXELS` times the
        median pixel footprint at the volume's centre. The levels halve the top level's cube
        down to it.
    min_share : float, optional
        Share of the most cameras that see any point of the volume that must find a cube (see
        the module docstring), in (0, 1] (at least two cameras).
    view_slack : int, optional
        A cube must also be found by the most cameras that find any cube of its frame set
        (at its level) less this many.
    min_support : int, optional
        Cameras in which a piece must alone explain silhouette pixels to be the subject's.
    support_share : float, optional
        Share of the silhouette pixels a piece covers in a camera that it must explain alone
        there for that camera to count, in (0, 1].
    support_plane : (4,) float array-like, optional
        ``(a, b, c, d)``: cubes wholly below ``a x + b y + c z + d = 0`` are not the subject.
    progress : callable, optional
        ``progress(done, total)`` every few frame sets.

    Returns
    -------
    SubjectBox

    Raises
    ------
    ValueError
        Bad arguments, or masks of the wrong number or size.
    pipeline.hull.EmptyHullError
        No subject in any frame set.
    """
    from pipeline.hull import EmptyHullError

    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    bounds = check_bounds(volume_bounds, "volume_bounds")
    n_sets = _check_masks_source(masks)
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, np.integer)) or tolerance < 0:
        raise ValueError(f"tolerance must be a non-negative integer, got {tolerance!r}")
    if not (isinstance(min_share, (int, float)) and 0 < min_share <= 1):
        raise ValueError(f"min_share must be in (0, 1], got {min_share!r}")
    if isinstance(view_slack, bool) or not isinstance(view_slack, (int, np.integer)) or view_slack < 0:
        raise ValueError(f"view_slack must be a non-negative integer, got {view_slack!r}")
    if isinstance(min_support, bool) or not isinstance(min_support, (int, np.integer)) or min_support < 1:
        raise ValueError(f"min_support must be a positive integer, got {min_support!r}")
    if not (isinstance(support_share, (int, float)) and 0 < support_share <= 1):
        raise ValueError(f"support_share must be in (0, 1], got {support_share!r}")
    plane = None if support_plane is None else check_plane(support_plane)
    cams = list(calibration)
    if finest_voxel is None:
        fp = pixel_footprint(calibration, bounds.mean(axis=0))[:, 0]
        fp = fp[np.isfinite(fp)]
        if fp.size == 0:
            raise ValueError("no camera sees the centre of volume_bounds; check the calibration or the volume")
        finest_voxel = FOOTPRINT_PIXELS * float(np.median(fp))
    elif not (isinstance(finest_voxel, (int, float)) and math.isfinite(finest_voxel) and finest_voxel > 0):
        raise ValueError(f"finest_voxel must be a positive number, got {finest_voxel!r}")
    voxels = _levels(bounds, float(finest_voxel))
    levels = [_Level(v, cache={} if i == 0 else None) for i, v in enumerate(voxels)]
    pooling = _pooling(cams, bounds, voxels[-1])
    n_top = np.maximum(1, np.ceil((bounds[1] - bounds[0]) / voxels[0] - 1e-9)).astype(np.int64)
    top = np.stack(np.meshgrid(*[np.arange(n) for n in n_top], indexing="ij"), axis=-1).reshape(-1, 3)
    min_views = max(2, math.ceil(min_share * _most_views(cams, bounds)))
    opts = {"pooling": pooling, "tolerance": int(tolerance), "min_views": min_views, "view_slack": int(view_slack),
            "min_support": int(min_support),
            "support_share": float(support_share), "plane": plane}
    stats = {"frame_sets": n_sets, "with_subject": 0, "pieces_kept": 0, "pieces_rejected": 0, "phantoms_rejected": 0}
    lo, fine = bounds[0], voxels[-1]
    frame_boxes = np.full((n_sets, 2, 3), np.nan)
    centres = np.full((n_sets, 3), np.nan)
    for k in range(n_sets):
        ijk = _frame_subject(_set_masks(masks, k, cams), cams, lo, levels, top, opts, stats)
        if ijk is not None:
            stats["with_subject"] += 1
            frame_boxes[k, 0] = lo + ijk.min(axis=0) * fine
            frame_boxes[k, 1] = lo + (ijk.max(axis=0) + 1) * fine
            centres[k] = lo + (ijk.mean(axis=0) + 0.5) * fine
        if progress is not None and (k % 8 == 7 or k == n_sets - 1):
            progress(k + 1, n_sets)
    found = np.isfinite(frame_boxes[:, 0, 0])
    if not found.any():
        raise EmptyHullError(
            f"no subject found in any of the {n_sets} frame sets: no piece of the silhouettes' hull is seen by "
            f"{min_views} cameras and explained by {min_support}"
        )
    box = np.stack([np.maximum(frame_boxes[found, 0].min(axis=0) - fine, bounds[0]),
                    np.minimum(frame_boxes[found, 1].max(axis=0) + fine, bounds[1])])
    log.info("subject box %s .. %s from %d of %d frame sets (levels %s)", box[0].round(1), box[1].round(1),
             stats["with_subject"], n_sets, [round(v, 1) for v in voxels])
    return SubjectBox(bounds=box, frame_boxes=frame_boxes, centres=centres, voxels=tuple(voxels), margin=fine,
                      min_views=min_views, pooling=pooling, stats=stats, view_slack=int(view_slack))
