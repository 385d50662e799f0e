"""Template tracking through one RGB-D camera's take (Tzionas & Gall 2016, §3).

The template (a static scan, mm, roughly placed) is placed on the first frame with depth by rigid
ICP, then every frame is preprocessed (:func:`pipeline.rgbd_preprocess.preprocess_depth`) and only
the vertices the camera and the data see get model->data pairs; the colour images add feature
tracks (:func:`pipeline.colour_tracks.colour_tracks`). Frames go to ``tracked/`` as
:mod:`pipeline.track_frames` writes them (atomic, resumable).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline.mesh_primitives import vertex_normals
from pipeline.run.settings import array_digest
from pipeline.track_frames import LastRead, load_template, predictor, run_frames, start_over_if_changed, write_report
from pipeline.tracking import TemplateTracker, TrackingError

__all__ = ["TrackingError", "track_rgbd_take"]

log = logging.getLogger("pipeline.track")


def _colour_tracks_for(rd, cam_id, cam, faces, frames: dict, tolerance: float, *, corners=None):
    """``tracks_for(k, k_prev, previous, frame, start)``: the previous frame's visible vertices
    followed into frame ``k``'s colour image (``frames``: preprocessed depth frames by index;
    ``corners``: the tracker's summing matrix of the face corners)."""
    from pipeline.colour_tracks import colour_tracks
    from pipeline.rgbd_preprocess import visible_vertices

    images = LastRead(lambda k: rd.frame(cam_id, k))

    def tracks_for(k, k_prev, prev, fr, start):
        seen = frames.get(k_prev)
        vis = visible_vertices(prev, faces, cam, normals=vertex_normals(prev, faces, corners=corners), tolerance=tolerance,
                               observed=None if seen is None else seen.valid)
        masks = None if seen is None else (seen.valid, fr.valid)
        before, now = images.pair(k_prev, k)
        return colour_tracks(before, now, prev, vis, cam, fr.depth, masks=masks, predicted=start, faces=faces)

    return tracks_for


def _keep_last(cache: dict) -> None:
    """Drop all but the latest preprocessed frame: the next frame's colour tracks start from it,
    also across frames without data."""
    for j in [j for j in cache if j != max(cache)]:
        del cache[j]


def _capture_bounds(reader, V: np.ndarray, margin: float):
    rig = reader.rig or {}
    vol = rig.get("volume") if isinstance(rig, dict) else None
    if isinstance(vol, dict) and "center" in vol and "size" in vol:
        c, s = np.asarray(vol["center"], float), np.asarray(vol["size"], float)
        return c - s / 2, c + s / 2
    return None if margin is None else (V.min(0) - margin, V.max(0) + margin)


def _depth_camera(rd, take_path, camera: str | None):
    """(camera id, calibrated camera) of the depth camera tracked: ``camera``, else the first with depth."""
    cams = [c for c in rd.cameras if rd.camera_info(c).get("has_depth")]
    if camera is not None:
        if camera not in rd.cameras:
            raise ValueError(f"camera {camera!r} is not in the take (cameras: {', '.join(rd.cameras)})")
        cams = [camera]
    if not cams:
        raise ValueError(f"{take_path}: no camera of the take records depth")
    cam_id = cams[0]
    calib = rd.calibration
    if calib is None or cam_id not in calib.names:
        raise ValueError(f"{take_path}: the take has no calibration of camera {cam_id} (run `stage calibrate`)")
    return cam_id, calib[calib.names.index(cam_id)]


def _depth_data(rd, cam_id: str, cam, cache: dict, *, fixed, size: float, remove_skin: bool):
    """``data_for(k, previous)``: frame ``k``'s preprocessed depth as (points, normals, frame), or None
    (no depth, or fewer than 10 points in the box: ``fixed``, else the previous frame's box grown by
    15 % of the template's ``size``); ``cache`` keeps the latest frame for the colour tracks."""
    from pipeline.rgbd_preprocess import preprocess_depth

    def data_for(k, previous=None):
        z = rd.depth(cam_id, k)
        if z is None or not np.any(z):
            return None
        img = rd.frame(cam_id, k) if remove_skin else None
        box = fixed if fixed is not None else (previous.min(0) - 0.15 * size, previous.max(0) + 0.15 * size)
        fr = preprocess_depth(z, cam, bounds=box, image=img, remove_skin=remove_skin)
        if len(fr.points) < 10:
            return None
        _keep_last(cache)
        cache[k] = fr
        return fr.points, fr.normals, fr

    return data_for


def _settings(tracker, V0: np.ndarray, F0: np.ndarray, **options) -> dict:
    """The tracker's and the options' entries of ``track.json`` (what a start-over compares)."""
    return {"template_sha256": array_digest(V0, F0), "vertices": int(len(V0)), "gamma": tracker.gamma,
            "gate_mm": tracker.gate, "rounds": tracker.rounds, "solver": tracker.system.backend,
            "remove_skin": bool(options["remove_skin"]), "contour": bool(options["contour"]),
            "predict": bool(options["predict"]), "prior": tracker.prior, "colour_tracks": bool(options["colour"]),
            "patches": tracker.patch_rule}


def _first_with_depth(rd, cam_id: str, n: int, data_for, V0: np.ndarray, take_path, lohi):
    """((frame, its data), the frames before it without data): where the template is placed (nothing
    is written when no frame has data: a TrackingError says why)."""
    skipped = []
    for k in range(n):
        d = data_for(k, V0)
        if d is not None:
            return (k, d), skipped
        skipped.append(k)
    if any(np.any(rd.depth(cam_id, k)) for k in range(n)):
        raise TrackingError(
            f"{take_path}: rigid ICP cannot place the template: no depth point of camera {cam_id} lies in the "
            f"capture volume {np.round(lohi[0]).tolist()}..{np.round(lohi[1]).tolist()} mm around it "
            "(is the template roughly placed in the calibration's world frame, in mm?)"
        )
    raise TrackingError(f"{take_path}: no frame of camera {cam_id} has depth")


def track_rgbd_take(
    take_path,
    template,
    out_dir,
    *,
    camera: str | None = None,
    remove_skin: bool = False,
    contour: bool = False,
    bounds=None,
    progress=None,
    gamma=None,
    gate=None,
    predict: bool = True,
    colour: bool = True,
) -> dict:
    """Track a template through one RGB-D camera's take.

    Parameters
    ----------
    take_path : path
        A take whose camera records depth (uint16 mm) and which holds a calibration.
    template : path or (vertices, faces)
        The object's mesh (mm, roughly placed in the world frame of the calibration).
    out_dir : path
        ``tracked/`` is written there.
    camera : str, optional
        The depth camera (default: the first camera with depth).
    remove_skin : bool
        Drop skin-coloured pixels (the hands) before tracking.
    contour : bool
        Add the contour term (depth edges, the paper's eq. 3).
    bounds : ((3,), (3,)), optional
        Capture volume; default the rig's volume, else, per frame, the box of the template's
        previous frame grown by 15 % of its size (a fixed box around the rest pose crops a part
        that bends out of it).
    predict : bool
        Start every frame from the constant-velocity prediction of the two frames before
        (:func:`pipeline.tracking_patches.predict_motion`; docs/tracking.md: a part faster than the gate is lost without it).
    colour : bool
        Follow the visible vertices in the colour images too (:func:`pipeline.colour_tracks.colour_tracks`):
        the feature tracks see a round part's twist about its own axis, which depth does not.

    Returns
    -------
    dict
        The report written to ``tracked/track.json`` (``skipped``: frames without depth).

    Raises
    ------
    TrackingError
        The template cannot be placed on the data (nothing is written then).
    """
    from pipeline.rgbd_preprocess import contour_pairs, rigid_icp, visible_vertices
    from stage.store import TakeReader

    V0, F0 = load_template(template)
    out = Path(out_dir)
    with TakeReader(take_path) as rd:
        cam_id, cam = _depth_camera(rd, take_path, camera)
        size = float(np.linalg.norm(V0.max(0) - V0.min(0)))
        fixed = bounds if bounds is not None else _capture_bounds(rd, V0, None)
        lohi = fixed if fixed is not None else _capture_bounds(rd, V0, 0.15 * size)
        n = rd.n_frames(cam_id)
        tracker = TemplateTracker(V0, F0, gamma=gamma, gate=gate)
        cache: dict = {}
        data_for = _depth_data(rd, cam_id, cam, cache, fixed=fixed, size=size, remove_skin=remove_skin)

        def visible_for(fr):
            return lambda V, nrm: visible_vertices(V, F0, cam, normals=nrm, tolerance=0.3 * tracker.gate, observed=fr.valid)

        def contour_for(fr):
            return lambda V, nrm: contour_pairs(V, nrm, F0, cam, fr.contour, gate=tracker.gate)

        first, skipped = _first_with_depth(rd, cam_id, n, data_for, V0, take_path, lohi)
        R, t, fit0 = rigid_icp(V0, F0, first[1][0], first[1][1], cam, gate=tracker.gate)
        placed = V0 @ R.T + t
        # a single view sees half the object: the prior keeps the previous frame's shape (see pipeline.tracking)
        tracker = TemplateTracker(placed, F0, gamma=tracker.gamma, gate=tracker.gate, prior="previous")
        report = {"mode": "rgbd", "take": str(Path(take_path).resolve()), "camera": cam_id,
                  "template": str(template) if not isinstance(template, (tuple, list)) else "array",
                  **_settings(tracker, V0, F0, remove_skin=remove_skin, contour=contour, predict=predict, colour=colour),
                  "icp": {"frame": first[0], "fit": round(fit0, 4), "R": R.tolist(), "t": t.tolist()},
                  "skipped": list(skipped), "frames": {}}
        kept = start_over_if_changed(out, report)
        (out / "tracked").mkdir(parents=True, exist_ok=True)
        run_frames(tracker, list(range(first[0], n)), out, F0, report, data_for=data_for, visible_for=visible_for,
                    progress=progress, start=first[0], prev=placed, contour_for=contour_for if contour else None,
                    predict=predictor(tracker, predict),
                    tracks_for=_colour_tracks_for(rd, cam_id, cam, F0, cache, 0.3 * tracker.gate,
                                                  corners=tracker.corner_sum) if colour else None)
    if report["skipped"]:
        log.warning("frames without depth skipped: %s", ", ".join(map(str, report["skipped"])))
    report["frames"] = dict(sorted({**kept, **report["frames"]}.items(), key=lambda kv: int(kv[0])))
    write_report(out, report)
    return report
