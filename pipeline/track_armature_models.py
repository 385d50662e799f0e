"""The armatures the rounds of :func:`pipeline.track_armature.track_with_armature` track with.

The motion's (:func:`_rig_of`: the motion segmentation of the tracking, :func:`pipeline.armature.build_armature`), the
take's spine rig as the first round's (:func:`spine_armature`, :func:`_spine_rig`), and the labels' limbs as chains
of rigid intervals along the spine's limb axes (:func:`_limb_rig`; the labels from
:mod:`pipeline.track_armature_labels`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["spine_armature", "SPINE_BONES"]

log = logging.getLogger("pipeline.track")

#: Bones per spine axis (limb, or the axis between two junctions) of the first round's armature
#: (:func:`spine_armature`): a limb's two halves turn on their own (six or three bones a limb track the fast
#: biped worse; docs/tracking.md, "The take's spine as the first armature").
SPINE_BONES = 2


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


def _limb_rig(vs: np.ndarray, faces: np.ndarray, frames: list[int], refi: int, labels: np.ndarray, axes: list):
    """The armature of a tracking from the template's labels: the body one part, every limb a chain of the intervals
    :func:`pipeline.limb_segments.limb_segments` cuts along its axis, rigid (``entry["cut"]``); -> as :func:`_rig_of`. The
    cuts' noise ratio is measured on the body (``limb_segments``' default); ``stage armature --parts limbs`` measures it on
    every limb (``rho="limb"``), not better for the round on every take (docs/tracking.md, "The round's armature from the labels").
    The cuts keep ``limb_segments``' default ``centres=False``: a cut ``armature_results(parts="limbs")`` drops as no joint
    still gives the round's skinned pose a freedom the surfaces use (the same section)."""
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


def spine_armature(rigged):
    """The take's spine rig as an armature: the first round's of :func:`pipeline.track_armature.track_with_armature`.

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
