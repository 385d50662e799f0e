"""Fitting an articulated model to every frame of a mesh sequence (Tzionas & Gall 2016, sections 4.2, 5).

The model (:class:`ArticulatedModel`): the rest mesh, an
:class:`~pipeline.armature_skeleton.ArticulatedSkeleton` and bone heat
skinning weights (Baran & Popovic 2007, :mod:`pipeline.skinning`, as the paper
computes them). Its pose is a global rigid motion plus one rotation per
articulation; bone lengths are fixed by construction (every part turns about
its joint, which its parent part carries).

Part ``p`` has the global rotation ``R_p = R_parent L_p`` and the translation
that keeps its joint ``c_p`` where the parent puts it. A vertex is posed by
linear blend skinning, ``x' = sum_k w_k (R_k x + t_k)`` over its bones' parts.

Per frame, :func:`fit_frame` minimises ``sum_v ||x'_v - y_v||^2`` (the
frame's vertices ``y``, corresponding by index: shared connectivity) by
Gauss-Newton; the Jacobian of a rotation
increment ``omega_p`` (world frame, about the part's current joint) is
``-[A_vp]_x`` with ``A_vp = sum_k w_vk [part_k below p] (x'_vk - c_p)``; a
Levenberg-Marquardt damping (Marquardt's diagonal scaling, dimensionless)
keeps every step descending, and the iterations stop once the linear model
promises less than 1e-4 of the residual. The normal equations are formed
without the 3V x 3(P+1) Jacobian: from the influences' moments summed per
pair of parts and then over subtrees (:func:`_normal_equations`), and every
rotation of a pose is kept a rotation (:func:`_forward`).
:func:`fit_sequence` initialises every frame from the previous one (the
paper's tracking) or from its constant-velocity prediction from the two
previous frames (:func:`predict_pose`), whichever fits better, and, as a
guard against fast motion, from a closed-form hierarchical Procrustes fit
of the parts (Arun et al. 1987 about each joint), keeping the best start;
when the closed-form start is already closer to the frame than the tracked
result, the frame is fitted from it too and the better fit kept (tracking
from frame to frame can settle in a worse basin and stay there).

The paper's measure (section 5): the mean 3-D vertex error between the fitted
model and the frame, per frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.armature_skeleton import ArticulatedSkeleton
from pipeline.skinning import bone_heat_weights, limit_influences

__all__ = ["ArticulatedModel", "Pose", "articulated_model", "fit_frame", "fit_subset", "fit_sequence", "predict_pose",
           "FitResult"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Pose:
    """Global rotation and translation of every part: ``x -> R[p] x + t[p]``.

    Attributes
    ----------
    R : (P, 3, 3) float ndarray
    t : (P, 3) float ndarray
    """

    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True, eq=False)
class ArticulatedModel:
    """A rest mesh bound to an articulated skeleton.

    Attributes
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    skeleton : ArticulatedSkeleton
    influences : (V, k) int ndarray
        Bones (rows of ``skeleton.bones``) influencing every vertex.
    weights : (V, k) float ndarray
        Rows sum to 1.
    active : (V,) bool ndarray or None
        The vertices the fit uses and its error counts (default all; a
        separate part the skeleton does not reach is left out).
    """

    vertices: np.ndarray
    faces: np.ndarray
    skeleton: ArticulatedSkeleton
    influences: np.ndarray
    weights: np.ndarray
    active: np.ndarray | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def bone_part(self) -> np.ndarray:
        """(B,) part driving every bone (that of its first joint)."""
        return self.skeleton.part[self.skeleton.bones[:, 0]]

    @property
    def vertex_parts(self) -> np.ndarray:
        """(V, k) part of every influence."""
        if "vp" not in self._cache:
            self._cache["vp"] = self.bone_part[self.influences]
        return self._cache["vp"]

    @property
    def below(self) -> np.ndarray:
        """(P, P) bool: ``below[q, p]`` when part ``q`` is ``p`` or in its subtree."""
        if "below" not in self._cache:
            sk = self.skeleton
            P = sk.n_parts
            M = np.eye(P, dtype=bool)
            for q in range(P):
                p = sk.part_parent[q]
                while p >= 0:
                    M[q, p] = True
                    p = sk.part_parent[p]
            self._cache["below"] = M
        return self._cache["below"]

    @property
    def pivots(self) -> np.ndarray:
        """(P, 3) rest position of every part's joint (part 0: the root)."""
        return self.skeleton.rest[self.skeleton.part_joint]

    def subset(self, n: int | None) -> np.ndarray:
        """Indices of at most ``n`` vertices, evenly drawn (fixed seed), sorted; all when ``n`` is None."""
        ids = np.arange(len(self.vertices)) if self.active is None else np.flatnonzero(self.active)
        if n is None or n >= len(ids):
            return ids
        key = ("subset", int(n))
        if key not in self._cache:
            self._cache[key] = np.sort(np.random.default_rng(0).choice(ids, int(n), replace=False))
        return self._cache[key]

    def identity(self) -> Pose:
        P = self.skeleton.n_parts
        return Pose(np.tile(np.eye(3), (P, 1, 1)), np.zeros((P, 3)))

    @property
    def part_weights(self) -> np.ndarray:
        """(V, P) skinning weight of every part (summed over the bones it drives)."""
        if "wp" not in self._cache:
            V = len(self.vertices)
            W = np.zeros((V, self.skeleton.n_parts))
            np.add.at(W, (np.repeat(np.arange(V), self.weights.shape[1]), self.vertex_parts.ravel()), self.weights.ravel())
            self._cache["wp"] = W
        return self._cache["wp"]

    def deform(self, pose: Pose, rows: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) vertices posed by linear blend skinning (``rows``: only those vertices).

        Blends every vertex's affine map first, ``sum_p w_vp [R_p | t_p]``, then applies it.
        """
        W = self.part_weights if rows is None else self.part_weights[rows]
        x = self.vertices if rows is None else self.vertices[rows]
        P = self.skeleton.n_parts
        T = W @ np.concatenate([pose.R.reshape(P, 9), pose.t], 1)  # (V, 12)
        return np.einsum("vij,vj->vi", T[:, :9].reshape(-1, 3, 3), x) + T[:, 9:]

    def posed_subset(self, pose: Pose, n: int | None) -> tuple[np.ndarray, np.ndarray]:
        """The vertices ``subset(n)`` posed, (S, 3), and their unit area-weighted normals in the posed
        mesh, (S, 3): :func:`pipeline.mesh_primitives.vertex_normals` of the whole posed mesh at those
        rows, from the faces around them alone (the same sums in the same order)."""
        key = ("ring", n)
        if key not in self._cache:
            from pipeline.mesh_primitives import summing_matrix

            rows = self.subset(n)
            faces = self.faces[np.isin(self.faces, rows).any(axis=1)]
            ring = np.unique(faces)
            local = np.searchsorted(ring, faces)
            corners = summing_matrix(local.ravel(), len(ring))[np.searchsorted(ring, rows)]
            self._cache[key] = (ring, local, corners, np.searchsorted(ring, rows))
        ring, f, corners, at = self._cache[key]
        v = self.deform(pose, ring)
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        nrm = corners @ np.repeat(fn, 3, axis=0)
        nn = np.linalg.norm(nrm, axis=1, keepdims=True)
        return v[at], nrm / np.where(nn > 0, nn, 1.0)

    def joint_positions(self, pose: Pose) -> np.ndarray:
        """(J, 3) joints in a pose."""
        sk = self.skeleton
        return np.einsum("jab,jb->ja", pose.R[sk.part], sk.rest) + pose.t[sk.part]


def articulated_model(vertices, faces, skeleton: ArticulatedSkeleton, *, max_influences: int = 4,
                      active=None) -> ArticulatedModel:
    """Bind a rest mesh to a skeleton with bone heat weights.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    skeleton : ArticulatedSkeleton
    max_influences : int
        Bones per vertex (1..4, glTF's limit per set).
    active : (V,) bool array_like, optional
        Vertices the fit uses (default all).

    Returns
    -------
    ArticulatedModel
    """
    if not isinstance(skeleton, ArticulatedSkeleton):
        raise ValueError(f"skeleton must be an ArticulatedSkeleton, got {type(skeleton).__name__}")
    if not 1 <= int(max_influences) <= 4:
        raise ValueError(f"max_influences must be within 1..4, got {max_influences}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    act = None if active is None else np.asarray(active, dtype=bool).reshape(-1)
    if act is not None and (act.shape != (len(v),) or not act.any()):
        raise ValueError(f"active must be a (V,) boolean mask with at least one vertex, got shape {act.shape}")
    sk = skeleton
    if len(sk.bones) == 0:
        # a single joint: everything moves rigidly with the root
        return ArticulatedModel(v, f, sk, np.zeros((len(v), 1), dtype=np.int64), np.ones((len(v), 1)), act)
    W = bone_heat_weights(v, f, sk.rest[sk.bones[:, 0]], sk.rest[sk.bones[:, 1]])
    cols, w = limit_influences(W, max_influences=max_influences)
    return ArticulatedModel(v, f, sk, cols, w, act)


# --------------------------------------------------------------------------- pose algebra


def _skew_batch(a: np.ndarray) -> np.ndarray:
    out = np.zeros(a.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -a[..., 2], a[..., 1]
    out[..., 1, 0], out[..., 1, 2] = a[..., 2], -a[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -a[..., 1], a[..., 0]
    return out


def _rotations(M: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the nearest rotations (polar decomposition by SVD)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-1])
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def _forward(model: ArticulatedModel, root_R, root_t, local: np.ndarray) -> Pose:
    """Global part transforms from the root motion and the local rotations.

    Every rotation is first projected onto the rotations: a pose is carried from frame to frame
    and iteration to iteration through ``_local`` (``R_parent^T R_p``), and along a chain of tens of
    parts the rounding of ``R_parent^T`` as the inverse would otherwise grow with every pass
    (the deepest parts shear and scale).
    """
    sk = model.skeleton
    P = sk.n_parts
    local = _rotations(np.asarray(local, dtype=np.float64))
    R = np.empty((P, 3, 3))
    t = np.empty((P, 3))
    R[0], t[0] = _rotations(np.asarray(root_R, dtype=np.float64)), root_t
    c = model.pivots
    for level in _levels(model):  # the parts one step deeper than the last level, all at once
        q = sk.part_parent[level]
        R[level] = R[q] @ local[level]
        t[level] = (R[q] @ c[level][:, :, None])[:, :, 0] + t[q] - (R[level] @ c[level][:, :, None])[:, :, 0]
    return Pose(R, t)


def _levels(model: ArticulatedModel) -> list:
    """The parts but the root by depth in the part tree (the root's children first), cached on the model."""
    if "levels" not in model._cache:
        parent = model.skeleton.part_parent
        depth = np.zeros(model.skeleton.n_parts, dtype=np.int64)
        for p in range(1, len(depth)):  # parents come first
            depth[p] = depth[parent[p]] + 1
        model._cache["levels"] = [np.flatnonzero(depth == d) for d in range(1, int(depth.max(initial=0)) + 1)]
    return model._cache["levels"]


def _local(model: ArticulatedModel, pose: Pose) -> np.ndarray:
    L = np.empty_like(pose.R)
    L[0] = np.eye(3)
    L[1:] = pose.R[model.skeleton.part_parent[1:]].transpose(0, 2, 1) @ pose.R[1:]
    return L


def _kabsch(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    H = X.T @ Y
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    return Vt.T @ D @ U.T


def procrustes_pose(model: ArticulatedModel, target, rows: np.ndarray | None = None) -> Pose:
    """Closed-form start: every part's rotation about its carried joint (Arun et al. 1987).

    The vertices of a part are those whose strongest influence it drives
    (``rows``: only those vertices, e.g. the least-squares subset).
    """
    y = np.asarray(target, dtype=np.float64)
    x = model.vertices
    dom = model.vertex_parts[:, 0]
    if rows is not None:
        x, y, dom = x[rows], y[rows], dom[rows]
    sk = model.skeleton
    P = sk.n_parts
    m0 = dom == 0
    if m0.sum() < 3:
        m0 = np.ones(len(x), dtype=bool)
    cx, cy = x[m0].mean(0), y[m0].mean(0)
    R0 = _kabsch(x[m0] - cx, y[m0] - cy)
    t0 = cy - R0 @ cx
    R = np.tile(np.eye(3), (P, 1, 1))
    t = np.zeros((P, 3))
    R[0], t[0] = R0, t0
    c = model.pivots
    for p in range(1, P):  # parents come first
        m = dom == p
        q = sk.part_parent[p]
        cw = R[q] @ c[p] + t[q]
        R[p] = _kabsch(x[m] - c[p], y[m] - cw) if m.sum() >= 3 else R[q]
        t[p] = cw - R[p] @ c[p]
    pose = Pose(R, t)
    return pose


def fit_frame(model: ArticulatedModel, target, start: Pose | None = None, *, iterations: int = 10,
              tol: float = 1e-5, max_points: int | None = 3000) -> tuple[Pose, float]:
    """Least-squares pose of the model for one frame (Gauss-Newton on the skinned vertices).

    Parameters
    ----------
    model : ArticulatedModel
    target : (V, 3) float ndarray
        The frame's vertices, in the model's vertex order.
    start : Pose, optional
        Initial pose (default: :func:`procrustes_pose`).
    iterations : int
        Gauss-Newton iterations at most.
    tol : float
        Stop when the update is below this (radians, and this times the
        subject's size for translations).
    max_points : int or None
        The least squares run on at most this many vertices (a fixed,
        evenly drawn subset: the pose of a few dozen parts is determined many
        times over); ``None`` uses all. The error is over all vertices.

    Returns
    -------
    pose : Pose
    error : float
        Mean vertex distance ``mean_v ||x'_v - y_v||`` over all vertices.
    """
    y = np.asarray(target, dtype=np.float64)
    if y.shape != model.vertices.shape:
        raise ValueError(f"target must have shape {model.vertices.shape}, got {y.shape}")
    pose = procrustes_pose(model, y) if start is None else start
    pose = fit_subset(model, y[model.subset(max_points)], pose, iterations=iterations, tol=tol, max_points=max_points)
    act = None if model.active is None else model.subset(None)
    err = float(np.linalg.norm(model.deform(pose, act) - (y if act is None else y[act]), axis=1).mean())
    return pose, err


def fit_subset(model: ArticulatedModel, target, start: Pose, *, iterations: int = 10, tol: float = 1e-5,
               max_points: int | None = 3000) -> Pose:
    """:func:`fit_frame` given only the targets of its least-squares subset (``model.subset(max_points)``,
    in that order), without the error over all vertices: what an articulated ICP needs, whose
    targets exist only where it paired vertices.

    Parameters
    ----------
    model : ArticulatedModel
    target : (S, 3) float ndarray
        Targets of the vertices ``model.subset(max_points)``.
    start : Pose
    iterations, tol, max_points
        As :func:`fit_frame`'s.

    Returns
    -------
    Pose
    """
    sub = model.subset(max_points)
    y = np.asarray(target, dtype=np.float64)
    if y.shape != (len(sub), 3):
        raise ValueError(f"target must have shape {(len(sub), 3)} (the subset's vertices), got {y.shape}")
    if not isinstance(start, Pose):
        raise ValueError(f"start must be a Pose, got {type(start).__name__}")
    pose = start
    sk = model.skeleton
    P = sk.n_parts
    x = model.vertices[sub]
    size = float(np.linalg.norm(x.max(0) - x.min(0))) or 1.0
    lsq = _lsq_weights(model, max_points)

    def linearise(pose):
        return _normal_equations(model, pose, x, y, lsq)

    def step(pose, delta, cw):
        dt, om = delta[:3], delta[3:].reshape(P, 3)
        Rinc = Rotation.from_rotvec(om).as_matrix()
        local = _local(model, pose)
        g0 = cw[0]  # the root turns about its carried joint, then translates
        root_R = Rinc[0] @ pose.R[0]
        root_t = Rinc[0] @ (pose.t[0] - g0) + g0 + dt
        Rq = pose.R[sk.part_parent[1:]]
        local[1:] = Rq.transpose(0, 2, 1) @ Rinc[1:] @ Rq @ local[1:]
        return _forward(model, root_R, root_t, local)

    sse, H, g, cw = linearise(pose)
    mu = 1e-3  # Marquardt's damping, relative to the diagonal of H (dimensionless)
    for _ in range(int(iterations)):  # Levenberg-Marquardt
        try:
            delta = -np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-9 * size * size), g)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(delta)):  # a singular system (a part with no vertices): keep the pose
            break
        # early stop: the linear model promises (almost) nothing more, or the step is negligible
        gain = -(2.0 * float(delta @ g) + float(delta @ H @ delta))
        if gain <= 1e-4 * sse or (np.abs(delta[3:]).max() < tol and np.abs(delta[:3]).max() < tol * size):
            break
        cand = step(pose, delta, cw)
        c_sse, c_H, c_g, c_cw = linearise(cand)
        if np.isfinite(c_sse) and c_sse < sse:
            done = sse - c_sse <= 1e-4 * sse
            pose, sse, H, g, cw = cand, c_sse, c_H, c_g, c_cw
            mu /= 3.0
            if done:
                break
        else:
            mu *= 4.0
            if mu > 1e8:
                break
    return pose


def _lsq_weights(model: ArticulatedModel, max_points: int | None) -> dict:
    """Per-subset constants of the normal equations, cached on the model.

    ``W`` (V, P) sparse skinning weight of every part (:attr:`ArticulatedModel.part_weights` of the
    subset's rows) and ``WT`` its transpose; the rest vertices' moments by part, ``n1`` (P,) and ``m1``
    (P, 3), the sums of ``W[v, a] [1, x_v]``, and by pair of parts ``(a, b)`` that share a vertex,
    ``a``, ``b`` (N,) and ``n2`` (N,), ``m2`` (N, 3), ``s2`` (N, 3, 3), the sums of
    ``W[v, a] W[v, b] [1, x_v, x_v x_v^T]``; the subtree sums as sparse matrices: ``below`` (P, P)
    (``below[p, a]``: part ``a`` is ``p`` or in its subtree) and ``pairs`` (P P, N) (``pairs[p P + q, i]``:
    ``a_i`` below ``p`` and ``b_i`` below ``q``).
    """
    from scipy import sparse

    key = ("lsq", max_points)
    if key not in model._cache:
        sub = model.subset(max_points)
        x = model.vertices[sub]
        W = sparse.csr_matrix(model.part_weights[sub])
        WT = sparse.csr_matrix(W.T)
        P = model.skeleton.n_parts
        n2 = (WT @ W).toarray()
        a, b = np.nonzero(n2)
        m2 = np.stack([(WT @ W.multiply(x[:, [i]])).toarray()[a, b] for i in range(3)], axis=1)
        s2 = np.stack([(WT @ W.multiply((x[:, i] * x[:, j])[:, None])).toarray()[a, b]
                       for i in range(3) for j in range(3)], axis=1).reshape(-1, 3, 3)
        up = [np.flatnonzero(row) for row in model.below]  # the parts every part is below: itself and its ancestors
        rows = [(p * P + q, i) for i in range(len(a)) for p in up[a[i]] for q in up[b[i]]]
        r, c = np.array(rows, dtype=np.int64).reshape(-1, 2).T
        pairs = sparse.csr_matrix((np.ones(len(r)), (r, c)), shape=(P * P, len(a)))
        model._cache[key] = {"W": W, "WT": WT, "below": sparse.csr_matrix(model.below.T.astype(np.float64)),
                             "pairs": pairs, "a": a, "b": b, "n1": np.asarray(WT.sum(1)).ravel(), "m1": WT @ x,
                             "n2": n2[a, b], "m2": m2, "s2": s2}
    return model._cache[key]


def _normal_equations(model: ArticulatedModel, pose: Pose, x: np.ndarray, y: np.ndarray, lsq: dict):
    """Gauss-Newton normal equations of the skinned fit at ``pose``: (sum of squares, H, g, carried joints).

    ``x``: the rest vertices of the subset ``lsq`` was made for (:func:`_lsq_weights`), ``y`` their targets.
    The Jacobian of a rotation increment ``omega_p`` about the part's carried joint ``c_p`` is
    ``-[A_vp]_x`` with ``A_vp = sum_a W_va [a below p] (q_va - c_p)`` (``q_va = R_a x_v + t_a``, the
    vertex moved by part ``a``, ``W_va`` its skinning weight). ``J^T J`` needs ``sum_v A_vp A_vq^T``
    for every pair of parts: a vertex's ``A`` is not zero for every ancestor of its parts, so on a
    deep tree most pairs are filled. Expanded, ``A_vp A_vq^T`` is a sum over pairs of parts ``(a, b)``
    of ``W_va W_vb (q_va - c_p)(q_vb - c_q)^T`` wherever ``a`` is below ``p`` and ``b`` below ``q``. The
    moments ``sum_v W_va W_vb [1, q_va, q_vb, q_va q_vb^T]`` are those of the rest vertices
    (``[1, x, x x^T]``, constant, :func:`_lsq_weights`) moved by the parts' current motions: a few
    small products per pair of parts that share a vertex, not a pass over the vertices; then summed
    over subtrees (one sparse product). The same for ``sum_v A_vp`` and ``sum_v A_vp r_v^T``, which
    need one pass over the vertices for the residuals ``r``. The cost grows with ``V P`` and the
    pairs' subtrees instead of ``V (3P)^2``.
    """
    P = model.skeleton.n_parts
    R, t = pose.R, pose.t
    T = lsq["W"] @ np.concatenate([R.reshape(P, 9), t], 1)  # every vertex's blended affine map
    r = np.einsum("vij,vj->vi", T[:, :9].reshape(-1, 3, 3), x) + T[:, 9:] - y
    cw = np.einsum("pij,pj->pi", R, model.pivots) + t  # carried joints
    Ra, Rb, ta, tb, n2 = R[lsq["a"]], R[lsq["b"]], t[lsq["a"]], t[lsq["b"]], lsq["n2"][:, None]
    ma = (Ra @ lsq["m2"][:, :, None])[:, :, 0]  # sum W_a W_b R_a x
    mb = (Rb @ lsq["m2"][:, :, None])[:, :, 0]
    S = Ra @ lsq["s2"] @ Rb.transpose(0, 2, 1) + ma[:, :, None] * tb[:, None, :] + ta[:, :, None] * mb[:, None, :] \
        + n2[:, :, None] * (ta[:, :, None] * tb[:, None, :])
    X2 = np.concatenate([n2, ma + n2 * ta, mb + n2 * tb, S.reshape(-1, 9)], axis=1)  # (pairs, 16)
    Z2 = (lsq["pairs"] @ X2).reshape(P, P, 16)  # summed over subtrees
    n, m, mq = Z2[..., 0], Z2[..., 1:4], Z2[..., 4:7]
    S = Z2[..., 7:].reshape(P, P, 3, 3)
    Mpq = (S - cw[:, None, :, None] * mq[:, :, None, :] - m[..., :, None] * cw[None, :, None, :]
           + n[..., None, None] * (cw[:, None, :, None] * cw[None, :, None, :]))
    M = Mpq.transpose(0, 2, 1, 3)  # M[p, i, q, j] = sum_v A_vp,i A_vq,j
    # per part a: sum_v W_va [q_va, r_v, q_va r_v^T], q_va r_v^T = R_a x_v r_v^T + t_a r_v^T
    F1 = lsq["WT"] @ np.concatenate([r, (x[:, :, None] * r[:, None, :]).reshape(-1, 9)], axis=1)  # (P, 12)
    qsum = np.einsum("aij,aj->ai", R, lsq["m1"]) + lsq["n1"][:, None] * t
    qr = np.einsum("aij,ajk->aik", R, F1[:, 3:].reshape(P, 3, 3)) + t[:, :, None] * F1[:, None, :3]
    Z1 = lsq["below"] @ np.concatenate([qsum, F1[:, :3], qr.reshape(P, 9)], axis=1)  # (P, 15), summed over subtrees
    n1 = lsq["below"] @ lsq["n1"]
    Asum = Z1[:, :3] - n1[:, None] * cw
    C = Z1[:, 6:].reshape(P, 3, 3) - cw[:, :, None] * Z1[:, None, 3:6]  # sum_v A_vp r_v^T
    # normal equations of J = [I, -[A_v0]_x, ..., -[A_vP-1]_x]: [a]_x^T [b]_x = (a.b) I - b a^T
    tr = np.einsum("piqi->pq", M)
    Hww = tr[:, None, :, None] * np.eye(3)[None, :, None, :] - M.transpose(0, 3, 2, 1)
    V = len(x)
    n_par = 3 * (P + 1)
    H = np.empty((n_par, n_par))
    H[:3, :3] = V * np.eye(3)
    H[:3, 3:] = -_skew_batch(Asum).transpose(1, 0, 2).reshape(3, 3 * P)
    H[3:, :3] = H[:3, 3:].T
    H[3:, 3:] = Hww.reshape(3 * P, 3 * P)
    g = np.r_[r.sum(0), np.stack([C[:, 1, 2] - C[:, 2, 1], C[:, 2, 0] - C[:, 0, 2], C[:, 0, 1] - C[:, 1, 0]], 1).ravel()]
    return float((r * r).sum()), H, g, cw


def predict_pose(model: ArticulatedModel, pose: Pose, before: Pose) -> Pose:
    """Constant-velocity prediction of the next pose from the last two.

    Every local rotation repeats its last change (``L' = L L_before^T L``),
    the root rotation likewise, and the root joint moves on by its last step.
    """
    L1, L0 = _local(model, pose), _local(model, before)
    L2 = np.einsum("pij,pkj,pkl->pil", L1, L0, L1)
    R2 = pose.R[0] @ before.R[0].T @ pose.R[0]
    c = model.pivots[0]
    g1, g0 = pose.R[0] @ c + pose.t[0], before.R[0] @ c + before.t[0]
    return _forward(model, R2, 2.0 * g1 - g0 - R2 @ c, L2)


def _deform_subset(model: ArticulatedModel, pose: Pose, sub: np.ndarray) -> np.ndarray:
    return model.deform(pose, sub)


@dataclass(frozen=True, eq=False)
class FitResult:
    """Poses and errors of a sequence.

    Attributes
    ----------
    poses : list of Pose
    errors : (T,) float ndarray
        Mean vertex error per frame (units of the input).
    joints : (T, J, 3) float ndarray
        Joint positions per frame.
    """

    poses: list
    errors: np.ndarray
    joints: np.ndarray


def fit_sequence(model: ArticulatedModel, frames, *, iterations: int = 10, progress=None) -> FitResult:
    """Fit every frame, starting each from the previous frame's pose.

    Parameters
    ----------
    model : ArticulatedModel
    frames : (T, V, 3) float ndarray
    iterations : int
    progress : callable, optional
        Called with the frame number after each frame.

    Returns
    -------
    FitResult
    """
    Y = np.asarray(frames, dtype=np.float64)
    if Y.ndim != 3 or Y.shape[1:] != model.vertices.shape:
        raise ValueError(f"frames must have shape (T, {len(model.vertices)}, 3), got {Y.shape}")
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, "blas"):  # small dense products: threads only contend
        return _fit_sequence(model, Y, iterations, progress)


def _fit_sequence(model, Y, iterations, progress) -> FitResult:
    poses, errs, joints = [], [], []
    prev = None
    sub = model.subset(3000)
    last_err = np.inf
    for t in range(len(Y)):
        start = prev
        if prev is not None:
            e_prev = np.linalg.norm(_deform_subset(model, prev, sub) - Y[t][sub], axis=1).mean()
        if len(poses) >= 2:  # constant velocity from the two previous frames, when it predicts better
            pred = predict_pose(model, poses[-1], poses[-2])
            e_pred = np.linalg.norm(_deform_subset(model, pred, sub) - Y[t][sub], axis=1).mean()
            if e_pred < e_prev:
                start, e_prev = pred, e_pred
        cand = procrustes_pose(model, Y[t], sub)
        e_new = np.linalg.norm(_deform_subset(model, cand, sub) - Y[t][sub], axis=1).mean()
        if prev is None or (e_prev > 2.0 * last_err and e_new < e_prev):  # fast motion: the closed-form start
            start = cand
        pose, e = fit_frame(model, Y[t], start, iterations=iterations)
        if start is not cand and e_new < e:  # the tracked pose fell into a worse basin: fit from the closed form
            pose2, e2 = fit_frame(model, Y[t], cand, iterations=iterations)
            if e2 < e:
                pose, e = pose2, e2
        last_err = e
        poses.append(pose)
        errs.append(e)
        joints.append(model.joint_positions(pose))
        prev = pose
        if progress is not None:
            progress(t)
    return FitResult(poses, np.asarray(errs), np.asarray(joints))
