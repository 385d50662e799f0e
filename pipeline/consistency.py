"""Silhouette consistency: how well the final hull explains every camera's silhouette.

A visual hull is the intersection of the cameras' silhouette cones, so the projection of a hull
made from consistent silhouettes and a right calibration covers each camera's silhouette
(Laurentini 1994). Where one camera's silhouette holds more than the others agree on (a keyer
that kept a wall, a person outside the volume, a camera whose calibration moved), the hull does
not explain it and that camera's agreement drops. Per camera and frame set, the agreement is the
intersection over union (IoU) of the camera's mask and the projection of the frame's surface.

The projection is the union of the surface's triangles that face the camera (every ray through a
closed surface's projection meets a front face), the vertices projected with the camera's lens
distortion, a pixel taken when its centre lies in a triangle. The triangles are filled here, as
runs of pixel centres per row (each edge bounds a row's run; the cover is the running sum of the
runs' ends), all triangles at once: OpenCV's many-polygon filler fills by the even-odd rule
(overlapping triangles and shared edges cancel), and its convex filler takes every pixel an edge
touches (half a pixel more all round, which on a limb a few pixels wide is a large share of its
area; it fills only triangles wider than :data:`_LARGEST` pixels, where that is small). The
projection and the grown mask are made only inside the window that holds both, which gives the
same IoU as the whole image.

The carver grows every silhouette by the job's margin before carving (a conservative hull,
:class:`pipeline.hull.HullCarver`), so the hull is compared with the masks grown the same way.

A camera whose silhouettes **miss** part of the subject carves that part from the hull for every
camera, so the others' IoU drops, not its own. :func:`leave_one_out_gain` names it: the hull
carved without one camera, projected into the others, raises their IoU when that camera was
cutting the subject, and lowers it a little otherwise (one camera fewer carves less).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera
from pipeline.mesh_primitives import check_mesh

__all__ = ["mesh_silhouette", "silhouette_iou", "silhouette_consistency", "leave_one_out_gain", "CONSISTENCY_WARN",
           "MISSING_WARN", "poor_sets", "walls_reached"]

#: A camera whose median consistency over the take is below this is named in a warning.
CONSISTENCY_WARN = 0.8
#: A camera that, left out of the hull, raises the other cameras' mean IoU by more than this
#: (median over the frame sets checked) misses part of the subject and is named in a warning.
#: Left out, a camera whose silhouettes are right makes the hull fatter (one camera fewer
#: carves), so the others' IoU drops a little (within 0.004 on the simulated takes of the tests);
#: a rise means it was cutting what the others see.
MISSING_WARN = 0.03

_SHIFT = 4  # fractional bits of the polygon filler's vertex coordinates (triangles wider than _LARGEST)
_LARGEST = 64  # pixels: wider triangles are filled by OpenCV (its half-pixel border is small beside them)


def _edge(tri: np.ndarray, i: int, j: int, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """The edge function of edge ``i -> j`` at pixel centres: <= 0 on the inner side (edge included)."""
    ax, ay = tri[i, :, 0], tri[i, :, 1]
    bx, by = tri[j, :, 0], tri[j, :, 1]
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def _spans(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel row of every triangle, the run ``[x0, x1]`` of pixel centres inside it, for (3, F, 2)
    clockwise triangles and their bounding boxes of pixel centres ``lo``, ``hi`` (F, 2): rows (R,),
    x0, x1 (R,), empty runs included (x0 > x1). The bound each edge puts on a row is solved for;
    where it falls within rounding of a pixel centre, the edge function itself (the test of pixel
    centres, :func:`_edge`) decides, so the runs hold exactly the centres that test inside."""
    heights = hi[:, 1] - lo[:, 1] + 1
    owner = np.repeat(np.arange(len(heights)), heights)
    first = np.cumsum(heights) - heights
    py = (lo[owner, 1] + np.arange(len(owner)) - first[owner]).astype(np.float64)
    x0 = lo[owner, 0].astype(np.int64)
    x1 = hi[owner, 0].astype(np.int64)
    big = float(1 << 40)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        ax, ay = tri[i, owner, 0], tri[i, owner, 1]
        dx, dy = tri[j, owner, 0] - ax, tri[j, owner, 1] - ay
        rel = py - ay
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = ax + dx * rel / dy
        down, up = dy > 0, dy < 0  # inside where px >= xs (dy > 0) or px <= xs (dy < 0)
        # a horizontal edge lets its whole row in or none of it
        shut = ~down & ~up & (dx * rel > 0)
        lower = np.where(down, np.clip(np.ceil(xs), -big, big), np.where(shut, big, -big)).astype(np.int64)
        upper = np.where(up, np.clip(np.floor(xs), -big, big), big).astype(np.int64)
        with np.errstate(invalid="ignore"):
            near = np.flatnonzero((down | up) & (np.abs(xs - np.rint(xs)) <= 1e-6 * (1.0 + np.abs(xs))))
        if near.size:  # the division's rounding may put the bound a pixel off: the edge function decides
            t, yy = tri[:, owner[near]], py[near]
            fit = np.rint(xs[near])
            edge_in = _edge(t, i, j, fit, yy) <= 0
            lower[near] = np.where(down[near], np.where(edge_in, fit, fit + 1), lower[near]).astype(np.int64)
            upper[near] = np.where(up[near], np.where(edge_in, fit, fit - 1), upper[near]).astype(np.int64)
        np.maximum(x0, lower, out=x0)
        np.minimum(x1, upper, out=x1)
    return py.astype(np.int64), x0, x1


def _fill(out: np.ndarray, tri: np.ndarray, origin: tuple[int, int] = (0, 0)) -> None:
    """Set the pixels of ``out`` whose centre lies in a triangle (edges included), for (3, F, 2)
    clockwise (negative area) triangles in pixel coordinates (vertex first: reductions over the
    three vertices run along whole rows). ``out`` is the window of the image whose top-left pixel
    is ``origin`` (column, row). Each triangle's rows of pixel centres become runs
    (:func:`_spans`), summed into a difference image whose running sum along the rows is the
    cover."""
    import cv2

    h, w = out.shape
    ox, oy = origin
    lo = np.maximum(np.ceil(np.minimum(np.minimum(tri[0], tri[1]), tri[2])), [ox, oy]).astype(np.int64)
    hi = np.minimum(np.floor(np.maximum(np.maximum(tri[0], tri[1]), tri[2])), [ox + w - 1, oy + h - 1]).astype(np.int64)
    n = hi - lo + 1
    ok = (n[:, 0] > 0) & (n[:, 1] > 0)
    size = np.maximum(n[:, 0], n[:, 1])
    small = np.flatnonzero(ok & (size <= _LARGEST))
    if small.size:
        rows, x0, x1 = _spans(tri[:, small], lo[small], hi[small])
        run = x0 <= x1
        rows, x0, x1 = rows[run] - oy, x0[run] - ox, x1[run] - ox
        diff = np.bincount(rows * (w + 1) + x0, minlength=h * (w + 1))
        diff -= np.bincount(rows * (w + 1) + x1 + 1, minlength=h * (w + 1))
        out |= (np.cumsum(diff.reshape(h, w + 1), axis=1)[:, :w] > 0).view(np.uint8)
    big = np.flatnonzero(ok & (size > _LARGEST))
    shift = np.array([ox, oy]) * (1 << _SHIFT)
    for p in np.round(tri[:, big].transpose(1, 0, 2) * (1 << _SHIFT)).astype(np.int32):
        cv2.fillConvexPoly(out, (p - shift).astype(np.int32), 1, cv2.LINE_8, _SHIFT)


def _front_triangles(v: np.ndarray, f: np.ndarray, camera: Camera) -> np.ndarray:
    """(3, F', 2) pixel coordinates of the triangles that face the camera and may cover a pixel
    centre of its image (every vertex in front of it)."""
    w, h = camera.size
    if len(f) == 0:
        return np.zeros((3, 0, 2))
    pix, z = camera.project(v, return_depth=True)
    ft = np.ascontiguousarray(f.T)
    tri = pix[ft]  # (3, F, 2), vertex first
    zt = z[ft]
    front = (zt[0] > 0) & (zt[1] > 0) & (zt[2] > 0)
    # an outward face seen from outside turns counter-clockwise; the image's y axis points down,
    # so a face turned towards the camera has a negative signed area in pixel coordinates
    d1, d2 = tri[1] - tri[0], tri[2] - tri[0]
    a = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    lo = np.minimum(np.minimum(tri[0], tri[1]), tri[2])
    hi = np.maximum(np.maximum(tri[0], tri[1]), tri[2])
    inside = (hi[:, 0] >= -0.5) & (lo[:, 0] <= w - 0.5) & (hi[:, 1] >= -0.5) & (lo[:, 1] <= h - 0.5)
    facing = front & inside & np.isfinite(a) & (a < 0)  # a NaN vertex makes the area NaN
    return tri[:, facing]


def mesh_silhouette(vertices: Any, faces: Any, camera: Camera) -> np.ndarray:
    """The projection of a closed surface into a camera: pixels whose centre it covers.

    Parameters
    ----------
    vertices : (V, 3) float array-like
        World units of the camera's calibration.
    faces : (F, 3) int array-like
        Triangles, counter-clockwise seen from outside (outward normals).
    camera : Camera

    Returns
    -------
    (H, W) bool ndarray
        Triangles with a vertex behind the camera are left out.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    v, f = check_mesh(vertices, faces)
    w, h = camera.size
    out = np.zeros((h, w), np.uint8)
    _fill(out, _front_triangles(v, f, camera))
    return out.view(bool)


def _window(tri: np.ndarray, mask: np.ndarray, margin: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (exclusive ends) holding every pixel centre the triangles may cover
    and the mask grown by ``margin``, within the image; empty when neither has any."""
    import cv2

    w, h = size
    x, y, bw, bh = cv2.boundingRect(mask.view(np.uint8))
    box = [] if bw == 0 else [(x - margin, y - margin, x + bw + margin, y + bh + margin)]
    if tri.shape[1]:
        lo = np.floor(np.minimum(np.minimum(tri[0], tri[1]), tri[2]).min(axis=0))
        hi = np.ceil(np.maximum(np.maximum(tri[0], tri[1]), tri[2]).max(axis=0)) + 1
        box.append((int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])))
    if not box:
        return 0, 0, 0, 0
    b = np.array(box)
    x0, y0 = max(0, int(b[:, 0].min())), max(0, int(b[:, 1].min()))
    x1, y1 = min(w, int(b[:, 2].max())), min(h, int(b[:, 3].max()))
    return x0, y0, max(x0, x1), max(y0, y1)


def silhouette_iou(mask: Any, projection: Any) -> float:
    """Intersection over union of two silhouettes of one image; NaN when both are empty.

    Parameters
    ----------
    mask, projection : (H, W) bool array-like

    Returns
    -------
    float
    """
    m = np.asarray(mask)
    p = np.asarray(projection)
    if m.ndim != 2 or m.shape != p.shape:
        raise ValueError(f"mask and projection must be (H, W) arrays of one shape, got {m.shape} and {p.shape}")
    m, p = m != 0, p != 0
    union = int(np.count_nonzero(m | p))
    if union == 0:
        return float("nan")
    return int(np.count_nonzero(m & p)) / union


def silhouette_consistency(vertices: Any, faces: Any, masks: Any, calibration: Calibration, *,
                           margin: int = 0) -> np.ndarray:
    """Per camera, the IoU of its mask and the projection of a frame's surface.

    Parameters
    ----------
    vertices : (V, 3) float array-like
    faces : (F, 3) int array-like
        The frame's surface (closed, outward normals), world units of ``calibration``.
    masks : sequence of (H, W) bool array-like or None
        One silhouette per camera of ``calibration``; None for a camera without one.
    calibration : Calibration
    margin : int, optional
        Pixels every mask grows by first (the margin the hull was carved with).

    Returns
    -------
    (C,) float ndarray
        NaN for a camera without a mask (or with nothing in its mask nor its projection).
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    if len(masks) != len(calibration):
        raise ValueError(f"masks: expected one mask per camera ({len(calibration)}), got {len(masks)}")
    v, f = check_mesh(vertices, faces)
    if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be a non-negative integer (pixels), got {margin!r}")
    disk = None
    if margin:
        import cv2

        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    out = np.full(len(calibration), np.nan)
    for i, (cam, m) in enumerate(zip(calibration, masks)):
        if m is None:
            continue
        w, h = cam.size
        if np.shape(m) != (h, w):
            raise ValueError(f"masks: camera {cam.name!r} is {w}x{h}, its mask has shape {np.shape(m)}")
        m = np.ascontiguousarray(np.asarray(m) != 0)
        tri = _front_triangles(v, f, cam)
        # the mask grown and the surface drawn only where either can be (exactly as on the whole image)
        x0, y0, x1, y1 = _window(tri, m, margin, (w, h))
        if x1 == x0 or y1 == y0:
            continue
        if disk is not None:
            import cv2

            gx0, gy0 = max(0, x0 - margin), max(0, y0 - margin)
            grown = cv2.dilate(m[gy0 : min(h, y1 + margin), gx0 : min(w, x1 + margin)].view(np.uint8), disk)
            mw = grown[y0 - gy0 : y1 - gy0, x0 - gx0 : x1 - gx0].view(bool)
        else:
            mw = m[y0:y1, x0:x1]
        proj = np.zeros((y1 - y0, x1 - x0), np.uint8)
        _fill(proj, tri, origin=(x0, y0))
        out[i] = silhouette_iou(mw, proj.view(bool))
    return out


def _occupancy_images(occ: np.ndarray, grid, calibration: Calibration) -> list[np.ndarray]:
    """Every camera's image of an occupancy: the pixels of its voxel centres, closed by the voxel's
    footprint (a surface-free projection, the same for every hull compared)."""
    import cv2

    centres = grid.lo + (np.argwhere(occ) + 0.5) * grid.voxel
    out = []
    for cam in calibration:
        w, h = cam.size
        img = np.zeros((h, w), np.uint8)
        if len(centres):
            uv, z = cam.project(centres, return_depth=True)
            ok = (z > 0) & np.isfinite(uv).all(axis=1)
            p = np.floor(uv[ok] + 0.5).astype(np.int64)
            inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
            img[p[inside, 1], p[inside, 0]] = 1
            foot = float(np.median(cam.K[0, 0] * grid.voxel / z[ok])) if ok.any() else 1.0
            r = max(1, int(np.ceil(foot / 2)))
            img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
        out.append(img.view(bool))
    return out


def leave_one_out_gain(masks: Any, carver, *, tolerance: int = 0, support_plane: Any = None,
                       margin: int = 0) -> np.ndarray:
    """Per camera, how much the other cameras' mean IoU rises when the hull is carved without it.

    Parameters
    ----------
    masks : sequence of (H, W) bool array-like or None
        One frame set's silhouettes, one per camera of ``carver.calibration``.
    carver : pipeline.hull.HullCarver
    tolerance, support_plane, margin
        The job's carving (the same for every hull).

    Returns
    -------
    (C,) float ndarray
        Mean over the other cameras (with a mask) of IoU(mask, hull without this camera) minus
        IoU(mask, hull of all); NaN for a camera without a mask, or when a hull is empty. Hulls
        are compared through the images of their voxel centres (closed by the voxel's footprint).
    """
    from pipeline.hull import EmptyHullError

    cal = carver.calibration
    if len(masks) != len(cal):
        raise ValueError(f"masks: expected one mask per camera ({len(cal)}), got {len(masks)}")
    kw = {"tolerance": tolerance, "support_plane": support_plane, "margin": margin}
    have = [i for i, m in enumerate(masks) if m is not None]
    out = np.full(len(cal), np.nan)
    try:
        full = _occupancy_images(carver.carve(masks, **kw).occupancy, carver.grid, cal)
    except EmptyHullError:
        return out
    base = {j: silhouette_iou(masks[j], full[j]) for j in have}
    for c in have:
        others = [j for j in have if j != c]
        if len(others) < 2:
            continue
        try:
            occ = carver.carve([None if i == c else m for i, m in enumerate(masks)], **kw).occupancy
        except EmptyHullError:
            continue
        imgs = _occupancy_images(occ, carver.grid, cal)
        out[c] = float(np.nanmean([silhouette_iou(masks[j], imgs[j]) - base[j] for j in others]))
    return out


def poor_sets(iou: Any, *, threshold: float = CONSISTENCY_WARN) -> tuple[list[int], np.ndarray]:
    """The frame sets whose surface explains little of the silhouettes: the median over the cameras of their
    consistency below ``threshold``.

    Parameters
    ----------
    iou : (C, S) array_like
        Consistency per camera and frame set (NaN: none, as ``consistency.json``'s ``iou``).
    threshold : float
        Default :data:`CONSISTENCY_WARN`, the per-camera rule's.

    Returns
    -------
    sets : list of int
        The frame sets below it, in order.
    median : (S,) float ndarray
        Every frame set's median over its cameras (NaN where no camera has one).

    Raises
    ------
    ValueError
        ``iou`` not a 2-D array of numbers within [0, 1] or NaN; ``threshold`` not within (0, 1].
    """
    a = np.asarray(iou, dtype=np.float64)
    if a.ndim != 2 or np.any(np.isinf(a)) or np.any((a < 0) | (a > 1)):
        raise ValueError(f"iou must be a (cameras, frame sets) array within [0, 1] or NaN, got shape {a.shape}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 < threshold <= 1:
        raise ValueError(f"threshold must be within (0, 1], got {threshold!r}")
    has = np.isfinite(a).any(axis=0)
    median = np.full(a.shape[1], np.nan)
    if has.any():
        median[has] = np.nanmedian(a[:, has], axis=0)
    return [int(k) for k in np.flatnonzero(has & (median < threshold))], median


def walls_reached(bounds: Any, box: Any, volume: Any, *, sets, tol: float) -> dict[str, list[int]]:
    """The walls of the capture volume that cut the subject in ``sets``: a side of the processing ``box`` that lies
    on the side of the ``volume`` it was searched in (the volume cut the box there) and that the surfaces of
    ``sets`` reach within ``tol``; a side the surfaces of at least three quarters of all the frame sets reach is
    left out (the floor a subject stands on: a subject that goes beyond a wall does so for a while, not throughout).

    Parameters
    ----------
    bounds : (S, 2, 3) array_like
        Every frame set's surface, its lowest and highest coordinates (NaN: no surface).
    box, volume : (2, 3) array_like
        The processing box's ``[lo, hi]`` and the volume it was searched in.
    sets : sequence of int
        The frame sets judged (:func:`poor_sets`).
    tol : float
        How near a surface comes to a side to reach it (world units, > 0; a voxel or two).

    Returns
    -------
    dict
        ``"x = -375"`` (the side's axis and coordinate) -> the frame sets of ``sets`` whose surface reaches it, in
        the order of the sides x, y, z, low before high.

    Raises
    ------
    ValueError
        Naming the parameter: shapes, a set outside ``bounds``, ``tol`` not positive.
    """
    b = np.asarray(bounds, dtype=np.float64)
    bx, vol = np.asarray(box, dtype=np.float64), np.asarray(volume, dtype=np.float64)
    if b.ndim != 3 or b.shape[1:] != (2, 3):
        raise ValueError(f"bounds must be (frame sets, 2, 3), got shape {b.shape}")
    for name, v in (("box", bx), ("volume", vol)):
        if v.shape != (2, 3) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite (2, 3) [lo, hi], got shape {v.shape}")
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol!r}")
    judged = sorted({int(k) for k in sets})
    if any(not 0 <= k < len(b) for k in judged):
        raise ValueError(f"sets must be frame sets within 0..{len(b) - 1}, got {list(sets)}")
    surfaced = int(np.all(np.isfinite(b), axis=(1, 2)).sum())
    out = {}
    for axis in range(3):
        for end in (0, 1):
            wall = bx[end, axis]
            if abs(wall - vol[end, axis]) > tol:
                continue  # the box ends inside the volume here: a subject there is whole
            reach = [k for k in range(len(b)) if np.isfinite(b[k, end, axis]) and abs(b[k, end, axis] - wall) <= tol]
            if 4 * len(reach) >= 3 * surfaced:
                continue
            hit = [k for k in judged if k in reach]
            if hit:
                out[f"{'xyz'[axis]} = {wall:.4g}"] = hit
    return out
