"""Silhouettes refined by a per-camera graph cut seeded by a first visual hull.

Where the backdrop does not fill the view (a green floor before dark walls, a lab with no
backdrop), a keyer leaves walls, lights and people outside the volume in the masks. The
visual hull of those masks still contains the subject (every mask does), and carving
removes most of what only one camera mistakes for the subject; projected back into each
camera it bounds where the subject can be. Inside that bound, colour decides:

* **sure background**: every pixel outside the hull's projection (grown by the voxel's
  footprint and a margin), and what the caller knows is background (outside the capture
  volume's image);
* **sure foreground**: the hull's projection shrunk by twice the voxel footprint, where
  the keyer also says subject;
* **probable** foreground or background: the rest of the projection, as the keyer says;

and a graph cut with colour mixtures (GrabCut, Rother, Kolmogorov & Blake 2004;
``cv2.grabCut`` with a mask) labels the probable pixels. The cut runs on the region of
interest around the projection, downscaled to at most :data:`MAX_CUT_PIXELS` (the colour
models need no more), and its labels are brought back to full size.

:func:`refine_silhouettes` is one frame set (arrays in and out); :func:`refine_take` runs
it over a take and stores the refined masks in place of the keyed ones (the ``refine`` step
of ``stage process``, ``stage key --key-layer graphcut``).

:func:`subject_hull` is the surface step's hull of one frame set, from its silhouettes and
the job's carving, without what the cameras do not agree is the subject:

* **phantom pieces**: the hull's largest piece is the subject's; another piece is kept only
  when as many cameras see it as see the largest, less ``view_slack`` (one). Where few
  cameras see, few silhouette cones cross, and their crossings are phantoms (two opposite
  cameras' cones cross along the whole line between them); a second real object seen by the
  cameras that see the subject stays. The rule of :mod:`pipeline.subject_box`, on the hull.
* **silhouette parts the subject does not explain**: a connected part of a camera's silhouette
  that the largest piece (the subject, as the surface step keeps it) does not project onto (a
  shadow, a reflection, a person outside the volume, a blob of noise) is no silhouette of the
  subject; it is dropped, and the hull carved again when any was. The share of each camera's
  silhouette dropped is returned (a keyer that keeps a wall shows there). A silhouette of one
  part stays whole (whether the subject explains it is the consistency's to judge).
* **one camera's miss** (``bridge_gaps``, for silhouettes whose keyer cannot tell the subject
  from the room where their colours match: a plate without a backdrop): a voxel carved by
  exactly one camera is kept when that camera's pixel lies in a gap of its own silhouette (inside
  the silhouette closed by a disc of ``bridge_gaps`` times its larger bounding-box side) and
  every other camera sees it on its silhouette; that camera's silhouette is then keyed again
  there (the kept voxels' image inside the gap is added to it). Black shorts before a black
  floor, missed in one view, otherwise cut the legs off the body for every camera, and a hole in
  one view's torso tunnels through the hull. The price: a real gap narrower than the closing that
  only one camera sees through (two limbs close together) is bridged too, so ``stage process``
  uses the keyer's own closing radius, the gaps it could not decide by colour. A piece the hull
  still holds apart from the largest (legs cut off at the shorts) is then joined to it across
  gaps twice as wide, by the voxels of the same kind on the shortest paths between the two only
  (within two steps of the shortest, :func:`_geodesic`): no webbing elsewhere. This runs before
  the silhouette parts the largest piece does not explain are dropped, so a joined piece's
  parts stay.
* **specks**: a piece other than the largest is kept only when, in at least two cameras, its
  image alone (outside the largest piece's) covers silhouette pixels, at least a fifth of the
  silhouette it covers there (the rule of :mod:`pipeline.subject_box`): a few voxels beside the
  body that every camera sees within the body's outline explain nothing; a second real object
  (or a limb the hull cut off) explains its own pixels.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Collection, Sequence

import cv2
import numpy as np

from calib.calibration import Calibration
from pipeline.hull import EmptyHullError, HullCarver
from pipeline.volume import Grid, grid_from_volume, volume_from_cameras

__all__ = ["refine_silhouette", "refine_silhouettes", "hull_projection", "refine_take", "subject_hull", "SubjectHull",
           "MAX_CUT_PIXELS", "DROPPED_WARN"]

log = logging.getLogger(__name__)

#: Pixels of the region a graph cut runs on at most (larger regions are downscaled).
MAX_CUT_PIXELS = 160_000
#: Largest voxel disc (pixels) splatted by dilation; larger ones are drawn one by one.
_SPLAT_DILATE_MAX = 12
#: Voxels along the longest side of the first hull's grid.
FIRST_HULL_RESOLUTION = 72
#: A camera whose keyed silhouettes hold more than this share of pixels the subject does not
#: explain (median over the take, :func:`subject_hull`) is named in a warning.
DROPPED_WARN = 0.2
#: A piece other than the largest explains a camera's silhouette when its image alone covers at
#: least this share of the silhouette pixels it covers there (:func:`subject_hull`, specks).
_ALONE_SHARE = 0.2


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def refine_silhouette(
    image: np.ndarray,
    mask: np.ndarray,
    hull: np.ndarray,
    *,
    footprint: float = 2.0,
    margin: int = 4,
    sure_background: np.ndarray | None = None,
    iterations: int = 3,
) -> np.ndarray:
    """One camera's silhouette cut by colour inside a first hull's projection.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        BGR frame.
    mask : (H, W) bool ndarray
        The keyer's silhouette.
    hull : (H, W) bool ndarray
        The first hull's projection into this camera (:func:`hull_projection`).
    footprint : float
        The hull's voxel edge in pixels in this camera (how far the projection may be off).
    margin : int
        Pixels the projection grows by before everything outside it is sure background.
    sure_background : (H, W) bool ndarray or None
        Pixels known to be background (e.g. outside the capture volume's image).
    iterations : int
        GrabCut iterations.

    Returns
    -------
    (H, W) bool ndarray
        The refined silhouette (inside the grown projection).

    Raises
    ------
    ValueError
        Shapes or dtypes that do not match, bad options.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be a (H, W, 3) uint8 array, got {getattr(image, 'dtype', type(image))} "
                         f"{getattr(image, 'shape', '')}")
    shape = image.shape[:2]
    for name, a in (("mask", mask), ("hull", hull), ("sure_background", sure_background)):
        if a is not None and (not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != bool):
            raise ValueError(f"{name} must be a bool array of shape {shape}, got {getattr(a, 'dtype', type(a))} "
                             f"{getattr(a, 'shape', '')}")
    if not (np.isfinite(footprint) and footprint > 0):
        raise ValueError(f"footprint must be a positive number of pixels, got {footprint!r}")
    if not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be a non-negative integer, got {margin!r}")
    if not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    grow = int(np.ceil(footprint)) + margin
    region = cv2.dilate(hull.view(np.uint8), _disk(grow)).view(bool)
    core = cv2.erode((hull & mask).view(np.uint8), _disk(int(np.ceil(2 * footprint)))).view(bool)
    if not core.any() or not region.any():
        return mask & region
    gc = np.full(shape, cv2.GC_BGD, np.uint8)
    gc[region & ~mask] = cv2.GC_PR_BGD
    gc[region & mask] = cv2.GC_PR_FGD
    gc[core] = cv2.GC_FGD
    if sure_background is not None:
        gc[sure_background & ~core] = cv2.GC_BGD
    # the region of interest: the grown projection and a band of sure background around it
    x, y, w, h = cv2.boundingRect(region.view(np.uint8))
    pad = max(8, int(0.15 * max(w, h)))
    x0, y0 = max(0, x - pad), max(0, y - pad)
    x1, y1 = min(shape[1], x + w + pad), min(shape[0], y + h + pad)
    roi_img, roi_gc = image[y0:y1, x0:x1], gc[y0:y1, x0:x1]
    if not (roi_gc == cv2.GC_BGD).any():
        return mask & region
    scale = min(1.0, float(np.sqrt(MAX_CUT_PIXELS / roi_gc.size)))
    small_img, small_gc = roi_img, roi_gc.copy()
    if scale < 1.0:
        size = (max(1, int(round(roi_img.shape[1] * scale))), max(1, int(round(roi_img.shape[0] * scale))))
        small_img = cv2.resize(roi_img, size, interpolation=cv2.INTER_AREA)
        small_gc = cv2.resize(roi_gc, size, interpolation=cv2.INTER_NEAREST)
    if not ((small_gc == cv2.GC_FGD) | (small_gc == cv2.GC_PR_FGD)).any() or not (small_gc == cv2.GC_BGD).any():
        return mask & region
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(small_img, small_gc, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    fg_small = ((small_gc == cv2.GC_FGD) | (small_gc == cv2.GC_PR_FGD)).astype(np.uint8) * 255
    if scale < 1.0:
        fg_small = cv2.resize(fg_small, (roi_img.shape[1], roi_img.shape[0]), interpolation=cv2.INTER_LINEAR)
    out = np.zeros(shape, bool)
    out[y0:y1, x0:x1] = fg_small >= 128
    out |= core
    return out & region


def hull_projection(occupancy: np.ndarray, grid: Grid, calibration: Calibration) -> tuple[list[np.ndarray], list[float]]:
    """Every camera's image of an occupancy grid, and the voxel's footprint in pixels there.

    Every voxel is drawn as a disc of its own footprint (half the diagonal of its projection;
    a superset of the exact projection, which the refinement needs).

    Returns
    -------
    images : list of (H, W) bool ndarray
    footprints : list of float
    """
    idx = np.argwhere(occupancy)
    centres = grid.lo + (idx + 0.5) * grid.voxel
    out, feet = [], []
    for cam in calibration:
        w, h = cam.size
        img = np.zeros((h, w), np.uint8)
        if len(centres) == 0:
            out.append(img.view(bool))
            feet.append(1.0)
            continue
        uv, z = cam.project(centres, return_depth=True)
        front = z > 0
        foot = cam.K[0, 0] * grid.voxel / z[front]
        radius = np.ceil(np.maximum(1.0, 0.5 * np.sqrt(3) * foot)).astype(np.int64)
        p = np.round(uv[front]).astype(np.int64)
        ok = (p[:, 0] >= -radius) & (p[:, 0] < w + radius) & (p[:, 1] >= -radius) & (p[:, 1] < h + radius)
        p, radius = p[ok], radius[ok]
        # every voxel a disc of its own footprint: small radii by dilating their points together,
        # the few large ones (voxels close to the camera) drawn one by one
        for rr in np.unique(radius[radius <= _SPLAT_DILATE_MAX]):
            sel = (radius == rr) & (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
            pts = np.zeros((h, w), np.uint8)
            pts[p[sel, 1], p[sel, 0]] = 1
            img |= cv2.dilate(pts, _disk(int(rr)))
        for (x, y), rr in zip(p[radius > _SPLAT_DILATE_MAX], radius[radius > _SPLAT_DILATE_MAX]):
            cv2.circle(img, (int(np.clip(x, -(1 << 20), 1 << 20)), int(np.clip(y, -(1 << 20), 1 << 20))),
                       int(min(rr, 1 << 20)), 1, -1)
        out.append(img.view(bool))
        feet.append(float(np.median(foot)) if front.any() else 1.0)
    return out, feet


def refine_silhouettes(
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    carver: HullCarver,
    *,
    sure_background: Sequence[np.ndarray | None] | None = None,
    margin: int = 4,
    hull_margin: int = 2,
) -> list[np.ndarray | None]:
    """One frame set's silhouettes refined (see module docstring); a camera without a mask
    (None) stays None, and a frame set whose first hull is empty keeps its masks."""
    use = [m if m is not None else np.zeros(carver.calibration[i].size[::-1], bool) for i, m in enumerate(masks)]
    try:
        hull = carver.carve(use, margin=hull_margin, min_views=2)
    except EmptyHullError:
        return list(masks)
    proj, feet = hull_projection(hull.occupancy, carver.grid, carver.calibration)
    out: list[np.ndarray | None] = []
    for i, m in enumerate(masks):
        if m is None:
            out.append(None)
            continue
        sb = sure_background[i] if sure_background is not None else None
        out.append(refine_silhouette(images[i], m, proj[i], footprint=feet[i], margin=margin, sure_background=sb))
    return out


def _first_hull_grid(calibration: Calibration, volume: Any) -> Grid:
    bounds = np.asarray(volume, float).reshape(2, 3) if volume is not None else volume_from_cameras(calibration)
    return grid_from_volume(bounds, FIRST_HULL_RESOLUTION)


def refine_take(
    take,
    *,
    volume: Any = None,
    progress: Callable[[int], Any] | None = None,
    margin: int = 4,
    skip_sets: Collection[int] = (),
) -> dict:
    """Refine every stored mask of a take with :func:`refine_silhouettes` and store them back.

    Parameters
    ----------
    take : path
        A take holding a calibration and every camera's masks.
    volume : (6,) floats, optional
        The first hull's box (default: the rig's capture volume, else the cameras' shared view).
    progress : callable, optional
        Called with the number of masks refined.
    margin : int
        Pixels the hull's projection grows by before the outside is sure background.
    skip_sets : collection of int
        Frame sets left as they are, their frames never read (damaged frames,
        :func:`stage.store.verify.verify_take`).

    Returns
    -------
    dict
        ``frames`` (masks refined), ``seconds``, ``grid`` (the first hull's).

    Raises
    ------
    ValueError
        A take without a calibration or without masks for every camera.
    """
    from stage.store import TakeReader, write_arrays

    t0 = time.perf_counter()
    with TakeReader(take) as r:
        if not r.has_calibration:
            raise ValueError(f"{take}: the take has no calibration")
        cams = list(r.cameras)
        missing = [c for c in cams if c not in r.masks_present()]
        if missing:
            raise ValueError(f"{take}: cameras {missing} have no masks; key the take first")
        calib = Calibration(tuple(r.calibration[c] for c in cams), units=r.calibration.units)
        if volume is None and (r.rig or {}).get("volume"):
            v = r.rig["volume"]
            c, s = np.asarray(v["center"], float), np.asarray(v["size"], float)
            volume = np.r_[c - s / 2, c + s / 2]
        grid = _first_hull_grid(calib, volume)
        carver = HullCarver(calib, grid)
        masks = {c: r.masks(c) for c in cams}
        params = {c: r.mask_params(c) or {} for c in cams}
        table = r.set_table()
        done = 0
        skip_sets = set(int(k) for k in skip_sets)
        for k in range(table.shape[0]):
            if k in skip_sets:
                continue
            rows = table[k]
            ms = [masks[c][rows[i]] if 0 <= rows[i] < len(masks[c]) else None for i, c in enumerate(cams)]
            ims = [r.frame(c, int(rows[i])) if ms[i] is not None else None for i, c in enumerate(cams)]
            new = refine_silhouettes(ims, ms, carver, margin=margin)
            for i, c in enumerate(cams):
                if new[i] is not None:
                    masks[c][rows[i]] = new[i]
                    done += 1
                    if progress is not None:
                        progress(1)
    arrays = []
    for c in cams:
        meta = dict(params[c])
        meta["refined"] = {"method": "graphcut", "first_hull_voxel": grid.voxel, "margin": margin}
        arrays.append((f"cameras/{c}", "masks", masks[c], meta))
    write_arrays(take, arrays)
    return {"frames": done, "seconds": time.perf_counter() - t0, "grid": grid.to_dict()}


@dataclass(frozen=True)
class SubjectHull:
    """One frame set's hull without phantom pieces, and the silhouettes it was carved from
    (:func:`subject_hull`).

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool ndarray
    masks : list of (H, W) bool ndarray or None
        The silhouettes without the parts no kept piece explains.
    dropped : (C,) float ndarray
        Per camera, the share of its silhouette's pixels dropped (NaN without a mask).
    pieces_dropped : int
        Phantom pieces and specks left out (of the last carving).
    views : int
        Cameras that see the largest piece.
    bridged : int
        Voxels kept although one camera's silhouette missed them (``bridge_gaps``).
    """

    occupancy: np.ndarray
    masks: list
    dropped: np.ndarray
    pieces_dropped: int
    views: int
    bridged: int = 0


#: Voxels of a piece whose views are counted at most (evenly spaced): the most cameras seeing a
#: piece of thousands of voxels does not need every one of them.
_VIEW_SAMPLE = 4096


def _views(idx: np.ndarray, grid: Grid, calibration: Calibration) -> np.ndarray:
    """Per voxel index (K, 3), the cameras whose image holds its centre."""
    from pipeline.volume import pixel_index

    centres = grid.lo + (idx + 0.5) * grid.voxel
    return sum((pixel_index(cam, centres)[0] >= 0).astype(np.int32) for cam in calibration)


def _kept_pieces(occ: np.ndarray, grid: Grid, calibration: Calibration,
                 view_slack: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The pieces (26-connected) seen by as many cameras as the largest less ``view_slack``: the
    occupancy, the largest piece, the pieces dropped, and the cameras that see the largest piece."""
    from scipy import ndimage

    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    idx = np.argwhere(occ)
    if n <= 1:
        step = max(1, len(idx) // _VIEW_SAMPLE)
        return occ, occ, 0, int(_views(idx[::step], grid, calibration).max()) if n else 0
    labels = lab[occ]  # argwhere order
    size = np.bincount(labels, minlength=n + 1)
    size[0] = 0
    largest = int(np.argmax(size))
    # every voxel of the other pieces, an even sample of the largest
    sample = np.flatnonzero(labels != largest)
    big = np.flatnonzero(labels == largest)
    sample = np.concatenate([sample, big[:: max(1, len(big) // _VIEW_SAMPLE)]])
    best = np.zeros(n + 1, np.int32)
    np.maximum.at(best, labels[sample], _views(idx[sample], grid, calibration))
    v = int(best[largest])
    keep = best >= v - view_slack
    keep[0] = False
    return keep[lab], lab == largest, int(n - keep[1:].sum()), v


def _explained_parts(mask: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    """The connected parts (8-connected) of ``mask`` that ``shadow`` (the kept pieces' projection) touches."""
    n, lab = cv2.connectedComponents(mask.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    if n <= 2:
        return mask if n < 2 or (shadow & mask).any() else np.zeros_like(mask)
    hit = np.zeros(n, bool)
    hit[np.unique(lab[shadow & mask])] = True
    hit[0] = False
    return hit[lab]


def _closed(mask: np.ndarray, relative: float) -> np.ndarray:
    """``mask`` closed by a disc of ``relative`` times its larger bounding-box side (the image's
    border does not close it)."""
    _, _, w, h = cv2.boundingRect(mask.view(np.uint8))
    r = max(1, int(round(relative * max(w, h))))
    pad = r + 1
    m = cv2.copyMakeBorder(mask.view(np.uint8), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    return cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(r))[pad:-pad, pad:-pad].view(bool)


def _gap_voxels(occ: np.ndarray, masks: list, carver: HullCarver, kw: dict,
                relative: float) -> tuple[np.ndarray, list]:
    """The voxels outside ``occ`` that one camera alone carves, with that camera's pixel inside a gap
    of its silhouette ``relative`` wide, and the silhouettes closed by that gap (see module docstring)."""
    closed = [None if m is None else _closed(m, relative) for m in masks]
    one_miss = carver.carve(masks, **{**kw, "tolerance": kw["tolerance"] + 1}).occupancy
    return one_miss & carver.carve(closed, **kw).occupancy & ~occ, closed


def _keyed_again(masks: list, added: np.ndarray, carver: HullCarver, closed: list) -> list:
    """The silhouettes with the image of the ``added`` voxels inside their ``closed`` gaps."""
    proj, _ = hull_projection(added, carver.grid, carver.calibration)
    return [None if m is None else m | (p & c) for m, p, c in zip(masks, proj, closed)]


def _bridged(occ: np.ndarray, masks: list, carver: HullCarver, kw: dict,
             relative: float) -> tuple[np.ndarray, list, np.ndarray]:
    """The hull with the voxels one camera alone carves inside a gap of its silhouette, the
    silhouettes keyed again there, and the voxels added (see module docstring)."""
    added, closed = _gap_voxels(occ, masks, carver, kw, relative)
    if not added.any():
        return occ, masks, added
    return occ | added, _keyed_again(masks, added, carver, closed), added


def _geodesic(seed: np.ndarray, allowed: np.ndarray, steps: int) -> np.ndarray:
    """Steps (26-neighbour moves through ``allowed``) from ``seed`` to every voxel of ``allowed``
    within ``steps`` (inf beyond; 0 on the seed): a breadth-first search on the graph of the
    allowed voxels (``scipy.sparse.csgraph``), which are few beside the box."""
    from scipy import ndimage
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    dist = np.full(seed.shape, np.inf)
    dist[seed] = 0
    flat = np.flatnonzero(allowed & ~seed)
    if flat.size == 0:
        return dist
    n = flat.size
    lut = np.full(seed.size, -1, np.int64)
    lut[flat] = np.arange(n)
    at = np.stack(np.unravel_index(flat, seed.shape), axis=1)
    rows, cols = [], []
    for off in np.argwhere(np.ones((3, 3, 3), bool)) - 1:
        if not off.any():
            continue
        nb = at + off
        ok = np.all((nb >= 0) & (nb < seed.shape), axis=1)
        k = lut[np.ravel_multi_index(tuple(nb[ok].T), seed.shape)]
        rows.append(np.flatnonzero(ok)[k >= 0])
        cols.append(k[k >= 0])
    first = np.flatnonzero(ndimage.binary_dilation(seed, np.ones((3, 3, 3), bool)).ravel()[flat])
    rows += [np.full(first.size, n)]
    cols += [first]
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = csr_matrix((np.ones(r.size), (r, c)), shape=(n + 1, n + 1))
    d = shortest_path(graph, unweighted=True, indices=n)[:n]
    d[d > steps] = np.inf
    dist.ravel()[flat] = d
    return dist


def _joined(occ: np.ndarray, masks: list, carver: HullCarver, kw: dict,
            relative: float) -> tuple[np.ndarray, list, int]:
    """Every other piece joined to the largest by the voxels one camera alone carves inside gaps of
    its silhouette ``relative`` wide, only those on the shortest paths through them between the two
    (within 2 steps of the shortest); the silhouettes keyed again there; the voxels added."""
    from scipy import ndimage

    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return occ, masks, 0
    extra, closed = _gap_voxels(occ, masks, carver, kw, relative)
    if not extra.any():
        return occ, masks, 0
    idx = np.argwhere(occ)
    lo, hi = np.maximum(idx.min(0) - 2, 0), np.minimum(idx.max(0) + 3, occ.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    sub, ex = lab[box], extra[box]
    size = np.bincount(sub.ravel())
    size[0] = 0
    largest = int(np.argmax(size))
    reach, _ = ndimage.label((sub > 0) | ex, structure=np.ones((3, 3, 3), bool))
    home = reach[sub == largest][0]
    joining = [j for j in range(1, n + 1) if j != largest and reach[sub == j][0] == home]
    if not joining:
        return occ, masks, 0
    # a path through the bridging voxels at most twice the straight gap (and 4 steps) long
    to_main = ndimage.distance_transform_edt(sub != largest)
    steps = {j: int(2 * to_main[sub == j].min()) + 4 for j in joining}
    from_main = _geodesic(sub == largest, ex, max(steps.values()))
    add = np.zeros_like(ex)
    for j in joining:
        total = from_main + _geodesic(sub == j, ex, steps[j])
        if np.isfinite(total).any():
            add |= ex & (total <= total[ex].min() + 2)
    if not add.any():
        return occ, masks, 0
    added = np.zeros_like(occ)
    added[box] = add
    return occ | added, _keyed_again(masks, added, carver, closed), int(np.count_nonzero(add))


def _without_specks(occ: np.ndarray, masks: list, grid: Grid, calibration: Calibration) -> tuple[np.ndarray, int]:
    """The occupancy without the pieces (other than the largest) whose image alone explains
    silhouette pixels in fewer than two cameras, and how many were left out."""
    from scipy import ndimage

    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return occ, 0
    size = np.bincount(lab.ravel())
    size[0] = 0
    largest = int(np.argmax(size))
    main = lab == largest
    main_img, _ = hull_projection(main & ~ndimage.binary_erosion(main), grid, calibration)
    keep = main
    dropped = 0
    for j, box in enumerate(ndimage.find_objects(lab), start=1):
        if j == largest or box is None:
            continue
        piece = np.zeros_like(occ)
        piece[box] = lab[box] == j
        img, _ = hull_projection(piece, grid, calibration)
        support = 0
        for m, a, b in zip(masks, img, main_img):
            if m is None:
                continue
            covered = np.count_nonzero(a & m)
            alone = np.count_nonzero(a & m & ~b)
            support += alone >= 2 and alone >= _ALONE_SHARE * covered
        if support >= 2:
            keep = keep | piece
        else:
            dropped += 1
    return keep, dropped


def subject_hull(
    masks: Sequence[np.ndarray | None],
    carver: HullCarver,
    *,
    tolerance: int = 0,
    support_plane: Any = None,
    margin: int = 0,
    view_slack: int = 1,
    bridge_gaps: float = 0.0,
) -> SubjectHull:
    """One frame set's hull without phantom pieces, from silhouettes without the parts no kept
    piece explains (see module docstring).

    Parameters
    ----------
    masks : sequence of (H, W) bool ndarray or None
        One silhouette per camera of ``carver.calibration`` (None: no valid mask).
    carver : HullCarver
    tolerance, support_plane, margin
        The job's carving (:meth:`pipeline.hull.HullCarver.carve`).
    view_slack : int
        A piece is kept when seen by at least the cameras that see the largest less this.
    bridge_gaps : float
        0 (off), or the closing disc's radius as a share of each silhouette's larger
        bounding-box side within which one camera's miss is bridged (see module docstring;
        ``stage process`` gives plate-keyed silhouettes the keyer's own closing radius,
        :data:`stage.keying.params.PLATE_CLOSE_RELATIVE`). Needs at least ``tolerance + 3``
        cameras with a silhouette (two others to agree), else off.

    Returns
    -------
    SubjectHull

    Raises
    ------
    pipeline.hull.EmptyHullError
        Nothing left after carving.
    ValueError
        Bad masks or options.
    """
    if isinstance(view_slack, bool) or not isinstance(view_slack, (int, np.integer)) or view_slack < 0:
        raise ValueError(f"view_slack must be a non-negative integer, got {view_slack!r}")
    if isinstance(bridge_gaps, bool) or not isinstance(bridge_gaps, (int, float)) or not 0 <= bridge_gaps <= 0.5:
        raise ValueError(f"bridge_gaps must be a number in [0, 0.5], got {bridge_gaps!r}")
    kw = {"tolerance": tolerance, "support_plane": support_plane, "margin": margin}
    grid, cal = carver.grid, carver.calibration
    hull = carver.carve(masks, **kw).occupancy
    out: list[np.ndarray | None] = [None if m is None else np.asarray(m, bool) for m in masks]
    bridged = 0
    if bridge_gaps > 0 and sum(m is not None for m in out) >= int(tolerance) + 3:
        hull, out, bridged = _bridge(hull, out, carver, kw, float(bridge_gaps), view_slack)
    occ, main, dropped_pieces, views = _kept_pieces(hull, grid, cal, view_slack)
    out, share = _drop_unexplained(out, main, grid, cal)
    if np.nansum(share) > 0:
        occ, main, dropped_pieces, views = _kept_pieces(carver.carve(out, **kw).occupancy, grid, cal, view_slack)
    occ, specks = _without_specks(occ, out, grid, cal) if np.count_nonzero(occ) > np.count_nonzero(main) else (occ, 0)
    return SubjectHull(occupancy=occ, masks=out, dropped=share, pieces_dropped=dropped_pieces + specks, views=views,
                       bridged=bridged)


def _bridge(hull: np.ndarray, masks: list, carver: HullCarver, kw: dict, relative: float,
            view_slack: int) -> tuple[np.ndarray, list, int]:
    """One camera's miss bridged inside the keyer's gaps (:func:`_bridged`), then the kept pieces
    joined to the largest across gaps twice as wide (:func:`_joined`): the hull, the silhouettes
    keyed again, the voxels added."""
    hull, masks, added = _bridged(hull, masks, carver, kw, relative)
    bridged = int(np.count_nonzero(added))
    occ, main, _, _ = _kept_pieces(hull, carver.grid, carver.calibration, view_slack)
    if np.count_nonzero(occ) > np.count_nonzero(main):
        occ, masks, joined = _joined(occ, masks, carver, kw, 2 * relative)
        hull = hull | occ
        bridged += joined
    return hull, masks, bridged


def _drop_unexplained(masks: list, main: np.ndarray, grid: Grid, calibration: Calibration) -> tuple[list, np.ndarray]:
    """The silhouettes without the parts the largest piece does not project onto (a silhouette of
    one part stays whole), and the share of each dropped (NaN without a mask)."""
    out = list(masks)
    share = np.array([np.nan if m is None else 0.0 for m in out])
    parts = [0 if m is None else cv2.connectedComponents(m.view(np.uint8), connectivity=8)[0] - 1 for m in out]
    if max(parts, default=0) <= 1:
        return out, share
    # the largest piece's image: its boundary voxels (the inside projects within it) as discs
    from scipy import ndimage

    proj, _ = hull_projection(main & ~ndimage.binary_erosion(main), grid, calibration)
    for i, m in enumerate(out):
        if m is None or parts[i] <= 1:
            continue
        kept = _explained_parts(m, proj[i])
        total = int(np.count_nonzero(m))
        share[i] = 0.0 if total == 0 else 1.0 - np.count_nonzero(kept) / total
        out[i] = kept
    return out, share
