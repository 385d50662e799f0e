"""Colour feature tracks of a processed multi-view take, for :func:`pipeline.track.track_results` (``colour=True``).

Per camera, the template vertices visible there on the previous frame are followed into the
current image (:func:`pipeline.colour_tracks.colour_tracks`); one camera gives no depth, so each
track is put on its viewing ray, and a vertex's tracks are kept where the rays of two cameras or
more agree (:func:`agreeing_rays`). The images, masks and calibration are those of the take the
results directory came from (``process.json``), when it is still there.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.colour_tracks import colour_tracks, ray_points
from pipeline.mesh_primitives import vertex_normals
from pipeline.track_frames import LastRead

__all__ = ["agreeing_rays", "colour_cameras", "colour_take", "multiview_colour", "multiview_tracks_for", "take_of"]

log = logging.getLogger("pipeline.track")


def take_of(root: Path) -> Path | None:
    """The take a results directory came from (``process.json``), when it is still there."""
    try:
        take = Path(json.loads((root / "process.json").read_text())["take"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return take if take.is_file() else None


def colour_cameras(rd) -> dict:
    """Camera id -> calibrated camera, for the take's cameras with a calibration and keyed masks."""
    calib = rd.calibration
    if calib is None:
        return {}
    keyed = set(rd.masks_present())
    return {c: calib[calib.names.index(c)] for c in rd.cameras if c in calib.names and c in keyed}


@contextlib.contextmanager
def colour_take(root: Path, enabled: bool = True):
    """(reader, cameras) of the take a results directory came from, or None (one line says why)."""
    take = take_of(root) if enabled else None
    if take is None:
        if enabled:
            log.info("%s: the take's images are not available; tracking without colour tracks", root)
        yield None
        return
    from stage.store import TakeError, TakeReader

    try:
        rd = TakeReader(take)
    except (TakeError, OSError) as exc:
        log.warning("tracking without colour tracks: %s", exc)
        yield None
        return
    with rd:
        cams = colour_cameras(rd)
        if not cams:
            log.info("%s: no camera of the take has both a calibration and masks; tracking without colour tracks", take)
        yield (rd, cams) if cams else None


@contextlib.contextmanager
def multiview_colour(root: Path, faces: np.ndarray, tolerance: float, *, enabled: bool = True, corners=None):
    """``tracks_for`` of a multi-view take (None without the take's images, masks and calibration).

    Per camera, the template vertices visible there on the previous frame (z-buffer of the
    previous fit, on the previous frame's mask) are followed into the current image
    (:func:`pipeline.colour_tracks.colour_tracks`, both images' keyed masks, windows warped by
    the camera's projection of the frame's start on the object's pixels only); one camera gives
    no depth, so each track is put on its viewing ray at the point nearest the frame's start
    (prediction) of its vertex: the fit uses only the two directions across the ray. One vertex
    seen by several cameras gets several rays: together they fix its slide along the surface,
    which the closest-point pairs of a smooth surface leave free.
    """
    with colour_take(root, enabled) as src:
        yield None if src is None else multiview_tracks_for(src[0], src[1], faces, tolerance, corners=corners)


def multiview_tracks_for(rd, cameras: dict, faces: np.ndarray, tolerance: float, *, corners=None):
    """``tracks_for(k, k_prev, previous, extra, start)`` over every camera (see :func:`multiview_colour`);
    ``corners``: the tracker's summing matrix of the face corners (:attr:`TemplateTracker.corner_sum`)."""
    from pipeline.rgbd_preprocess import visible_vertices
    from stage.store import TakeError

    warned: set = set()  # cameras whose unreadable image or mask has been reported

    def view(cam_id, k):
        """(image, mask) of frame set ``k`` in one camera, (None, None) where it has none."""
        if not 0 <= k < rd.n_sets:
            return None, None
        try:
            r = rd.set_rows(k)[cam_id]
            return (None, None) if r < 0 else (rd.frame(cam_id, r), rd.mask(cam_id, r))
        except (IndexError, TakeError, OSError) as exc:  # truncated masks, corrupt image, unreadable file
            if cam_id not in warned:
                warned.add(cam_id)
                log.warning("colour tracks: camera %s, frame set %d unreadable (%s); "
                            "this camera's colour tracks skip the frames it cannot read", cam_id, k, exc)
            return None, None

    def follow(cam, before, now, V, vis, start):
        (img0, m0), (img1, m1) = before, now
        # no depth in one camera: a plane at the visible vertices' depth gives each track its ray ...
        z = float(np.median(cam.project(V[vis], return_depth=True)[1]))
        # (windows warped by this camera's projection of the start, on its keyed object pixels only)
        idx, _, rays = colour_tracks(img0, img1, V, vis, cam, np.full(m1.shape, z), masks=(m0, m1), predicted=start,
                                     faces=faces)
        # ... and the target is the ray's point nearest the vertex's start (the fit uses only the directions across it)
        along = np.einsum("ij,ij->i", start[idx] - cam.center, rays)
        return idx, cam.center + rays * along[:, None], rays

    views = {cam_id: LastRead(functools.partial(view, cam_id)) for cam_id in cameras}

    def tracks_for(k, k_prev, prev, extra, start):
        start = prev if start is None else start
        vn = vertex_normals(prev, faces, corners=corners)
        out = []
        for cam_id, cam in cameras.items():
            before, now = views[cam_id].pair(k_prev, k)
            if any(x is None for x in (*before, *now)):
                continue
            vis = visible_vertices(prev, faces, cam, normals=vn, tolerance=tolerance, observed=before[1])
            if vis.any():
                out.append(follow(cam, before, now, prev, vis, start))
        if not out:
            return None
        return agreeing_rays(*(np.concatenate(a) for a in zip(*out)), len(prev))

    return tracks_for


def agreeing_rays(idx: np.ndarray, targets: np.ndarray, rays: np.ndarray, n: int, *, factor: float = 3.0):
    """The tracks of vertices seen by two cameras or more whose rays meet: per vertex the point
    nearest all its rays (least squares); a track is kept when its ray passes within ``factor``
    times the median such distance of that point. A single camera's track cannot be checked
    and is dropped: a track held back by the static shading, or caught on a shadow, has no
    second view to contradict it."""
    ok, x = ray_points(idx, targets, rays, n)
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # projectors across each ray
    keep = ok[idx]
    dist = np.linalg.norm(np.einsum("tij,tj->ti", P, x[idx] - targets), axis=1)
    if keep.any():
        keep &= dist <= factor * float(np.median(dist[keep]))
    return idx[keep], targets[keep], rays[keep]
