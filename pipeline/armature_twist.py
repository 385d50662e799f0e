"""A prior on an armature's parts' twists about their own axes relative to their parents.

A round limb turns about its own axis without moving its surface: the point-to-plane pairs of the articulated ICP
(:func:`pipeline.armature_track.fit_pose_to_surface`) do not see that turn. :func:`twist_prior` makes a term that
keeps every part's twist relative to its parent near a reference pose's (the previous frame's), as far as the
surface does not see it; :func:`pipeline.armature_fit.fit_subset` adds it to its sum of squares (``twist=``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.armature_fit import ArticulatedModel, Pose, _local
from pipeline.mesh_primitives import vertex_normals

__all__ = ["TwistPrior", "twist_prior", "relative_twists", "twist_terms"]


@dataclass(frozen=True, eq=False)
class TwistPrior:
    """A prior on every part's turn about its own axis relative to its parent (:func:`twist_prior`).

    Attributes
    ----------
    local : (P, 3, 3) float ndarray
        The local rotations (``R_parent^T R_p``) whose twists the prior keeps.
    axes : (P, 3) float ndarray
        Every part's unit axis at rest (zero: no prior on the part, the root's).
    weights : (P,) float ndarray
        The prior's weight on every part's twist (mm^2 per radian^2; zero for the root).
    """

    local: np.ndarray
    axes: np.ndarray
    weights: np.ndarray


def _part_axes(model: ArticulatedModel) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) every part's unit axis at rest: from its joint to the centroid of the vertices it and the parts below it
    drive most (zero for the root and a part without such vertices), and (V,) every vertex's part
    (``vertex_parts[:, 0]``)."""
    if "axes" not in model._cache:
        dom = model.vertex_parts[:, 0]
        P = model.skeleton.n_parts
        axes = np.zeros((P, 3))
        below = model.below
        for p in range(1, P):
            mine = below[dom, p]
            if mine.any():
                d = model.vertices[mine].mean(0) - model.pivots[p]
                n = np.linalg.norm(d)
                axes[p] = d / n if n > 0 else 0.0
        model._cache["axes"] = axes
    return model._cache["axes"], model.vertex_parts[:, 0]


def twist_prior(model: ArticulatedModel, reference: Pose, strength: float, *, axes=None, normals=None,
                max_points: int | None = 3000) -> TwistPrior:
    """A prior that keeps every part's twist about its own axis, relative to its parent, at ``reference``'s.

    Part ``p``'s twist is the angle ``tau_p`` about its axis ``a_p`` at rest (``axes``, or from its joint to the
    centroid of its and its descendants' vertices: the line a limb turns about) of the turn ``L_ref,p^T L_p`` from the
    reference's local rotation to the pose's (swing-twist decomposition). :func:`pipeline.armature_fit.fit_subset`
    adds ``w_p tau_p^2`` to its sum of squares, with ``w_p = strength sum_v |m_v - (m_v . n_v) n_v|^2`` over the
    part's vertices of the least-squares subset: ``m_v = a_p x (x_v - c_p)`` is how the turn moves vertex ``v``
    (``c_p`` the part's joint), ``n_v`` its normal at rest, so ``w_p`` counts the share of the turn that slides the
    part's surface along itself, which point-to-plane pairs do not see (a round limb's turn about its axis: all of
    it; a flat or bent part's: less). At ``strength`` 1 the prior weighs as much as the part's vertices would if each
    held its place along the surface.

    Parameters
    ----------
    model : ArticulatedModel
    reference : Pose
        The pose whose parts' twists relative to their parents are kept (e.g. the previous frame's).
    strength : float
        Positive.
    axes : (P, 3) float array_like, optional
        Every part's axis at rest (any length; a zero row: no prior on that part). Default: from the part's joint to
        the centroid of the vertices it and the parts below it drive most (the root none).
    normals : (V, 3) float array_like, optional
        The model's unit vertex normals at rest (default: the rest mesh's, zero for a vertex in no face; a zero
        normal counts the vertex's whole motion).
    max_points : int or None
        The least-squares subset the prior is used with (:func:`pipeline.armature_fit.fit_subset`'s ``max_points``).

    Returns
    -------
    TwistPrior
    """
    if not isinstance(model, ArticulatedModel):
        raise ValueError(f"model must be an ArticulatedModel, got {type(model).__name__}")
    if not isinstance(reference, Pose) or reference.R.shape != (model.skeleton.n_parts, 3, 3):
        raise ValueError(f"reference must be a Pose of the model's {model.skeleton.n_parts} parts")
    if isinstance(strength, bool) or not isinstance(strength, (int, float, np.floating)) or not np.isfinite(strength) \
            or strength <= 0:
        raise ValueError(f"strength must be a positive number, got {strength!r}")
    own, dom = _part_axes(model)
    if axes is None:
        axes = own
    else:
        axes = np.asarray(axes, dtype=np.float64)
        if axes.shape != own.shape or not np.isfinite(axes).all():
            raise ValueError(f"axes must be a finite {own.shape} array, got shape {axes.shape}")
        n = np.linalg.norm(axes, axis=1, keepdims=True)
        axes = np.where(n > 0, axes / np.where(n > 0, n, 1.0), 0.0)
        axes[0] = 0.0
    if normals is None:
        normals = _rest_normals(model)
    else:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != model.vertices.shape or not np.isfinite(normals).all():
            raise ValueError(f"normals must be a finite {model.vertices.shape} array, got shape {normals.shape}")
    sub = model.subset(max_points)
    m = np.cross(axes[dom[sub]], model.vertices[sub] - model.pivots[dom[sub]])
    nv = normals[sub]
    slide = m - np.einsum("ij,ij->i", m, nv)[:, None] * nv
    w = float(strength) * np.bincount(dom[sub], weights=np.einsum("ij,ij->i", slide, slide),
                                      minlength=model.skeleton.n_parts)
    w[0] = 0.0
    return TwistPrior(_local(model, reference), axes, w)


def _rest_normals(model: ArticulatedModel) -> np.ndarray:
    """(V, 3) the rest mesh's unit vertex normals (zero for a vertex in no face), cached on the model."""
    if "normals" not in model._cache:
        model._cache["normals"] = vertex_normals(model.vertices, model.faces) if len(model.faces) else \
            np.zeros_like(model.vertices)
    return model._cache["normals"]


def relative_twists(model: ArticulatedModel, pose: Pose, prior: TwistPrior) -> np.ndarray:
    """(P,) every part's twist (radians) about its axis at rest (``prior.axes``) of the turn ``L_ref^T L`` from the
    prior's local rotations to ``pose``'s (swing-twist decomposition); 0 for a part without an axis."""
    return _twists(model, pose, prior.local, prior.axes)[0]


def _twists(model: ArticulatedModel, pose: Pose, local_reference: np.ndarray, axes: np.ndarray):
    """(P,) the twists of :func:`relative_twists` and (P, 3) their derivatives by the parts' world rotation
    increments ``omega_p`` (:func:`pipeline.armature_fit.fit_subset`'s unknowns; ``R_p -> exp(omega_p) R_p``)."""
    D = np.einsum("pji,pjk->pik", local_reference, _local(model, pose))
    q = Rotation.from_matrix(D).as_quat()  # x, y, z, w
    q = np.where(q[:, 3:] < 0, -q, q)  # the one of q, -q with w >= 0: the turn's angle within (-pi, pi]
    v, w = q[:, :3], q[:, 3]
    p = np.einsum("pi,pi->p", v, axes)
    tau = 2.0 * np.arctan2(p, w)
    # D exp(delta) (delta in the part's rest frame, R_p^T omega): dq = q (delta, 0) / 2, then tau = 2 atan2(v.a, w)
    n = np.maximum(p * p + w * w, 1e-12)
    dd = (w[:, None] * (w[:, None] * axes + np.cross(axes, v)) + p[:, None] * v) / n[:, None]
    return tau, np.einsum("pij,pj->pi", pose.R, dd)


def twist_terms(model: ArticulatedModel, pose: Pose, prior: TwistPrior):
    """The prior's (sum of squares, H, g) in :func:`pipeline.armature_fit.fit_subset`'s unknowns (3 translation, then 3 per part)."""
    tau, J = _twists(model, pose, prior.local, prior.axes)
    P = len(tau)
    H = np.zeros((3 * (P + 1), 3 * (P + 1)))
    for p in np.flatnonzero(prior.weights):
        H[3 + 3 * p:6 + 3 * p, 3 + 3 * p:6 + 3 * p] = prior.weights[p] * np.outer(J[p], J[p])
    g = np.concatenate([np.zeros(3), ((prior.weights * tau)[:, None] * J).ravel()])
    return float((prior.weights * tau * tau).sum()), H, g
