"""A rigged, animated model from a spine: joints, hierarchy, per-frame pose, skin.

The goal of Tzionas & Gall 2016: "a watertight mesh, an embedded skeleton and
skinning weights" that can be "used out of the box" for animation. Here the
skeleton is the take's spine (Brostow et al. 2004, section 4.3: one graph for
the whole take, every limb resampled at the same interval), so the rig plays
the take back.

Joints (:func:`armature_from_spine`)
    The root junction is the root joint. Every spine axis (limb, or the
    chain from a parent junction to a child junction) is resampled to
    ``segments + 1`` points ``p_0 .. p_n``; it gets a *base* joint at ``p_0``
    (child of the parent junction's joint: each axis leaving a junction turns
    on its own), one joint per inner point, and an *end* joint at ``p_n`` (the
    tip of a limb, or the child junction). The bone ``p_k -> p_{k+1}`` belongs
    to the joint at ``p_k``.

Rest pose
    The spine in the reference frame (the first correspondence reference
    with every limb seen): local rotations are the identity, local
    translations are the offsets between the joints.

Animation (one key per frame)
    The root follows the root junction; its rotation is the least-squares
    rotation (Arun et al.) of the first bone directions of its child axes.
    Every bone joint's global rotation is its parent's, followed by the
    smallest rotation taking the carried rest bone direction onto the frame's
    bone direction; junction joints fit their child axes like the root.
    Local translations place every joint exactly on the frame's spine (bones
    may stretch). A limb that is null in a frame holds its pose from the
    neighbouring frame nearer to the reference.

Skin (:func:`rigged_model`)
    Bone heat weights (:mod:`pipeline.skinning`) on the reference frame's
    mesh, at most 4 influences per vertex, normalised.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.skinning import bone_heat_weights, limit_influences
from pipeline.spine import resample_polyline

__all__ = ["SpineArmature", "RiggedModel", "armature_from_spine", "rigged_model", "reference_frame", "NoCompleteFrameError"]

log = logging.getLogger(__name__)


class NoCompleteFrameError(ValueError):
    """A spine with no frame in which every limb was seen (no rest pose)."""


@dataclass(frozen=True, eq=False)
class SpineArmature:
    """A joint hierarchy with a rest pose and one pose per frame.

    Attributes
    ----------
    names : tuple of str
        Joint names (``j0``, ``limb0.0`` .. ``limb0.tip``, ``j1`` ...).
    parents : (J,) int ndarray
        Parent joint of every joint, -1 for the root (parents come first).
    element : tuple of str
        The spine limb or junction id every joint belongs to (the root: its
        junction id).
    rest : (J, 3) float ndarray
        Joint positions in the rest pose (spine units).
    bones : (B, 2) int ndarray
        ``(joint, child joint)`` pairs: the bone of ``joint``.
    rotations : (T, J, 4) float ndarray
        Local rotations per frame, quaternions ``(x, y, z, w)`` (glTF order),
        sign-continuous over time.
    translations : (T, J, 3) float ndarray
        Local translations per frame.
    times : (T,) float ndarray
        Seconds from the first frame.
    frame_indices : (T,) int ndarray
    reference : int
        Position (in ``frame_indices``) of the rest-pose frame.
    units : str
    """

    names: tuple
    parents: np.ndarray
    element: tuple
    rest: np.ndarray
    bones: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    times: np.ndarray
    frame_indices: np.ndarray
    reference: int
    units: str = "mm"

    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def rest_local(self) -> np.ndarray:
        """(J, 3) local rest translations (root: its rest position)."""
        out = self.rest.copy()
        nz = self.parents >= 0
        out[nz] = self.rest[nz] - self.rest[self.parents[nz]]
        return out

    def global_transforms(self, t: int) -> np.ndarray:
        """(J, 4, 4) world transforms of the joints in frame ``t`` (a position)."""
        if not (0 <= int(t) < self.n_frames):
            raise ValueError(f"t must be within 0..{self.n_frames - 1}, got {t}")
        R = Rotation.from_quat(self.rotations[t]).as_matrix()
        out = np.zeros((self.n_joints, 4, 4))
        for j, p in enumerate(self.parents):
            M = np.eye(4)
            M[:3, :3] = R[j]
            M[:3, 3] = self.translations[t, j]
            out[j] = M if p < 0 else out[p] @ M
        return out

    def skin_matrices(self, t: int) -> np.ndarray:
        """(J, 4, 4) ``global(t) @ inverse_bind``: rest space -> frame ``t``."""
        G = self.global_transforms(t)
        ibm = np.tile(np.eye(4), (self.n_joints, 1, 1))
        ibm[:, :3, 3] = -self.rest
        return G @ ibm

    def joint_positions(self, t: int) -> np.ndarray:
        """(J, 3) joint positions in frame ``t``."""
        return self.global_transforms(t)[:, :3, 3]


@dataclass(frozen=True, eq=False)
class RiggedModel:
    """A mesh bound to a :class:`SpineArmature`.

    Attributes
    ----------
    vertices : (V, 3) float ndarray
        Rest-pose mesh (the reference frame's surface), spine units.
    faces : (F, 3) int ndarray
    joints : (V, k) int ndarray
        Influencing joints per vertex (``k <= 4``), by decreasing weight.
    weights : (V, k) float ndarray
        Rows sum to 1.
    rig : SpineArmature
    meta : dict
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    rig: SpineArmature
    meta: dict = field(default_factory=dict)

    def deform(self, t: int) -> np.ndarray:
        """(V, 3) vertices posed for frame ``t`` by linear blend skinning."""
        S = self.rig.skin_matrices(t)
        vh = np.c_[self.vertices, np.ones(len(self.vertices))]
        out = np.zeros((len(self.vertices), 3))
        for c in range(self.joints.shape[1]):
            M = S[self.joints[:, c]]
            out += self.weights[:, c : c + 1] * np.einsum("vij,vj->vi", M[:, :3, :], vh)
        return out


# --------------------------------------------------------------------------- geometry


def _align(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction ``u`` onto direction ``w`` (3x3)."""
    nu, nw = np.linalg.norm(u), np.linalg.norm(w)
    if nu <= 0 or nw <= 0:
        return np.eye(3)
    a, b = u / nu, w / nw
    v = np.cross(a, b)
    c = float(a @ b)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: half turn about any axis perpendicular to a
        p = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = np.cross(a, [0.0, 1.0, 0.0])
        p /= np.linalg.norm(p)
        return 2 * np.outer(p, p) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K * ((1 - c) / (s * s))


def _fit_rotation(U: np.ndarray, W: np.ndarray) -> np.ndarray | None:
    """Least-squares rotation R with ``R u_i ~ w_i`` (Arun et al. 1987) for unit directions.

    Returns None without data; a single (or collinear) direction gives the
    smallest aligning rotation.
    """
    if len(U) == 0:
        return None
    U = U / np.maximum(np.linalg.norm(U, axis=1, keepdims=True), 1e-300)
    W = W / np.maximum(np.linalg.norm(W, axis=1, keepdims=True), 1e-300)
    H = U.T @ W
    s = np.linalg.svd(H, compute_uv=False)
    if len(U) < 2 or s[1] < 1e-6 * max(s[0], 1e-300):
        sign = np.where(U @ U[0] < 0, -1.0, 1.0)[:, None]
        return _align((sign * U).sum(0), (sign * W).sum(0))
    X, _, Yt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Yt.T @ X.T)) or 1.0])
    return Yt.T @ D @ X.T


# --------------------------------------------------------------------------- rig


def reference_frame(spine, *, prefer=None) -> int:
    """Position of the rest-pose frame: every limb and junction axis seen.

    Parameters
    ----------
    spine : pipeline.spine_format.Spine
    prefer : int, optional
        A frame position to use if complete.

    Returns
    -------
    int
        ``prefer`` if complete, else the first correspondence reference
        (``spine.meta["references"]``) that is complete, else the complete
        frame nearest the middle of the take.

    Raises
    ------
    NoCompleteFrameError
    """
    T = spine.frame_count
    ok = np.ones(T, dtype=bool)
    for a in spine.axes.values():
        ok &= np.all(np.isfinite(a.reshape(T, -1)), axis=1)
    ok &= np.all(np.isfinite(spine.junctions.reshape(T, -1)), axis=1) if spine.junctions.size else True
    if prefer is not None:
        p = int(prefer)
        if not (0 <= p < T):
            raise ValueError(f"reference must be within 0..{T - 1}, got {prefer}")
        if not ok[p]:
            raise NoCompleteFrameError(f"frame position {p} does not have every limb of the spine")
        return p
    for r in spine.meta.get("references", []) or []:
        if isinstance(r, (int, np.integer)) and 0 <= r < T and ok[r]:
            return int(r)
    good = np.flatnonzero(ok)
    if len(good) == 0:
        raise NoCompleteFrameError("no frame of the spine has every limb: cannot pick a rest pose")
    return int(good[np.argmin(np.abs(good - (T - 1) / 2))])


def armature_from_spine(spine, *, reference: int | None = None, segments: int | None = 6) -> SpineArmature:
    """Joints along the spine's limbs and their pose in every frame.

    Parameters
    ----------
    spine : pipeline.spine_format.Spine
        A take's spine (``capture-stage/spine@1``).
    reference : int, optional
        Position of the rest-pose frame (default: :func:`reference_frame`).
    segments : int or None
        Bones per limb/junction axis (the axis is resampled to ``segments + 1``
        points); None keeps the spine's own resampling.

    Returns
    -------
    SpineArmature

    Raises
    ------
    NoCompleteFrameError
        When no frame has every limb (no rest pose).
    """
    from pipeline.spine_format import Spine

    if not isinstance(spine, Spine):
        raise ValueError(f"spine must be a pipeline.spine_format.Spine, got {type(spine).__name__}")
    if segments is not None and int(segments) < 1:
        raise ValueError(f"segments must be >= 1 or None, got {segments}")
    T = spine.frame_count
    if T == 0:
        raise ValueError("spine has no frames")
    ref = reference_frame(spine, prefer=reference)
    axes = _resampled_axes(spine, segments)
    tree = _joint_tree(spine, axes)
    positions = _joint_positions(spine, axes, tree)  # (T, J, 3)
    rest = positions[ref].copy()
    if not np.all(np.isfinite(rest)):
        raise NoCompleteFrameError(f"reference frame {ref} is incomplete")
    local_rotations, local_translations = _local_poses(tree, positions, rest, ref)
    fi = np.asarray(spine.frame_indices, dtype=np.int64)
    times = (fi - fi[0]) / float(spine.fps)
    return SpineArmature(
        names=tuple(tree.names),
        parents=tree.parents,
        element=tuple(tree.element),
        rest=rest,
        bones=np.asarray(tree.bones, dtype=np.int64).reshape(-1, 2),
        rotations=_continuous_quaternions(local_rotations, ref),
        translations=local_translations,
        times=times.astype(np.float64),
        frame_indices=fi,
        reference=ref,
        units=spine.units,
    )


# --------------------------------------------------------------------------- armature_from_spine, step by step


def _resampled_axes(spine, segments: int | None) -> dict[str, np.ndarray]:
    """Every spine axis resampled to ``segments + 1`` points: (T, n, 3), nan rows where unseen."""
    T = spine.frame_count
    out_axes: dict[str, np.ndarray] = {}
    for name, a in spine.axes.items():
        n = a.shape[1] if segments is None else int(segments) + 1
        out = np.full((T, n, 3), np.nan)
        for t in range(T):
            if np.all(np.isfinite(a[t])) and a.shape[1] >= 2:
                out[t] = resample_polyline(a[t], n) if a.shape[1] != n else a[t]
        out_axes[name] = out
    return out_axes


@dataclass
class _JointTree:
    """The joint hierarchy in parent-first order, and where each joint sits on the spine."""

    names: list[str] = field(default_factory=list)
    parent: list[int] = field(default_factory=list)
    element: list[str] = field(default_factory=list)  # the spine element (junction or axis) it belongs to
    source: list[tuple] = field(default_factory=list)  # ("junction", id) or ("axis", name, point)
    kind: list[str] = field(default_factory=list)  # "root" | "bone" | "tip" | "junction"
    children: list[list[int]] = field(default_factory=list)
    bone_end: dict[int, int] = field(default_factory=dict)  # bone joint -> next joint on its axis
    fit_targets: list[list[int]] = field(default_factory=list)  # root/junction joint -> first bone ends below

    def add(self, name: str, parent: int, element: str, source: tuple, kind: str) -> int:
        self.names.append(name)
        self.parent.append(parent)
        self.element.append(element)
        self.source.append(source)
        self.kind.append(kind)
        return len(self.names) - 1

    @property
    def parents(self) -> np.ndarray:
        return np.asarray(self.parent, dtype=np.int64)

    @property
    def bones(self) -> list[tuple[int, int]]:
        return [(j, self.bone_end[j]) for j in range(len(self.names)) if self.kind[j] == "bone"]


def _joint_tree(spine, axes: dict[str, np.ndarray]) -> _JointTree:
    """Root joint at the root junction; per axis below a junction: bone joints, then a tip or junction joint."""
    below: dict[str, list[str]] = {}
    for name, p in spine.parents.items():
        if p is not None:
            below.setdefault(p, []).append(name)
    junctions = set(spine.junction_ids)
    tree = _JointTree()

    def grow(junction: str, junction_joint: int) -> None:
        for axis in sorted(below.get(junction, []), key=lambda c: (c in junctions, c)):
            n = axes[axis].shape[1]
            joint = junction_joint
            for k in range(n - 1):
                joint = tree.add(f"{axis}.{k}", joint, axis, ("axis", axis, k), "bone")
            if axis in junctions:
                grow(axis, tree.add(axis, joint, axis, ("axis", axis, n - 1), "junction"))
            else:
                tree.add(f"{axis}.tip", joint, axis, ("axis", axis, n - 1), "tip")

    grow(spine.root, tree.add(spine.root, -1, spine.root, ("junction", spine.root), "root"))
    J = len(tree.names)
    tree.children = [[] for _ in range(J)]
    for j, p in enumerate(tree.parent):
        if p >= 0:
            tree.children[p].append(j)
            if tree.kind[p] == "bone":
                tree.bone_end[p] = j
    tree.fit_targets = [_first_bone_ends(tree, j, []) if tree.kind[j] in ("root", "junction") else []
                        for j in range(J)]
    return tree


def _first_bone_ends(tree: _JointTree, j: int, out: list[int]) -> list[int]:
    """Joints ending the first bone of every axis below junction joint ``j`` (through child junctions)."""
    for c in tree.children[j]:
        end = tree.bone_end.get(c)
        if end is not None:
            out.append(end)
        if tree.kind[c] == "junction":
            _first_bone_ends(tree, c, out)
        elif tree.kind[c] == "bone":
            last = c  # walk to the axis' last bone joint; a junction joint below it continues the tree
            while last in tree.bone_end:
                last = tree.bone_end[last]
            for k in tree.children[last]:
                if tree.kind[k] == "junction":
                    out.append(k)
                    _first_bone_ends(tree, k, out)
    return out


def _joint_positions(spine, axes: dict[str, np.ndarray], tree: _JointTree) -> np.ndarray:
    """(T, J, 3) joint positions on the spine; a junction without a position takes its axes' common start."""
    junction_index = {j: i for i, j in enumerate(spine.junction_ids)}
    below: dict[str, list[str]] = {}
    for name, p in spine.parents.items():
        if p is not None:
            below.setdefault(p, []).append(name)

    def position(t: int, src: tuple) -> np.ndarray:
        if src[0] == "axis":
            return axes[src[1]][t, src[2]]
        p = spine.junctions[t, junction_index[src[1]]] if spine.junctions.size else np.full(3, np.nan)
        if not np.all(np.isfinite(p)):
            starts = [axes[c][t, 0] for c in below.get(src[1], []) if np.all(np.isfinite(axes[c][t]))]
            p = np.mean(starts, axis=0) if starts else np.full(3, np.nan)
        return p

    return np.array([[position(t, src) for src in tree.source] for t in range(spine.frame_count)])


def _local_poses(tree: _JointTree, positions: np.ndarray, rest: np.ndarray, ref: int):
    """Local rotations (T, J, 3, 3) and translations (T, J, 3), solved outwards from the reference frame."""
    T, J = positions.shape[:2]
    parents = tree.parents
    rest_local = rest.copy()
    rest_local[1:] = rest[1:] - rest[parents[1:]]
    rotations = np.zeros((T, J, 3, 3))
    translations = np.zeros((T, J, 3))
    order = [(ref, None)] + [(t, t - 1) for t in range(ref + 1, T)] + [(t, t + 1) for t in range(ref - 1, -1, -1)]
    for t, previous in order:
        _pose_frame(tree, positions[t], rest, rest_local, rotations, translations, t, previous)
    return rotations, translations


def _pose_frame(tree: _JointTree, here: np.ndarray, rest: np.ndarray, rest_local: np.ndarray,
                rotations: np.ndarray, translations: np.ndarray, t: int, previous: int | None) -> None:
    """Fill frame ``t`` of the local poses; unseen joints hold ``previous``'s pose (the rest pose at first)."""
    J = len(tree.names)
    global_rotation = np.zeros((J, 3, 3))
    global_position = np.zeros((J, 3))
    for j in range(J):
        p = tree.parent[j]
        parent_rotation = np.eye(3) if p < 0 else global_rotation[p]
        parent_position = np.zeros(3) if p < 0 else global_position[p]
        rotation = None
        if np.all(np.isfinite(here[j])) and (p < 0 or np.all(np.isfinite(here[p]))):
            rotation = _joint_rotation(tree, j, here, rest, parent_rotation)
        if rotation is not None:
            rotations[t, j] = parent_rotation.T @ rotation
            translations[t, j] = parent_rotation.T @ (here[j] - parent_position) if p >= 0 else here[j]
        elif previous is not None:
            rotations[t, j] = rotations[previous, j]
            translations[t, j] = translations[previous, j]
        else:
            rotations[t, j] = np.eye(3)
            translations[t, j] = rest_local[j]
        global_rotation[j] = parent_rotation @ rotations[t, j]
        global_position[j] = parent_position + parent_rotation @ translations[t, j]


def _joint_rotation(tree: _JointTree, j: int, here: np.ndarray, rest: np.ndarray,
                    parent_rotation: np.ndarray) -> np.ndarray | None:
    """Global rotation of seen joint ``j`` in one frame, or None when its bone's end is unseen.

    Root and junction joints fit the first bones of their axes (Arun et al.); a bone joint
    turns its carried rest bone onto the frame's bone; a tip follows its parent.
    """
    kind = tree.kind[j]
    if kind in ("root", "junction"):
        U, W = [], []
        for b in tree.fit_targets[j]:
            if np.all(np.isfinite(here[b])):
                U.append(rest[b] - rest[j])
                W.append(here[b] - here[j])
        fitted = _fit_rotation(np.array(U).reshape(-1, 3), np.array(W).reshape(-1, 3))
        return parent_rotation if fitted is None else fitted
    if kind == "bone":
        end = tree.bone_end[j]
        if not np.all(np.isfinite(here[end])):
            return None
        carried = parent_rotation @ (rest[end] - rest[j])
        return _align(carried, here[end] - here[j]) @ parent_rotation
    return parent_rotation  # tip


def _continuous_quaternions(rotations: np.ndarray, ref: int) -> np.ndarray:
    """(T, J, 4) quaternions with signs continuous outwards from the reference (slerp takes the short way)."""
    T, J = rotations.shape[:2]
    q = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat().reshape(T, J, 4)
    for t in range(ref + 1, T):
        flip = (q[t] * q[t - 1]).sum(1) < 0
        q[t, flip] *= -1
    for t in range(ref - 1, -1, -1):
        flip = (q[t] * q[t + 1]).sum(1) < 0
        q[t, flip] *= -1
    return q


def rigged_model(
    spine,
    vertices,
    faces,
    *,
    reference: int | None = None,
    segments: int | None = 6,
    max_influences: int = 4,
    heat: float = 1.0,
) -> RiggedModel:
    """Bind the reference frame's mesh to the spine's rig (bone heat weights).

    Parameters
    ----------
    spine : pipeline.spine_format.Spine
    vertices : (V, 3) float ndarray
    faces : (F, 3) int ndarray
        The surface of the reference frame (see :func:`reference_frame`),
        same units as the spine.
    reference : int, optional
        Position of the frame the mesh belongs to.
    segments : int or None
        Bones per axis (see :func:`armature_from_spine`).
    max_influences : int
        Joints per vertex (glTF: 4 per ``JOINTS_n`` set; 1..4 here).
    heat : float
        Bone heat constant ``c`` (Baran & Popović 2007).

    Returns
    -------
    RiggedModel
    """
    if not 1 <= int(max_influences) <= 4:
        raise ValueError(f"max_influences must be within 1..4, got {max_influences}")
    rig = armature_from_spine(spine, reference=reference, segments=segments)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if len(rig.bones) == 0:
        raise ValueError("the spine has no bones")
    W = bone_heat_weights(v, f, rig.rest[rig.bones[:, 0]], rig.rest[rig.bones[:, 1]], heat=heat)
    cols, w = limit_influences(W, max_influences=max_influences)
    joints = rig.bones[cols, 0]
    return RiggedModel(
        vertices=v,
        faces=f.astype(np.int64),
        joints=joints,
        weights=w,
        rig=rig,
        meta={"reference": rig.reference, "frame": int(rig.frame_indices[rig.reference]), "weights": "bone heat"},
    )
