"""Tracking a tracked multi-view take again with an armature as the articulated prior.

:func:`track_with_armature` (Tzionas & Gall 2016, §4 and the way out of its chicken-and-egg): the
armature built from the current tracking (:func:`pipeline.armature.build_armature`) tracks every
frame again (:class:`pipeline.armature_track.ArmatureTracker`), then the armature is built again
from that tracking, while a round helps. The frames are written as :mod:`pipeline.track_frames`
writes them, over the ``tracked/`` folder :func:`pipeline.track.track_results` made
(``stage track --armature-rounds``); docs/tracking.md, "Fast motion", has the figures.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import time
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.armature_track import ArmatureTracker
from pipeline.mesh_primitives import mesh_volume
from pipeline.run.context import submit_aside
from pipeline.track import _patch_labels, _spine_labels, _tracked_labels, mesh_data, spine_model, spine_starts
from pipeline.track_frames import surface_meshes, write_frame, write_report, write_round_segments
from pipeline.tracking import TemplateTracker

__all__ = ["track_with_armature", "armature_half_task", "spine_armature", "AUTO_RIG_ROUNDS", "ARMATURE_FIT_ROUNDS",
           "ARMATURE_ICP_POINTS", "SPINE_BONES"]

log = logging.getLogger("pipeline.track")


#: At most this many rounds of ``track_with_armature(rounds="auto")`` (``stage track --armature-rounds auto``).
AUTO_RIG_ROUNDS = 4
#: Rounds of the template fit from the armature's skinned pose (the default tracking's are
#: :attr:`pipeline.tracking.TemplateTracker.rounds`): it starts on the surface, where the later rounds
#: of a fit from the previous frame move nothing (docs/tracking.md, "Fast motion").
ARMATURE_FIT_ROUNDS = 8
#: Vertices the articulated ICP pairs and fits a frame's pose with (:class:`pipeline.armature_track.ArmatureTracker`):
#: a pose of 60 parts is determined many times over by 1000 (the same accuracy as 2000, a sixth less CPU;
#: docs/tracking.md, "Fast motion").
ARMATURE_ICP_POINTS = 1000
#: Bones per spine axis (limb, or the axis between two junctions) of the first round's armature
#: (:func:`spine_armature`): a limb's two halves turn on their own (six or three bones a limb track the fast
#: biped worse; docs/tracking.md, "The take's spine as the first armature").
SPINE_BONES = 2
_JOB_PARTS = "parameters track.armature_parts 'limbs'"  # parts="limbs" in a job's words (a warning's job_message)


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
    (:func:`spine_armature`: built from the visual hulls frame by frame, so it does not inherit the
    tracking's drift). A round
    helps when its armature explains the frames' surfaces better: the mean over frames of
    ``rig_residual_mm`` (:func:`pipeline.armature_track.surface_residual` of the armature's pose
    on each frame's surface; the surfaces, not the tracking the armature was built from, so the
    figure does not improve merely because the tracking was drawn to the armature) falls by at least
    ``1 %``. The rounds stop at the first that does not help, and the tracking of the best round
    is kept.

    Parameters
    ----------
    results_dir : path
        A multi-view results directory tracked by :func:`track_results`.
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
        :data:`SPINE_BONES` bones an axis, :func:`spine_armature`) when the take has a spine with
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
        before it; a process pool: :func:`armature_half_task` is its task) while this process tracks the
        other, as :func:`pipeline.track.track_results` splits the take; the same frames as in order here
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
        the spine has no axis for, :func:`_unclaimed_limbs`); then every limb takes back the body's vertices on
        its root tube (:func:`pipeline.template_labels.root_tubes`). Without labels or a usable spine one line says so
        and the parts come from the motion. Only as good as the labels' body: a limb the labels give the body
        moves with it (docs/tracking.md, "The round's armature from the labels").

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
    ``chain``: (labels, limb axes) the built armatures' parts follow (:func:`_limb_rig`), or None: the motion's."""
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


def _limbs(labels):
    """The template's labels (-1 the body, 0.. a limb) as the armature's :class:`pipeline.armature_limbs.VertexLimbs`."""
    if labels is None:
        return None
    from pipeline.armature_limbs import VertexLimbs

    return VertexLimbs(np.asarray(labels, dtype=np.int64), tuple(f"limb{i}" for i in range(int(labels.max()) + 1)))


def _rig_of(vs: np.ndarray, faces: np.ndarray, frames: list[int], refi: int, lambda_thr: float, limbs=None):
    """The armature of a tracking, rest frame the reference: (model, poses by frame, its report entry).
    ``limbs``: every vertex's limb (no segment spans two, :func:`pipeline.armature.build_armature`), or None."""
    from pipeline.armature import build_armature

    # with the peel: a prior tolerates parts cut in two (the paper's over-segmentation), not parts fused
    rig = build_armature(vs, faces, reference=refi, peel_parts=True, lambda_thr=lambda_thr, limbs=limbs)
    entry = {"armature": "tracking", "segments": int(rig.segmentation.n_segments),
             "fit_error_mm": round(float(rig.fit.errors.mean()), 4)}
    return rig.model, dict(zip(frames, rig.fit.poses)), entry


def _limb_chain(root: Path, labels, refi: int, n_frames: int):
    """``parts="limbs"``: (labels, the spine's limb axes at the reference position ``refi``), or None (one line
    says why) without labels or a spine of the take's frames that sees every limb of the labels there."""
    from pipeline.armature_files import spine_limb_axes
    from pipeline.spine_format import SpineFormatError, read_spine

    why = None
    if labels is None:
        why = "no labels"
    else:
        try:
            spine = read_spine(root / "spine.json")
            if spine.frame_count != n_frames:
                raise ValueError(f"it has {spine.frame_count} frames, the take {n_frames}")
            if not _body_measurable(labels):
                raise ValueError("the labels' body has too few vertices")
            return labels, spine_limb_axes(spine, labels, refi)
        except (OSError, SpineFormatError, ValueError) as exc:
            why = f"no usable spine.json ({exc})"
    log.warning("parts='limbs': the armature's parts come from the motion: %s", why,
                extra={"job_message": f"{_JOB_PARTS}: the armature's parts come from the motion: {why}"})
    return None


def _surface_points(by_frame: dict, frames: list[int]):
    """Every frame's surface vertices in ``frames`` order, or None (one line says why)."""
    from pipeline.meshio import load_mesh

    try:
        return [load_mesh(by_frame[k], largest=False)[0] for k in frames]
    except (OSError, ValueError) as exc:
        log.warning("parts='limbs': the surfaces cannot be read (%s); the armature's labels are the tracking's", exc,
                    extra={"job_message": f"{_JOB_PARTS}: the surfaces are unreadable ({exc}): the tracking's labels"})
        return None


def _surface_labels(root: Path, template: np.ndarray, faces: np.ndarray, refi: int, surfaces: list,
                    fallback: np.ndarray) -> np.ndarray:
    """``labels="spine"`` for the armature's parts: :func:`pipeline.template_labels.template_labels` with every frame's
    surface (the body also split by its motion there), or ``fallback`` (one line says why)."""
    from pipeline.template_labels import template_labels

    try:
        return np.asarray(template_labels(root, template, faces, reference=refi, surfaces=surfaces), dtype=np.int64)
    except ValueError as exc:
        log.warning("parts='limbs': the armature's labels are the tracking's (no labels from the surfaces: %s)", exc,
                    extra={"job_message": f"{_JOB_PARTS}: the tracking's labels (none from the surfaces: {exc})"})
        return fallback


def _unclaimed_limbs(vertices, faces, labels, axes, surfaces, *, reference: int = 0, keep: float = 0.5,
                    rounds: int = 3) -> tuple[np.ndarray, list]:
    """Pieces of the body that do not move with it, as limbs of their own (a limb the spine has no axis for).

    The body's rigid motion (the best rigid motion of its tracked vertices from the ``reference`` frame,
    :func:`pipeline.rigid_parts.rigid_motions`, refitted ``rounds`` times to the ``keep`` share of them it
    carries best) is applied to every body vertex; those it keeps further than one mesh edge (the mean edge of the
    template; root mean square over the frames) from the frame's surface, and that the motion of their nearest
    labelled limb does not keep within one mesh edge either (:func:`_claimed`: a limb the piece touches, as a forearm
    lying against a thigh, is not fused into it), form connected pieces over the mesh, and a
    piece with at least as many vertices as the smallest labelled limb (and leaving the body at least 8, to measure
    its noise on) becomes a limb, its axis the line from
    the centroid of its vertices next to the rest of the body to its vertex farthest from there.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
        The tracked template.
    faces : (F, 3) int ndarray
    labels : (V,) int ndarray
        Limb of every vertex (index into ``axes``) or -1 for the body.
    axes : list of (n, 3) float ndarray
        Every limb's axis at frame ``reference``.
    surfaces : list of (n_t, 3) float ndarray
        Every frame's surface vertices.
    reference : int
    keep : float
        Share of the body's vertices its motion is refitted to.
    rounds : int

    Returns
    -------
    labels : (V,) int64 ndarray
        With the new limbs numbered after the given ones.
    axes : list of (n, 3) float ndarray
        The given axes, then the new limbs'.
    """
    from scipy.spatial import cKDTree

    from pipeline.mesh_primitives import edge_components
    from pipeline.rigid_parts import rigid_motions

    vs, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    out, axes = np.asarray(labels, dtype=np.int64).copy(), list(axes)
    body = np.flatnonzero(out == -1)
    sizes = np.bincount(out[out >= 0], minlength=len(axes))
    if not _body_measurable(out) or not (sizes > 0).any() or len(surfaces) != len(vs):
        return out, axes
    V = vs[reference]
    ids = body
    for _ in range(rounds):  # the body's motion, from the share of its vertices that follows it best
        R, t = rigid_motions(vs[:, ids], reference=reference)
        gap = np.linalg.norm(np.einsum("tij,vj->tvi", R, V[body]) + t[:, None] - vs[:, body], axis=2).mean(0)
        ids = body[np.argsort(gap)[:max(3, int(keep * len(body)))]]
    trees = [cKDTree(S) for S in surfaces]
    rms = _surface_rms(*rigid_motions(vs[:, ids], reference=reference), V[body], trees)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edge = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).mean()
    off = np.zeros(len(V), dtype=bool)
    off[body[rms > edge]] = True
    candidates = np.flatnonzero(off)
    off[candidates[_claimed(vs, out, candidates, trees, reference, edge)]] = False
    inner = e[off[e[:, 0]] & off[e[:, 1]]]
    piece = edge_components(inner, len(V))
    rest = (out == -1) & ~off
    for p in np.unique(piece[off]):
        mine = off & (piece == p)
        if mine.sum() < sizes[sizes > 0].min() or not _body_measurable(np.where(mine, len(axes), out)):
            continue
        next_to_body = np.unique(e[mine[e[:, 0]] & rest[e[:, 1]], 0])
        if len(next_to_body) == 0:
            continue
        root = V[next_to_body].mean(0)
        far = V[mine][np.argmax(np.linalg.norm(V[mine] - root, axis=1))]
        out[mine] = len(axes)
        axes.append(np.stack([root, far]))
    return out, axes


def _rooted(template: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The armature's labels with the limbs' roots the body holds given back
    (:func:`pipeline.template_labels.root_tubes`), unless the body would keep too few vertices to measure the cuts'
    noise on (:func:`_body_measurable`)."""
    from pipeline.template_labels import root_tubes

    out = root_tubes(template, faces, labels)
    return out if _body_measurable(out) else labels


def _body_measurable(labels: np.ndarray) -> bool:
    """Whether the labels' body keeps enough vertices (twice :data:`pipeline.limb_segments.MIN_VERTICES`) for the
    round's :func:`pipeline.limb_segments.limb_segments` to measure the cuts' noise on."""
    from pipeline.armature_limbs import BODY
    from pipeline.limb_segments import MIN_VERTICES

    return bool((np.asarray(labels) == BODY).sum() >= 2 * MIN_VERTICES)


def _claimed(vs: np.ndarray, labels: np.ndarray, body: np.ndarray, trees: list, reference: int,
             edge: float) -> np.ndarray:
    """(len(body),) bool: the body vertices ``body`` that the rigid motion of their nearest labelled limb keeps within
    ``edge`` of every frame's surface (KD-trees ``trees``; root mean square over the frames); a limb of fewer than 3
    vertices is nobody's nearest. A limb's motion is that of its proximal half
    (:func:`pipeline.template_labels.proximal_half`, as :func:`pipeline.template_labels.template_labels` takes it),
    fitted to its tracked vertices ``vs`` (T, V, 3) from frame ``reference``."""
    from pipeline.rigid_parts import rigid_motions
    from pipeline.template_labels import nearest_limb, proximal_half

    V = vs[reference]
    near = nearest_limb(V[body], V, labels, min_vertices=3)
    out = np.zeros(len(body), dtype=bool)
    for k in np.unique(near[near >= 0]):
        mine = np.flatnonzero(near == k)
        rms = _surface_rms(*rigid_motions(vs[:, proximal_half(V, labels, k)], reference=reference), V[body[mine]],
                           trees)
        out[mine[rms <= edge]] = True
    return out


def _surface_rms(R: np.ndarray, t: np.ndarray, X: np.ndarray, trees: list) -> np.ndarray:
    """(n,): the distance of the points ``X`` carried by the rigid motions ``R`` (T, 3, 3), ``t`` (T, 3) from every
    frame's surface (KD-trees ``trees``), root mean square over the frames."""
    carried = np.einsum("tij,vj->tvi", R, X) + t[:, None]
    return np.sqrt(np.mean([tree.query(c)[0] ** 2 for tree, c in zip(trees, carried)], axis=0))


def _limb_rig(vs: np.ndarray, faces: np.ndarray, frames: list[int], refi: int, labels: np.ndarray, axes: list):
    """The armature of a tracking from the template's labels: the body one part, every limb a chain of the intervals
    :func:`pipeline.limb_segments.limb_segments` cuts along its axis, rigid (``entry["cut"]``); -> as :func:`_rig_of`. The
    cuts' noise ratio is measured on the body (``limb_segments``' default); ``stage armature --parts limbs`` measures it on
    every limb (``rho="limb"``), not better for the round on every take (docs/tracking.md, "The round's armature from the labels")."""
    from pipeline.armature_fit import fit_sequence
    from pipeline.armature_track import segment_armature
    from pipeline.limb_segments import limb_segments

    seg = limb_segments(vs, labels, axes, reference=refi)
    parents = np.zeros(int(seg.max()) + 1, dtype=np.int64)
    parents[0] = -1  # the body; a limb's first interval hangs from it, every other from the one before
    for k in range(len(axes)):
        mine = np.unique(seg[labels == k])
        parents[mine[1:]] = mine[:-1]
    model = segment_armature(vs[refi], faces, seg, parents, motion=vs, reference=refi)
    fit = fit_sequence(model, vs)
    entry = {"armature": "limbs", "segments": len(parents), "fit_error_mm": round(float(fit.errors.mean()), 4), "cut": seg}
    return model, dict(zip(frames, fit.poses)), entry


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
    """One half of the frames of a round of :func:`track_with_armature` (from the reference frame), tracked in a worker
    process (``executor``): the tracker, the surfaces, the spine's steps and the colour tracks set up here
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


def _spine_rig(root: Path, frames: list[int], template: np.ndarray, faces: np.ndarray, refi: int):
    """The take's spine rig as the first round's armature (:func:`spine_armature`, rest: ``template`` at
    the reference position ``refi``), or None (one line says why) without a spine of every frame with
    every limb seen there."""
    from pipeline.armature_spine import NoCompleteFrameError, rigged_model
    from pipeline.spine_format import SpineFormatError, read_spine

    path = root / "spine.json"
    try:
        spine = read_spine(path)
        if spine.frame_count != len(frames):
            raise ValueError(f"it has {spine.frame_count} frames, the take {len(frames)}")
        return spine_armature(rigged_model(spine, template, faces, reference=refi, segments=SPINE_BONES))
    except (OSError, SpineFormatError, NoCompleteFrameError, ValueError) as exc:
        log.warning("the first armature is built from the tracking: no usable spine in %s (%s)", path, exc,
                    extra={"job_message": f"parameters track.spine_armature: the first armature is built from the "
                           f"tracking: no usable spine in {path} ({exc})"})
        return None


def _spine_steps(root: Path, frames: list[int], by_frame: dict, template: np.ndarray):
    """``step(k, k_prev)``: how the spine's skinned pose of the template moves from frame ``k_prev``
    to ``k`` (the spine's limb motion, :func:`spine_starts`), or None without a usable spine of
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


def spine_armature(rigged):
    """The take's spine rig as an armature: the first round's of :func:`track_with_armature`.

    The spine (Brostow et al. 2004) is built from every frame's visual hull, so its armature does not
    inherit a tracking's drift, and its parts follow the limbs (a forearm that touches a thigh in the
    reference frame still belongs to the arm's axis).

    Parts: one per bone of the rig (:class:`pipeline.armature_spine.RiggedModel`: every spine axis cut into
    equal bones), turning about the bone's first joint; a part hangs from the part of the nearest bone joint
    above its joint in the rig's joint tree, or from the root (the root junction's rigid motion). Weights:
    rigid; every vertex moves with one bone, the nearest in the rest pose (distance to the bone's segment)
    of the spine axis that carries the largest share of its bone heat weights (heat weights themselves
    spread a limb's bones over the body and over a touching limb).

    Parameters
    ----------
    rigged : pipeline.armature_spine.RiggedModel
        The spine's rig bound to the template at its rest (reference) frame.

    Returns
    -------
    pipeline.armature_fit.ArticulatedModel
    """
    from pipeline.armature_fit import ArticulatedModel
    from pipeline.armature_skeleton import ArticulatedSkeleton
    from pipeline.armature_spine import RiggedModel
    from pipeline.skinning import segment_distances

    if not isinstance(rigged, RiggedModel):
        raise ValueError(f"rigged must be a RiggedModel, got {type(rigged).__name__}")
    rig = rigged.rig
    bones = np.asarray(rig.bones, dtype=np.int64).reshape(-1, 2)
    if len(bones) == 0:
        raise ValueError("rigged has no bones")
    bone_of = np.full(rig.n_joints, -1)
    bone_of[bones[:, 0]] = np.arange(len(bones))
    part = np.zeros(rig.n_joints, dtype=np.int64)  # parents come first: a joint's part is known before its children's
    part_joint = [0]
    for j in range(1, rig.n_joints):
        if bone_of[j] >= 0:
            part_joint.append(j)
            part[j] = len(part_joint) - 1
        else:
            part[j] = part[rig.parents[j]]
    part_joint = np.asarray(part_joint)
    part_parent = np.r_[-1, part[rig.parents[part_joint[1:]]]]
    articulation = np.zeros(rig.n_joints, dtype=bool)
    articulation[part_joint[1:]] = True
    skeleton = ArticulatedSkeleton(names=tuple(rig.names), parents=np.asarray(rig.parents), rest=np.asarray(rig.rest, float),
                                   articulation=articulation, segment_pairs=(None,) * rig.n_joints, part=part,
                                   part_joint=part_joint, part_parent=part_parent, bones=bones,
                                   placement=(None,) * rig.n_joints)
    axes = sorted(set(rig.element[j] for j in bones[:, 0]))
    axis = np.array([axes.index(rig.element[j]) for j in bones[:, 0]])
    share = np.zeros((len(rigged.vertices), len(axes)))
    np.add.at(share, (np.repeat(np.arange(len(share)), rigged.joints.shape[1]), axis[bone_of[rigged.joints]].ravel()),
              rigged.weights.ravel())
    dist = segment_distances(rigged.vertices, rig.rest[bones[:, 0]], rig.rest[bones[:, 1]])
    dist[axis[None, :] != share.argmax(axis=1)[:, None]] = np.inf
    return ArticulatedModel(np.asarray(rigged.vertices, float), np.asarray(rigged.faces, np.int64), skeleton,
                            dist.argmin(axis=1)[:, None], np.ones((len(share), 1)))
