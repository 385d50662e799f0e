"""Template tracking with an armature as the articulated prior (Tzionas & Gall 2016, sections 1 and 5).

The paper's chicken-and-egg: with a rigged model the mesh motion is tracked accurately, and with
the mesh motion the armature is found. Once a first armature exists (:mod:`pipeline.armature` on a
first tracking), every frame is tracked with it:

1. **The armature's pose on the frame's surface** (:func:`fit_pose_to_surface`): articulated ICP.
   Each round pairs the skinned model with the surface (gated closest points both ways, normals
   within 45 degrees, as the template tracking pairs), moves every paired vertex along the data
   normals onto the surface (point-to-plane) and refits the pose to those targets by the
   articulated least squares of :func:`pipeline.armature_fit.fit_frame`. The first half of the
   rounds pairs within twice the gate (a limb several voxels from its last place is still
   caught), the second within the gate. It starts from every candidate pose given (the previous
   frame's pose, its constant-velocity prediction in joint angles, the armature's own fit of the frame
   from the tracking it was built on): a third of the rounds from each, within twice the gate,
   and the rest from the one whose skinned surface the frame's surface explains best
   (:func:`surface_residual`).
2. **The skinned pose as the start and as a regulariser** (:class:`ArmatureTracker`): the template
   tracking of :class:`pipeline.tracking.TemplateTracker` starts from the skinned pose and every
   vertex is drawn towards it with ``weight`` (in pairs, ``fit(anchor=)``), so within a rigid
   part the surface cannot slide along itself, while the data and the Laplacian still shape what
   the armature does not (the skinning's error at the joints, non-rigid parts).

A pose fitted in joint angles extrapolates a limb's swing where the vertices' constant velocity
cannot (a rotating limb's points move on circles). Why the ICP is written here: the articulated
least squares is the project's own (:mod:`pipeline.armature_fit`); pairing and gating are the
template tracker's.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial import cKDTree

from pipeline.armature_fit import ArticulatedModel, Pose, fit_subset
from pipeline.colour_tracks import ray_points
from pipeline.tracking import FrameFit, TemplateTracker, closest_pairs

__all__ = ["fit_pose_to_surface", "surface_residual", "mark_points", "mark_residual", "ArmatureTracker", "segment_armature"]


def _check_points(points, normals) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(points, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or N.shape != X.shape or len(X) == 0:
        raise ValueError(f"points and normals must both have shape (P, 3) with P > 0, got {X.shape} and {N.shape}")
    return X, N


def _check_positive(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def surface_residual(vertices, points, *, gate: float, tree=None) -> float:
    """Mean closest-point distance both ways, each clipped at ``gate``: how well a surface explains
    a mesh's vertices and the mesh the surface's points.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    points : (P, 3) float ndarray
    gate : float
        Distances are clipped here (a far part counts as ``gate``, not its distance).
    tree : scipy.spatial.cKDTree, optional
        Over ``points`` (built here when not given).

    Returns
    -------
    float
        Same units as the coordinates.
    """
    V = np.asarray(vertices, dtype=np.float64)
    X = np.asarray(points, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0 or X.ndim != 2 or X.shape[1] != 3 or len(X) == 0:
        raise ValueError(f"vertices and points must have shape (N, 3), N > 0, got {V.shape} and {X.shape}")
    g = _check_positive(gate, "gate")
    tree = cKDTree(X) if tree is None else tree
    d1, _ = tree.query(V, distance_upper_bound=g)
    d2, _ = cKDTree(V).query(X, distance_upper_bound=g)
    return float(np.minimum(d1, g).mean() + np.minimum(d2, g).mean())


def fit_pose_to_surface(model: ArticulatedModel, start: Pose, points, normals, *, gate: float, rounds: int = 6,
                        iterations: int = 3, max_points: int = 2000, tree=None, marks=None) -> tuple[Pose, float]:
    """The armature's pose on a surface: articulated ICP, point-to-plane (see the module docstring).

    Parameters
    ----------
    model : ArticulatedModel
    start : Pose
    points, normals : (P, 3) float ndarray
        The frame's surface points and their outward unit normals.
    gate : float
        Pair distance gate (the template tracker's, :attr:`TemplateTracker.gate`); the first half
        of the rounds pair within twice it.
    rounds : int
        Rounds of pairing and refitting.
    iterations : int
        Levenberg-Marquardt iterations of each refit (:func:`fit_frame`).
    max_points : int
        Vertices paired and fitted (a fixed, evenly drawn subset, :meth:`ArticulatedModel.subset`).
    tree : scipy.spatial.cKDTree, optional
        Over ``points``.
    marks : ((M,) int, (M, 3) float) ndarrays, optional
        Where the images say some vertices went (:func:`mark_points`): each round, a marked vertex
        within the round's gate of its mark has its mark as its target (:data:`MARK_PULL`; the surface
        pairs cannot see a round part's turn about its own axis, the images can).

    Returns
    -------
    pose : Pose
    residual : float
        :func:`surface_residual` of the posed model (all vertices) against the surface, within ``gate``.
    """
    if not isinstance(model, ArticulatedModel):
        raise ValueError(f"model must be an ArticulatedModel, got {type(model).__name__}")
    if not isinstance(start, Pose) or start.R.shape != (model.skeleton.n_parts, 3, 3):
        raise ValueError(f"start must be a Pose of the model's {model.skeleton.n_parts} parts")
    X, N = _check_points(points, normals)
    g = _check_positive(gate, "gate")
    for value, name in ((rounds, "rounds"), (iterations, "iterations"), (max_points, "max_points")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    sub = model.subset(int(max_points))
    marks = _subset_marks(_check_marks(marks, len(model.vertices)), sub)
    tree = cKDTree(X) if tree is None else tree
    n = len(sub)
    pose = start
    for r in range(int(rounds)):
        gr = 2.0 * g if r < int(rounds) // 2 else g
        S, vn = model.posed_subset(pose, int(max_points))  # only the paired vertices are posed
        i, j = closest_pairs(S, vn, tree, N, gate=gr)
        jd, iv = closest_pairs(X, N, cKDTree(S), vn, gate=gr)
        pv = np.concatenate([i, iv])
        px = np.concatenate([X[j], X[jd]])
        pn = np.concatenate([N[j], N[jd]])
        if len(pv) == 0:
            break
        shift = pn * np.einsum("ij,ij->i", px - S[pv], pn)[:, None]
        count = np.bincount(pv, minlength=n).astype(np.float64)
        moved = np.stack([np.bincount(pv, weights=shift[:, c], minlength=n) for c in range(3)], axis=1)
        target = S + moved / np.maximum(count, 1.0)[:, None]  # unpaired vertices stay where they are
        if marks is not None:
            _pull_to_marks(target, S, marks, gr)
        pose = fit_subset(model, target, pose, iterations=int(iterations), max_points=int(max_points))
    return pose, surface_residual(model.deform(pose), X, gate=g, tree=tree)


def _check_marks(marks, n: int):
    if marks is None:
        return None
    try:
        v, x = np.asarray(marks[0]), np.asarray(marks[1], dtype=np.float64)
    except (TypeError, IndexError, ValueError):
        raise ValueError("marks must be a pair ((M,) vertex indices, (M, 3) points)") from None
    if v.ndim != 1 or not np.issubdtype(v.dtype, np.integer) or x.shape != (len(v), 3) or len(v) == 0 \
            or v.min() < 0 or v.max() >= n or not np.isfinite(x).all():
        raise ValueError(f"marks must be a pair ((M,) vertex indices in 0..{n - 1}, (M, 3) finite points), M > 0, "
                         f"got shapes {v.shape} and {x.shape}")
    return v, x


def _subset_marks(marks, sub: np.ndarray):
    """The marks of the vertices in ``sub`` (sorted vertex indices), as positions in it (None without any)."""
    if marks is None:
        return None
    pos = np.minimum(np.searchsorted(sub, marks[0]), len(sub) - 1)
    hit = sub[pos] == marks[0]
    return (pos[hit], marks[1][hit]) if hit.any() else None


def mark_points(tracks, n: int):
    """Colour feature tracks (``(idx, targets, rays)``, :func:`pipeline.track_colour.multiview_tracks_for`) as marks:
    ((M,) int vertices, (M, 3) float points), every vertex with two rays or more at the point nearest them."""
    if tracks is None or len(tracks[0]) == 0:
        return None
    ok, x = ray_points(*tracks[:3], n)
    v = np.flatnonzero(ok)
    return (v, x[v]) if len(v) else None


#: How far a marked vertex's target moves from its surface pairs' towards its mark, each round of the ICP (1: the
#: mark is the target; 0.5 followed less of a turn the surface cannot see, docs/tracking.md, "Fast motion").
MARK_PULL = 1.0


def _pull_to_marks(target: np.ndarray, S: np.ndarray, marks, gate: float) -> None:
    """Move the targets of the marked vertices within ``gate`` of their mark :data:`MARK_PULL` of the way to it."""
    v, x = marks
    near = np.linalg.norm(x - S[v], axis=1) <= gate
    target[v[near]] += MARK_PULL * (x[near] - target[v[near]])


def mark_residual(vertices, marks, *, gate: float) -> float:
    """Mean distance of the marked vertices from their marks, each clipped at ``gate`` (0 without marks)."""
    if marks is None:
        return 0.0
    v, x = marks
    return float(np.minimum(np.linalg.norm(np.asarray(vertices)[v] - x, axis=1), gate).mean())


class ArmatureTracker:
    """Tracks a template frame by frame with an armature as the articulated prior.

    Parameters
    ----------
    tracker : TemplateTracker
        The template tracker; its template is the model's vertex order.
    model : ArticulatedModel
        The armature, bound to a rest shape in the template's vertex order.
    weight : float
        How strongly every vertex is drawn to the skinned pose, in pairs (``fit(anchor=)``).
    rounds, iterations, max_points : int
        Of :func:`fit_pose_to_surface`.
    """

    def __init__(self, tracker: TemplateTracker, model: ArticulatedModel, *, weight: float = 2.0, rounds: int = 6,
                 iterations: int = 3, max_points: int = 2000):
        if not isinstance(tracker, TemplateTracker):
            raise ValueError(f"tracker must be a TemplateTracker, got {type(tracker).__name__}")
        if not isinstance(model, ArticulatedModel):
            raise ValueError(f"model must be an ArticulatedModel, got {type(model).__name__}")
        if model.vertices.shape != tracker.template.shape or not np.array_equal(model.faces, tracker.faces):
            raise ValueError("model must be bound to a mesh of the tracker's connectivity "
                             f"({len(model.vertices)} vertices against the template's {tracker.n_vertices})")
        self.tracker = tracker
        self.model = model
        self.weight = _check_positive(weight, "weight")
        for value, name, least in ((rounds, "rounds", 2), (iterations, "iterations", 1), (max_points, "max_points", 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        self.rounds, self.iterations, self.max_points = int(rounds), int(iterations), int(max_points)

    def fit(self, points, normals, *, previous, candidates, tracks=None) -> tuple[FrameFit, Pose, float]:
        """One frame: the best candidate's pose on the surface, then the template fitted from its
        skinned pose and drawn towards it.

        Parameters
        ----------
        points, normals : (P, 3) float ndarray
        previous : (V, 3) float ndarray
            The template on the previous frame.
        candidates : sequence of Pose
            Starts of the articulated ICP (at least one; a start given twice is fitted once).
        tracks : ((T,) int, (T, 3) float, (T, 3) float) ndarrays, optional
            Colour feature tracks across the take's cameras (vertices, a point on each track's ray,
            the ray; :func:`pipeline.track_colour.multiview_tracks_for`): as marks (:func:`mark_points`)
            in the ICP and in the choice of its start (the surface residual plus
            :func:`mark_residual`), and as the template fit's ``tracks``.

        Returns
        -------
        fit : FrameFit
        pose : Pose
        residual : float
            The chosen pose's :func:`surface_residual`.
        """
        X, N = _check_points(points, normals)
        cands = []
        for c in candidates:  # the same start twice (a zero spine step gives the previous pose back) is fitted once
            if not isinstance(c, Pose) or c.R.shape != (self.model.skeleton.n_parts, 3, 3):
                raise ValueError(f"candidates must be Poses of the model's {self.model.skeleton.n_parts} parts")
            if not any(c is d or (np.array_equal(c.R, d.R) and np.array_equal(c.t, d.t)) for d in cands):
                cands.append(c)
        if not cands:
            raise ValueError("candidates must hold at least one Pose")
        tree = cKDTree(X)
        marks = mark_points(tracks, len(self.model.vertices))
        kw = dict(iterations=self.iterations, max_points=self.max_points, tree=tree, marks=marks)
        coarse = max(1, self.rounds // 3)  # every candidate's first rounds at twice the gate, then the best one on
        best = None
        g2 = 2.0 * self.tracker.gate
        for c in cands:
            pose, res = fit_pose_to_surface(self.model, c, X, N, gate=g2, rounds=coarse, **kw)
            score = res + (mark_residual(self.model.deform(pose), marks, gate=g2) if marks is not None else 0.0)
            if best is None or score < best[1]:
                best = (pose, score)
        pose, res = fit_pose_to_surface(self.model, best[0], X, N, gate=self.tracker.gate, rounds=self.rounds - coarse,
                                        **kw)
        skinned = self.model.deform(pose)
        fit = self.tracker.fit(X, N, previous=previous, init=skinned, anchor=(skinned, self.weight),
                               tracks=None if marks is None else tracks)
        return fit, pose, res


def segment_armature(vertices, faces, segments, parents, *, motion=None, reference: int = 0) -> ArticulatedModel:
    """An armature whose parts are given rigid segments, every vertex moving with its own segment.

    Every segment but the root turns about one joint with its parent segment: the two segments'
    centre of rotation over ``motion`` (:func:`pipeline.armature_skeleton.joint_residual` of their rigid
    motions, :func:`pipeline.rigid_parts.rigid_motions`), drawn towards their boundary as far as it is
    uncertain (the prior weighs as much as all frames when the two motions carry the centre apart by the
    boundary's radius), or without ``motion`` the boundary: the centroid of the vertices on the edges
    between the two, or of the child's vertices nearest the parent's when they share none.
    Rigid weights: a vertex's skinned position is its segment's rigid motion, so a limb's bone
    carries no torso and a touching limb carries nothing of another (bone heat weights spread a
    limb's bones over the body; docs/tracking.md, "Fast motion").

    Parameters
    ----------
    vertices : (V, 3) float array_like
        The rest shape (the template at its reference frame).
    faces : (F, 3) int array_like
    segments : (V,) int array_like
        Segment of every vertex, ``0 .. S-1``, each with a vertex.
    parents : (S,) int array_like
        Parent segment of every segment, -1 for the one root; a tree.
    motion : (T, V, 3) float array_like, optional
        The segments' motion (the tracked template) that places the joints; without it they sit on the
        boundaries.
    reference : int
        The frame of ``motion`` that is the rest shape.

    Returns
    -------
    ArticulatedModel
        Part 0 the root segment's rigid motion, then one part per other segment, parents first;
        ``influences`` one bone of the vertex's segment, ``weights`` 1.
    """
    from pipeline.armature_skeleton import ArticulatedSkeleton, joint_residual
    from pipeline.rigid_parts import rigid_motions

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.isfinite(v).all():
        raise ValueError(f"vertices must be a finite (V, 3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= len(v))):
        raise ValueError(f"faces must be (F, 3) indices into the {len(v)} vertices")
    seg = np.asarray(segments)
    if seg.shape != (len(v),) or not np.issubdtype(seg.dtype, np.integer) or seg.min() < 0:
        raise ValueError(f"segments must be ({len(v)},) integers >= 0, got {seg.dtype} shape {seg.shape}")
    S = int(seg.max()) + 1
    if len(np.unique(seg)) != S:
        raise ValueError("segments must number the segments 0 .. S-1, each with a vertex")
    par = np.asarray(parents)
    if par.shape != (S,) or not np.issubdtype(par.dtype, np.integer) or par.min() < -1 or par.max() >= S \
            or (par == -1).sum() != 1:
        raise ValueError(f"parents must be ({S},) segment indices with one root (-1), got {par.tolist()}")
    order = [int(np.flatnonzero(par == -1)[0])]
    for s in order:  # parents first (breadth first); a cycle leaves segments out
        order.extend(int(c) for c in np.flatnonzero(par == s))
    if len(order) != S:
        raise ValueError(f"parents must form a tree, got {par.tolist()}")
    mot = None
    if motion is not None:
        mot = np.asarray(motion, dtype=np.float64)
        if mot.ndim != 3 or mot.shape[1:] != v.shape or not np.isfinite(mot).all():
            raise ValueError(f"motion must be a finite (T, {len(v)}, 3) array, got shape {mot.shape}")
        if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) or not 0 <= reference < len(mot):
            raise ValueError(f"reference must be a frame in 0 .. {len(mot) - 1}, got {reference!r}")
    centroid = np.stack([v[seg == s].mean(0) for s in range(S)])
    part_of = np.empty(S, dtype=np.int64)
    part_of[order] = np.arange(S)
    pivots = [centroid[order[0]]]
    for s in order[1:]:
        pivots.append(_segment_pivot(v, f, seg, s, int(par[s]), mot, reference, joint_residual, rigid_motions))
    # joints: the root, one articulation per other part, one end per part (its bone's second joint)
    rest = np.vstack([np.asarray(pivots), centroid[order]])
    parent_part = np.r_[-1, part_of[par[order[1:]]]]
    parents_j = np.r_[-1, parent_part[1:], np.arange(S)]
    part = np.r_[np.arange(S), np.arange(S)]
    names = ("root",) + tuple(f"joint{p}" for p in range(1, S)) + tuple(f"aux{p}" for p in range(S))
    skeleton = ArticulatedSkeleton(names=names, parents=parents_j, rest=rest,
                                   articulation=np.r_[False, np.ones(S - 1, bool), np.zeros(S, bool)],
                                   segment_pairs=(None,) + tuple((int(s), int(par[s])) for s in order[1:]) + (None,) * S,
                                   part=part, part_joint=np.arange(S), part_parent=parent_part,
                                   bones=np.stack([np.arange(S), S + np.arange(S)], 1), placement=(None,) * (2 * S))
    return ArticulatedModel(v, f, skeleton, part_of[seg][:, None], np.ones((len(v), 1)))


def _segment_pivot(v, f, seg, child: int, parent: int, motion, reference, joint_residual, rigid_motions):
    """The joint of segment ``child`` with ``parent`` (:func:`segment_armature`): the centre of rotation drawn
    towards the boundary as far as the motion leaves it uncertain."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    a, b = seg[e[:, 0]], seg[e[:, 1]]
    cross = e[((a == child) & (b == parent)) | ((a == parent) & (b == child))]
    if len(cross):
        ring = v[np.unique(cross)]
    else:  # no shared edge: the child's vertices nearest the parent's
        mine = np.flatnonzero(seg == child)
        d, _ = cKDTree(v[seg == parent]).query(v[mine])
        ring = v[mine[d <= np.quantile(d, 0.1)]]
    boundary = ring.mean(0)
    if motion is None:
        return boundary
    radius = max(float(np.linalg.norm(ring - boundary, axis=1).mean()), 1e-9)
    rng = np.random.default_rng(0)
    motions = []
    for s in (child, parent):
        ids = np.flatnonzero(seg == s)
        ids = rng.choice(ids, min(len(ids), 400), replace=False)
        motions.append(rigid_motions(motion[:, ids], reference=int(reference)))
    res, _ = joint_residual(motions[0], motions[1], boundary)
    # the prior weighs as much as all frames when the motions carry the centre apart by the boundary's radius
    return joint_residual(motions[0], motions[1], boundary, ridge=max((res / radius) ** 2, 1e-3))[1]
