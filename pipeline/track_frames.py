"""The ``tracked/`` folder of a tracking and the frame loop both forms of tracking share.

``tracked/NNNNNN.ply`` holds the template at every frame, in its vertex order; ``tracked/track.json``
the settings, the skipped frames and per-frame fit figures; ``tracked/labels.npy`` the template's limb/body
labels a tracking with labels cut its patches at (:func:`write_labels`, :func:`read_labels`). :func:`run_frames` tracks frames in
order (Tzionas & Gall 2016, §3), writing each frame atomically as soon as it is fitted and keeping
the frames a killed run already wrote. :func:`start_over_if_changed` is the start-over rule
(:mod:`pipeline.run.settings`): frames tracked with other settings are removed first, with the
rig built on them, in one warning. :func:`surface_meshes` lists the surfaces a tracking follows
(every frame set has one, or a record of why not). The two forms: :mod:`pipeline.track` (a
processed multi-view take) and :mod:`pipeline.track_rgbd` (one RGB-D camera).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import time
from pathlib import Path

import numpy as np

from pipeline.mesh_primitives import mesh_volume
from pipeline.results import atomic_write_bytes, ply_bytes
from pipeline.run.context import warn_once
from pipeline.run.settings import changed_settings, read_settings

__all__ = ["LABELS_FILE", "LastRead", "labels_digest", "load_template", "predictor", "read_labels", "read_tracked", "remove_tracking",
           "run_frames", "slowed_starts", "start_for", "start_over_if_changed", "tracked_path", "write_frame", "write_labels",
           "write_report"]

log = logging.getLogger("pipeline.track")


def tracked_path(out_dir, frame: int) -> Path:
    """``OUT/tracked/NNNNNN.ply``."""
    return Path(out_dir) / "tracked" / f"{int(frame):06d}.ply"


def read_tracked(path: Path, n_vertices: int) -> np.ndarray | None:
    from pipeline.meshio import load_mesh

    try:
        v, _ = load_mesh(path, largest=False)
    except (ValueError, OSError) as exc:
        log.warning("re-tracking %s: unreadable (%s)", path, exc)
        return None
    return v if v.shape == (n_vertices, 3) else None


def write_frame(out_dir: Path, frame: int, vertices: np.ndarray, faces: np.ndarray) -> None:
    atomic_write_bytes(tracked_path(out_dir, frame), ply_bytes(vertices, faces))


def write_report(out_dir: Path, report: dict) -> None:
    atomic_write_bytes(Path(out_dir) / "tracked" / "track.json", json.dumps(report, indent=1).encode())


#: The template's limb (0, 1, ...) / body (-1) labels a tracking cut its rigid patches at: (V,) int64, in
#: ``tracked/``; ``track.json``'s ``patch_labels_sha256`` is the digest of their bytes.
LABELS_FILE = "labels.npy"


def labels_digest(labels: np.ndarray) -> str:
    """``track.json``'s ``patch_labels_sha256`` of the (V,) int64 ``labels``."""
    return hashlib.sha256(np.ascontiguousarray(labels, dtype=np.int64).tobytes()).hexdigest()


def write_labels(out_dir, labels: np.ndarray | None) -> None:
    """Write the labels a tracking uses to ``tracked/labels.npy`` atomically (None: a tracking without labels
    removes an earlier one's file)."""
    path = Path(out_dir) / "tracked" / LABELS_FILE
    if labels is None:
        path.unlink(missing_ok=True)
        return
    _write_vertex_values(path, labels)


def _write_vertex_values(path: Path, values: np.ndarray) -> None:
    """``values`` (V,) as int64 to the ``.npy`` file ``path``, atomically."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(values, dtype=np.int64), allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def _read_vertex_values(path: Path, digest: str, n_vertices: int, what: str, key: str) -> np.ndarray:
    """The (V,) int64 ``what`` of the ``.npy`` file ``path``, checked against ``n_vertices`` and ``track.json``'s
    ``digest`` (its ``key``); ValueError, one line naming the file, when they are not."""
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{path} cannot be read ({exc})") from None
    if not isinstance(values, np.ndarray):
        raise ValueError(f"{path} is not one array (.npy)")
    if values.shape != (n_vertices,) or values.dtype != np.int64:
        raise ValueError(f"{path} holds {values.dtype} of shape {values.shape}, not the template's {n_vertices} {what}")
    if labels_digest(values) != digest:
        raise ValueError(f"{path} is not the {what} track.json's {key} names")
    return values


def read_labels(out_dir, report: dict, n_vertices: int) -> np.ndarray | None:
    """The template's (V,) int64 labels the tracking of ``out_dir`` cut its patches at (``report``: its
    ``track.json``), or None when it wrote none (a tracking without labels, or of an earlier version: the
    caller computes them again).

    Raises
    ------
    ValueError
        One line naming the file, when it cannot be read, is not ``n_vertices`` integers or is not the labels
        whose digest ``track.json`` records (``patch_labels_sha256``).
    """
    path = Path(out_dir) / "tracked" / LABELS_FILE
    if not report.get("patch_labels_sha256") or not path.is_file():
        return None
    return _read_vertex_values(path, report["patch_labels_sha256"], n_vertices, "labels", "patch_labels_sha256")


#: The rigid segments of the limbs armature a tracking's kept armature round tracked with
#: (:func:`pipeline.track_armature.track_with_armature`, ``parts="limbs"``): (V,) int64, in ``tracked/``;
#: ``track.json``'s ``rig_prior.segments_sha256`` is the digest of their bytes. Where two meet, the round's skinned
#: pose tore the surface and the template fit stretched it (:func:`pipeline.limb_segments.limb_segments`, ``seams``).
ROUND_SEGMENTS_FILE = "rig_segments.npy"


def write_round_segments(out_dir, segments: np.ndarray | None, rig_prior: dict) -> None:
    """Write the kept armature round's segments to ``tracked/rig_segments.npy`` atomically and their digest to
    ``rig_prior["segments_sha256"]`` (``track.json``'s; None: a round without them removes an earlier one's file)."""
    path = Path(out_dir) / "tracked" / ROUND_SEGMENTS_FILE
    if segments is None:
        path.unlink(missing_ok=True)
        return
    rig_prior["segments_sha256"] = labels_digest(segments)
    _write_vertex_values(path, segments)


def read_round_segments(out_dir, report: dict, n_vertices: int) -> np.ndarray | None:
    """The (V,) int64 segments of the armature the kept round of ``out_dir``'s tracking tracked with (``report``:
    its ``track.json``), or None when it names none (no limbs armature round).

    Raises
    ------
    ValueError
        One line naming the file, when it cannot be read, is not ``n_vertices`` integers or is not the segments
        whose digest ``track.json`` records (``rig_prior.segments_sha256``).
    """
    digest = (report.get("rig_prior") or {}).get("segments_sha256")
    if not digest:
        return None
    path = Path(out_dir) / "tracked" / ROUND_SEGMENTS_FILE
    return _read_vertex_values(path, digest, n_vertices, "segments", "rig_prior.segments_sha256")


def load_template(template) -> tuple[np.ndarray, np.ndarray]:
    from pipeline.meshio import load_mesh

    if isinstance(template, (tuple, list)) and len(template) == 2:
        return np.asarray(template[0], float), np.asarray(template[1], np.int64)
    v, f = load_mesh(template, largest=False)
    if len(f) == 0:
        raise ValueError(f"template {template}: the mesh has no triangles")
    return v, f


def run_frames(tracker, frames, out_dir, faces, report, *, data_for, visible_for, progress, start, prev,
                contour_for=None, init_for=None, total=None, prev_frame=None, predict=None, before=None, tracks_for=None,
                choose=None):
    """Track ``frames`` in order; ``data_for(k, previous_vertices)`` -> (points, normals, extra) or None (no data);
    ``predict``, ``init_for``, ``choose``: where each frame's rounds start (:func:`start_for`);
    ``before``: (frame, vertices) before ``prev``;
    ``tracks_for(k, previous_frame, previous_vertices, extra, start)`` -> feature tracks of frame ``k`` or None."""
    V0 = tracker.template
    vol0 = mesh_volume(V0, faces)
    per = report.setdefault("frames", {})
    done = 0
    seen = None
    for k in frames:
        t0 = time.perf_counter()
        existing = read_tracked(tracked_path(out_dir, k), len(V0)) if tracked_path(out_dir, k).is_file() else None
        if existing is not None:
            before = (prev_frame, prev) if prev_frame is not None else None
            prev, prev_frame = existing, k
        else:
            data = data_for(k, prev)
            if data is None:
                report["skipped"].append(int(k))
            else:
                pts, nrm, extra = data
                contour = contour_for(extra) if contour_for is not None else None
                init, from_spine = start_for(k, prev_frame, prev, before, seen, pts, nrm, predict=predict,
                                              init_for=init_for, choose=choose)
                tracks = None
                if tracks_for is not None and prev_frame is not None:
                    tracks = tracks_for(k, prev_frame, prev, extra, init)
                fit = tracker.fit(pts, nrm, previous=prev, init=init, visible=visible_for(extra), contour=contour,
                                  tracks=tracks)
                seen = fit.constrained
                before = (prev_frame, prev) if prev_frame is not None else None
                prev, prev_frame = fit.vertices, k
                write_frame(out_dir, k, prev, faces)
                per[str(k)] = {
                    "model_pairs": fit.model_pairs, "data_pairs": fit.data_pairs,
                    "residual_mm": round(fit.residual, 4) if np.isfinite(fit.residual) else None,
                    "volume_ratio": round(mesh_volume(prev, faces) / vol0, 5) if vol0 > 0 else None,
                    "seconds": round(time.perf_counter() - t0, 4),
                }
                if tracks is not None:
                    per[str(k)]["colour_tracks"] = int(len(tracks[0]))
                if from_spine is not None:
                    per[str(k)]["spine_start_patches"] = round(from_spine, 4)
        done += 1
        if progress is not None:
            progress("track", start + done, total if total is not None else start + len(frames))
    return prev


def start_for(k, prev_frame, prev, before, seen, points, normals, *, predict, init_for, choose):
    """Where frame ``k``'s rounds start (None: the previous frame ``prev``) and the share of the
    patches that took the second start (None without a choice). Each start is computed only
    when it is used:

    - ``init_for(k, previous_frame, previous_vertices)`` (the spine's skinned step) without
      ``choose``: it, for every patch;
    - with ``choose(candidates, points, normals)`` -> (start, share): per patch, the prediction
      (or the previous frame) or ``init_for``'s start, whichever the frame's data explain; with
      a prediction also the previous frame itself and half the prediction's step (a swinging
      limb slows and turns back where constant velocity would carry it on: :func:`slowed_starts`);
    - without ``init_for``: ``predict(previous, before, constrained)``, the start from the two
      frames before, when both are the neighbouring frames of ``k`` (``before``: (frame,
      vertices) before ``prev``; ``seen``: the previous fit's constrained motions).
    """
    if prev_frame is None:
        return None, None
    if init_for is not None and choose is None:
        return init_for(k, prev_frame, prev), None
    predicted = None
    if predict is not None and before is not None and abs(k - prev_frame) == 1 and abs(prev_frame - before[0]) == 1:
        predicted = predict(prev, before[1], seen)
    if init_for is None:
        return predicted, None
    if predicted is None:
        return choose([prev, init_for(k, prev_frame, prev)], points, normals)
    return choose([predicted, init_for(k, prev_frame, prev), *slowed_starts(prev, predicted)], points, normals)


def slowed_starts(previous, predicted) -> list[np.ndarray]:
    """The starts of a frame that take less than the predicted step: the previous frame itself and
    half the step from it to ``predicted``.

    The constant-velocity prediction carries a swinging limb on where it slows and turns back, and
    its predicted start lands out of the gate's reach; a patch whose prediction is out of reach
    takes, among these and the spine's skinned step, the start the frame's data explain best
    (:func:`pipeline.tracking.choose_start`).

    Parameters
    ----------
    previous, predicted : (V, 3) float ndarray
        The previous frame's vertices and the frame's predicted start.

    Returns
    -------
    list of two (V, 3) float ndarrays
        ``previous`` (a copy) and ``(previous + predicted) / 2``.
    """
    a = np.asarray(previous, dtype=np.float64)
    b = np.asarray(predicted, dtype=np.float64)
    if a.ndim != 2 or a.shape[1:] != (3,) or b.shape != a.shape:
        raise ValueError(f"previous and predicted must both have shape (V, 3), got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("previous and predicted must be finite")
    return [a.copy(), 0.5 * (a + b)]


def predictor(tracker, predict: bool):
    """``predict(previous, before, constrained)`` -> the next frame's start, or None
    (:meth:`pipeline.tracking.TemplateTracker.predict`: its matrices built once per take)."""
    if not predict:
        return None
    return lambda prev, before, seen: tracker.predict(prev, before, constrained=seen)


class LastRead:
    """One camera's reads by frame index (``read(k)``), keeping the last one: following the
    previous frame into the current one reads each frame once, the RGB-D and the multi-view
    colour tracks alike."""

    def __init__(self, read):
        self._read, self._k, self._value = read, None, None

    def pair(self, k_prev: int, k: int):
        """(what frame ``k_prev`` reads, what frame ``k`` reads); the second is kept for the next call."""
        before = self._value if k_prev == self._k else self._read(k_prev)
        now = self._value if k == self._k else self._read(k)
        self._k, self._value = k, now
        return before, now


#: Report entries that are not settings: results (a resumed run may differ in them), the
#: template's name as it was given (its content is ``template_sha256``) and what a start-over removed.
RESULT_KEYS = frozenset({"skipped", "frames", "worker_cpu_seconds", "icp", "template", "started_over"})


def start_over_if_changed(out_dir: Path, report: dict) -> dict:
    """Per-frame figures of the frames an earlier run of the same settings tracked (they are
    kept), or ``{}``: tracked frames of other settings are removed first, as ``stage process``
    removes results of other parameters, and so is the rig built on them (``rig/``), with one
    warning naming what changed (also in ``report["started_over"]``). The settings are written
    before any frame is tracked, so a killed run's frames keep theirs; ``report`` names no armature round's
    segments, so an earlier round's ``tracked/rig_segments.npy`` goes."""
    path = Path(out_dir) / "tracked" / "track.json"
    (path.parent / ROUND_SEGMENTS_FILE).unlink(missing_ok=True)  # (the armature rounds write theirs after)
    old = read_settings(path)
    kept = {}
    if old is not None:
        spine = Path(out_dir) / "spine.json"
        newer = spine.is_file() and spine.stat().st_mtime_ns > path.stat().st_mtime_ns

        def was(k):
            return _old_setting(old, k, report[k], spine_rewritten=newer)

        changed = changed_settings(old, report, results=RESULT_KEYS, was=lambda _, k, __: was(k))
        if "surfaces" in changed:  # from meshes/ to carved/ (or back): their digest says nothing more
            changed = [k for k in changed if k != "surfaces_sha256"]
        if changed:
            _remove_tracked_frames(path.parent)
            rig_note = _remove_stale_rig(Path(out_dir))
            msg = (f"{path.parent} holds frames tracked with other settings "
                   f"({', '.join(_change(k, was(k), report[k]) for k in changed)}); tracking again{rig_note}")
            if set(changed) <= {"surfaces", "surfaces_sha256"} and not rig_note:
                log.info("%s", msg)  # the rounds of --carve: each tracks the surfaces the last one carved
            else:
                report["started_over"] = msg
                log.warning("%s", msg)
        elif isinstance(old.get("frames"), dict):
            kept = old["frames"]
    write_report(out_dir, {**report, "frames": kept})
    return kept


def _old_setting(old: dict, key: str, new, *, spine_rewritten: bool = False):
    """A setting of an earlier run's ``track.json``, with the keys an earlier version did not
    write read as what it did: without ``spine_start``, every patch started from the spine's
    skinned step with ``spine_init`` and from the prediction without; without ``spine_sha256``,
    the spine was not recorded: read as the current one (its frames are kept) unless
    ``spine.json`` was written after ``track.json`` (``spine_rewritten``: the frames' starts
    came from an earlier spine); without ``patches``, the patches were a grid's cells (``"grid"``);
    without ``slowed_starts``, no patch could start from the previous frame or half the step (False)."""
    if key in old:
        return old[key]
    if key == "spine_start":
        return "all" if old.get("spine_init") else "none"
    if key == "spine_sha256":
        return None if spine_rewritten else new
    if key == "surfaces":  # before the carved surfaces, every run tracked meshes/
        return "meshes"
    if key == "rig_rounds":  # before the articulated prior, no run tracked with a rig
        return 0
    if key == "patches":  # before the patches that follow the surface, they were a grid's cells
        return "grid"
    if key == "slowed_starts":  # before them, a patch out of reach had the prediction and the skinned step only
        return False
    return None


def remove_tracking(out_dir) -> str:
    """Remove the tracking of ``out_dir`` and the rig built on it: what ``stage process`` does
    when it starts over, since both follow the surfaces it removes.

    ``tracked/NNNNNN.ply``, ``tracked/track.json``, ``tracked/labels.npy`` and ``tracked/rig_segments.npy`` go
    (the folder too when that leaves it empty; other files stay), the surfaces carved with the tracked motion (``carved/``,
    :mod:`pipeline.carve`), then the rig as a tracking start-over removes it
    (``rig/``, :func:`pipeline.armature_files.remove_armature`).

    Parameters
    ----------
    out_dir : path
        A results directory.

    Returns
    -------
    str
        What the start-over's warning says of it: ``""`` when there was nothing to remove, else
        ``"; removed ..."`` naming each folder.
    """
    out = Path(out_dir)
    tracked = out / "tracked"
    files = _remove_tracked_frames(tracked)
    for name in ("track.json", LABELS_FILE, ROUND_SEGMENTS_FILE):
        if (tracked / name).is_file():
            (tracked / name).unlink()
            files += 1
    with contextlib.suppress(OSError):  # not there, or not empty: kept
        tracked.rmdir()
    note = f"; removed the frames tracked on the old surfaces ({tracked})" if files else ""
    from pipeline.carve import remove_carved

    return note + remove_carved(out) + _remove_stale_rig(out)


def _remove_tracked_frames(tracked: Path) -> int:
    """Remove ``tracked/NNNNNN.ply``; -> how many there were."""
    from pipeline.armature_files import FRAME_GLOB

    files = list(tracked.glob(FRAME_GLOB))  # a user's 1_fixed.ply stays
    for f in files:
        f.unlink(missing_ok=True)
    return len(files)


def _remove_stale_rig(out_dir: Path) -> str:
    """Remove the rig built on the frames that are tracked again (``OUT/rig/``,
    :func:`pipeline.armature_files.remove_armature`); -> what the start-over's warning says of it."""
    from pipeline.armature_files import remove_armature

    if not remove_armature(out_dir / "rig"):
        return ""
    note = f"; removed the rig built on them ({out_dir / 'rig'})"
    page = out_dir / "report.html"
    try:
        shown = '<section id="rig">' in page.read_text(encoding="utf-8", errors="replace")
    except OSError:  # no report
        shown = False
    return note + (f"; {page} still shows it until `stage report` runs again" if shown else "")


def _change(key: str, old, new) -> str:
    if key == "template_sha256":
        return "template mesh changed"
    if key == "spine_sha256":
        return "spine.json changed"
    if key == "surfaces_sha256":
        return "carved surfaces changed"
    return f"{key} {old!r} -> {new!r}"


def surface_meshes(root: Path, folder: str = "meshes") -> tuple[list[int], dict]:
    """The per-frame surfaces of a results directory: frame numbers in order, and their
    ``meshes/frame_NNNNNN.ply`` (``folder="carved"``: the surfaces carved across time); a frame
    without one is an error unless ``stage process`` recorded why (:func:`_check_no_gap`)."""
    mesh_dir = root / folder
    paths = sorted(mesh_dir.glob("frame_*.ply"))
    if not paths:
        run = "`stage track --carve`" if folder != "meshes" else "`stage process`"
        raise FileNotFoundError(f"{mesh_dir}: no frame_NNNNNN.ply meshes (run {run} first)")
    frames = [int(p.stem.split("_")[1]) for p in paths]
    _check_no_gap(root, mesh_dir, frames)
    return frames, dict(zip(frames, paths))


def _check_no_gap(root: Path, mesh_dir: Path, frames: list[int]) -> None:
    """Every frame of the run has its surface file, or a record saying why it has none: ``stage
    process`` writes a surface per frame set, and ``frames/frame_NNNNNN.json`` with status
    ``empty`` (nothing seen) or ``damaged`` (a set ``--skip-damaged`` left out) where it wrote none;
    those are tracked past with a warning naming them. Any other missing file is an error naming
    it, never a frame tracked past in silence."""
    expected = None
    record = root / "process.json"
    if record.is_file():
        try:
            expected = int(json.loads(record.read_text()).get("frames"))
        except (ValueError, TypeError, OSError, AttributeError):
            expected = None
    want = range(expected) if expected else range(frames[0], frames[-1] + 1)
    missing = sorted(set(want) - set(frames))
    why = {k: _no_surface_status(root, k) for k in missing}
    passed = [k for k in missing if why[k] is not None]
    if passed:
        warn_once(log, "%d frame sets have no surface and are tracked past: %s", len(passed),
                    ", ".join(f"{k} ({why[k]})" for k in passed[:10]) + (" ..." if len(passed) > 10 else ""))
    missing = [k for k in missing if why[k] is None]
    if missing:
        names = ", ".join(f"frame_{k:06d}.ply" for k in missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise FileNotFoundError(f"{mesh_dir}: {len(missing)} of {len(want)} surfaces missing ({names}); "
                                f"run `stage process` again to make them")


def _no_surface_status(root: Path, k: int) -> str | None:
    """``empty`` or ``damaged`` when ``stage process`` recorded that frame set ``k`` has no surface, else None."""
    try:
        status = json.loads((root / "frames" / f"frame_{k:06d}.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return None
    return status if status in ("empty", "damaged") else None
