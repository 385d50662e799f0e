"""Which limb of a take's spine every template vertex lies on: structure for an armature built from motion.

A take's spine (Brostow et al. 2004, :mod:`pipeline.spine`) is built from every frame's visual hull, so
it does not share the tracking's drift. Bound to the tracked template by bone heat weights
(:func:`pipeline.armature_spine.rigged_model`), it says which limb every vertex lies on: the spine axis of
its heaviest bone, or the *body*: the axes between junctions, and the first bone of every limb, which
starts at a junction (where the limbs' level sets meet, in the middle of the body).

:func:`pipeline.armature_skeleton.articulated_skeleton` uses it (``limbs``) where the segments' adjacency
closes a cycle (parts that touch): a segment on one limb is never hung from a segment on another limb
while the kinematic tree can be closed through the body. Two limbs that touch (a thigh against a thigh,
a leg tucked against a leg) share no joint; their relative motion composes two.

Written by hand: a majority vote over arrays that no library offers in this form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["VertexLimbs", "BODY", "vertex_limbs", "segment_limbs", "limb_pairs", "limbs_last", "check_limbs"]

#: the limb index of the body (the junctions, the axes between them and every limb's first bone)
BODY = -1


@dataclass(frozen=True, eq=False)
class VertexLimbs:
    """The spine limb of every template vertex.

    Attributes
    ----------
    limb : (V,) int ndarray
        Index into ``names``, or :data:`BODY`.
    names : tuple of str
        The spine's limb axes (``limb0`` ...).
    """

    limb: np.ndarray
    names: tuple


def vertex_limbs(model) -> VertexLimbs:
    """The limb of every vertex of a mesh bound to a spine's armature: the axis of its heaviest bone.

    Parameters
    ----------
    model : pipeline.armature_spine.RiggedModel
        The template bound to the take's spine (``joints`` ordered by decreasing weight).

    Returns
    -------
    VertexLimbs
        Joints whose name is their element (the root and the junctions), the axes they name and the
        first bone below each of them are the body; every other axis is a limb.
    """
    from pipeline.armature_spine import RiggedModel

    if not isinstance(model, RiggedModel):
        raise ValueError(f"model must be a pipeline.armature_spine.RiggedModel, got {type(model).__name__}")
    rig = model.rig
    body = {e for n, e in zip(rig.names, rig.element) if n == e}  # root and junction joints name their element
    names = tuple(sorted({e for e in rig.element if e not in body}))
    index = {n: i for i, n in enumerate(names)}
    of_joint = np.array([index.get(e, BODY) for e in rig.element], dtype=np.int64)
    # a limb's first bone starts at a junction, in the middle of the body: its vertices are the body's
    of_joint[[p >= 0 and rig.names[p] == rig.element[p] for p in rig.parents]] = BODY
    return VertexLimbs(of_joint[np.asarray(model.joints)[:, 0]], names)


def segment_limbs(labels, limb) -> np.ndarray:
    """(S,) the limb most vertices of every segment lie on (:data:`BODY` included; ties: the lower index).

    Parameters
    ----------
    labels : (V,) int array_like
        Segment of every vertex, ``0 .. S-1``.
    limb : (V,) int array_like
        Limb of every vertex (:attr:`VertexLimbs.limb`).
    """
    lab = np.asarray(labels).reshape(-1)
    lb = np.asarray(limb).reshape(-1)
    if lab.shape != lb.shape or len(lab) == 0 or not np.issubdtype(lab.dtype, np.integer) or lab.min() < 0:
        raise ValueError(f"labels and limb must have one entry per vertex (integers, labels >= 0), got "
                         f"{lab.shape} and {lb.shape}")
    if not np.issubdtype(lb.dtype, np.integer) or lb.min() < BODY:
        raise ValueError(f"limb must hold limb indices or BODY ({BODY})")
    counts = np.zeros((int(lab.max()) + 1, int(lb.max()) + 2), dtype=np.int64)
    np.add.at(counts, (lab, lb + 1), 1)
    return counts.argmax(1) - 1


def limb_pairs(pairs, seg_limbs) -> set:
    """The segment pairs whose two segments lie on two different limbs (neither on the body)."""
    sl = np.asarray(seg_limbs)
    return {tuple(p) for p in pairs if sl[p[0]] != BODY and sl[p[1]] != BODY and sl[p[0]] != sl[p[1]]}


def limbs_last(residual: dict, labels, limbs) -> tuple[dict, set]:
    """Joint residuals of adjacent segment pairs (pair -> float) with every pair on two different limbs raised
    above all the others, so that a minimum spanning tree takes those pairs last; and those pairs.

    Parameters
    ----------
    residual : dict
        ``(a, b) -> residual`` (:func:`pipeline.armature_skeleton.joint_residual`).
    labels : (V,) int array_like
        Segment of every vertex.
    limbs : (V,) int array_like
        Limb of every vertex (:attr:`VertexLimbs.limb`).
    """
    across = limb_pairs(list(residual), segment_limbs(labels, limbs))
    last = 1.0 + 2.0 * max((abs(r) for r in residual.values()), default=0.0)  # above every other pair's weight
    return {pair: r + last if pair in across else r for pair, r in residual.items()}, across


def check_limbs(limbs, n: int, *, name: str = "limbs") -> np.ndarray:
    """``limbs`` as an (n,) int array (the limb of every vertex, :data:`BODY` or an index); ValueError naming it
    ``name``."""
    lb = np.asarray(limbs)
    if lb.shape != (n,) or not np.issubdtype(lb.dtype, np.integer) or (len(lb) and lb.min() < BODY):
        raise ValueError(f"{name} must hold the spine limb of every vertex ({n},) as integers >= {BODY}, got "
                         f"shape {lb.shape}")
    return lb
