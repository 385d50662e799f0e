"""Armatures from motion: segmentation, skeleton, fit, and the contents of the files users open.

:func:`build_armature` runs Tzionas & Gall 2016 section 4 on a mesh
sequence with shared connectivity: motion segmentation (4.1,
:mod:`pipeline.motion_segmentation`), the kinematic topology (4.2,
:mod:`pipeline.armature_skeleton`), bone heat skinning, and the
per-frame least-squares fit (:mod:`pipeline.armature_fit`). Arrays in, an
:class:`Armature` out; :func:`armature_dict` (``rig.json``, capture-stage/rig@1),
:func:`bvh_text` and :func:`glb_bytes` are the rig directory's contents, which
:mod:`pipeline.armature_files` reads from and writes to a results directory
(``docs/armature-format.md``).

The rest (template) frame is the frame whose curve skeleton shows the most
limb tips among a few evenly spaced candidates (first one on ties): a limb
pressed against the body in one frame is apart in another.

BVH is written by hand (a text format: HIERARCHY with OFFSET/CHANNELS,
MOTION with one line per frame); rotations are ``Zrotation Xrotation
Yrotation`` in degrees (intrinsic Z-X-Y), positions in the source units.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.armature_fit import ArticulatedModel, FitResult, articulated_model, fit_sequence
from pipeline.armature_limbs import BODY, VertexLimbs, segment_limbs
from pipeline.armature_skeleton import ArticulatedSkeleton, articulated_skeleton, curve_skeleton
from pipeline.motion_segmentation import Segmentation, check_sequence, motion_segmentation, subject_size

__all__ = [
    "RIG_FORMAT", "Armature", "build_armature", "armature_dict", "bvh_text", "bvh_from_rig_json", "glb_bytes",
    "choose_reference", "counted", "armature_counts", "check_armature_options",
]

log = logging.getLogger(__name__)

RIG_FORMAT = "capture-stage/rig@1"


@dataclass(frozen=True, eq=False)
class Armature:
    """Everything :func:`build_armature` found.

    Attributes
    ----------
    segmentation : Segmentation
    skeleton : ArticulatedSkeleton
    model : ArticulatedModel
        Bound to the rest frame.
    fit : FitResult
    reference : int
        Position of the rest frame.
    frame_indices : (T,) int ndarray
    units : str
    fps : float
    size : float
        Bounding-box diagonal of the rest frame.
    lambda_thr : float
    timings : dict
        Seconds per step.
    spine : dict or None
        What the take's spine decided (``rig.json``'s ``spine``; None without its limbs): the limb of
        every segment and the pairs on two limbs left out of the kinematic tree.
    """

    segmentation: Segmentation
    skeleton: ArticulatedSkeleton
    model: ArticulatedModel
    fit: FitResult
    reference: int
    frame_indices: np.ndarray
    units: str
    fps: float
    size: float
    lambda_thr: float
    timings: dict
    spine: dict | None = None

    @property
    def n_frames(self) -> int:
        return len(self.frame_indices)

    def posed(self, t: int) -> np.ndarray:
        """(V, 3) the fitted model at frame position ``t``."""
        return self.model.deform(self.fit.poses[t])


def counted(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural unless one: ``"1 articulation"``, ``"0 articulations"``.

    ``n`` is a count (an integer >= 0), ``noun`` a non-empty word whose plural takes an ``s``.
    """
    _check_count(n, "n")
    if not isinstance(noun, str) or not noun.strip():
        raise ValueError(f"noun must be a non-empty string, got {noun!r}")
    return f"{int(n)} {noun}{'' if int(n) == 1 else 's'}"


def armature_counts(segments: int, articulations: int, joints: int) -> str:
    """What an armature is summed up by: ``"2 segments, 1 articulation, 2 joints"`` (counts, integers >= 0)."""
    for n, name in ((segments, "segments"), (articulations, "articulations"), (joints, "joints")):
        _check_count(n, name)
    return ", ".join(counted(n, w) for n, w in ((segments, "segment"), (articulations, "articulation"), (joints, "joint")))


def _check_count(n, name: str) -> None:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"{name} must be a count (an integer >= 0), got {n!r}")


#: connected parts holding less than this share of the mesh's vertices are specks (surface debris):
#: they follow their nearest bone; a larger second part is a second subject, an error
SPECK = 0.005


def _main_part(n_vertices: int, faces) -> np.ndarray | None:
    """Mask of the subject's connected part when specks lie apart from it (a warning), None when the
    mesh is one part; ValueError when a second part is larger than a speck (vertices in no face are
    ignored)."""
    from pipeline.geodesic import mesh_edges
    from pipeline.mesh_primitives import edge_components

    comp = edge_components(mesh_edges(faces), int(n_vertices))
    used = np.unique(np.asarray(faces).ravel())
    sizes = np.bincount(comp[used], minlength=int(comp.max()) + 1)
    parts = np.argsort(-sizes, kind="stable")
    parts = parts[sizes[parts] > 0]
    if len(parts) <= 1:
        return None
    if sizes[parts[1]] >= SPECK * len(used):
        shown = ", ".join(map(str, sizes[parts[:4]])) + (", ..." if len(parts) > 4 else "")
        raise ValueError(
            f"faces: the mesh has {len(parts)} connected parts ({shown} vertices): an armature is found for one "
            "connected subject; keep its part (the largest, as stage track's template does) or build an armature "
            "of each part on its own"
        )
    log.warning("the mesh has %s apart from the subject (%d vertices, each part under %g %% of them): they "
                "follow their nearest bone", counted(len(parts) - 1, "speck"), int(sizes[parts[1:]].sum()), 100 * SPECK)
    return comp == parts[0]


def choose_reference(vertices, faces, *, candidates: int = 8) -> int:
    """Frame (position) whose curve skeleton has the most tips among evenly spaced candidates."""
    from pipeline.frame_skeleton import frame_skeleton

    v = np.asarray(vertices)
    T = len(v)
    cand = np.unique(np.linspace(0, T - 1, min(int(candidates), T)).round().astype(int))
    tips = []
    for t in cand:
        try:
            tips.append(frame_skeleton(v[t], faces).n_tips)
        except ValueError:
            tips.append(-1)
    return int(cand[int(np.argmax(tips))])


def check_armature_options(*, lambda_thr: float | None = None, n_samples: int | None = None, reference: int | None = None,
                           frames: int | None = None, names: dict[str, str] | None = None) -> None:
    """The bounds of :func:`build_armature`'s options, checked before any work (a results directory's armature may
    track the take first): ``stage armature``'s ``--lambda-thr``, ``--samples``, ``--reference`` and an API job's
    ``parameters.rig`` check theirs here. An option left ``None`` is not checked.

    Parameters
    ----------
    lambda_thr : float, optional
        Within ``(0, 2)``.
    n_samples : int, optional
        At least 2.
    reference : int, optional
        A position ``>= 0``; below ``frames`` when given.
    frames : int, optional
        Frames of the sequence (known once the take is tracked, or its surfaces counted).
    names : dict, optional
        The caller's name of each option (``{"n_samples": "--samples"}``) in the messages; default its keyword.

    Raises
    ------
    ValueError
        Naming the option as the caller does, with its bounds and the value given.
    """
    name = {"lambda_thr": "lambda_thr", "n_samples": "n_samples", "reference": "reference", **(names or {})}
    if n_samples is not None and (isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer))
                                  or n_samples < 2):
        raise ValueError(f"{name['n_samples']} must be >= 2, got {n_samples}")
    if lambda_thr is not None and (isinstance(lambda_thr, bool) or not isinstance(lambda_thr, (int, float, np.floating))
                                   or not 0 < lambda_thr < 2):
        raise ValueError(f"{name['lambda_thr']} must be within (0, 2), got {lambda_thr}")
    if reference is not None:
        if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or reference < 0:
            raise ValueError(f"{name['reference']} must be a position >= 0 (0-based), got {reference}")
        if frames is not None and reference >= frames:
            raise ValueError(f"{name['reference']} must be a position within 0..{frames - 1} (the sequence has {frames} "
                             f"frames), got {reference}")


def build_armature(
    vertices,
    faces,
    *,
    units: str = "mm",
    fps: float = 30.0,
    frame_indices=None,
    lambda_thr: float = 0.7,
    n_samples: int = 1000,
    reference: int | None = None,
    progress=None,
    peel_parts: bool = True,
    min_gap: float | None = None,
    limbs=None,
    parts=None,
    whole_crossing_paths: bool = False,
) -> Armature:
    """An articulated, skinned model fitted to every frame of a mesh sequence.

    Parameters
    ----------
    vertices : (T, V, 3) float ndarray
        Shared connectivity: vertex ``i`` is the same surface point in every frame.
    faces : (F, 3) int ndarray
    units : str
        Units of the coordinates (``mm``, ``cm``, ``m`` or anything: the
        defaults follow the subject's size, see :mod:`pipeline.motion_segmentation`).
    fps : float
        Frame rate (for the animation files).
    frame_indices : (T,) int array_like, optional
        Frame numbers (default ``0 .. T-1``).
    lambda_thr : float
        Eigenvalue threshold of the segmentation (0.7; 0.98 for small parts
        with small motion).
    n_samples : int
        Sampled vertices of the segmentation.
    reference : int, optional
        Position of the rest frame (default: :func:`choose_reference`).
    progress : callable, optional
        ``progress(step, done, total)``.
    peel_parts : bool
        See :func:`pipeline.motion_segmentation.motion_segmentation` (off for a tracked template:
        :func:`pipeline.armature_files.armature_results`, ``stage armature RESULTS_DIR``).
    min_gap : float or None
        See :func:`pipeline.motion_segmentation.motion_segmentation` (:data:`~pipeline.motion_segmentation.MIN_GAP`
        for a tracked template, ``None`` for a mesh sequence).
    limbs : pipeline.armature_limbs.VertexLimbs, optional
        The take's spine limb of every vertex (a tracked take with a spine:
        :func:`pipeline.armature_files.armature_results`): see ``limbs`` of
        :func:`pipeline.armature_skeleton.articulated_skeleton`.
    parts : (V,) int array_like or (V,) int array_like and str, optional
        The rigid part of every vertex when it is known, in place of the motion segmentation (``lambda_thr``,
        ``n_samples``, ``peel_parts`` and ``min_gap`` then do nothing): ``(labels, source)``, ``source`` saying
        where they came from (``rig.json``'s ``segmentation.source``; :func:`pipeline.armature_files.limb_parts`
        gives ``"limbs"``), or the labels alone (``"given"``). Parts are renumbered by decreasing size.
    whole_crossing_paths : bool
        A bone whose curve path itself crosses the mesh is not split (``whole_crossing_paths`` of
        :func:`pipeline.armature_skeleton.articulated_skeleton`): on in the armature step (``stage armature``,
        :func:`pipeline.armature_files.armature_results`), where a ragged surface (a real four-camera hull) otherwise
        gets many auxiliary joints with no degree of freedom; off (the default) in the tracking's armature rounds,
        whose armature is the tracking's prior and whose figures are measured without it
        (docs/notes/armature-decisions.md, "Bones not split where their curve path itself leaves the mesh").

    Returns
    -------
    Armature
    """
    import time

    v, f = check_sequence(vertices, faces)
    T = len(v)
    if T < 2:
        raise ValueError("vertices: one frame: an armature is found from how the subject moves, give at least 2 frames")
    main = _main_part(v.shape[1], f)
    if not (fps > 0 and np.isfinite(fps)):
        raise ValueError(f"fps must be > 0, got {fps}")
    if not isinstance(whole_crossing_paths, (bool, np.bool_)):
        raise ValueError(f"whole_crossing_paths must be True or False, got {whole_crossing_paths!r}")
    if limbs is not None and not isinstance(limbs, VertexLimbs):
        raise ValueError(f"limbs must be a pipeline.armature_limbs.VertexLimbs, got {type(limbs).__name__}")
    fi = np.arange(T) if frame_indices is None else np.asarray(frame_indices, dtype=np.int64).reshape(-1)
    if len(fi) != T:
        raise ValueError(f"frame_indices must have {T} entries, got {len(fi)}")
    if reference is not None and not 0 <= int(reference) < T:  # before the segmentation's seconds
        raise ValueError(f"reference must be within 0..{T - 1}, got {reference}")
    timings = {}
    t0 = time.perf_counter()
    if parts is None:
        seg = motion_segmentation(v, f, lambda_thr=lambda_thr, n_samples=n_samples, peel_parts=peel_parts,
                                  min_gap=min_gap)
    else:
        seg = _given_segmentation(parts, v.shape[1])
    timings["segmentation"] = time.perf_counter() - t0
    if progress:
        progress("segmentation", 1, 1)
    t0 = time.perf_counter()
    ref = choose_reference(v, f) if reference is None else int(reference)
    rest = v[ref]
    skel = articulated_skeleton(rest, f, seg.labels, curve_skeleton(rest, f), motion=v, reference=ref,
                                limbs=None if limbs is None else limbs.limb, whole_crossing_paths=whole_crossing_paths)
    model = articulated_model(rest, f, skel, active=main)
    timings["skeleton"] = time.perf_counter() - t0
    if progress:
        progress("skeleton", 1, 1)
    t0 = time.perf_counter()
    fit = fit_sequence(model, v, progress=(lambda t: progress("fit", t + 1, T)) if progress else None)
    timings["fit"] = time.perf_counter() - t0
    size = subject_size(rest[None])
    log.info(
        "armature: %s; mean vertex error %.3g %s (%.2f %% of size)",
        armature_counts(seg.n_segments, int(skel.articulation.sum()), skel.n_joints), fit.errors.mean(), units,
        100 * fit.errors.mean() / size,
    )
    return Armature(seg, skel, model, fit, ref, fi, str(units), float(fps), size, float(lambda_thr), timings,
                    None if limbs is None else _spine_decisions(limbs, seg.labels, skel))


def _given_segmentation(parts, n_vertices: int) -> Segmentation:
    """A :class:`~pipeline.motion_segmentation.Segmentation` of given parts (``parts`` of :func:`build_armature`):
    ``(labels, source)`` or labels alone, (V,) non-negative integers, renumbered ``0 .. k-1`` by decreasing size."""
    pair = isinstance(parts, (tuple, list)) and len(parts) == 2 and isinstance(parts[1], str)
    labels, source = (parts[0], parts[1]) if pair else (parts, "given")
    if source == "motion":
        raise ValueError("parts: 'motion' is the motion segmentation's source, not one of given parts")
    lab = np.asarray(labels)
    if lab.shape != (n_vertices,) or not np.issubdtype(lab.dtype, np.integer) or (len(lab) and lab.min() < 0):
        raise ValueError(f"parts must give a non-negative integer part of every one of the {n_vertices} vertices, "
                         f"got {lab.dtype} shape {lab.shape}")
    _, inv, counts = np.unique(lab, return_inverse=True, return_counts=True)
    rank = np.empty(len(counts), dtype=np.int64)
    rank[np.argsort(-counts, kind="stable")] = np.arange(len(counts))
    out = rank[inv.ravel()]
    k = len(counts)
    empty = np.zeros(0, dtype=np.int64)
    return Segmentation(out, empty, empty, np.zeros(0), k, 0, float("nan"), float("nan"), source)


def _spine_decisions(limbs: VertexLimbs, labels, skeleton: ArticulatedSkeleton) -> dict:
    """``rig.json``'s ``spine``: the spine limb most of every segment lies on (``"body"`` for the body) and the
    adjacent pairs on two limbs that the kinematic tree left out (contacts, not joints)."""
    sl = segment_limbs(labels, limbs.limb)
    return {
        "limbs": list(limbs.names),
        "segment_limbs": ["body" if x == BODY else limbs.names[x] for x in sl],
        "limb_contacts": [[int(a), int(b)] for a, b in skeleton.limb_contacts],
    }


# --------------------------------------------------------------------------- local transforms


def _local_motion(armature: Armature) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T, J, 3, 3) and translations (T, J, 3) of every joint per frame."""
    sk = armature.skeleton
    G = np.stack([pose.R[sk.part] for pose in armature.fit.poses])  # (T, J, 3, 3) global rotation of every joint
    return _local_from_global(sk.parents, sk.rest, G, np.asarray(armature.fit.joints, dtype=np.float64))


def _local_from_global(parents, rest, G: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations and translations from global joint rotations ``G`` (T, J, 3, 3) and positions (T, J, 3)."""
    parents = np.asarray(parents)
    T, J = G.shape[:2]
    R = np.empty((T, J, 3, 3))
    tr = np.empty((T, J, 3))
    for j in range(J):
        p = parents[j]
        if p < 0:
            R[:, j], tr[:, j] = G[:, j], pos[:, j]
        else:
            R[:, j] = np.matmul(G[:, p].transpose(0, 2, 1), G[:, j])
            tr[:, j] = np.einsum("tji,tj->ti", G[:, p], pos[:, j] - pos[:, p])
    rest = np.asarray(rest, dtype=np.float64).copy()
    nz = parents >= 0
    rest[nz] = rest[nz] - rest[parents[nz]]
    return _hold_invalid(R, tr, rest)


def _hold_invalid(R: np.ndarray, tr: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A joint whose frame rotation is undefined (non-finite, zero, not a rotation) or whose position is
    unknown keeps its previous frame's local motion (the rest pose in the first frame)."""
    det = np.linalg.det(np.where(np.isfinite(R), R, 0.0))
    orth = np.abs(np.einsum("tjik,tjil->tjkl", np.nan_to_num(R), np.nan_to_num(R)) - np.eye(3)).max(axis=(2, 3))
    bad_r = ~np.isfinite(R).all(axis=(2, 3)) | (np.abs(det - 1.0) > 1e-3) | (orth > 1e-3)
    bad_t = ~np.isfinite(tr).all(axis=2)
    if not (bad_r.any() or bad_t.any()):
        return R, tr
    log.warning("%d joint rotations and %d joint positions are undefined in some frames: they hold the "
                "previous frame's", int(bad_r.sum()), int(bad_t.sum()))
    for t in range(len(R)):
        R[t, bad_r[t]] = R[t - 1, bad_r[t]] if t > 0 else np.eye(3)
        tr[t, bad_t[t]] = tr[t - 1, bad_t[t]] if t > 0 else rest[bad_t[t]]
    return R, tr


def _quats(R: np.ndarray) -> np.ndarray:
    """(T, J, 4) xyzw quaternions, sign-continuous over time."""
    T, J = R.shape[:2]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(T, J, 4)
    for t in range(1, T):
        flip = (q[t] * q[t - 1]).sum(1) < 0
        q[t, flip] *= -1
    return q


def armature_dict(armature: Armature) -> dict:
    """The ``rig.json`` document (capture-stage/rig@1, docs/armature-format.md)."""
    sk = armature.skeleton
    names = list(sk.names)
    kinds = ["root" if p < 0 else ("joint" if a else "aux") for p, a in zip(sk.parents, sk.articulation)]
    joints = [
        {
            "name": n,
            "parent": None if sk.parents[j] < 0 else names[sk.parents[j]],
            "kind": kinds[j],
            "segments": list(sk.segment_pairs[j]) if sk.segment_pairs[j] is not None else None,
            "rest": [float(x) for x in sk.rest[j]],
            **({"placement": sk.placement[j]} if j < len(sk.placement) and sk.placement[j] is not None else {}),
        }
        for j, n in enumerate(names)
    ]
    frames = []
    for t in range(armature.n_frames):
        P = armature.fit.joints[t]
        G = armature.fit.poses[t].R[sk.part]
        ok = np.isfinite(G).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.nan_to_num(G)) - 1.0) < 1e-3)
        q = Rotation.from_matrix(np.where(ok[:, None, None], G, np.eye(3))).as_quat()
        frames.append({
            "index": int(armature.frame_indices[t]),
            "joints": {n: ([float(x) for x in P[j]] if np.all(np.isfinite(P[j])) else None) for j, n in enumerate(names)},
            "rotations": {n: ([round(float(x), 9) for x in q[j]] if ok[j] else None) for j, n in enumerate(names)},
        })
    err = armature.fit.errors
    seg = armature.segmentation
    return {
        "format": RIG_FORMAT,
        "units": armature.units,
        "fps": armature.fps,
        "frame_count": armature.n_frames,
        "reference_frame": int(armature.frame_indices[armature.reference]),
        "size": armature.size,
        "joints": joints,
        "frames": frames,
        "fit": {
            "vertex_error": [float(e) for e in err],
            "vertex_error_percent": [float(100 * e / armature.size) for e in err],
            "mean_vertex_error": float(err.mean()),
        },
        "segmentation": {"segments": seg.n_segments, "source": seg.source} if seg.source != "motion" else {
            "segments": seg.n_segments,
            "source": "motion",
            "clusters": seg.k,
            "lambda_thr": seg.lambda_thr if np.isfinite(seg.lambda_thr) else armature.lambda_thr,
            "lambda": seg.lam,
            "interval": seg.interval,
            "samples": int(len(seg.samples)),
            "eigenvalues": [float(x) for x in seg.eigenvalues[:16]],
        },
        **({"spine": armature.spine} if armature.spine is not None else {}),
    }


def bvh_text(armature: Armature) -> str:
    """The armature as a BVH file (one ROOT/JOINT per joint; leaves carry an ``End Site``)."""
    sk = armature.skeleton
    R, tr = _local_motion(armature)
    return _bvh(sk.names, sk.parents, sk.rest, R, tr, armature.fps)


def bvh_from_rig_json(doc: dict) -> str:
    """BVH text from a ``rig.json`` document (capture-stage/rig@1 with per-frame ``rotations``).

    The joints, their rest positions, the per-frame global joint positions and
    rotations (xyzw quaternions) of ``rig.json`` give the same file
    :func:`bvh_text` writes for the armature itself.

    Raises
    ------
    ValueError
        When ``doc`` is not an armature document (``rig.json``), or its frames carry no rotations
        (a ``rig.json`` written before they were stored: run ``stage armature`` again).
    """
    if not isinstance(doc, dict) or doc.get("format") != RIG_FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"doc must be a {RIG_FORMAT} document (rig.json), got {got!r}")
    try:
        names = [str(j["name"]) for j in doc["joints"]]
        index = {n: i for i, n in enumerate(names)}
        parents = np.array([-1 if j["parent"] is None else index[j["parent"]] for j in doc["joints"]], dtype=np.int64)
        rest = np.asarray([j["rest"] for j in doc["joints"]], dtype=np.float64).reshape(len(names), 3)
        frames = doc["frames"]
        fps = float(doc["fps"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"rig.json: a joint or frame entry is malformed ({exc!s})") from None
    if not frames or any("rotations" not in fr for fr in frames):
        raise ValueError("rig.json has no joint rotations per frame (written by an older stage armature): run stage armature again")
    T, J = len(frames), len(names)
    G = np.full((T, J, 3, 3), np.nan)
    pos = np.full((T, J, 3), np.nan)
    for t, fr in enumerate(frames):
        for j, n in enumerate(names):
            q, p = fr["rotations"].get(n), fr["joints"].get(n)
            if q is not None:
                G[t, j] = Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()
            if p is not None:
                pos[t, j] = p
    R, tr = _local_from_global(parents, rest, G, pos)
    return _bvh(names, parents, rest, R, tr, fps)


def _bvh(names, parents, rest, R: np.ndarray, tr: np.ndarray, fps: float) -> str:
    """BVH text of a joint tree (rest positions) and its local rotations ``R`` (T, J, 3, 3), root translations."""
    parents = np.asarray(parents)
    J = len(names)
    T = len(R)
    rest_local = np.asarray(rest, dtype=np.float64).copy()
    nz = parents >= 0
    rest_local[nz] = rest_local[nz] - np.asarray(rest)[parents[nz]]
    kids = [[int(k) for k in np.flatnonzero(parents == j)] for j in range(J)]
    lines = ["HIERARCHY"]
    order = []

    def emit(j: int, depth: int) -> None:
        ind = "  " * depth
        head = "ROOT" if parents[j] < 0 else "JOINT"
        lines.append(f"{ind}{head} {names[j]}")
        lines.append(f"{ind}{{")
        o = rest_local[j] if parents[j] >= 0 else np.zeros(3)
        lines.append(f"{ind}  OFFSET {o[0]:.6f} {o[1]:.6f} {o[2]:.6f}")
        if parents[j] < 0:
            lines.append(f"{ind}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{ind}  CHANNELS 3 Zrotation Xrotation Yrotation")
        order.append(j)
        for k in kids[j]:
            emit(k, depth + 1)
        if not kids[j]:
            lines.append(f"{ind}  End Site")
            lines.append(f"{ind}  {{")
            lines.append(f"{ind}    OFFSET 0.000000 0.000000 0.000000")
            lines.append(f"{ind}  }}")
        lines.append(f"{ind}}}")

    emit(int(np.flatnonzero(parents < 0)[0]), 0)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / fps:.6f}"]
    eul = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("ZXY", degrees=True).reshape(T, J, 3)
    root = order[0]
    for t in range(T):
        vals = list(tr[t, root]) + list(eul[t, root])
        for j in order[1:]:
            vals += list(eul[t, j])
        lines.append(" ".join(f"{x:.5f}" for x in vals))
    return "\n".join(lines) + "\n"


def glb_bytes(armature: Armature, *, scale: float | None = None) -> bytes:
    """The armature as GLB: the skinned rest mesh, joints at the articulations, one key per frame."""
    from pipeline.armature_spine import RiggedModel, SpineArmature
    from pipeline.gltf_export import armature_to_glb

    sk = armature.skeleton
    R, tr = _local_motion(armature)
    times = (armature.frame_indices - armature.frame_indices[0]) / armature.fps
    if armature.n_frames > 1 and np.any(np.diff(times) <= 0):
        times = np.arange(armature.n_frames) / armature.fps
    element = tuple(
        "root" if p < 0 else (f"segments {sk.segment_pairs[j][0]}-{sk.segment_pairs[j][1]}" if sk.articulation[j] else "aux")
        for j, p in enumerate(sk.parents)
    )
    grig = SpineArmature(
        names=tuple(sk.names),
        parents=sk.parents.copy(),
        element=element,
        rest=sk.rest.copy(),
        bones=sk.bones.copy() if len(sk.bones) else np.zeros((0, 2), dtype=np.int64),
        rotations=_quats(R),
        translations=tr,
        times=times.astype(np.float64),
        frame_indices=armature.frame_indices.copy(),
        reference=armature.reference,
        units=armature.units,
    )
    m = armature.model
    if len(sk.bones):
        joints = sk.bones[m.influences, 0]
    else:
        joints = np.zeros_like(m.influences)
    model = RiggedModel(m.vertices, m.faces, joints, m.weights, grig, meta={"weights": "bone heat"})
    return armature_to_glb(model, scale=scale, include_spine=len(sk.bones) > 0)


