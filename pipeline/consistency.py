"""Silhouette consistency: how well the final hull explains every camera's silhouette.

A visual hull is the intersection of the cameras' silhouette cones, so the projection of a hull
made from consistent silhouettes and a right calibration covers each camera's silhouette
(Laurentini 1994). Where one camera's silhouette holds more than the others agree on (a keyer
that kept a wall, a person outside the volume, a camera whose calibration moved), the hull does
not explain it and that camera's agreement drops. Per camera and frame set, the agreement is the
intersection over union (IoU) of the camera's mask and the projection of the frame's surface.

The projection is the union of the surface's triangles that face the camera (every ray through a
closed surface's projection meets a front face), the vertices projected with the camera's lens
distortion, a pixel taken when its centre lies in a triangle. The triangles are filled here, in
vectorised groups by size: OpenCV's many-polygon filler fills by the even-odd rule (overlapping
triangles and shared edges cancel), and its convex filler takes every pixel an edge touches (half a
pixel more all round, which on a limb a few pixels wide is a large share of its area).

The carver grows every silhouette by the job's margin before carving (a conservative hull,
:class:`pipeline.hull.HullCarver`), so the hull is compared with the masks grown the same way.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.calibration import Calibration
from calib.camera import Camera

__all__ = ["mesh_silhouette", "silhouette_iou", "silhouette_consistency", "CONSISTENCY_WARN"]

#: A camera whose median consistency over the take is below this is named in a warning.
CONSISTENCY_WARN = 0.8

_SHIFT = 4  # fractional bits of the polygon filler's vertex coordinates (triangles wider than _LARGEST)
_LARGEST = 64  # pixels: wider triangles are filled by OpenCV (its half-pixel border is small beside them)
_CHUNK = 1 << 21  # candidate pixels tested at once


def _fill(out: np.ndarray, tri: np.ndarray) -> None:
    """Set the pixels of ``out`` whose centre lies in a triangle (edges included), for (3, F, 2)
    clockwise (negative area) triangles in pixel coordinates (vertex first: reductions over the
    three vertices run along whole rows): each triangle's bounding box of pixel centres is tested
    against its three edges, triangles grouped by box size."""
    import cv2

    h, w = out.shape
    lo = np.maximum(np.ceil(np.minimum(np.minimum(tri[0], tri[1]), tri[2])), 0).astype(np.int64)
    hi = np.minimum(np.floor(np.maximum(np.maximum(tri[0], tri[1]), tri[2])), [w - 1, h - 1]).astype(np.int64)
    n = hi - lo + 1
    ok = (n[:, 0] > 0) & (n[:, 1] > 0)
    size = np.maximum(n[:, 0], n[:, 1])
    s_lo = 0
    for s_hi in (1, 2, 4, 8, 16, 32, _LARGEST):
        sel = np.flatnonzero(ok & (size > s_lo) & (size <= s_hi))
        s_lo = s_hi
        oy, ox = (g.ravel() for g in np.mgrid[0:s_hi, 0:s_hi])
        for part in np.array_split(sel, max(1, len(sel) * s_hi * s_hi // _CHUNK)):
            if part.size == 0:
                continue
            t, corner, m = tri[:, part], lo[part], n[part]
            px = corner[:, :1] + ox
            py = corner[:, 1:] + oy
            inside = (ox < m[:, :1]) & (oy < m[:, 1:])
            for i, j in ((0, 1), (1, 2), (2, 0)):
                ax, ay = t[i, :, :1], t[i, :, 1:]
                bx, by = t[j, :, :1], t[j, :, 1:]
                inside &= (bx - ax) * (py - ay) - (by - ay) * (px - ax) <= 0
            out[py[inside], px[inside]] = 1
    big = np.flatnonzero(ok & (size > _LARGEST))
    for p in np.round(tri[:, big].transpose(1, 0, 2) * (1 << _SHIFT)).astype(np.int32):
        cv2.fillConvexPoly(out, p, 1, cv2.LINE_8, _SHIFT)


def _check_mesh(vertices: Any, faces: Any) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise ValueError(f"vertices must be a finite (V, 3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer (F, 3) array, got shape {f.shape} of {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("faces index vertices that do not exist")
    return v, f.astype(np.int64)


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
    v, f = _check_mesh(vertices, faces)
    w, h = camera.size
    out = np.zeros((h, w), np.uint8)
    if len(f) == 0:
        return out.view(bool)
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
    _fill(out, tri[:, facing])
    return out.view(bool)


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
    v, f = _check_mesh(vertices, faces)
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
        m = np.asarray(m) != 0
        if disk is not None:
            import cv2

            m = cv2.dilate(m.view(np.uint8), disk).view(bool)
        out[i] = silhouette_iou(m, mesh_silhouette(v, f, cam))
    return out
