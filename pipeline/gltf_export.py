"""Binary glTF 2.0 (GLB) of a rigged, animated model and of the spine alone.

The GLB is written by hand (JSON chunk + BIN chunk, Khronos glTF 2.0
specification, section 4.4 "GLB File Format Specification"): no dependency.
What it holds (:func:`armature_to_glb`):

* one skinned triangle mesh (``POSITION``, ``NORMAL``, ``JOINTS_0``,
  ``WEIGHTS_0``, ``indices``): the reference frame's surface;
* optionally a second skinned mesh, named ``spine``: thin tubes along the
  bones, bound to their joints (shows the skeleton in any viewer);
* one skin: the rig's joints as nodes (parent-first), ``inverseBindMatrices``
  = inverse of every joint's rest transform (translation only: rest
  rotations are the identity);
* one animation ``take``: one key per frame (``LINEAR``), a rotation and a
  translation channel per joint.

glTF's unit is the metre: positions are scaled from the spine's units
(``mm``, ``cm``, ``m``) unless ``scale`` is given; ``asset.extras`` records
the source units, the scale, the frame numbers and each joint's spine limb.

:func:`export_rig` does it for a results directory (``spine.json`` +
``meshes/frame_NNNNNN.ply``); :func:`spine_to_glb` exports the animated
spine without a surface.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np

from pipeline.armature_spine import RiggedModel, SpineArmature, armature_from_spine, reference_frame, rigged_model
from pipeline.mesh_primitives import vertex_normals

__all__ = [
    "UNIT_SCALE",
    "armature_to_glb",
    "spine_to_glb",
    "spine_tubes",
    "export_rig",
    "find_frame_mesh",
    "NoSpineError",
]

log = logging.getLogger(__name__)

UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6}

_FLOAT, _UINT, _USHORT = 5126, 5125, 5123
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class NoSpineError(FileNotFoundError):
    """A results directory without ``spine.json`` (the spine stage has not run yet)."""


class _Builder:
    """Accumulates buffer views and accessors in one binary buffer."""

    def __init__(self) -> None:
        self.bin = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, data: np.ndarray, *, type_: str, component: int, target: int | None = None, minmax=False) -> int:
        data = np.ascontiguousarray(data)
        while len(self.bin) % 4:
            self.bin.append(0)
        raw = data.tobytes()
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.bin += raw
        self.views.append(view)
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": int(data.shape[0]),
            "type": type_,
        }
        if minmax:
            flat = data.reshape(data.shape[0], -1)
            acc["min"] = [float(x) for x in flat.min(0)]
            acc["max"] = [float(x) for x in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _unit_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """float32 vertex normals for glTF, which wants every NORMAL of unit length: a vertex in no face
    (no normal, zero in :func:`pipeline.mesh_primitives.vertex_normals`) gets (0, 0, 1)."""
    n = vertex_normals(v, f)
    n[~np.any(n != 0, axis=1)] = (0.0, 0.0, 1.0)
    return n.astype(np.float32)


def _pack_weights(joints: np.ndarray, weights: np.ndarray, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """(V, 4) uint16 joints and float32 weights summing to 1 in float32."""
    V, k = joints.shape
    J = np.zeros((V, 4), dtype=np.uint16 if n_joints < 65536 else np.uint32)
    W = np.zeros((V, 4), dtype=np.float32)
    J[:, :k] = joints
    W[:, :k] = weights
    W[W < 0] = 0
    W /= W.sum(1, keepdims=True)
    # put the float32 rounding residue on the largest weight
    top = W.argmax(1)
    W[np.arange(V), top] += np.float32(1.0) - W.sum(1, dtype=np.float32)
    return J, W


def spine_tubes(rig: SpineArmature, *, radius: float | None = None, sections: int = 6):
    """Thin tubes along the rig's bones, bound to their joints (rest pose).

    Parameters
    ----------
    rig : SpineArmature
    radius : float, optional
        Tube radius (default 1 % of the rest pose's extent).
    sections : int
        Vertices around each tube.

    Returns
    -------
    vertices : (N, 3) float ndarray
    faces : (M, 3) int ndarray
    joints : (N, 1) int ndarray
        The bone's joint at the tube's start ring, the child joint at its end ring.
    weights : (N, 1) float ndarray
        All ones.
    """
    if int(sections) < 3:
        raise ValueError(f"sections must be >= 3, got {sections}")
    ext = float(np.linalg.norm(rig.rest.max(0) - rig.rest.min(0))) or 1.0
    r = 0.01 * ext if radius is None else float(radius)
    if not r > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    # every parent->child link (bones and the zero-length junction links are skipped)
    links = [(int(p), j) for j, p in enumerate(rig.parents) if p >= 0]
    ang = 2 * np.pi * np.arange(sections) / sections
    verts, faces, joints = [], [], []
    for a, b in links:
        pa, pb = rig.rest[a], rig.rest[b]
        d = pb - pa
        L = np.linalg.norm(d)
        if L <= 1e-9 * ext:
            continue
        d = d / L
        e1 = np.cross(d, [1.0, 0.0, 0.0])
        if np.linalg.norm(e1) < 1e-3:
            e1 = np.cross(d, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        ring = r * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
        base = sum(len(x) for x in verts)
        verts.append(np.vstack([pa + ring, pb + ring]))
        joints.append(np.r_[np.full(sections, a), np.full(sections, b)])
        s = np.arange(sections)
        n = (s + 1) % sections
        q = np.c_[s, n, sections + n, s, sections + n, sections + s].reshape(-1, 3)
        faces.append(base + q)
    if not verts:
        raise ValueError("rig has no bone of non-zero length")
    v = np.vstack(verts)
    j = np.concatenate(joints)[:, None].astype(np.int64)
    return v, np.vstack(faces).astype(np.int64), j, np.ones((len(v), 1))


def _unit_scale(units: str, scale: float | None) -> float:
    if scale is not None:
        s = float(scale)
        if not (s > 0 and np.isfinite(s)):
            raise ValueError(f"scale must be > 0, got {scale}")
        return s
    if units not in UNIT_SCALE:
        log.warning("unknown units %r: writing them unscaled (glTF expects metres)", units)
        return 1.0
    return UNIT_SCALE[units]


def _glb(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary = bytes(binary) + b"\x00" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (
        struct.pack("<III", 0x46546C67, 2, total)
        + struct.pack("<II", len(js), 0x4E4F534A)
        + js
        + struct.pack("<II", len(binary), 0x004E4942)
        + binary
    )


def _document(
    rig: SpineArmature,
    meshes: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    *,
    scale: float,
    extras: dict,
) -> bytes:
    b = _Builder()
    J = rig.n_joints
    rest_local = rig.rest_local * scale
    nodes: list[dict] = []
    gl_meshes: list[dict] = []
    mesh_nodes = []
    for name, v, f, jn, w in meshes:
        v = np.asarray(v, dtype=np.float64)
        pos = b.add((v * scale).astype(np.float32), type_="VEC3", component=_FLOAT, target=_ARRAY_BUFFER, minmax=True)
        nrm = b.add(_unit_normals(v, f), type_="VEC3", component=_FLOAT, target=_ARRAY_BUFFER)
        Jp, Wp = _pack_weights(np.asarray(jn), np.asarray(w), J)
        jac = b.add(Jp, type_="VEC4", component=_USHORT if Jp.dtype == np.uint16 else _UINT, target=_ARRAY_BUFFER)
        wac = b.add(Wp, type_="VEC4", component=_FLOAT, target=_ARRAY_BUFFER)
        idx = b.add(
            np.asarray(f, dtype=np.uint32).reshape(-1), type_="SCALAR", component=_UINT, target=_ELEMENT_ARRAY_BUFFER
        )
        prim = {
            "attributes": {"POSITION": pos, "NORMAL": nrm, "JOINTS_0": jac, "WEIGHTS_0": wac},
            "indices": idx,
            "mode": 4,
            "material": 0 if name != "spine" else 1,
        }
        gl_meshes.append({"name": name, "primitives": [prim]})
        mesh_nodes.append(len(nodes))
        nodes.append({"name": name, "mesh": len(gl_meshes) - 1, "skin": 0})
    first_joint = len(nodes)
    for j in range(J):
        node = {"name": rig.names[j], "translation": [float(x) for x in rest_local[j]]}
        kids = [first_joint + int(k) for k in np.flatnonzero(rig.parents == j)]
        if kids:
            node["children"] = kids
        nodes.append(node)
    ibm = np.tile(np.eye(4), (J, 1, 1))
    ibm[:, :3, 3] = -rig.rest * scale
    # glTF matrices are column-major: store the transpose row by row
    ibm_acc = b.add(ibm.transpose(0, 2, 1).reshape(J, 16).astype(np.float32), type_="MAT4", component=_FLOAT)
    root = first_joint + int(np.flatnonzero(rig.parents < 0)[0])
    skin = {"joints": [first_joint + j for j in range(J)], "inverseBindMatrices": ibm_acc, "skeleton": root}
    times = np.asarray(rig.times, dtype=np.float32)
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        raise ValueError("rig times must increase strictly")
    t_acc = b.add(times, type_="SCALAR", component=_FLOAT, minmax=True)
    samplers, channels = [], []
    for j in range(J):
        r = b.add(rig.rotations[:, j].astype(np.float32), type_="VEC4", component=_FLOAT)
        tr = b.add((rig.translations[:, j] * scale).astype(np.float32), type_="VEC3", component=_FLOAT)
        for out, path in ((r, "rotation"), (tr, "translation")):
            samplers.append({"input": t_acc, "output": out, "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": first_joint + j, "path": path}})
    doc = {
        "asset": {"version": "2.0", "generator": "capture-stage", "extras": extras},
        "scene": 0,
        "scenes": [{"name": "take", "nodes": mesh_nodes + [root]}],
        "nodes": nodes,
        "meshes": gl_meshes,
        "materials": [
            {"name": "surface", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.72, 0.6, 1.0],
                                                         "metallicFactor": 0.0, "roughnessFactor": 0.8}},
            {"name": "spine", "pbrMetallicRoughness": {"baseColorFactor": [0.85, 0.1, 0.1, 1.0],
                                                       "metallicFactor": 0.0, "roughnessFactor": 0.5}},
        ],
        "skins": [skin],
        "animations": [{"name": "take", "samplers": samplers, "channels": channels}],
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.bin) + (-len(b.bin) % 4)}],
    }
    return _glb(doc, bytes(b.bin))


def _extras(rig: SpineArmature, scale: float, **more) -> dict:
    return {
        "format": "capture-stage/rig@1",
        "source_units": rig.units,
        "scale_to_metres": scale,
        "frame_indices": [int(x) for x in rig.frame_indices],
        "reference_frame": int(rig.frame_indices[rig.reference]),
        "joint_limbs": list(rig.element),
        **more,
    }


def armature_to_glb(model: RiggedModel, *, scale: float | None = None, include_spine: bool = True) -> bytes:
    """A rigged model as GLB bytes.

    Parameters
    ----------
    model : RiggedModel
        From :func:`pipeline.armature_spine.rigged_model`.
    scale : float, optional
        Factor from the model's units to the file's (default: to metres).
    include_spine : bool
        Add the ``spine`` tube mesh bound to the same skin.

    Returns
    -------
    bytes
        A GLB (glTF 2.0 binary) file.
    """
    if not isinstance(model, RiggedModel):
        raise ValueError(f"model must be a RiggedModel, got {type(model).__name__}")
    s = _unit_scale(model.rig.units, scale)
    meshes = [("surface", model.vertices, model.faces, model.joints, model.weights)]
    if include_spine:
        meshes.append(("spine", *spine_tubes(model.rig)))
    return _document(model.rig, meshes, scale=s, extras=_extras(model.rig, s, weights=model.meta.get("weights")))


def spine_to_glb(spine, *, segments: int | None = 6, scale: float | None = None, reference: int | None = None) -> bytes:
    """The animated spine alone (tubes along the bones) as GLB bytes.

    Parameters
    ----------
    spine : pipeline.spine_format.Spine or dict
        A spine, or a parsed ``spine.json``.
    segments : int or None
        Bones per axis (see :func:`pipeline.armature_spine.armature_from_spine`).
    scale : float, optional
        Default: to metres.
    reference : int, optional
        Rest-pose frame position.

    Returns
    -------
    bytes
    """
    from pipeline.spine_format import Spine

    if isinstance(spine, dict):
        spine = Spine.from_dict(spine)
    rig = armature_from_spine(spine, reference=reference, segments=segments)
    s = _unit_scale(rig.units, scale)
    return _document(rig, [("spine", *spine_tubes(rig))], scale=s, extras=_extras(rig, s))


def find_frame_mesh(results_dir, frame_index: int) -> Path | None:
    """The mesh file of one frame in a results directory (``meshes/frame_NNNNNN.{ply,obj,off}``), or None."""
    d = Path(results_dir) / "meshes"
    for ext in (".ply", ".obj", ".off"):
        p = d / f"frame_{int(frame_index):06d}{ext}"
        if p.is_file():
            return p
    return None


def export_rig(
    results_dir,
    *,
    out=None,
    reference: int | None = None,
    segments: int | None = 6,
    include_spine: bool = True,
) -> Path:
    """Write ``DIR/spine_rig.glb``: the reference frame's mesh rigged to the take's spine.

    Parameters
    ----------
    results_dir : str or Path
        A results directory with ``spine.json`` and ``meshes/frame_NNNNNN.ply``.
    out : str or Path, optional
        Output file (default ``results_dir/spine_rig.glb``).
    reference : int, optional
        Take frame number of the rest pose (default: the spine's reference
        frame, or the complete frame nearest to it).
    segments : int or None
        Bones per limb.
    include_spine : bool
        Also bind tubes along the bones.

    Returns
    -------
    Path

    Raises
    ------
    NoSpineError
        No ``spine.json`` yet.
    FileNotFoundError
        The reference frame has no mesh file (never another frame in its place).
    """
    from pipeline.meshio import load_mesh
    from pipeline.spine_format import read_spine

    d = Path(results_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"results directory not found: {d}")
    if not (d / "spine.json").is_file():
        raise NoSpineError(f"{d} has no spine.json yet: run the spine stage (`stage process`) before exporting")
    spine = read_spine(d / "spine.json")
    fi = [int(x) for x in spine.frame_indices]
    if reference is not None:
        if int(reference) not in fi:
            raise ValueError(f"reference must be a frame number of the take, got {reference}")
        pos = reference_frame(spine, prefer=fi.index(int(reference)))
        candidates = [pos]
    else:
        best = reference_frame(spine)
        T = len(fi)
        complete = []
        for t in sorted(range(T), key=lambda t: abs(t - best)):
            try:
                complete.append(reference_frame(spine, prefer=t))
            except ValueError:
                continue
        candidates = complete
    if not candidates:
        raise ValueError(f"{d / 'spine.json'}: no frame where the spine is complete")
    pos = candidates[0]
    mp = find_frame_mesh(d, fi[pos])
    if mp is None and not (d / "meshes").is_dir():  # a spine of a mesh sequence (`stage spines --meshes`)
        raise FileNotFoundError(
            f"{d} has no meshes/ folder (the spine of a mesh sequence keeps none): the rigged mesh needs the rest "
            f"frame's surface, meshes/frame_{fi[pos]:06d}.ply (spine.json's frame {fi[pos]}); or export the spine "
            "alone (--format spine-glb)")
    if mp is None:  # `stage process` writes every frame's mesh: another frame would be another rest pose
        raise FileNotFoundError(
            f"{d / 'meshes'}: the reference frame's mesh frame_{fi[pos]:06d}.ply is missing; run `stage process` "
            f"again to make it, or choose the rest pose with --reference FRAME")
    v, f = load_mesh(mp)
    if len(f) == 0:
        raise ValueError(f"{mp} is empty")
    log.info("rigging %s (frame %d) to %s", mp.name, fi[pos], d / "spine.json")
    model = rigged_model(spine, v, f, reference=pos, segments=segments)
    data = armature_to_glb(model, include_spine=include_spine)
    from calib.fileio import atomic_write  # the project's one atomic write: its own temporary name, none left behind

    return atomic_write(Path(out) if out is not None else d / "spine_rig.glb", data)
