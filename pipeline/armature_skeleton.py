"""Kinematic topology from motion segments and a curve skeleton (Tzionas & Gall 2016, section 4.2).

Given a motion segmentation (:mod:`pipeline.motion_segmentation`) of a mesh
and a curve skeleton running inside it:

1. for every pair of adjacent segments, the centroid of the vertices on their
   shared boundary, moved to the nearest point of the curve skeleton, is a
   *joint* (an articulation, three rotational degrees of freedom);
2. *auxiliary joints* (no degree of freedom) where the curve skeleton
   branches or ends;
3. bones follow the curve skeleton from joint to joint;
4. a bone that links an end with an auxiliary joint of the same motion
   segment is dropped (the segment of a curve point is the majority label of
   its nearest surface vertices);
5. a bone whose straight segment leaves the mesh (segment-triangle test) is
   split at the middle of the curve path between its ends, until every bone
   is inside (at most ``max_splits`` rounds); with ``whole_crossing_paths`` not
   a bone whose curve path itself crosses the mesh (no split brings it inside).

The paper's curve skeleton is the mean curvature skeleton (Tagliasacchi et
al. 2012). Here it is the spine's curve skeleton in the rest frame (where
the rest frame shows no spine, fewer than two tips, the mesh contraction
skeleton of :mod:`pipeline.contraction_skeleton`): the
level-set skeleton of Brostow et al. 2004 (:func:`pipeline.frame_skeleton.frame_skeleton`,
merged over the tips), which runs through the middle of every limb and
branches at the junctions -- the role the mean curvature skeleton plays. Any
other curve skeleton can be passed as a :class:`CurveSkeleton`.

The tree is hung from an auxiliary joint of the largest segment (the graph
centre among them), so that the root's rigid motion is that segment's.
Every joint is driven by a *part*: the root's, or that of the nearest
articulation at or above it; a bone belongs to the part of its first joint.
"""

from __future__ import annotations

import logging
from collections import Counter, defaultdict, deque
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

from pipeline.armature_limbs import check_limbs, limbs_last
from pipeline.geodesic import mesh_edges
from pipeline.mesh_primitives import edge_components, winding_number
from pipeline.rigid_parts import relative_bend, rigid_motions

__all__ = [
    "CurveSkeleton", "ArticulatedSkeleton", "curve_skeleton", "articulated_skeleton", "segment_hits_mesh", "joint_residual",
    "relative_bend", "PIVOT_UNCERTAINTY",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class CurveSkeleton:
    """A curve skeleton as a graph of points.

    Attributes
    ----------
    points : (P, 3) float ndarray
    edges : (E, 2) int ndarray
    """

    points: np.ndarray
    edges: np.ndarray


@dataclass(frozen=True, eq=False)
class ArticulatedSkeleton:
    """Joints, hierarchy and parts of an articulated model.

    Attributes
    ----------
    names : tuple of str
        ``root``, ``joint<i>`` (articulations), ``aux<i>`` (auxiliary joints).
    parents : (J,) int ndarray
        Parent of every joint (-1 for the root); parents come first.
    rest : (J, 3) float ndarray
        Joint positions in the rest frame.
    articulation : (J,) bool ndarray
        True for the joints with degrees of freedom.
    segment_pairs : tuple
        For every joint, the pair of motion segments it joins (``None`` for
        auxiliary joints).
    part : (J,) int ndarray
        Part driving every joint: 0 is the root's rigid motion, ``p >= 1`` is
        the rotation of articulation ``part_joint[p]``.
    part_joint : (P,) int ndarray
        The joint of every part (the root for part 0).
    part_parent : (P,) int ndarray
        Parent part (-1 for part 0).
    bones : (B, 2) int ndarray
        ``(joint, child joint)``.
    placement : tuple
        For every joint, how an articulation was placed (``None`` for the others, or without the
        motion): ``{"method": "centre of rotation" | "boundary", "bend_degrees": float,
        "reason": str}`` (``reason`` says why the centre of rotation was not used).
    limb_contacts : tuple
        Adjacent segment pairs on two limbs of the take's spine left out of the tree (contacts, not joints).
    """

    names: tuple
    parents: np.ndarray
    rest: np.ndarray
    articulation: np.ndarray
    segment_pairs: tuple
    part: np.ndarray
    part_joint: np.ndarray
    part_parent: np.ndarray
    bones: np.ndarray
    placement: tuple = ()
    limb_contacts: tuple = ()

    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def n_parts(self) -> int:
        return len(self.part_joint)

    @property
    def joints(self) -> np.ndarray:
        """(A, 3) rest positions of the articulations."""
        return self.rest[self.articulation]


# --------------------------------------------------------------------------- curve skeleton


def curve_skeleton(vertices, faces) -> CurveSkeleton:
    """The rest frame's curve skeleton from the spine machinery (Brostow et al. 2004, 4.1).

    When the surface has fewer than two tips (no spine), the curve skeleton
    of the mesh contraction (:func:`pipeline.contraction_skeleton.contraction_skeleton`,
    Au et al. 2008, in place of the mean curvature skeleton) is used.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray

    Returns
    -------
    CurveSkeleton
    """
    from pipeline.frame_skeleton import frame_skeleton

    v = np.asarray(vertices, dtype=np.float64)
    pts, edges = [], []

    def chain(start_id, interior, end_id=None):
        prev = start_id
        for p in np.asarray(interior, dtype=np.float64).reshape(-1, 3):
            pts.append(p)
            edges.append((prev, len(pts) - 1))
            prev = len(pts) - 1
        if end_id is not None:
            edges.append((prev, end_id))

    fs = frame_skeleton(v, faces)
    if fs.n_tips >= 2:
        m = fs.merged()
        topo = m.topology
        jid = {}
        for j, p in enumerate(m.junctions):
            if np.all(np.isfinite(p)):
                pts.append(np.asarray(p, dtype=np.float64))
                jid[j] = len(pts) - 1
        for j, ax in enumerate(m.junction_axes):
            par = topo.junction_parent[j]
            if ax is not None and j in jid and par in jid:
                chain(jid[par], np.asarray(ax)[1:-1], jid[j])
        for i, ax in enumerate(m.tip_axes):
            par = topo.tip_parent[i]
            if ax is not None and par in jid and len(ax) >= 2:
                chain(jid[par], np.asarray(ax)[1:])
        if len(edges) >= 1:
            return _clean(np.asarray(pts), np.asarray(edges, dtype=np.int64))
    log.warning("no curve skeleton from the spine (fewer than two tips): using the mesh contraction skeleton")
    from pipeline.contraction_skeleton import contraction_skeleton

    P, E = contraction_skeleton(v, faces)
    if len(E) == 0:  # contracted to a single point: the principal axis through it
        c = v.mean(0)
        _, _, Vt = np.linalg.svd(v - c, full_matrices=False)
        lo, hi = np.percentile((v - c) @ Vt[0], [2, 98])
        line = c + np.linspace(lo, hi, 21)[:, None] * Vt[0]
        return CurveSkeleton(line, np.c_[np.arange(20), np.arange(1, 21)])
    return CurveSkeleton(P, E)


def _clean(points: np.ndarray, edges: np.ndarray) -> CurveSkeleton:
    """Drop unreferenced points, self-loops and duplicate edges."""
    e = np.sort(edges, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    e = np.unique(e, axis=0)
    used = np.unique(e)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(len(used))
    return CurveSkeleton(points[used], remap[e])


def _densify(cs: CurveSkeleton, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Insert points so that no edge is longer than ``step``; keep the largest tree."""
    P = [p for p in cs.points]
    E = []
    for a, b in cs.edges:
        L = np.linalg.norm(cs.points[b] - cs.points[a])
        m = int(np.ceil(L / step)) if L > step else 1
        prev = int(a)
        for k in range(1, m):
            P.append(cs.points[a] + (cs.points[b] - cs.points[a]) * k / m)
            E.append((prev, len(P) - 1))
            prev = len(P) - 1
        E.append((prev, int(b)))
    P = np.asarray(P)
    E = np.asarray(E, dtype=np.int64)
    n = len(P)
    w = np.linalg.norm(P[E[:, 0]] - P[E[:, 1]], axis=1) + 1e-9
    G = sp.csr_matrix((w, (E[:, 0], E[:, 1])), shape=(n, n))
    T = minimum_spanning_tree(G + G.T).tocoo()  # a tree (cycles dropped)
    E = np.c_[T.row, T.col]
    comp = edge_components(E, n)
    if comp.max() > 0:
        keep = comp == np.bincount(comp).argmax()
        remap = np.full(n, -1)
        remap[keep] = np.arange(keep.sum())
        E = remap[E[keep[E[:, 0]]]]
        P = P[keep]
    return P, E


# --------------------------------------------------------------------------- collision


def segment_hits_mesh(a, b, vertices, faces, *, margin: float = 1e-3) -> bool:
    """Whether the open segment ``a -> b`` crosses a triangle of the mesh (Moller-Trumbore).

    ``margin`` trims that fraction of the segment at both ends.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a = np.asarray(a, dtype=np.float64)
    d = np.asarray(b, dtype=np.float64) - a
    v0 = v[f[:, 0]]
    e1 = v[f[:, 1]] - v0
    e2 = v[f[:, 2]] - v0
    p = np.cross(d, e2)
    det = (e1 * p).sum(1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = a - v0
    u = (s * p).sum(1) * inv
    q = np.cross(s, e1)
    w = (q @ d) * inv
    t = (q * e2).sum(1) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > margin) & (t < 1 - margin)
    return bool(hit.any())


# --------------------------------------------------------------------------- topology


def _boundary_joints(vertices, faces, labels, min_edges: int) -> list[tuple[tuple[int, int], np.ndarray, float]]:
    """Per pair of adjacent segments: the pair, the centroid of its boundary vertices and their mean distance to it."""
    e = mesh_edges(faces)
    la, lb = labels[e[:, 0]], labels[e[:, 1]]
    cross = la != lb
    out = []
    pairs = np.sort(np.c_[la[cross], lb[cross]], axis=1)
    ec = e[cross]
    if len(pairs) == 0:
        return out
    keys, inv = np.unique(pairs, axis=0, return_inverse=True)
    inv = inv.ravel()
    for k, (sa, sb) in enumerate(keys):
        m = inv == k
        if m.sum() < min_edges:
            continue
        vid = np.unique(ec[m].ravel())
        c = vertices[vid].mean(0)
        out.append(((int(sa), int(sb)), c, float(np.linalg.norm(vertices[vid] - c, axis=1).mean())))
    return out


def _segment_motions(motion: np.ndarray, labels: np.ndarray, segments, reference: int, per_segment: int = 400):
    """Per segment, its best rigid motion from the reference frame to every frame
    (:func:`pipeline.rigid_parts.rigid_motions` of at most ``per_segment`` of its vertices).

    Returns dict segment -> (R (T, 3, 3), t (T, 3)) with ``x_t ~ R_t x_ref + t_t``.
    """
    rng = np.random.default_rng(0)
    out = {}
    for sgm in segments:
        ids = np.flatnonzero(labels == sgm)
        if len(ids) > per_segment:
            ids = rng.choice(ids, per_segment, replace=False)
        out[int(sgm)] = rigid_motions(motion[:, ids], reference=reference)
    return out


def joint_residual(motion_a, motion_b, centroid, *, ridge: float = 1e-3) -> tuple[float, np.ndarray]:
    """How far two rigid motions are from sharing a pivot: a ball joint between them.

    The pivot ``c`` minimises ``sum_t ||(R_a,t c + t_a,t) - (R_b,t c + t_b,t)||^2``
    plus ``ridge * T ||c - centroid||^2`` (a hinge leaves ``c`` free along
    its axis: it stays at the boundary centroid there).

    Parameters
    ----------
    motion_a, motion_b : tuple of (T, 3, 3) and (T, 3) float ndarray
        ``x_t = R_t x + t_t`` of each segment.
    centroid : (3,) float ndarray
        Centroid of the shared boundary (rest frame).
    ridge : float
        Weight of the pull towards the centroid.

    Returns
    -------
    residual : float
        RMS over frames of the distance between the pivot carried by either motion (units of the input).
    pivot : (3,) float ndarray
    """
    Ra, ta = motion_a
    Rb, tb = motion_b
    M = Ra - Rb  # (T, 3, 3)
    b = tb - ta  # (T, 3)
    c0 = np.asarray(centroid, dtype=np.float64)
    T = len(M)
    A = np.einsum("tji,tjk->ik", M, M) + ridge * T * np.eye(3)
    rhs = np.einsum("tji,tj->i", M, b) + ridge * T * c0
    c = np.linalg.solve(A, rhs)
    gap = np.einsum("tij,j->ti", M, c) - b
    return float(np.sqrt((gap**2).sum(1).mean())), c


def _kinematic_tree(candidates, residual, *, index=None) -> list:
    """The candidate pairs that form a spanning tree of the segments with the smallest residuals.

    A kinematic tree has no cycles: when the segments' adjacency does (two
    limbs that touch, arms that meet round a body), the pairs whose motion
    is least like a joint are not articulations. ``index``: segment -> its
    position among the pairs' segments in ascending order (when the caller has it).
    """
    idx = {x: i for i, x in enumerate(sorted({x for c in candidates for x in c[0]}))} if index is None else index
    segs = list(idx)
    if len(segs) < 2:
        return list(candidates)
    rows = [idx[c[0][0]] for c in candidates]
    cols = [idx[c[0][1]] for c in candidates]
    w = np.asarray([residual[c[0]] for c in candidates], dtype=np.float64)
    w = w + 1e-12 * (1.0 + np.abs(w).max()) + 1e-300  # a zero residual is still an edge
    n = len(segs)
    T = minimum_spanning_tree(sp.csr_matrix((w, (rows, cols)), shape=(n, n))).tocoo()
    keep = {(segs[min(a, b)], segs[max(a, b)]) for a, b in zip(T.row, T.col)}
    return [c for c in candidates if c[0] in keep]


def _articulation_pairs(v, f, lab, min_edges, motion, reference, limbs=None) -> tuple[list, dict | None, list]:
    """Boundary centroids of adjacent segments, reduced to a tree, and the segments' rigid motions.
    Returns ``[(pair, centroid, radius)]``, ``{segment: (R, t)}`` (None without ``motion``) and the pairs on two
    ``limbs`` that the tree, taking them last (:func:`pipeline.armature_limbs.limbs_last`), left out.
    """
    cand = _boundary_joints(v, f, lab, min_edges)
    segs = sorted({x for pair, _, _ in cand for x in pair})
    motions = None
    if motion is not None:
        mo = np.asarray(motion)
        if mo.ndim != 3 or mo.shape[1:] != v.shape or not 0 <= int(reference) < len(mo):
            raise ValueError(f"motion must have shape (T, {len(v)}, 3) with reference within 0..T-1, got {mo.shape}")
        motions = _segment_motions(mo, lab, segs, int(reference))
    idx = {x: i for i, x in enumerate(segs)}
    n = len(segs)
    pairs = np.array([(idx[p[0]], idx[p[1]]) for p, _, _ in cand], dtype=np.int64)
    if len(cand) == 0 or len(cand) - n + int(edge_components(pairs, n).max()) + 1 == 0:
        return cand, motions, []  # no cycle: a tree (or a forest) already
    if motions is not None:
        residual = {pair: joint_residual(motions[pair[0]], motions[pair[1]], c)[0] for pair, c, _ in cand}
    else:
        e = mesh_edges(f)
        la, lb = np.sort(np.c_[lab[e[:, 0]], lab[e[:, 1]]], axis=1).T
        residual = {pair: -float(((la == pair[0]) & (lb == pair[1])).sum()) for pair, _, _ in cand}
    residual, across = (residual, set()) if limbs is None else limbs_last(residual, lab, limbs)
    kept = _kinematic_tree(cand, residual, index=idx)
    if len(kept) < len(cand):
        log.info("%d adjacent segment pairs are contacts, not joints (the kinematic tree keeps %d)",
                 len(cand) - len(kept), len(kept))
    return kept, motions, sorted(across - {pair for pair, _, _ in kept})


#: an articulation keeps the paper's placement when its centre of rotation is ill-determined: when the
#: centre's uncertainty (the pivot residual over the root-mean-square size of ``R_a - R_b`` across the
#: hinge, i.e. residual / bend) exceeds this fraction of the mean radius of the boundary where the two
#: parts meet -- the centre could then be anywhere in that cross-section
PIVOT_UNCERTAINTY = 1.0
#: ... and it keeps it too when the centre lies beyond the cross-section where the two parts meet (farther from
#: the boundary's centroid than the boundary's mean radius) and its uncertainty exceeds this fraction of that
#: radius: a centre far from where the parts meet is taken only when the motion determines it well
PIVOT_FAR_UNCERTAINTY = 0.1


def _drawn_centre(motion_a, motion_b, point, *, residual: float, radius: float) -> np.ndarray:
    """The centre of rotation of two rigid motions drawn towards ``point`` as far as it is uncertain: the
    most probable centre when ``point`` (the boundary's, on the curve skeleton) is right to within
    ``radius`` and the motions carry the centre apart by ``residual`` (their noise). The frames' gaps are
    not independent (a tracked surface's noise is smooth in time: docs/armature-format.md), so the prior
    weighs as much as all of them: ``argmin_c sum_t ||(R_a,t - R_b,t) c - (t_b,t - t_a,t)||^2 +
    T (residual / radius)^2 ||c - point||^2``."""
    (Ra, ta), (Rb, tb) = motion_a, motion_b
    M = Ra - Rb
    w = len(M) * (float(residual) / max(float(radius), 1e-300)) ** 2
    A = np.einsum("tji,tjk->ik", M, M) + w * np.eye(3)
    return np.linalg.solve(A, np.einsum("tji,tj->i", M, tb - ta) + w * np.asarray(point, dtype=np.float64))


def _inside(point: np.ndarray, v: np.ndarray, f: np.ndarray) -> bool:
    """Whether ``point`` lies inside the surface: its winding number (:func:`pipeline.mesh_primitives.winding_number`,
    either way the faces wind) exceeds one half; the nearest vertices' normals face a point beside a fold."""
    return abs(winding_number(point, v, f)) > 0.5


def _pivot_positions(P, joint_pairs, cand, motions, v, f) -> tuple[dict, dict]:
    """Articulations moved to their centre of rotation where it is determined (:data:`PIVOT_UNCERTAINTY`; beyond
    the cross-section where the two parts meet, :data:`PIVOT_FAR_UNCERTAINTY`) and inside the mesh
    (:func:`_inside`); how every articulation was placed, and why."""
    if motions is None:
        return {}, {}
    radius = {pair: r for pair, _, r in cand}
    out, how = {}, {}
    for node, pairs in joint_pairs.items():
        a, b = pairs[0]
        bend = relative_bend(motions[a], motions[b])
        info = {"method": "boundary", "bend_degrees": round(bend, 2)}
        how[node] = info
        res, c = joint_residual(motions[a], motions[b], P[node])
        M = motions[a][0] - motions[b][0]
        e = np.linalg.eigvalsh(np.einsum("tji,tjk->ik", M, M) / len(M))  # ascending; e[0] ~ 0 along a hinge's axis
        sigma = res / np.sqrt(max(float(e[1]), 1e-300))
        info["uncertainty"] = round(float(sigma / max(radius[(a, b)], 1e-300)), 3)
        if sigma > PIVOT_UNCERTAINTY * radius[(a, b)]:
            info["reason"] = (f"bends {bend:.1f} degrees: its centre of rotation is ill-determined (uncertain by "
                              f"{info['uncertainty']:.2f} of the boundary's radius), the boundary's centroid on the "
                              "curve skeleton is kept")
        elif np.linalg.norm(c - P[node]) > radius[(a, b)] and sigma > PIVOT_FAR_UNCERTAINTY * radius[(a, b)]:
            info["reason"] = (f"the centre of rotation lies outside the cross-section where the two parts meet and is "
                              f"not determined well enough to move that far (uncertain by {info['uncertainty']:.2f} of "
                              f"the boundary's radius, more than {PIVOT_FAR_UNCERTAINTY:g})")
            drawn = _drawn_centre(motions[a], motions[b], P[node], residual=res, radius=radius[(a, b)])
            if _inside(drawn, v, f):
                out[node] = drawn
                info["method"] = "centre of rotation, drawn to the boundary"
                info["reason"] += "; the centre drawn towards the boundary's point by as much"
        elif not _inside(c, v, f):
            info["reason"] = "the centre of rotation lies outside the mesh"
        else:
            out[node] = c
            info["method"] = "centre of rotation"
    return out, how


def articulated_skeleton(
    vertices,
    faces,
    labels,
    curve: CurveSkeleton | None = None,
    *,
    spacing: float = 0.01,
    min_boundary_edges: int = 3,
    max_splits: int = 4,
    motion=None,
    reference: int = 0,
    refine_joints: bool = True,
    limbs=None,
    whole_crossing_paths: bool = False,
) -> ArticulatedSkeleton:
    """Joints and bones of an articulated model (Tzionas & Gall 2016, section 4.2).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        The rest frame.
    faces : (F, 3) int ndarray
    labels : (V,) int ndarray
        Motion segment of every vertex.
    curve : CurveSkeleton, optional
        Default: :func:`curve_skeleton` of the rest frame.
    spacing : float
        The curve skeleton is resampled at this fraction of the subject's size
        (the precision of a joint along the curve).
    min_boundary_edges : int
        Two segments are adjacent when they share at least this many edges.
    max_splits : int
        Rounds of splitting bones that leave the mesh.
    motion : (T, V, 3) float ndarray, optional
        The vertex trajectories. When the segments' adjacency has cycles
        (segments that touch without being jointed), only the spanning tree
        of pairs whose rigid motions best share a pivot
        (:func:`joint_residual`) become articulations. Without it, the
        longest shared boundaries win.
    reference : int
        Position of ``vertices`` in ``motion``.
    refine_joints : bool
        With ``motion``: an articulation placed on the curve skeleton moves
        to the centre of rotation of its two segments (:func:`joint_residual`,
        pulled towards the curve point along a hinge's axis) when the two
        segments turn against each other enough for it to be determined
        (``PIVOT_UNCERTAINTY``), and the centre lies within the mean radius of their shared
        boundary from the curve point and inside the mesh (its winding number); otherwise it stays
        (``placement`` says which, and why).
    limbs : (V,) int array_like, optional
        The spine limb of every vertex (-1: the body; :func:`pipeline.armature_limbs.vertex_limbs`): a segment
        is hung from one on another limb only when nothing else closes the tree (``limb_contacts``).
    whole_crossing_paths : bool
        A bone whose curve path itself crosses the mesh (a ragged surface's) is not split: off in the tracking's
        armature rounds, on in the armature step (:func:`pipeline.armature.build_armature`).

    Returns
    -------
    ArticulatedSkeleton
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 4, got {v.shape}")
    if lab.shape != (len(v),):
        raise ValueError(f"labels must have shape ({len(v)},), got {lab.shape}")
    if not 0 < spacing < 0.5:
        raise ValueError(f"spacing must be within (0, 0.5), got {spacing}")
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    cs = curve_skeleton(v, f) if curve is None else curve
    P, E = _densify(cs, spacing * size)
    n = len(P)
    adj = defaultdict(set)
    for a, b in E:
        adj[int(a)].add(int(b))
        adj[int(b)].add(int(a))
    tree = cKDTree(v)
    _, nn = tree.query(P, k=min(8, len(v)))
    nn = np.atleast_2d(nn)
    node_seg = np.array([np.bincount(lab[r]).argmax() for r in nn])

    # 1. articulations: boundary centroids moved to the curve skeleton
    ptree = cKDTree(P)
    joint_pairs: dict[int, list] = defaultdict(list)
    cand, motions, contacts = _articulation_pairs(v, f, lab, min_boundary_edges, motion, reference,
                                                  None if limbs is None else check_limbs(limbs, len(v)))
    for pair, c, _ in cand:
        _, node = ptree.query(c)
        joint_pairs[int(node)].append(pair)
    pivots, how = _pivot_positions(P, joint_pairs, cand, motions, v, f) if refine_joints else ({}, {})
    # 2. auxiliary joints at ends and branches
    key = set(joint_pairs) | {i for i in range(n) if len(adj[i]) != 2}
    if not key:
        key = {0}
    # 3. bones along the curve between key nodes
    bones = _key_bones(adj, key)
    # 4. drop end bones inside one segment
    bones = _drop_end_bones(bones, key, joint_pairs, node_seg)
    # 5. split bones that leave the mesh
    bones = _split_bones(bones, key, P, v, f, max_splits=int(max_splits), whole=bool(whole_crossing_paths))
    P = P.copy()
    for node, c in pivots.items():
        P[node] = c
    return replace(_hang(P, bones, joint_pairs, node_seg, lab, how), limb_contacts=tuple(contacts))


def _split_bones(bones: list, key: set, P: np.ndarray, v, f, *, max_splits: int, whole: bool) -> list:
    """Step 5 of :func:`articulated_skeleton` (``key`` gets the nodes added); ``whole``: a bone whose curve ``path``
    crosses the mesh is not split (docs/notes/armature-decisions.md, "Bones not split where their curve path...")."""
    for _ in range(max_splits):
        split = [i for i, (a, b, path) in enumerate(bones) if len(path) > 2 and segment_hits_mesh(P[a], P[b], v, f)
                 and not (whole and any(segment_hits_mesh(P[j], P[k], v, f) for j, k in zip(path, path[1:])))]
        if not split:
            break
        for i in sorted(split, reverse=True):
            a, b, path = bones.pop(i)
            mid = len(path) // 2
            key.add(path[mid])
            bones += [(a, path[mid], path[: mid + 1]), (path[mid], b, path[mid:])]
    return bones


def _key_bones(adj, key) -> list:
    bones, seen = [], set()
    for s in key:
        for nb in adj[s]:
            if (s, nb) in seen:
                continue
            path = [s, nb]
            prev, cur = s, nb
            while cur not in key:
                nxt = [x for x in adj[cur] if x != prev]
                if not nxt:
                    break
                prev, cur = cur, nxt[0]
                path.append(cur)
            seen |= {(path[-1], path[-2]), (s, nb)}
            if cur in key:
                bones.append((s, cur, path))
    return bones


def _drop_end_bones(bones, key, joint_pairs, node_seg) -> list:
    changed = True
    while changed and len(bones) > 1:
        changed = False
        deg = Counter(n for a, b, _ in bones for n in (a, b))
        for i, (a, b, _path) in enumerate(bones):
            for end, other in ((a, b), (b, a)):
                if (deg[end] == 1 and end not in joint_pairs and other not in joint_pairs
                        and node_seg[end] == node_seg[other]):
                    bones.pop(i)
                    changed = True
                    break
            if changed:
                break
    return bones


def _hang(P, bones, joint_pairs, node_seg, lab, how=None) -> ArticulatedSkeleton:
    nodes = sorted({a for a, _, _ in bones} | {b for _, b, _ in bones}) or [0]
    nbrs = defaultdict(list)
    plen = {}
    for a, b, path in bones:
        L = float(np.linalg.norm(np.diff(P[path], axis=0), axis=1).sum())
        nbrs[a].append(b)
        nbrs[b].append(a)
        plen[(a, b)] = plen[(b, a)] = L
    largest = int(np.bincount(lab).argmax())
    aux = [x for x in nodes if x not in joint_pairs]
    cand = [x for x in aux if node_seg[x] == largest] or aux or nodes

    def ecc(s):
        dist = {s: 0.0}
        dq = deque([s])
        while dq:
            u = dq.popleft()
            for w in nbrs[u]:
                if w not in dist:
                    dist[w] = dist[u] + plen[(u, w)]
                    dq.append(w)
        return max(dist.values())

    root = min(cand, key=ecc)
    order, parent = [root], {root: -1}
    dq = deque([root])
    while dq:
        u = dq.popleft()
        for w in sorted(nbrs[u]):
            if w not in parent:
                parent[w] = u
                order.append(w)
                dq.append(w)
    idx = {node: i for i, node in enumerate(order)}
    J = len(order)
    parents = np.array([idx[parent[x]] if parent[x] >= 0 else -1 for x in order], dtype=np.int64)
    artic = np.array([x in joint_pairs and x != root for x in order])
    part = np.zeros(J, dtype=np.int64)
    part_joint, part_parent = [0], [-1]
    for i in range(1, J):
        if artic[i]:
            part_joint.append(i)
            part_parent.append(int(part[parents[i]]))
            part[i] = len(part_joint) - 1
        else:
            part[i] = part[parents[i]]
    names, na, nx = [], 0, 0
    for i in range(J):
        if i == 0:
            names.append("root")
        elif artic[i]:
            names.append(f"joint{na}")
            na += 1
        else:
            names.append(f"aux{nx}")
            nx += 1
    pairs = tuple(tuple(joint_pairs[x][0]) if artic[i] else None for i, x in enumerate(order))
    bone_arr = np.array([(int(parents[i]), i) for i in range(1, J)], dtype=np.int64).reshape(-1, 2)
    return ArticulatedSkeleton(
        names=tuple(names),
        parents=parents,
        rest=P[order].copy(),
        articulation=artic,
        segment_pairs=pairs,
        part=part,
        part_joint=np.asarray(part_joint, dtype=np.int64),
        part_parent=np.asarray(part_parent, dtype=np.int64),
        bones=bone_arr,
        placement=tuple((how or {}).get(x) if artic[i] else None for i, x in enumerate(order)),
    )
