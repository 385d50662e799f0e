"""Mesh sequences with shared connectivity and true joints, from the simulated creatures.

A rest mesh (marching cubes of the creature's signed distance at the rest
time) is posed along the creature's kinematic tree: every vertex belongs to
the capsule nearest to it at rest and moves rigidly with it (the body's
capsules with the body, limb segment ``i`` with the body, the limb's swing
and the bend angles of joints ``0..i``). Vertex ``i`` is thus the same
surface point in every frame, as the input of
:func:`pipeline.motion_segmentation.motion_segmentation` requires.

Ground truth (:class:`MeshSequence`): every limb joint's position per frame
and whether it *articulates* -- whether the rotation between the two parts
it joins changes by more than ``min_bend`` over the sequence (a joint with no
motion cannot be found from motion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fake_cameras.creatures import Creature, _rot, _unit, make_creature

__all__ = ["MeshSequence", "rest_mesh", "mesh_sequence"]


@dataclass(frozen=True, eq=False)
class MeshSequence:
    """A posed mesh sequence of a creature.

    Attributes
    ----------
    vertices : (T, V, 3) float ndarray
        mm.
    faces : (F, 3) int ndarray
    times : (T,) float ndarray
        Seconds.
    joint_names : tuple of str
        ``<limb>.<i>``: joint ``i`` of a limb (0 = where it meets the body).
    joints : (T, K, 3) float ndarray
        True joint positions per frame.
    articulates : (K,) bool ndarray
        The joints that bend during the sequence.
    part : (V,) int ndarray
        The rigid part of every vertex (-1: body; else ``limb * 16 + segment``).
    size : float
        Rest mesh bounding-box diagonal (mm).
    """

    vertices: np.ndarray
    faces: np.ndarray
    times: np.ndarray
    joint_names: tuple
    joints: np.ndarray
    articulates: np.ndarray
    part: np.ndarray
    size: float


def rest_mesh(creature: Creature, *, time_s: float = 0.0, voxel: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of the creature at ``time_s`` (mm).

    Returns
    -------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    """
    from skimage.measure import marching_cubes

    if not voxel > 0:
        raise ValueError(f"voxel must be > 0, got {voxel}")
    pose = creature.pose(time_s)
    lo, hi = pose.bounds()
    lo, hi = lo - 2 * voxel, hi + 2 * voxel
    axes = [np.arange(lo[k], hi[k] + voxel, voxel) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sdf = pose.sdf(grid).reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    v, f, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3)
    v = v + lo
    # marching cubes' faces wind inward for a negative-inside field: flip to outward normals
    return v.astype(np.float64), f[:, ::-1].astype(np.int64)


def _segment_frames(creature: Creature, t: float):
    """Per capsule (body first, then limb segments): rotation and origin in the world."""
    pos, R = creature._body_transform(t)
    mats, origins, joints = [], [], {}
    for _ in creature.body:
        mats.append(R)
        origins.append(pos)
    for lb in creature.limbs:
        w = 2 * math.pi * lb.freq
        R_swing = _rot(lb.swing_axis, lb.swing * math.sin(w * t + lb.phase)) if lb.swing else np.eye(3)
        axis = _unit(lb.bend_axis)
        chain = creature._limb_chain(lb, t)
        theta = 0.0
        for i in range(len(lb.lengths)):
            theta += lb.rest[i] + lb.amp[i] * math.sin(w * t + lb.phase - i * lb.lag)
            M = R @ R_swing @ _rot(axis, theta)
            mats.append(M)
            origins.append(R @ chain[i] + pos)
            joints[f"{lb.name}.{i}"] = (R @ chain[i] + pos, M)
    return mats, origins, joints


def mesh_sequence(
    name: str,
    *,
    frames: int = 40,
    duration: float | None = None,
    voxel: float = 8.0,
    seed: int = 0,
    scale: float = 1.0,
    min_bend: float = math.radians(10.0),
    dtype=np.float64,
) -> MeshSequence:
    """A creature's rest mesh posed along its kinematic tree over ``frames`` frames.

    Parameters
    ----------
    name : {"starfish", "quadruped", "biped"}
    frames : int
        Number of frames (>= 1).
    duration : float, optional
        Seconds covered (default: one period of the slowest limb).
    voxel : float
        Marching-cubes cell (mm): the mesh resolution.
    seed, scale
        As :func:`fake_cameras.creatures.make_creature`.
    min_bend : float
        A joint articulates when its relative rotation varies by more than
        this (radians) over the sequence.
    dtype : numpy dtype
        Of the vertices (float32 halves the memory of long, fine sequences).

    Returns
    -------
    MeshSequence
    """
    if int(frames) < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    cr = make_creature(name, seed=seed, scale=scale)
    if duration is None:
        duration = 1.0 / min(lb.freq for lb in cr.limbs)
    if not duration > 0:
        raise ValueError(f"duration must be > 0, got {duration}")
    times = np.linspace(0.0, float(duration), int(frames), endpoint=False)
    v0, f = rest_mesh(cr, time_s=0.0, voxel=voxel)
    pose0 = cr.pose(0.0)
    capsule = pose0.capsule_sdf(v0).argmin(1)
    mats0, org0, _ = _segment_frames(cr, 0.0)
    M0 = np.asarray(mats0)
    org0_a = np.asarray(org0)
    local = np.einsum("vji,vj->vi", M0[capsule], v0 - org0_a[capsule])  # vertex in its capsule's frame
    verts = np.empty((len(times), len(v0), 3), dtype=dtype)
    joint_pos, rel = [], []
    names = None
    for ti, t in enumerate(times):
        mats, org, joints = _segment_frames(cr, float(t))
        M = np.asarray(mats)
        org_a = np.asarray(org)
        verts[ti] = np.einsum("vij,vj->vi", M[capsule], local) + org_a[capsule]
        names = tuple(joints)
        joint_pos.append(np.asarray([joints[k][0] for k in names]))
        # relative rotation between the two parts a joint links
        pos, Rb = cr._body_transform(float(t))
        r = []
        for k in names:
            limb, i = k.rsplit(".", 1)
            i = int(i)
            parent = Rb if i == 0 else joints[f"{limb}.{i - 1}"][1]
            r.append(parent.T @ joints[k][1])
        rel.append(np.asarray(r))
    rel = np.asarray(rel)  # (T, K, 3, 3)
    # largest angle between the relative rotations of any two frames
    K = rel.shape[1]
    spread = np.zeros(K)
    for k in range(K):
        Rk = rel[:, k]
        cosang = (np.einsum("aij,bij->ab", Rk, Rk) - 1.0) / 2.0
        spread[k] = float(np.arccos(np.clip(cosang, -1.0, 1.0)).max())
    n_body = len(cr.body)
    part = np.where(capsule < n_body, -1, 0)
    seg_ids = []
    for li, lb in enumerate(cr.limbs):
        seg_ids += [li * 16 + i for i in range(len(lb.lengths))]
    seg_ids = np.asarray(seg_ids)
    part[capsule >= n_body] = seg_ids[capsule[capsule >= n_body] - n_body]
    size = float(np.linalg.norm(v0.max(0) - v0.min(0)))
    return MeshSequence(
        vertices=verts,
        faces=f,
        times=times,
        joint_names=names,
        joints=np.asarray(joint_pos),
        articulates=spread > min_bend,
        part=part,
        size=size,
    )
