"""Tracking a tracked multi-view take again with an armature as the articulated prior.

:func:`track_with_armature` (Tzionas & Gall 2016, §4 and the way out of its chicken-and-egg): the
armature built from the current tracking (:func:`pipeline.armature.build_armature`) tracks every
frame again (:class:`pipeline.armature_track.ArmatureTracker`), then the armature is built again
from that tracking, while a round helps. The frames are written as :mod:`pipeline.track_frames`
writes them, over the ``tracked/`` folder :func:`pipeline.track.track_results` made
(``stage track --armature-rounds``: one round by default, 0 the tracking alone); docs/tracking.md, "Fast motion"
and "Which tracking is the default", have the figures.

This module is the rounds: what a round tracks with comes from :mod:`pipeline.track_armature_models` (the
armature of the motion, of the spine, of the labels' limbs; the labels those follow from
:mod:`pipeline.track_armature_labels`), and one round's tracking of the frames is
:mod:`pipeline.track_armature_round`.
"""

from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.run.context import once_per_run
from pipeline.track import _patch_labels, _spine_labels, _tracked_labels
from pipeline.track_armature_labels import (
    _JOB_PARTS,
    _limb_chain,
    _rooted,
    _surface_labels,
    _surface_points,
    _unclaimed_limbs,
)
from pipeline.track_armature_models import _limb_rig, _limbs, _rig_of, _spine_rig
from pipeline.track_armature_round import ARMATURE_FIT_ROUNDS, _rig_round, _spine_steps
from pipeline.track_frames import surface_meshes, write_frame, write_report, write_round_segments
from pipeline.tracking import TemplateTracker

__all__ = ["track_with_armature", "AUTO_RIG_ROUNDS"]

log = logging.getLogger("pipeline.track")


#: At most this many rounds of ``track_with_armature(rounds="auto")`` (``stage track --armature-rounds auto``).
AUTO_RIG_ROUNDS = 4


@once_per_run()  # (what every round's halves say of the surfaces: once)
def track_with_armature(results_dir, model=None, *, poses=None, rounds: int | str = 1, weight: float = 2.0,
                        lambda_thr: float = 0.98, colour: bool = False, spine: bool = False, progress=None,
                        executor=None, labels=None, parts: str = "motion") -> dict:
    """Track a tracked results directory again with an armature as the articulated prior.

    Every frame but the reference frame (``tracked/track.json``) is tracked again, in order from
    it, forwards and backwards, by :class:`pipeline.armature_track.ArmatureTracker`: the armature's pose
    fitted to the frame's surface from the previous frame's pose, its constant-velocity
    prediction, the previous pose moved by the spine's limb motion (``spine.json``, where the
    prediction is wrong: a leg that turns) and the armature's own fit of the frame, then the template
    fitted from the skinned pose and drawn towards it. Without ``model`` each round builds the
    armature from the current tracking (:func:`pipeline.armature.build_armature`, rest frame the
    reference frame) and tracks with it: the paper's first rig (armature), then track, refit, repeat
    while it helps; with ``spine`` a round with the take's spine as the armature comes first
    (:func:`pipeline.track_armature_models.spine_armature`: built from the visual hulls frame by frame, so it does not
    inherit the tracking's drift). A round
    helps when its armature explains the frames' surfaces better: the mean over frames of
    ``rig_residual_mm`` (:func:`pipeline.armature_track.surface_residual` of the armature's pose
    on each frame's surface; the surfaces, not the tracking the armature was built from, so the
    figure does not improve merely because the tracking was drawn to the armature) falls by at least
    ``1 %``. The rounds stop at the first that does not help, and the tracking of the best round
    is kept.

    Parameters
    ----------
    results_dir : path
        A multi-view results directory tracked by :func:`pipeline.track.track_results`.
    model : pipeline.armature_fit.ArticulatedModel, optional
        A given armature, bound to a rest shape in the template's vertex order at the reference frame
        (one round with it).
    poses : dict int -> pipeline.armature_fit.Pose, optional
        The given armature's poses by frame number (further starts of its fit).
    rounds : int or "auto"
        At most this many rounds of armature building and tracking (without ``model``; after the
        spine's round, with ``spine``); ``"auto"``: at most :data:`AUTO_RIG_ROUNDS`.
    weight : float
        Pull towards the skinned pose, in pairs.
    lambda_thr : float
        Eigenvalue threshold of the armature's motion segmentation. The default is the paper's
        threshold for small parts with small motion, its finest: a prior tolerates a rigid part
        cut in two, not two parts fused into one segment (a drifting first tracking fuses
        limbs at the paper's 0.7).
    spine : bool
        Without ``model``: the first round's armature is the take's spine rig (``spine.json``,
        :data:`pipeline.track_armature_models.SPINE_BONES` bones an axis,
        :func:`pipeline.track_armature_models.spine_armature`) when the take has a spine with
        every limb seen in the reference frame (else one line says so), then ``rounds`` rounds
        build it from the tracking (``stage track --spine-armature``). Off by default: better on one
        fast biped and quadruped, worse on the fast starfish, the slow quadruped and other fast
        quadrupeds (docs/tracking.md, "The take's spine as the first armature").
    colour : bool
        Follow the template in every camera's colour images too (``stage track --colour``,
        :func:`pipeline.track_colour.multiview_colour`, started from the skinned constant-velocity
        prediction): the tracks pull the articulated ICP's vertices, count in the choice of its start
        and enter the template fit (:meth:`pipeline.armature_track.ArmatureTracker.fit`, ``tracks``). The
        surfaces cannot see a round limb's turn about its own axis; the images can. Without the take's
        images, masks or calibration one line says so and the surfaces alone are used.
    progress : callable(step, done, total), optional
        Every round's tracking is its own step, ``"track with the rig round N"`` (``N`` from 1, as ``kept_round``).
    executor : concurrent.futures.Executor, optional
        Tracks the longer of each round's two halves (the frames after the reference frame, or those
        before it; a process pool: :func:`pipeline.track_armature_round.armature_half_task` is its task) while this
        process tracks the other, as :func:`pipeline.track.track_results` splits the take; the same frames as in order here
        (the two halves depend only on the reference frame's pose).
    labels : "spine", (V,) int ndarray or callable, optional
        The template's limb (``0, 1, ...``) or body (``-1``) of every vertex, or ``labels(vertices, faces,
        frame)`` giving them for the reference frame's tracked template, or ``"spine"`` (as
        ``track_results(labels=)``; the labels the tracking wrote, ``tracked/labels.npy``, when it was tracked
        with ``"spine"``, else computed again on the reference frame's tracked template):
        the template fit's rigid patches follow them (``TemplateTracker(patch_labels=)``) and every round's
        armature keeps a segment on one limb (``build_armature(limbs=)``).
    parts : {"motion", "limbs"}
        Where every round's armature (without ``model``) gets its parts. ``"motion"``: the motion segmentation
        of the tracking, hung on its curve skeleton, bone heat weights (:func:`pipeline.armature.build_armature`).
        ``"limbs"``: from ``labels`` and the take's spine (``spine.json``, its limb axes at the reference frame,
        which the labels' limbs index): the body one part, every limb a chain of the intervals along its axis
        that :func:`pipeline.limb_segments.limb_segments` cuts from the tracking, every vertex moving rigidly with
        its part (:func:`pipeline.armature_track.segment_armature`). With ``labels="spine"`` the armature's
        labels also split the body by its motion on every frame's surface (``template_labels(surfaces=)``), and
        a piece of the body that the body's motion carries off the surfaces becomes a limb of its own (a limb
        the spine has no axis for, :func:`pipeline.track_armature_labels._unclaimed_limbs`); then every limb takes
        back the body's vertices on its root tube (:func:`pipeline.template_labels.root_tubes`). Without labels or a
        usable spine one line says so and the parts come from the motion. Only as good as the labels' body: a limb
        the labels give the body moves with it (docs/tracking.md, "The round's armature from the labels").

    Returns
    -------
    dict
        The report written to ``tracked/track.json``, with ``rig_rounds`` (the round kept) and
        per round run where its armature came from (``armature``: ``"spine"``, ``"tracking"`` or
        ``"given"``), its segments (the spine's: its parts), its fit error to the tracking it was built from and
        the mean ``rig_residual_mm`` (``rig_prior``; ``rig_prior.colour_tracks``: whether the colour
        tracks were used; ``rig_prior.worker_cpu_seconds``: the other process's CPU seconds, with
        ``executor``), per frame ``rig_residual_mm``.
    """
    from pipeline.armature_fit import ArticulatedModel

    root = Path(results_dir)
    if rounds == "auto":
        rounds = AUTO_RIG_ROUNDS
    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 1:
        raise ValueError(f"rounds must be a positive integer or 'auto', got {rounds!r}")
    if model is not None and not isinstance(model, ArticulatedModel):
        raise ValueError(f"model must be an ArticulatedModel, got {type(model).__name__}")
    if isinstance(lambda_thr, bool) or not isinstance(lambda_thr, (int, float)) or not 0 < lambda_thr < 1:
        raise ValueError(f"lambda_thr must be a number in (0, 1), got {lambda_thr!r}")
    if not isinstance(spine, (bool, np.bool_)):
        raise ValueError(f"spine must be True or False, got {spine!r}")
    if not (isinstance(parts, str) and parts in ("motion", "limbs")):
        raise ValueError(f"parts must be 'motion' or 'limbs', got {parts!r}")
    report, frames, by_frame, vs, faces, refi = _tracked_sequence(root)
    source_of_labels = labels if isinstance(labels, str) else "given"
    kept_labels = _tracked_labels(root, report, labels, len(vs[refi]))  # the ones the tracking wrote
    if kept_labels is not None:
        labels = kept_labels
    elif isinstance(labels, str):  # the tracking's template frame is the spine's reference frame when it has one
        labels = _spine_labels(root, labels, refi if report.get("spine_start", "none") != "none" else None)
    patch_labels = _patch_labels(labels, vs[refi], faces, frames[refi])
    chain = None
    if parts == "limbs" and model is not None:
        log.warning("parts='limbs' does nothing with a given model: its round tracks with the model's parts",
                    extra={"job_message": f"{_JOB_PARTS} does nothing with a given model"})
    if parts == "limbs" and model is None:
        surfaces = _surface_points(by_frame, frames) if source_of_labels == "spine" and patch_labels is not None else None
        limb_labels = patch_labels if surfaces is None else _surface_labels(root, vs[refi], faces, refi, surfaces,
                                                                            patch_labels)
        chain = _limb_chain(root, limb_labels, refi, len(frames))
        if chain is not None and surfaces is not None:  # (labels="spine": a limb the spine has no axis for)
            chain = _unclaimed_limbs(vs, faces, *chain, surfaces, reference=refi)
            chain = (_rooted(vs[refi], faces, chain[0]), chain[1])
    first = _spine_rig(root, frames, vs[refi], faces, refi) if spine and model is None else None
    tracker = TemplateTracker(vs[refi], faces, gamma=report["gamma"], gate=report["gate_mm"], prior=report["prior"],
                              rounds=ARMATURE_FIT_ROUNDS, patch_labels=patch_labels)
    steps = _spine_steps(root, frames, by_frame, vs[refi])
    from threadpoolctl import threadpool_limits

    from pipeline.track_colour import multiview_colour

    aside = None if executor is None else (executor, {"surfaces": report.get("surfaces", "meshes"), "gamma": report["gamma"],
                                                      "gate": report["gate_mm"], "prior": report["prior"],
                                                      "colour": bool(colour), "patch_labels": patch_labels})
    with threadpool_limits(1, "blas"), \
            multiview_colour(root, faces, 0.3 * tracker.gate, enabled=bool(colour), corners=tracker.corner_sum) as tracks_for:
        # (the articulated fits' small dense products: threads only contend)
        history, best = _armature_rounds(model if first is None else first, poses, int(rounds), vs, faces, frames, refi,
                                         by_frame, root, tracker, weight, lambda_thr, progress, steps, tracks_for, aside,
                                         given=model is not None, limbs=_limbs(patch_labels), chain=chain)
    kept, _, per = best
    if kept != len(history) - 1:  # the last round did not help: the best round's tracking again
        for k in per["figures"]:
            write_frame(root, k, per["vertices"][k], faces)
    report["frames"].update({str(k): {**report["frames"].get(str(k), {}), **v} for k, v in per["figures"].items()})
    report["rig_rounds"] = kept + 1
    report["rig_prior"] = {"weight": float(weight), "lambda_thr": float(lambda_thr), "max_rounds": int(rounds),
                           "parts": "limbs" if chain is not None else "motion",
                           "patch_labels": None if patch_labels is None else source_of_labels, "kept_round": kept + 1,
                           "colour_tracks": tracks_for is not None, "rounds": history}
    write_round_segments(root, [r.pop("cut", None) for r in history][kept], report["rig_prior"])  # limbs rounds' parts
    worker = [r.pop("worker_cpu_seconds") for r in history if r.get("worker_cpu_seconds") is not None]
    if worker:
        report["rig_prior"]["worker_cpu_seconds"] = round(float(sum(worker)), 3)
    write_report(root, report)
    return report


def _armature_rounds(model, poses, rounds: int, vs, faces, frames, refi, by_frame, root, tracker, weight, lambda_thr,
                     progress, spine, tracks_for=None, aside=None, given: bool = True, limbs=None, chain=None):
    """The rounds of :func:`track_with_armature`: -> (history, (kept round, its residual, its tracking)).
    ``model``: the first round's armature (the only round's when ``given``), or None: every round's built.
    ``limbs``: the template's limbs (:class:`pipeline.armature_limbs.VertexLimbs`) the built armatures keep, or None.
    ``chain``: (labels, limb axes) the built armatures' parts follow (:func:`pipeline.track_armature_models._limb_rig`),
    or None: the motion's."""
    history, best = [], None
    for r in range(1 if given else rounds + (model is not None)):  # (the spine's round comes before ``rounds``)
        if r == 0 and model is not None:
            use, by_pose = model, dict(poses or {})
            entry = {"armature": "given", "segments": None, "fit_error_mm": None} if given else \
                {"armature": "spine", "segments": int(model.skeleton.n_parts), "fit_error_mm": None}
        elif chain is not None:
            use, by_pose, entry = _limb_rig(vs, faces, frames, refi, *chain)
        else:
            use, by_pose, entry = _rig_of(vs, faces, frames, refi, lambda_thr, limbs=limbs)
        per = _rig_round(tracker, use, by_pose, vs, frames, refi, by_frame, root, faces, weight,
                         None if progress is None else partial(_round_progress, progress, r + 1), spine=spine,
                         tracks_for=tracks_for, aside=aside)
        entry["worker_cpu_seconds"] = per.pop("worker_cpu_seconds", None)
        res = [f["rig_residual_mm"] for f in per["figures"].values()]
        entry["residual_mm"] = round(float(np.mean(res)), 4) if res else None
        history.append(entry)
        if best is not None and not (entry["residual_mm"] is not None and entry["residual_mm"] < 0.99 * best[1]):
            break
        if best is None or (entry["residual_mm"] is not None and entry["residual_mm"] < best[1]):
            best = (r, entry["residual_mm"] if entry["residual_mm"] is not None else np.inf, per)
        vs = np.stack([per["vertices"][k] for k in frames])
    return history, best


def _round_progress(progress, r: int, step: str, done: int, total: int) -> None:
    """``progress`` of round ``r`` (1-based, as ``rig_prior.kept_round`` counts): every round its own entry."""
    progress(f"{step} round {r}", done, total)


def _tracked_sequence(root: Path):
    """(track.json, frames, surfaces by frame, tracked vertices (T, V, 3), faces, reference position) of a
    tracked results directory; FileNotFoundError / ValueError when it is not tracked."""
    from pipeline.armature_files import load_sequence, tracked_meshes

    try:
        report = json.loads((root / "tracked" / "track.json").read_text())
        ref = int(report["reference_frame"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FileNotFoundError(f"{root}: no readable tracked/track.json ({exc}); run `stage track` first") from None
    frames, by_frame = surface_meshes(root, report.get("surfaces", "meshes"))
    vs, faces, numbers = load_sequence(tracked_meshes(root))
    if list(numbers) != list(frames) or ref not in frames:
        raise ValueError(f"{root}: tracked/ does not hold every frame of {report.get('surfaces', 'meshes')}/; "
                         "run `stage track` first")
    return report, frames, by_frame, vs, faces, frames.index(ref)
