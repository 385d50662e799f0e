"""Template tracking of a processed multi-view take: ``tracked/NNNNNN.ply`` in the template's vertex order.

:func:`track_results` (Tzionas & Gall 2016, §3): the template is the reference frame's surface (or
a given mesh), the data every frame's surface ``meshes/frame_NNNNNN.ply`` (or the surfaces carved
across time, ``carved/``); every template vertex may pair (the data are whole surfaces). The two
halves from the reference frame run at once on an executor (:func:`track_chain_task`); the colour
images of the take add feature tracks across every camera's viewing ray.
:func:`pipeline.track_armature.track_with_armature` tracks a tracked take again with an armature as the
articulated prior (``stage track RESULTS_DIR`` and a job's track step run one such round after this tracking by
default; ``--armature-rounds 0``: this tracking alone).

Frames are written and resumed as :mod:`pipeline.track_frames` does for both forms of tracking
(one RGB-D camera: :mod:`pipeline.track_rgbd`); ``tracked/track.json`` records the settings, the
skipped frames and per-frame fit figures, ``tracked/labels.npy`` the template's labels when it was tracked
with them (``labels=``; :func:`pipeline.track_frames.read_labels` reads them back).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.mesh_primitives import vertex_normals
from pipeline.run.context import once_per_run, submit_aside, warn_once
from pipeline.run.settings import array_digest, file_digest
from pipeline.track_colour import colour_take, multiview_colour, multiview_tracks_for
from pipeline.track_frames import (
    labels_digest,
    load_template,
    predictor,
    read_labels,
    remove_tracking,
    run_frames,
    start_over_if_changed,
    surface_meshes,
    tracked_path,
    write_labels,
    write_report,
)
from pipeline.tracking import TemplateTracker, TrackingError
from pipeline.tracking_patches import _check_labels

__all__ = ["track_results", "track_chain_task", "spine_model", "spine_starts", "mesh_data", "tracked_path",
           "remove_tracking", "TrackingError", "check_track_options"]

log = logging.getLogger("pipeline.track")


def spine_model(root: Path, frames: list[int], by_frame: dict, template):
    """(reference position, RiggedModel) of the take's spine, or None without a usable spine."""
    from pipeline.armature_spine import NoCompleteFrameError, reference_frame, rigged_model
    from pipeline.meshio import load_mesh
    from pipeline.spine_format import read_spine

    path = root / "spine.json"
    if not path.is_file():
        return None
    try:
        spine = read_spine(path)
        if spine.frame_count != len(frames):
            return None
        ref = reference_frame(spine)
        V, F = load_mesh(by_frame[frames[ref]], largest=True) if template is None else load_template(template)
        return ref, rigged_model(spine, V, F, reference=ref)
    except (NoCompleteFrameError, ValueError, KeyError) as exc:
        log.warning("tracking without the spine's pose (%s)", exc)
        return None


def check_track_options(*, carve: int = 0, carve_margin: float | None = None, armature_rounds: int | str = 0,
                        spine_armature: bool = False, armature_parts: str = "motion", labels: bool = False,
                        names: dict[str, str] | None = None) -> None:
    """The rules between ``stage track RESULTS_DIR``'s options, checked before any work: an option that would do
    nothing is refused, not ignored. ``stage track`` and an API job's ``parameters.track`` check theirs here.

    Parameters
    ----------
    carve : int
        Rounds of the carving (``--carve``).
    carve_margin : float, optional
        The carving's silhouettes' margin (``--carve-margin``): needs ``carve``.
    armature_rounds : int or "auto"
        Armature rounds (``--armature-rounds``).
    spine_armature : bool
        The take's spine as the first round's armature (``--spine-armature``): needs ``armature_rounds``.
    armature_parts : str
        Where every round's armature gets its parts (``--armature-parts``): other than ``"motion"`` needs
        ``armature_rounds`` and ``labels``.
    labels : bool
        Whether the tracking has the template's limb/body labels (``--labels``; a job's ``track.labels``, or its
        ``rig.parts`` "limbs", whose tracking takes them: :attr:`pipeline.process.ProcessParams.track_labels`).
    names : dict, optional
        The caller's name of each option (``{"carve": "--carve"}``) in the messages; default its keyword.

    Raises
    ------
    ValueError
        One line naming the options as the caller does; a rule's missing option is named alone (what to add).
    """
    name = {k: k for k in ("carve", "carve_margin", "armature_rounds", "spine_armature", "armature_parts", "labels")}
    name.update(names or {})
    if carve_margin is not None and not carve:
        raise ValueError(f"{name['carve_margin']} needs {name['carve']} (the margin of the carving's silhouettes)")
    if spine_armature and not armature_rounds:
        raise ValueError(f"{name['spine_armature']} needs {name['armature_rounds']} (it is the first of the armature "
                         "rounds)")
    if armature_parts != "motion" and not (armature_rounds and labels):
        missing = " and ".join(name[k] for k, given in (("armature_rounds", armature_rounds), ("labels", labels))
                               if not given)
        raise ValueError(f"{name['armature_parts']} {armature_parts!r} needs {missing} (its parts are the labels' body "
                         "and limbs)")


@once_per_run()  # (what its halves say again of the surfaces: once)
def track_results(results_dir, *, template=None, progress=None, gamma=None, gate=None, spine_init: bool = False,
                  choose: bool = True, predict: bool = True, colour: bool = False, shape_memory: bool = False,
                  surfaces: str = "meshes", executor=None, labels=None) -> dict:
    """Track a template through the surfaces of a processed multi-view take.

    With the take's spine (``spine.json``) the template is the spine's reference frame's
    surface and tracking runs from that frame forwards and backwards. Every frame has two
    starts then: the constant-velocity prediction (or the previous frame) and the previous
    frame moved as the spine's skinned pose of the template moves (linear blend skinning);
    each patch of the template starts from the one this frame's surface explains better
    (``choose``, :func:`pipeline.tracking.choose_start`). Without a spine: the first frame's
    surface, and every frame starts from the prediction (or the previous frame).

    The two halves, forwards and backwards from the reference frame, depend on nothing but
    that frame's fit: with ``executor`` the backward half runs there as one task while this
    process tracks the forward half (the same vertices as in order, in about half the wall
    time). Chunks that start further from the reference frame would start from the spine's
    skinned pose, which is not accurate enough (``spine_init`` below).

    Parameters
    ----------
    results_dir : path
        Output of ``stage process`` (``meshes/frame_NNNNNN.ply``).
    template : path or (vertices, faces), optional
        Default: the reference (or first) frame's surface.
    progress : callable(step, done, total), optional
    gamma, gate : float, optional
        See :class:`pipeline.tracking.TemplateTracker`.
    spine_init : bool
        Start every patch of every frame from the spine's skinned motion (it takes precedence
        over ``choose``). Off by default: on slow motions the skinned pose's step from one frame
        to the next is much further from the true step than the constant-velocity prediction; on
        a fast gallop it is the other way round for the legs (docs/tracking.md, "Spine-posed starts").
    choose : bool
        With a spine, choose per patch and frame between the prediction and the skinned start
        by the gated closest-point residual against the frame's surface, both ways
        (default). False: the prediction only.
    predict : bool
        Start every frame from the constant-velocity prediction of the two frames before
        (:func:`pipeline.tracking_patches.predict_motion`) instead of the previous frame.
    colour : bool
        Follow the template's visible vertices in every camera's images too (feature tracks
        across each camera's viewing ray, :func:`pipeline.track_colour.multiview_colour`) when the take that
        ``process.json`` names is still there: they hold the slide along the surface that
        closest-point pairs leave free. Each track's window is warped by that camera's
        projection of the frame's start, on the camera's keyed object pixels only
        (:func:`pipeline.colour_tracks.colour_tracks`, ``faces=``). Off by default: it helps the
        capsule creatures but not every take (docs/tracking.md, "Colour feature tracks (multi-view)").
    shape_memory : bool
        Keep the previous frame's shape in the rigid prior, placed by overlapping blended
        patches (``TemplateTracker(prior="previous")``, what one RGB-D camera always uses)
        instead of each round's own start. Off by default: it holds the volume and helps where
        the surfaces are close to the truth, but on the hull's surfaces it is mixed
        (docs/tracking.md, "The tracker apart from the surfaces").
    surfaces : {"meshes", "carved"}
        The per-frame surfaces tracked (and the template's source): ``stage process``'s
        ``meshes/``, or the surfaces carved across time with an earlier tracking's motion
        (``carved/``, :func:`pipeline.carve.carve_results`; ``stage track --carve``).
    executor : concurrent.futures.Executor, optional
        Runs the backward half (a process pool: :func:`track_chain_task` is its task).
    labels : "spine", (V,) int ndarray or callable, optional
        The template's limb (``0, 1, ...``) or body (``-1``) of every vertex, or
        ``labels(vertices, faces, frame)`` giving them for the template this call picks (``frame``
        its source frame): the template's rigid patches then never span two parts, the body is one
        patch and every limb is cut on its own grid (``TemplateTracker(patch_labels=)``).
        ``"spine"``: the labels of the take's spine and the template's own sections
        (:func:`pipeline.template_labels.template_labels`; ``stage track --labels``) when the take has a
        usable spine, else none (one line says so). Default: the patches follow the surface alone.

    Returns
    -------
    dict
        The report written to ``tracked/track.json`` (``worker_cpu_seconds``: the CPU seconds
        of the backward half when another process tracked it).
    """
    if not isinstance(shape_memory, (bool, np.bool_)):
        raise ValueError(f"shape_memory must be True or False, got {shape_memory!r}")
    if surfaces not in ("meshes", "carved"):
        raise ValueError(f"surfaces must be 'meshes' or 'carved', got {surfaces!r}")
    root = Path(results_dir)
    frames, by_frame = surface_meshes(root, surfaces)
    loaded = None if template is None else load_template(template)  # a bad template is the user's error, said once
    name = None if template is None else ("array" if isinstance(template, (tuple, list)) else str(template))
    skinned = spine_model(root, frames, by_frame, loaded)
    if skinned is None and (spine_init or not choose):  # asked of a spine the take does not have
        asked = "spine_init" if spine_init else "choose=False"
        warn_once(log, "%s has no effect: no usable spine.json in %s, every frame starts from the prediction",
                  f"{asked} (--spine-init)" if spine_init else f"{asked} (--prediction-only)", root,
                  extra={"job_message": f"{asked} has no effect: no usable spine.json in {root}, every frame starts "
                         "from the prediction"})
    ref, V0, F0, source = _multiview_template(frames, by_frame, skinned, loaded, name)
    prior = "previous" if shape_memory else "round"
    source_of_labels = labels if isinstance(labels, str) else None if labels is None else "given"
    if isinstance(labels, str):
        labels = _spine_labels(root, labels, None if skinned is None else skinned[0])
    patch_labels = _patch_labels(labels, V0, F0, frames[ref])
    tracker = TemplateTracker(V0, F0, gamma=gamma, gate=gate, prior=prior, patch_labels=patch_labels)
    use_spine = skinned is not None and bool(spine_init)
    spine_start = "all" if use_spine else "choose" if skinned is not None and choose else "none"
    with colour_take(root, bool(colour)) as take:  # opened once in this process (a worker opens its own)
        report = {"mode": "multi-view", "template": source, "template_sha256": array_digest(V0, F0),
                  "vertices": int(len(V0)), "gamma": tracker.gamma,
                  "gate_mm": tracker.gate, "rounds": tracker.rounds, "solver": tracker.system.backend,
                  "reference_frame": frames[ref], "spine_init": use_spine, "spine_start": spine_start,
                  "predict": bool(predict), "prior": tracker.prior, "colour_tracks": take is not None,
                  "surfaces": surfaces, "rig_rounds": 0, "patches": tracker.patch_rule,
                  "slowed_starts": spine_start == "choose",
                  "patch_labels": None if patch_labels is None else source_of_labels, "skipped": [], "frames": {}}
        if patch_labels is not None:  # the patches, and so every frame, depend on them
            report["patch_labels_sha256"] = labels_digest(patch_labels)
        write_labels(root, patch_labels)  # what later readers use (tracked/labels.npy), none: an old file goes
        if surfaces == "carved":  # carved with an earlier tracking's motion: their digest says which
            report["surfaces_sha256"] = file_digest(root / surfaces / "carve.json")
        if spine_start != "none":  # every frame's start depends on the spine then
            report["spine_sha256"] = file_digest(root / "spine.json")
        kept = start_over_if_changed(root, report)
        chain = {"root": str(root), "template": (V0, F0), "gamma": tracker.gamma, "gate": tracker.gate,
                 "spine_start": spine_start, "spine_template": loaded, "predict": bool(predict),
                 "colour": report["colour_tracks"], "prior": prior, "surfaces": surfaces,
                 "patch_labels": patch_labels}
        first = _track_reference(tracker, (V0, F0), frames[ref], root, report, by_frame=by_frame, progress=progress,
                                 total=len(frames))
        _track_halves({**chain, "prev": first, "prev_frame": frames[ref]}, frames, ref, report, tracker=tracker,
                      by_frame=by_frame, skinned=skinned, progress=progress, executor=executor, take=take)
    report["frames"] = {**kept, **report["frames"]}
    report["frames"] = {str(k): report["frames"][str(k)] for k in frames if str(k) in report["frames"]}
    write_report(root, report)
    return report


def _spine_labels(root: Path, labels: str, reference: int | None):
    """``labels="spine"``: the callable giving the template's labels from the take's spine
    (:func:`pipeline.template_labels.template_labels`, the template in the pose of the spine's frame
    ``reference``), or None without a usable spine (``reference`` None; said once)."""
    if labels != "spine":
        raise ValueError(f"labels must be 'spine', an array or a callable, got {labels!r}")
    if reference is None:
        warn_once(log, "labels='spine' (--labels) has no effect: no usable spine.json in %s, the patches follow the "
                  "surface alone", root, extra={"job_message": f"the template's labels (parameters track.labels, or "
                                                f"rig.parts 'limbs') are not used: no usable spine.json in {root}, the "
                                                "patches follow the surface alone"})
        return None

    def spine_labels(vertices, faces, frame):
        from pipeline.template_labels import template_labels

        try:
            return template_labels(root, vertices, faces, reference=reference)
        except ValueError as exc:
            log.warning("the template's patches follow the surface alone: no labels from the spine (%s)", exc)
            return None

    return spine_labels


def _tracked_labels(root: Path, report: dict, labels, n_vertices: int):
    """``labels="spine"`` of a tracking tracked again: the labels its ``track.json`` (``report``) says it used with
    ``"spine"``, read back (``tracked/labels.npy``, :func:`pipeline.track_frames.read_labels`), or None: the
    caller computes them again (:func:`_spine_labels`; a file that is not them is one line)."""
    if not (isinstance(labels, str) and labels == "spine" and report.get("patch_labels") == "spine"):
        return None
    try:
        return read_labels(root, report, n_vertices)
    except ValueError as exc:
        log.warning("the template's labels are computed again from the spine: %s", exc)
        return None


def _patch_labels(labels, vertices, faces, frame: int):
    """The template's (V,) labels of :func:`track_results` (``labels`` given or called), or None."""
    if labels is None:
        return None
    out = labels(vertices, faces, frame) if callable(labels) else labels
    if out is None:  # the callable found none
        return None
    return _check_labels(out, len(vertices))


def _multiview_template(frames: list[int], by_frame: dict, skinned, loaded, name):
    """(reference index into ``frames``, template vertices, faces, its source for the report);
    ``loaded``: the user's template (vertices, faces), or None, and ``name`` its source."""
    from pipeline.meshio import load_mesh

    if skinned is not None:
        source = str(by_frame[frames[skinned[0]]]) if loaded is None else name
        return skinned[0], skinned[1].vertices, skinned[1].faces, source
    if loaded is None:
        V0, F0 = load_mesh(by_frame[frames[0]], largest=True)
        return 0, V0, F0, str(by_frame[frames[0]])
    return 0, loaded[0], loaded[1], name


def _track_reference(tracker, template: tuple, frame: int, root: Path, report: dict, *, by_frame: dict, progress,
                     total: int) -> np.ndarray:
    """Fit the reference frame (or keep its tracked file); -> where both halves start: that fit,
    or the template when the frame has no surface (one warning says so)."""
    V0, F0 = template
    first = run_frames(tracker, [frame], root, F0, report, data_for=mesh_data(by_frame),
                        visible_for=lambda e: None, progress=progress, start=0, prev=V0.copy(), total=total)
    if frame in report["skipped"]:
        log.warning("reference frame %d has no surface (%s has no triangles): both halves start from the template",
                    frame, by_frame[frame])
    return first


def _track_halves(chain: dict, frames: list[int], ref: int, report: dict, *, tracker, by_frame: dict, skinned,
                  progress, executor, take=None) -> None:
    """The frames after the reference frame here, those before it (backwards) on ``executor`` at the
    same time, or here afterwards; their figures merged into ``report``. Progress counts the
    worker's frames by the tracked files it writes (:func:`_written_count`), also while this
    process waits for it. ``take``: this process's open (reader, cameras) of the colour tracks
    (:func:`pipeline.track_colour.colour_take`), or None."""
    forward, backward = frames[ref + 1:], frames[:ref][::-1]
    total = len(frames)
    later = submit_aside(executor if backward else None, partial(track_chain_task, {**chain, "frames": backward}),
                         unavailable="the second tracking process is not available ({exc}); tracking the frames "
                                     "before the reference here", logger=log)
    worker_done = _written_count(Path(chain["root"]), backward) if later is not None else (lambda: 0)

    def progress_both(step, done, n):
        progress(step, min(done + worker_done(), n), n)

    def here(part, start, bar):
        return _track_chain({**chain, "frames": part}, tracker=tracker, by_frame=by_frame, frame_list=frames,
                            skinned=skinned, progress=bar, start=start, total=total, take=take)

    _merge_chain(report, here(forward, 1, progress_both if progress is not None else None))
    if backward and later is None:
        _merge_chain(report, here(backward, 1 + len(forward), progress))
    if later is None:
        return
    while not later.wait(_POLL_SECONDS):
        if progress is not None:
            progress_both("track", 1 + len(forward), total)
    try:
        part = later.result()
    except cf.BrokenExecutor as exc:  # the worker process was killed: its frames are tracked here (resuming its files)
        log.warning("the second tracking process stopped (%s); tracking the frames before frame %d here", exc, frames[ref])
        part = here(backward, 1 + len(forward), progress)
    if later.cpu_seconds is not None:  # a thread's CPU seconds are already this process's
        report["worker_cpu_seconds"] = round(later.cpu_seconds, 3)
    _merge_chain(report, part)
    if progress is not None:
        progress("track", total, total)


#: Seconds between two looks at the worker's tracked files while this process waits for it.
_POLL_SECONDS = 0.5
#: Frames looked at past a missing tracked file (a frame without a surface writes none).
_LOOK_AHEAD = 4


def _written_count(root: Path, frames: list[int]):
    """``count()`` -> how many of ``frames``, tracked in this order by another process, are done,
    judged by their tracked files. Linear in the frames: a count looks at the files from the first
    missing one of the last count on, and past a missing file (a frame without a surface, or the
    one being tracked) at no more than ``_LOOK_AHEAD`` more."""
    paths = [tracked_path(root, k) for k in frames]
    done = 0

    def count() -> int:
        nonlocal done
        i = done
        while i < len(paths):
            if paths[i].is_file():
                i += 1
                continue
            ahead = [j for j in range(i + 1, min(i + 1 + _LOOK_AHEAD, len(paths))) if paths[j].is_file()]
            if not ahead:
                break
            i = ahead[-1] + 1
        done = i
        return i

    return count


def mesh_data(by_frame: dict):
    """``data_for(k, previous)`` of a multi-view take: frame ``k``'s surface and its normals (None: no surface)."""
    from pipeline.meshio import load_mesh

    def data_for(k, previous=None):
        v, f = load_mesh(by_frame[k], largest=False)
        if len(f) == 0:
            return None
        return v, vertex_normals(v, f), None

    return data_for


def spine_starts(model, frames: list[int]):
    """``init_for(k, k_prev, prev)``: the previous frame moved as the spine's skinned pose of the template moves."""
    pos = {k: i for i, k in enumerate(frames)}
    lbs: dict = {}

    def pose(k):
        if k not in lbs:
            lbs[k] = model.deform(pos[k])
        return lbs[k]

    return lambda k, k_prev, prev: prev + (pose(k) - pose(k_prev))


def _chooser(tracker):
    """``choose(candidates, points, normals)`` -> (start, share of the patches that took the second
    candidate): :func:`pipeline.tracking.choose_start` over the tracker's patches and gate."""
    from pipeline.tracking import choose_start

    def choose(cands, pts, nrm):
        start, chosen = choose_start(cands, pts, nrm, tracker.faces, tracker.patches, gate=tracker.gate,
                                     smoother=tracker.smoother, corners=tracker.corner_sum)
        return start, float(np.mean(chosen == 1))

    return choose


def _track_chain(chain: dict, *, tracker=None, by_frame=None, frame_list=None, skinned=None, progress=None, start=0,
                 total=None, take=None) -> dict:
    """Track ``chain["frames"]`` in order from ``chain["prev"]`` (the fit of ``chain["prev_frame"]``);
    -> {"frames": per-frame figures, "skipped": frames without a surface}. The colour tracks
    (``chain["colour"]``) read ``take`` (an open (reader, cameras)), else open the take here."""
    root = Path(chain["root"])
    V0, F0 = chain["template"]
    if by_frame is None:
        frame_list, by_frame = surface_meshes(root, chain.get("surfaces", "meshes"))
    if tracker is None:
        tracker = TemplateTracker(V0, F0, gamma=chain["gamma"], gate=chain["gate"], prior=chain["prior"],
                                  patch_labels=chain.get("patch_labels"))
    init_for = None
    if chain["spine_start"] in ("all", "choose"):
        if skinned is None:
            skinned = spine_model(root, frame_list, by_frame, chain["spine_template"])
        init_for = spine_starts(skinned[1], frame_list) if skinned is not None else None
    part = {"skipped": [], "frames": {}}
    tolerance = 0.3 * tracker.gate
    corners = tracker.corner_sum
    colour = contextlib.nullcontext(multiview_tracks_for(*take, F0, tolerance, corners=corners)) if take is not None \
        else multiview_colour(root, F0, tolerance, enabled=chain.get("colour", False), corners=corners)
    with colour as tracks_for:
        run_frames(tracker, list(chain["frames"]), root, F0, part, data_for=mesh_data(by_frame), visible_for=lambda e: None,
                    progress=progress, start=start, prev=np.asarray(chain["prev"], float), init_for=init_for, total=total,
                    prev_frame=chain["prev_frame"], predict=predictor(tracker, chain["predict"]), tracks_for=tracks_for,
                    choose=_chooser(tracker) if chain["spine_start"] == "choose" else None)
    return part


def track_chain_task(chain: dict) -> dict:
    """One half of a multi-view take tracked in a worker process (see :func:`track_results`)."""
    return _track_chain(chain)


def _merge_chain(report: dict, part: dict) -> None:
    report["skipped"] = sorted(set(report["skipped"]) | set(part["skipped"]))
    report["frames"].update(part["frames"])


