"""The armature of a results directory: its tracked template read in, ``rig/`` written and removed.

:func:`armature_results` builds the armature (:func:`pipeline.armature.build_armature`, arrays in
and out) of the template tracked through a take (``tracked/NNNNNN.ply``, :func:`tracked_meshes`,
:func:`load_sequence`) and writes the rig directory (``docs/armature-format.md``) with
:func:`write_armature`, every file atomically and durably:

``rig.json``         capture-stage/rig@1: joints, joint positions per frame, fit errors
``segments.npy``     (V,) motion segment of every template vertex
``posed/NNNNNN.ply`` the fitted model at every frame, in the template's vertex order
``rig.glb``          glTF 2.0: skinned template, joints at the articulations, one key per frame
``rig.bvh``          BVH motion capture: the same joints and local rotations

:func:`remove_armature` removes them when the frames they were built on are tracked again.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from pipeline.armature import Armature, armature_dict, build_armature, bvh_text, glb_bytes
from pipeline.armature_limbs import VertexLimbs, vertex_limbs
from pipeline.motion_segmentation import MIN_GAP
from pipeline.results import atomic_write_bytes, ply_bytes

__all__ = ["FRAME_GLOB", "NoTrackingError", "armature_results", "armature_summary", "limb_parts", "load_sequence",
           "remove_armature", "spine_limbs", "tracked_meshes", "write_armature"]

log = logging.getLogger(__name__)


class NoTrackingError(FileNotFoundError):
    """A results directory without a tracked template (``tracked/NNNNNN.ply``)."""


def tracked_meshes(results_dir) -> list[Path]:
    """The tracked template's meshes of a results directory, in frame order.

    Raises
    ------
    NoTrackingError
        When ``RESULTS_DIR/tracked/`` holds no ``NNNNNN.ply``.
    """
    d = Path(results_dir)
    paths = sorted((d / "tracked").glob(FRAME_GLOB)) if (d / "tracked").is_dir() else []
    if not paths:
        raise NoTrackingError(
            f"{d} has no tracked/NNNNNN.ply: the per-frame surfaces of a take do not share connectivity, "
            f"so the template must be tracked through the take first (stage track {d})"
        )
    return paths


def load_sequence(paths) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (T, V, 3), faces (F, 3) and frame numbers (T,) of a mesh sequence with shared connectivity.

    Frame numbers are the last number in each file name (positions when
    they are missing or repeated).

    Raises
    ------
    ValueError
        When the meshes do not share connectivity (vertex counts or faces differ).
    """
    import re

    from pipeline.meshio import load_mesh

    paths = [Path(p) for p in paths]
    verts, faces, numbers = [], None, []
    for i, p in enumerate(paths):
        v, f = load_mesh(p, largest=False)
        if len(f) == 0:
            raise ValueError(f"{p.name}: empty mesh (no faces)")
        if faces is None:
            faces = f
        elif len(v) != len(verts[0]):
            raise ValueError(
                f"{p.name} has {len(v)} vertices, {paths[0].name} has {len(verts[0])}: the meshes do not share "
                "connectivity; track the template through the take first (stage track)"
            )
        elif f.shape != faces.shape or not np.array_equal(f, faces):
            raise ValueError(
                f"{p.name}: its faces differ from {paths[0].name}'s: the meshes do not share connectivity; "
                "track the template through the take first (stage track)"
            )
        verts.append(v)
        m = re.findall(r"\d+", p.stem)
        numbers.append(int(m[-1]) if m else i)
    if len(set(numbers)) != len(numbers):
        numbers = list(range(len(paths)))
    return np.asarray(verts), faces, np.asarray(numbers, dtype=np.int64)


def armature_results(results_dir, *, units: str = "mm", fps: float = 30.0, out=None, progress=None, parts=None,
                     **options):
    """Build the armature of a results directory from its tracked template; writes ``RESULTS_DIR/rig/`` (or ``out``).

    With the take's spine (``spine.json``), the spine's limbs (:func:`spine_limbs`) keep a segment on one
    limb from being hung from a segment on another (``limbs`` of :func:`pipeline.armature.build_armature`;
    ``rig.json``'s ``spine`` says what it decided); ``limbs=None`` builds it without them. A bone whose curve path
    itself crosses the mesh is not split (``whole_crossing_paths=True``, the armature step's; the tracking's armature
    rounds leave it off).

    ``parts="limbs"``: when the template was tracked with its limb/body labels (``stage track --labels``), the
    parts are the labels' body and every limb cut along its spine axis (:func:`limb_parts`) in place of the
    motion segmentation (``rig.json``'s ``segmentation.source`` says which; off by default:
    docs/armature-format.md, "Segments along the limb axes"). Without such labels one line says so and the
    motion segmentation is used; ``parts=None`` or ``"motion"``: the motion segmentation. The labels are those
    of the spine at its rest frame on the tracked template there, checked against the digest the tracking
    recorded: a tracking from another template (``stage track --template``) or one whose labels came out
    otherwise falls back (one line says so).

    Returns
    -------
    Armature
    """
    vertices, faces, numbers = load_sequence(tracked_meshes(results_dir))
    options.setdefault("peel_parts", False)  # a tracked template: its tracking noise is no part
    options.setdefault("min_gap", MIN_GAP)  # and the eigengap tells many small joints from a few large ones
    options.setdefault("whole_crossing_paths", True)  # the armature step's rule (off in the tracking's rounds)
    if "limbs" not in options:
        options["limbs"] = spine_limbs(results_dir, vertices, faces, numbers)
    if not (parts is None or (isinstance(parts, str) and parts in ("motion", "limbs"))):
        raise ValueError(f"parts must be None, 'motion' or 'limbs', got {parts!r}")
    if parts == "limbs":
        found = limb_parts(results_dir, vertices, faces, numbers)
        if found is not None:
            options["parts"] = (found, "limbs")
    rig = build_armature(vertices, faces, units=units, fps=fps, frame_indices=numbers, progress=progress,
                                **options)
    write_armature(rig, Path(out) if out is not None else Path(results_dir) / "rig", progress=progress)
    return rig


def spine_limbs(results_dir, vertices, faces, numbers) -> VertexLimbs | None:
    """The spine limb of every tracked template vertex (:func:`pipeline.armature_limbs.vertex_limbs`), or None
    when the results directory has no spine of these frames (a mesh sequence, a spine of other frames, no
    frame with every limb).

    The spine's rest frame must be a tracked frame; the template is bound to the spine there (bone heat
    weights, :func:`pipeline.armature_spine.rigged_model`).
    """
    from pipeline.armature_spine import NoCompleteFrameError, reference_frame, rigged_model
    from pipeline.spine_format import read_spine

    path = Path(results_dir) / "spine.json"
    if not path.is_file():
        return None
    try:
        spine = read_spine(path)
        ref = reference_frame(spine)
        at = np.flatnonzero(np.asarray(numbers) == int(spine.frame_indices[ref]))
        if len(at) == 0:
            raise ValueError(f"the spine's rest frame {int(spine.frame_indices[ref])} is not tracked")
        return vertex_limbs(rigged_model(spine, vertices[int(at[0])], faces, reference=ref))
    except (NoCompleteFrameError, ValueError, KeyError) as exc:
        log.warning("the armature is built without the spine's limbs (%s)", exc)
        return None


def limb_parts(results_dir, vertices, faces, numbers) -> np.ndarray | None:
    """The rigid parts of a template tracked with its limb/body labels: the body one part, every limb cut along
    its spine axis (:func:`pipeline.limb_segments.limb_segments`), or None (one line says why).

    The labels are the ones the tracking used (``tracked/track.json``'s ``patch_labels`` ``"spine"``), read
    from ``tracked/labels.npy`` (:func:`pipeline.track_frames.read_labels`, checked against the tracking's
    digest of them, ``patch_labels_sha256``, and the template's vertex count). A tracking of an earlier version
    wrote no such file: :func:`pipeline.template_labels.template_labels` of the take's spine at its rest frame
    then gives them again, checked against the digest; a file that is not the tracking's labels is one line and
    the same recomputation. The limbs' axes are the spine's at its rest frame, which must be tracked; every
    limb's noise is measured on the limb (``rho="limb"``: the body is tracked as one patch, the limbs on a grid,
    so the body's noise is not theirs). A tracking whose kept armature round tracked with a limbs armature
    (``tracked/rig_segments.npy``, :func:`pipeline.track_frames.read_round_segments`) gives its segments as the
    cuts' ``seams``: no candidate cut within half a spacing of where two of them meet (a file that is not the one
    ``track.json`` names is one line, and the cuts are made without). A cut is kept only where its two intervals'
    centre of rotation lies within the limb (``centres=True``).
    """
    from pipeline.armature_spine import reference_frame
    from pipeline.limb_segments import limb_segments
    from pipeline.spine_format import SpineFormatError, read_spine
    from pipeline.track_frames import read_labels, read_round_segments

    root = Path(results_dir)
    try:
        report = json.loads((root / "tracked" / "track.json").read_text())
        if report.get("patch_labels") != "spine":
            raise ValueError("the template was not tracked with the spine's labels (stage track --labels)")
        spine = read_spine(root / "spine.json")
        ref = reference_frame(spine)
        at = np.flatnonzero(np.asarray(numbers) == int(spine.frame_indices[ref]))
        if len(at) == 0:
            raise ValueError(f"the spine's rest frame {int(spine.frame_indices[ref])} is not tracked")
        at = int(at[0])
        try:
            labels, bad = read_labels(root, report, len(vertices[at])), ""
        except ValueError as exc:
            labels, bad = None, f"{exc}; "
        if labels is None:
            labels = _recomputed_labels(spine, vertices[at], faces, ref, report, bad)
        try:
            seams = read_round_segments(root, report, len(vertices[at]))
        except ValueError as exc:  # the cuts as without a round
            log.warning("parts='limbs': the cuts do not keep off the armature round's seams: %s", exc,
                        extra={"job_message": f"parameters rig.parts 'limbs': the cuts do not keep off the armature "
                               f"round's seams: {exc}"})
            seams = None
        return limb_segments(vertices, labels, spine_limb_axes(spine, labels, ref), reference=at, rho="limb",
                             faces=None if seams is None else faces, seams=seams, centres=True)
    except (OSError, SpineFormatError, ValueError, KeyError) as exc:
        # (the job's words for the one command this function names: the tracking's labels)
        job = str(exc).replace("stage track --labels", "parameters track.labels")
        log.warning("parts='limbs': the armature's parts come from the motion segmentation: %s", exc,
                    extra={"job_message": f"parameters rig.parts 'limbs': the armature's parts come from the motion "
                           f"segmentation: {job}"})
        return None


def _recomputed_labels(spine, template, faces, reference: int, report: dict, bad: str = "") -> np.ndarray:
    """:func:`limb_parts`'s labels of a tracking without its ``tracked/labels.npy`` (``bad``: why the file was not
    used, said once here when the labels come out as the tracking's): the spine's at its frame ``reference``,
    ValueError unless they are the ones the tracking's digest names."""
    from pipeline.template_labels import template_labels
    from pipeline.track_frames import labels_digest

    labels = np.asarray(template_labels(spine, template, faces, reference=reference), dtype=np.int64)
    if labels_digest(labels) != report.get("patch_labels_sha256"):
        raise ValueError(f"{bad}the spine's labels are not the ones the template was tracked with")
    if bad:
        log.warning("parts='limbs': %sthe labels are the spine's again, the ones the template was tracked with", bad,
                    extra={"job_message": f"parameters rig.parts 'limbs': {bad}the labels are the spine's again, the "
                           "ones the template was tracked with"})
    return labels


def spine_limb_axes(spine, labels, reference: int) -> list:
    """Every limb's axis of ``spine`` at its frame ``reference`` (its finite points), as
    :func:`pipeline.limb_segments.limb_segments` takes them for the template's ``labels`` (-1 the body, ``k`` the
    spine's limb ``k``; a limb without vertices gets a stand-in it never reads); ValueError (one line) when a
    limb of the labels has no axis there."""
    labels = np.asarray(labels)
    axes = [np.asarray(spine.axes[lid][reference], dtype=np.float64) for lid in spine.limb_ids]
    axes = [a[np.isfinite(a).all(axis=1)] for a in axes]
    if len(axes) <= int(labels.max()) or any(len(axes[k]) < 2 for k in np.unique(labels[labels >= 0])):
        raise ValueError(f"a limb of the labels has no axis at the spine's frame {reference}")
    return [a if len(a) >= 2 else np.zeros((2, 3)) for a in axes]


def write_armature(rig: Armature, out_dir, *, progress=None) -> dict:
    """Write the rig directory (``rig.json``, ``segments.npy``, ``posed/``, ``rig.glb``, ``rig.bvh``).

    Every file is written atomically (temporary file, then rename).

    Returns
    -------
    dict
        Name -> path.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    posed = out / "posed"
    posed.mkdir(exist_ok=True)
    for t in range(rig.n_frames):
        atomic_write_bytes(posed / f"{int(rig.frame_indices[t]):06d}.ply", ply_bytes(rig.posed(t), rig.model.faces))
        if progress:
            progress("write", t + 1, rig.n_frames)
    import io

    buf = io.BytesIO()
    np.save(buf, rig.segmentation.labels.astype(np.int32))
    paths = {
        "segments": atomic_write_bytes(out / "segments.npy", buf.getvalue()),
        "rig_json": atomic_write_bytes(out / "rig.json", json.dumps(armature_dict(rig), indent=1).encode()),
        "bvh": atomic_write_bytes(out / "rig.bvh", bvh_text(rig).encode()),
        "glb": atomic_write_bytes(out / "rig.glb", glb_bytes(rig)),
        "posed": posed,
    }
    return paths


#: The files :func:`write_armature` writes in a rig directory, besides ``posed/NNNNNN.ply``.
RIG_FILES = ("rig.json", "segments.npy", "rig.bvh", "rig.glb")


#: A frame's file in ``tracked/`` and ``posed/``: ``NNNNNN.ply``, exactly six digits (a user's
#: ``1_fixed.ply`` beside them is not a frame: not read as one, not removed).
FRAME_GLOB = "[0-9]" * 6 + ".ply"


#: The names of the frames :func:`write_armature` writes in ``posed/``, and nothing else.
POSED_GLOB = FRAME_GLOB


def armature_summary(path) -> dict | None:
    """Segments and joints of a ``rig.json``: what a job's armature is (its report and its results' listing).

    Parameters
    ----------
    path : str or Path
        A ``rig.json`` (capture-stage/rig@1).

    Returns
    -------
    dict or None
        ``segments``, ``articulations`` (joints of kind ``joint``), ``joints`` (``name``, ``parent``, ``kind``,
        ``segments``, ``rest``, ``placement`` of each), ``mean_vertex_error`` and ``units``; None when the file
        is missing or cannot be read as one.

    Raises
    ------
    ValueError
        When ``path`` is not a path.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a path to a rig.json, got {type(path).__name__}")
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
        joints = [{k: j.get(k) for k in ("name", "parent", "kind", "segments", "rest", "placement")} for j in doc["joints"]]
        return {
            "segments": int(doc["segmentation"]["segments"]),
            "articulations": sum(j["kind"] == "joint" for j in joints),
            "joints": joints,
            "mean_vertex_error": doc.get("fit", {}).get("mean_vertex_error"),
            "units": doc.get("units"),
        }
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def remove_armature(out_dir) -> bool:
    """Remove what :func:`write_armature` wrote in ``out_dir``: a rig of frames that were tracked
    again belongs to other frames.

    ``rig.json``, ``segments.npy``, ``rig.bvh``, ``rig.glb`` and ``posed/NNNNNN.ply`` go; the
    folders too when that leaves them empty. Other files stay.

    Parameters
    ----------
    out_dir : str or os.PathLike
        The rig directory (``OUT/rig``); it need not exist.

    Returns
    -------
    bool
        Whether there was a rig file to remove.
    """
    if not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a path, got {type(out_dir).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir must be a rig directory, got the file {out}")
    posed = sorted((out / "posed").glob(POSED_GLOB))  # exactly six digits: a user's 1_fixed.ply stays
    files = [out / name for name in RIG_FILES if (out / name).is_file()] + posed
    for f in files:
        f.unlink(missing_ok=True)
    for d in (out / "posed", out):
        with contextlib.suppress(OSError):  # not there, or not empty: kept
            d.rmdir()
    return bool(files)
