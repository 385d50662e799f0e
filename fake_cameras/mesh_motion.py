"""Mesh sequences with shared connectivity and true joints, from the simulated creatures.

A rest mesh (marching cubes of the creature's signed distance in a scanning
pose) is posed along the creature's kinematic tree: every vertex belongs to
the capsule nearest to it at rest and moves rigidly with it (the body's
capsules with the body, limb segment ``i`` with the body, the limb's swing
and the bend angles of joints ``0..i``). Vertex ``i`` is thus the same
surface point in every frame, as the input of
:func:`pipeline.motion_segmentation.motion_segmentation` requires.

The scanning pose is the creature at time 0 with every limb that runs along
the body or another limb opened at its root (:func:`scan_opening`), the way
a template scan is taken (arms held away from the torso, an "A pose"): a
limb pressed against the body over its length would be fused to it in the
template, and no motion could then separate the two surfaces -- neither in
this simulation nor for a real scanned subject. Limbs already clear of
everything (a starfish's arms, a quadruped's legs) are not moved. Only the
template is opened; the motion itself is the creature's own.

Ground truth (:class:`MeshSequence`): every limb joint's position per frame
and whether it *articulates* -- whether the rotation between the two parts
it joins changes by more than ``min_bend`` over the sequence (a joint with no
motion cannot be found from motion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fake_cameras.creatures import Creature, Pose, _rot, _unit, make_creature

__all__ = ["MeshSequence", "rest_mesh", "mesh_sequence", "scan_opening", "true_joints"]


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
        Bounding-box diagonal of the first frame (mm).
    """

    vertices: np.ndarray
    faces: np.ndarray
    times: np.ndarray
    joint_names: tuple
    joints: np.ndarray
    articulates: np.ndarray
    part: np.ndarray
    size: float


def scan_opening(
    creature: Creature, *, gap: float = 1.0, step: float = math.radians(5.0), max_angle: float = math.radians(90.0)
) -> dict:
    """Per limb, the rotation about its root that holds it clear of the body for a template scan.

    A limb is opened (rotated about its attachment point, in the plane of
    its direction and the outward direction from the nearest body axis) by
    the smallest multiple of ``step`` at which every point of its axis beyond
    the junction (two root radii from the attachment, at most half the limb)
    is at least ``gap`` times the limb's local radius away from the surface
    of the body and of every other limb, at time 0. A limb that is already clear,
    or that no angle up to ``max_angle`` clears (a head on top of a torso,
    attached end-on), keeps its pose.

    Returns
    -------
    dict str -> (3, 3) float ndarray
        Body-frame rotation about the limb's ``attach`` point (identity when not opened).
    """
    if not gap >= 0 or not step > 0 or not max_angle >= 0:
        raise ValueError("gap must be >= 0, step > 0, max_angle >= 0")
    chains = {lb.name: creature._limb_chain(lb, 0.0) for lb in creature.limbs}
    body = [(np.asarray(a, float), np.asarray(b, float), ra, rb) for a, b, ra, rb in creature.body]
    out = {}
    for lb in creature.limbs:
        caps = body + [
            (c[i], c[i + 1], o.radii[i], o.radii[i + 1])
            for o in creature.limbs
            if o.name != lb.name
            for c in [chains[o.name]]
            for i in range(len(o.lengths))
        ]
        p0, p1, r0, r1 = (np.asarray(x, dtype=np.float64) for x in zip(*caps))
        out[lb.name] = _opening(lb, chains[lb.name], body, (p0, p1, r0, r1), gap, step, max_angle)
    return out


def _opening(lb, chain, body, caps, gap, step, max_angle) -> np.ndarray:
    """Smallest clearing rotation of one limb (see :func:`scan_opening`)."""
    from fake_cameras.creatures import round_cone_sdf

    att = np.asarray(lb.attach, dtype=np.float64)
    d = _unit(chain[-1] - chain[0])
    near = min((_closest_on_segment(att, a, b) for a, b, _, _ in body), key=lambda q: float(np.linalg.norm(att - q)))
    outward = att - near
    outward = outward - d * (outward @ d)
    axis = np.cross(d, outward)
    if np.linalg.norm(outward) < 1e-6 or np.linalg.norm(axis) < 1e-9:
        return np.eye(3)
    # the limb beyond its junction (two root radii): points along its axis polyline and their radii
    seg = np.linalg.norm(np.diff(chain, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(min(2.0 * lb.radii[0], 0.5 * arc[-1]), arc[-1], 12)
    pts = np.stack([np.interp(s, arc, chain[:, k]) for k in range(3)], 1)
    rad = np.interp(s, arc, np.asarray(lb.radii, dtype=np.float64))
    for k in range(int(max_angle // step) + 1):
        A = _rot(axis, k * step)
        q = att + (pts - att) @ A.T
        clear = round_cone_sdf(q, *caps).min(1) - rad
        if np.all(clear >= gap * rad):
            return A
    return np.eye(3)


def _closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    L2 = float(ab @ ab)
    u = 0.0 if L2 == 0 else float(np.clip((p - a) @ ab / L2, 0.0, 1.0))
    return a + u * ab


def _pose_from_frames(creature: Creature, mats: list, origins: list) -> Pose:
    """The capsules of the creature placed by per-capsule frames (see :func:`_segment_frames`)."""
    R, pos = mats[0], origins[0]
    p0, p1, r0, r1, lab = [], [], [], [], []
    for a, b, ra, rb in creature.body:
        p0.append(R @ np.asarray(a, float) + pos)
        p1.append(R @ np.asarray(b, float) + pos)
        r0.append(ra)
        r1.append(rb)
        lab.append(-1)
    k = len(creature.body)
    for li, lb in enumerate(creature.limbs):
        d0 = _unit(lb.direction)
        for i, L in enumerate(lb.lengths):
            p0.append(origins[k])
            p1.append(origins[k] + mats[k] @ (L * d0))
            r0.append(lb.radii[i])
            r1.append(lb.radii[i + 1])
            lab.append(li)
            k += 1
    return Pose(
        p0=np.asarray(p0),
        p1=np.asarray(p1),
        r0=np.asarray(r0),
        r1=np.asarray(r1),
        limb=np.asarray(lab),
        names=tuple(creature.names),
    )


def rest_mesh(
    creature: Creature, *, time_s: float = 0.0, voxel: float = 8.0, opening: dict | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of the creature at ``time_s`` (mm).

    Parameters
    ----------
    opening : dict, optional
        Per-limb root rotations (:func:`scan_opening`) applied to the pose.

    Returns
    -------
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
    """
    from skimage.measure import marching_cubes

    if not voxel > 0:
        raise ValueError(f"voxel must be > 0, got {voxel}")
    if opening is None:
        pose = creature.pose(time_s)
    else:
        mats, org, _ = _segment_frames(creature, float(time_s), opening)
        pose = _pose_from_frames(creature, mats, org)
    lo, hi = pose.bounds()
    lo, hi = lo - 2 * voxel, hi + 2 * voxel
    axes = [np.arange(lo[k], hi[k] + voxel, voxel) for k in range(3)]
    v, f, _, _ = marching_cubes(pose.grid_sdf(axes), level=0.0, spacing=(voxel,) * 3)
    v = v + lo
    # marching cubes' faces wind inward for a negative-inside field: flip to outward normals
    return v.astype(np.float64), f[:, ::-1].astype(np.int64)


def _segment_frames(creature: Creature, t: float, opening: dict | None = None):
    """Per capsule (body first, then limb segments): rotation and origin in the world.

    ``opening`` (:func:`scan_opening`) rotates every limb about its attachment point.
    """
    opening = opening or {}
    pos, R = creature._body_transform(t)
    mats, origins, joints = [], [], {}
    for _ in creature.body:
        mats.append(R)
        origins.append(pos)
    for lb in creature.limbs:
        w = 2 * math.pi * lb.freq
        R_swing = _rot(lb.swing_axis, lb.swing * math.sin(w * t + lb.phase)) if lb.swing else np.eye(3)
        axis = _unit(lb.bend_axis)
        A = opening.get(lb.name, np.eye(3))
        att = np.asarray(lb.attach, dtype=np.float64)
        chain = att + (creature._limb_chain(lb, t) - att) @ A.T
        theta = 0.0
        for i in range(len(lb.lengths)):
            theta += lb.rest[i] + lb.amp[i] * math.sin(w * t + lb.phase - i * lb.lag)
            M = R @ A @ R_swing @ _rot(axis, theta)
            mats.append(M)
            origins.append(R @ chain[i] + pos)
            joints[f"{lb.name}.{i}"] = (R @ chain[i] + pos, M)
    return mats, origins, joints


def true_joints(creature: Creature, times, *, min_bend: float = math.radians(10.0)):
    """A creature's joints over time: names, positions and which of them articulate.

    Parameters
    ----------
    creature : Creature
    times : (T,) float array_like
        Seconds (a take's ``times``).
    min_bend : float
        A joint articulates when the relative rotation of the two parts it links varies by more
        than this (radians) over ``times`` (the largest angle between any two frames').

    Returns
    -------
    names : tuple of str
        ``limb.i``, the joint at the start of limb segment ``i``.
    positions : (T, K, 3) float ndarray
    articulates : (K,) bool ndarray
    """
    t_arr = np.asarray(times, dtype=np.float64).reshape(-1)
    if len(t_arr) == 0 or not np.all(np.isfinite(t_arr)):
        raise ValueError(f"times must be a non-empty array of finite seconds, got {np.shape(times)}")
    if not (min_bend >= 0 and np.isfinite(min_bend)):
        raise ValueError(f"min_bend must be a finite angle >= 0 (radians), got {min_bend}")
    joint_pos, rel = [], []
    names = ()
    for t in t_arr:
        _, _, joints = _segment_frames(creature, float(t))
        names = tuple(joints)
        joint_pos.append(np.asarray([joints[k][0] for k in names]))
        # relative rotation between the two parts a joint links
        _, Rb = creature._body_transform(float(t))
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
    return names, np.asarray(joint_pos), spread > min_bend


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
    open_pose: bool = True,
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
    open_pose : bool
        Template in the scanning pose (:func:`scan_opening`, the default);
        False: the creature's pose at time 0, limbs touching the body included.

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
    opening = scan_opening(cr) if open_pose else {}
    if not any(np.abs(A - np.eye(3)).max() > 0 for A in opening.values()):
        opening = None  # nothing to open: the creature's own pose at time 0
    v0, f = rest_mesh(cr, time_s=0.0, voxel=voxel, opening=opening)
    mats0, org0, _ = _segment_frames(cr, 0.0, opening)
    pose0 = cr.pose(0.0) if opening is None else _pose_from_frames(cr, mats0, org0)
    capsule = pose0.capsule_sdf(v0).argmin(1)
    M0 = np.asarray(mats0)
    org0_a = np.asarray(org0)
    local = np.einsum("vji,vj->vi", M0[capsule], v0 - org0_a[capsule])  # vertex in its capsule's frame
    verts = np.empty((len(times), len(v0), 3), dtype=dtype)
    for ti, t in enumerate(times):
        mats, org, _ = _segment_frames(cr, float(t))
        M = np.asarray(mats)
        org_a = np.asarray(org)
        verts[ti] = np.einsum("vij,vj->vi", M[capsule], local) + org_a[capsule]
    names, joint_pos, articulates = true_joints(cr, times, min_bend=min_bend)
    n_body = len(cr.body)
    part = np.where(capsule < n_body, -1, 0)
    seg_ids = []
    for li, lb in enumerate(cr.limbs):
        seg_ids += [li * 16 + i for i in range(len(lb.lengths))]
    seg_ids = np.asarray(seg_ids)
    part[capsule >= n_body] = seg_ids[capsule[capsule >= n_body] - n_body]
    # the subject's size as it moves (frame 0), not the opened template's
    size = float(np.linalg.norm(np.ptp(verts[0], axis=0)))
    return MeshSequence(
        vertices=verts,
        faces=f,
        times=times,
        joint_names=names,
        joints=np.asarray(joint_pos),
        articulates=articulates,
        part=part,
        size=size,
    )
