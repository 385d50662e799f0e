"""One round of :func:`pipeline.track_armature.track_with_armature`: every frame tracked again with an armature.

From the reference frame forwards and backwards (:func:`armature_half_task` tracks one half in a worker process
meanwhile), every frame by :class:`pipeline.armature_track.ArmatureTracker` from its starts: the previous frame's pose,
its constant-velocity prediction, the armature's own fit of the frame and the previous pose moved by the spine's limb
motion (:func:`_spine_steps`).
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import time
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.armature_track import ArmatureTracker
from pipeline.mesh_primitives import mesh_volume
from pipeline.run.context import submit_aside
from pipeline.track import mesh_data, spine_model, spine_starts
from pipeline.track_frames import surface_meshes, write_frame
from pipeline.tracking import TemplateTracker

__all__ = ["armature_half_task", "ARMATURE_FIT_ROUNDS", "ARMATURE_ICP_POINTS"]

log = logging.getLogger("pipeline.track")

#: Rounds of the template fit from the armature's skinned pose (the first tracking's, before the rounds, are
#: :attr:`pipeline.tracking.TemplateTracker.rounds`): it starts on the surface, where the later rounds
#: of a fit from the previous frame move nothing (docs/tracking.md, "Fast motion").
ARMATURE_FIT_ROUNDS = 8
#: Vertices the articulated ICP pairs and fits a frame's pose with (:class:`pipeline.armature_track.ArmatureTracker`):
#: a pose of 60 parts is determined many times over by 1000 (the same accuracy as 2000, a sixth less CPU;
#: docs/tracking.md, "Fast motion").
ARMATURE_ICP_POINTS = 1000


def _rig_round(tracker, model, by_pose: dict, vs: np.ndarray, frames: list[int], refi: int, by_frame: dict, root: Path,
               faces: np.ndarray, weight: float, progress, spine=None, tracks_for=None, aside=None) -> dict:
    """One tracking of every frame but the reference with ``model`` as the prior; -> {"vertices": frame -> (V, 3),
    "figures": frame -> per-frame figures}. ``spine``: ``step(k, k_prev)`` -> the spine's skinned step of the
    template from frame ``k_prev`` to ``k`` (:func:`_spine_steps`), or None. ``tracks_for``: the colour
    tracks (:func:`pipeline.track_colour.multiview_tracks_for`), or None. ``aside``: (executor, the half's
    settings for :func:`armature_half_task`): the longer half (from the reference frame forwards or backwards) is
    tracked there meanwhile."""
    from pipeline.armature_track import fit_pose_to_surface

    data_for = mesh_data(by_frame)
    ref = frames[refi]
    ref_data = data_for(ref)
    start = by_pose.get(ref, model.identity())
    ref_pose = start if ref_data is None else fit_pose_to_surface(model, start, ref_data[0], ref_data[1],
                                                                  gate=tracker.gate)[0]
    # the longer half aside (this process built the armature first), or both here in order
    halves = sorted((frames[refi + 1:], frames[:refi][::-1]), key=len) if aside is not None else \
        (frames[refi + 1:], frames[:refi][::-1])
    mine, other = halves
    half = {"prev": vs[refi], "pose": ref_pose, "ref": ref, "faces": faces, "root": str(root), "weight": weight}
    later = None
    if aside is not None and other and mine:  # (one half only: here, without a second set-up)
        later = submit_aside(aside[0], partial(armature_half_task, {**aside[1], **half, "model": model, "by_pose": by_pose,
                                                                   "frames": other}),
                             unavailable="the second tracking process is not available ({exc}); tracking both "
                                         "halves here", logger=log)
    rig = ArmatureTracker(tracker, model, weight=weight, max_points=ARMATURE_ICP_POINTS)
    here = partial(_track_half, rig, by_pose, data_for, spine=spine, tracks_for=tracks_for, **half)
    count = {"done": 1}

    def tick():
        count["done"] += 1
        if progress is not None:
            progress("track with the rig", count["done"], len(frames))

    out = {"vertices": {ref: vs[refi]}, "figures": {}}
    for part in (mine, *([] if later is not None else [other])):
        _merge(out, here(part, tick=tick))
    if later is not None:
        try:
            part = later.result()
        except cf.BrokenExecutor as exc:  # the worker process was killed: its frames are tracked here
            log.warning("the second tracking process stopped (%s); tracking its frames (%d..%d) here", exc, other[0],
                        other[-1])
            part = here(other, tick=tick)
        _merge(out, part)
        out["worker_cpu_seconds"] = later.cpu_seconds
        if progress is not None:
            progress("track with the rig", len(frames), len(frames))
    return out


def _merge(out: dict, part: dict) -> None:
    out["vertices"].update(part["vertices"])
    out["figures"].update(part["figures"])


def _track_half(rig, by_pose: dict, data_for, frames: list[int], *, prev: np.ndarray, pose, ref: int, faces: np.ndarray,
                root, weight: float, spine=None, tracks_for=None, tick=None) -> dict:
    """``frames`` tracked in order from the reference frame ``ref`` (its fit ``prev``, its pose ``pose``) with
    ``rig`` (:class:`pipeline.armature_track.ArmatureTracker`); -> {"vertices": ..., "figures": ...} of them."""
    from pipeline.armature_fit import predict_pose

    model = rig.model
    out = {"vertices": {}, "figures": {}}
    vol0 = mesh_volume(prev, faces)
    before, prev_k = None, ref
    for k in frames:
        t0 = time.perf_counter()
        data = data_for(k)
        if data is not None:
            cands = [pose] + ([predict_pose(model, pose, before)] if before is not None else []) + \
                ([by_pose[k]] if k in by_pose else []) + _spine_pose(model, pose, spine, k, prev_k)
            tracks = None
            if tracks_for is not None:  # followed from the previous frame, started at the skinned prediction
                tracks = tracks_for(k, prev_k, prev, None, model.deform(cands[1]) if before is not None else prev)
            fit, new_pose, res = rig.fit(data[0], data[1], previous=prev, candidates=cands, tracks=tracks)
            prev, before, pose, prev_k = fit.vertices, pose, new_pose, k
            write_frame(Path(root), k, prev, faces)
            out["figures"][k] = {"rig_residual_mm": round(res, 4), "residual_mm": round(fit.residual, 4),
                                 "volume_ratio": round(mesh_volume(prev, faces) / vol0, 5) if vol0 > 0 else None,
                                 "seconds": round(time.perf_counter() - t0, 4)}
        out["vertices"][k] = prev
        if tick is not None:
            tick()
    return out


def armature_half_task(half: dict) -> dict:
    """One half of the frames of a round of :func:`pipeline.track_armature.track_with_armature` (from the reference
    frame), tracked in a worker process (``executor``): the tracker, the surfaces, the spine's steps and the colour tracks set up here
    as that process sets them up, then :func:`_track_half`."""
    from threadpoolctl import threadpool_limits

    from pipeline.track_colour import multiview_colour

    root, faces = Path(half["root"]), half["faces"]
    frames, by_frame = surface_meshes(root, half["surfaces"])
    tracker = TemplateTracker(half["prev"], faces, gamma=half["gamma"], gate=half["gate"], prior=half["prior"],
                              rounds=ARMATURE_FIT_ROUNDS, patch_labels=half.get("patch_labels"))
    spine = _spine_steps(root, frames, by_frame, half["prev"])
    rig = ArmatureTracker(tracker, half["model"], weight=half["weight"], max_points=ARMATURE_ICP_POINTS)
    with threadpool_limits(1, "blas"), multiview_colour(root, faces, 0.3 * tracker.gate, enabled=half["colour"],
                                                        corners=tracker.corner_sum) as tracks_for:
        return _track_half(rig, half["by_pose"], mesh_data(by_frame), half["frames"], prev=half["prev"], pose=half["pose"],
                           ref=half["ref"], faces=faces, root=root, weight=half["weight"], spine=spine,
                           tracks_for=tracks_for)


def _spine_steps(root: Path, frames: list[int], by_frame: dict, template: np.ndarray):
    """``step(k, k_prev)``: how the spine's skinned pose of the template moves from frame ``k_prev``
    to ``k`` (the spine's limb motion, :func:`pipeline.track.spine_starts`), or None without a usable spine of
    this template."""
    skinned = spine_model(root, frames, by_frame, None)
    if skinned is None or skinned[1].vertices.shape != template.shape:
        return None
    starts = spine_starts(skinned[1], frames)
    zero = np.zeros_like(template)
    return lambda k, k_prev: starts(k, k_prev, zero)


def _spine_pose(model, pose, spine, k: int, k_prev: int) -> list:
    """[the armature's pose fitted to its skinned ``pose`` moved by the spine's step to frame ``k``], or []
    without a spine: a start where the constant-velocity prediction is wrong (a leg that turns)."""
    from pipeline.armature_fit import fit_frame

    if spine is None:
        return []
    return [fit_frame(model, model.deform(pose) + spine(k, k_prev), pose, iterations=3, max_points=2000)[0]]
