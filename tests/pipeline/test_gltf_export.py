"""Rigged GLB export (pipeline.gltf_export, stage export): loads back, skin, weights, animation, posing."""

from __future__ import annotations

import io
import json

import numpy as np
import pygltflib
import pytest
import trimesh

from pipeline.armature_spine import armature_from_spine, rigged_model
from pipeline.gltf_export import NoSpineError, armature_to_glb, export_rig, find_frame_mesh, spine_to_glb, spine_tubes
from pipeline.spine_format import write_spine
from tests.pipeline.creature_truth import FPS, creature_size, creature_take, surface, true_spine

FRAMES = 12
SEGMENTS = 6
HIDE = {"tail": [2, 3]}  # the tail is not seen in frames 2-3: it holds frame 4's pose


@pytest.fixture(scope="module")
def take():
    _, poses = creature_take("quadruped", FRAMES)
    spine = true_spine("quadruped", poses, hide=HIDE)
    v, f = surface(poses[spine.meta["references"][0]], step=8.0)
    return poses, spine, v, f


@pytest.fixture(scope="module")
def glb(take):
    _, spine, v, f = take
    model = rigged_model(spine, v, f, segments=SEGMENTS)
    return model, armature_to_glb(model)


# ----------------------------------------------------------------- reading the GLB back, independently


def _accessor(g, i):
    """An accessor's data as an array, read straight from the GLB's binary chunk."""
    acc = g.accessors[i]
    view = g.bufferViews[acc.bufferView]
    blob = g.binary_blob()
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[acc.componentType]
    ncomp = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    a = np.frombuffer(blob, dtype=dtype, count=acc.count * ncomp, offset=start)
    return a.reshape(acc.count, ncomp) if ncomp > 1 else a


def _quat_matrix(q):
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pose_from_glb(g, t):
    """Surface vertices posed for key ``t`` by linear blend skinning, from the GLB data alone (metres)."""
    skin = g.skins[0]
    joints = list(skin.joints)
    ibm = _accessor(g, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
    trs = {n: {"t": np.array(g.nodes[n].translation or [0, 0, 0], float),
               "r": np.array(g.nodes[n].rotation or [0, 0, 0, 1], float)} for n in joints}
    anim = g.animations[0]
    for ch in anim.channels:
        out = _accessor(g, anim.samplers[ch.sampler].output)
        trs[ch.target.node]["t" if ch.target.path == "translation" else "r"] = out[t].astype(np.float64)
    parent = {c: n for n in range(len(g.nodes)) for c in (g.nodes[n].children or [])}
    world = {}

    def glob(n):
        if n not in world:
            M = np.eye(4)
            M[:3, :3] = _quat_matrix(trs[n]["r"])
            M[:3, 3] = trs[n]["t"]
            world[n] = glob(parent[n]) @ M if n in parent else M
        return world[n]

    S = np.array([glob(n) for n in joints]) @ ibm
    mesh = next(m for m in g.meshes if m.name == "surface")
    attr = mesh.primitives[0].attributes
    V = _accessor(g, attr.POSITION).astype(np.float64)
    J = _accessor(g, attr.JOINTS_0).astype(np.int64)
    W = _accessor(g, attr.WEIGHTS_0).astype(np.float64)
    vh = np.c_[V, np.ones(len(V))]
    out = np.zeros_like(V)
    for c in range(4):
        out += W[:, c : c + 1] * np.einsum("vij,vj->vi", S[J[:, c]][:, :3, :], vh)
    return out


# ----------------------------------------------------------------- tests


def test_glb_loads_back_with_pygltflib_and_trimesh(glb, take):
    model, data = glb
    _, spine, v, f = take
    g = pygltflib.GLTF2.load_from_bytes(data)
    assert g.asset.version == "2.0"
    # expected joints: the root + (segments + 1) per axis: 6 limbs and 2 junction-to-junction axes
    assert len(g.skins[0].joints) == 1 + (len(spine.limb_ids) + len(spine.junction_ids) - 1) * (SEGMENTS + 1)
    scene = trimesh.load(io.BytesIO(data), file_type="glb")
    geom = scene.geometry["surface"]
    assert len(geom.faces) == len(f)
    np.testing.assert_allclose(np.sort(geom.vertices[:, 2]), np.sort(v[:, 2] / 1000.0), atol=1e-6)
    assert "spine" in scene.geometry
    extras = g.asset.extras
    assert extras["source_units"] == "mm" and extras["scale_to_metres"] == 0.001
    assert len(extras["joint_limbs"]) == len(g.skins[0].joints)


def test_normals_are_the_unit_area_weighted_face_normals(glb):
    """Every mesh's NORMAL against a per-vertex loop over its own POSITION and indices (float32: 1e-5)."""
    _, data = glb
    g = pygltflib.GLTF2.load_from_bytes(data)
    with_normals = [m.primitives[0] for m in g.meshes if m.primitives[0].attributes.NORMAL is not None]
    assert with_normals
    for prim in with_normals:
        P = _accessor(g, prim.attributes.POSITION).astype(np.float64)
        F = _accessor(g, prim.indices).reshape(-1, 3).astype(np.int64)
        ref = np.zeros_like(P)
        for a, b, c in F:
            n = np.cross(P[b] - P[a], P[c] - P[a])
            ref[a] += n
            ref[b] += n
            ref[c] += n
        length = np.linalg.norm(ref, axis=1, keepdims=True)
        ref = np.where(length > 0, ref / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
        np.testing.assert_allclose(_accessor(g, prim.attributes.NORMAL), ref, atol=1e-5)


def test_weights_sum_to_one_with_at_most_four_influences(glb):
    _, data = glb
    g = pygltflib.GLTF2.load_from_bytes(data)
    for mesh in g.meshes:
        attr = mesh.primitives[0].attributes
        W = _accessor(g, attr.WEIGHTS_0)
        J = _accessor(g, attr.JOINTS_0)
        assert W.shape[1] == 4 and W.min() >= 0
        np.testing.assert_allclose(W.astype(np.float64).sum(1), 1.0, atol=2e-7)
        assert J.max() < len(g.skins[0].joints)


def test_animation_has_one_key_per_frame(glb):
    model, data = glb
    g = pygltflib.GLTF2.load_from_bytes(data)
    (anim,) = g.animations
    n_joints = len(g.skins[0].joints)
    assert len(anim.channels) == 2 * n_joints
    assert {c.target.path for c in anim.channels} == {"rotation", "translation"}
    for s in anim.samplers:
        times = _accessor(g, s.input)
        assert len(times) == FRAMES == len(_accessor(g, s.output))
        np.testing.assert_allclose(times, np.arange(FRAMES) / FPS, atol=1e-6)


def test_posed_mesh_stays_on_each_frames_true_surface(glb, take):
    """Mean |sdf| < 3 % and 95th percentile < 6 % of the creature's size (bounding-box diagonal), every frame."""
    model, data = glb
    poses, *_ = take
    g = pygltflib.GLTF2.load_from_bytes(data)
    worst = []
    for t in range(FRAMES):
        posed = _pose_from_glb(g, t) * 1000.0  # metres -> mm
        np.testing.assert_allclose(posed, model.deform(t), atol=0.05)  # our own LBS agrees with the file's
        d = np.abs(poses[t].sdf(posed)) / creature_size(poses[t])
        worst.append((float(d.mean()), float(np.percentile(d, 95))))
    mean, p95 = max(w[0] for w in worst), max(w[1] for w in worst)
    print(f"posing error over {FRAMES} frames: worst mean |sdf| {mean:.2%}, worst p95 {p95:.2%} of size")
    assert mean < 0.03 and p95 < 0.06


def test_spine_only_glb(take):
    _, spine, *_ = take
    data = spine_to_glb(spine.to_dict())
    g = pygltflib.GLTF2.load_from_bytes(data)
    assert [m.name for m in g.meshes] == ["spine"]
    assert len(_accessor(g, g.animations[0].samplers[0].input)) == FRAMES
    tubes = spine_tubes(armature_from_spine(spine))
    assert len(_accessor(g, g.meshes[0].primitives[0].attributes.POSITION)) == len(tubes[0])


@pytest.fixture
def results_dir(tmp_path, take):
    poses, spine, v, f = take
    write_spine(tmp_path / "spine.json", spine)
    (tmp_path / "meshes").mkdir()
    ref = spine.meta["references"][0]
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "meshes" / f"frame_{ref:06d}.ply")
    return tmp_path


def test_export_rig_writes_spine_rig_glb(results_dir):
    path = export_rig(results_dir)
    assert path == results_dir / "spine_rig.glb"
    g = pygltflib.GLTF2.load_from_bytes(path.read_bytes())
    assert g.asset.extras["reference_frame"] == FRAMES // 2
    assert find_frame_mesh(results_dir, FRAMES // 2).suffix == ".ply"


def test_export_with_the_reference_mesh_deleted_names_it_and_rigs_no_other_frame(results_dir, capsys):
    from stage.cli import main

    ref = FRAMES // 2
    mesh = results_dir / "meshes" / f"frame_{ref:06d}.ply"
    mesh.rename(results_dir / "meshes" / f"frame_{ref + 1:06d}.ply")  # a neighbour has a mesh, the reference not
    with pytest.raises(FileNotFoundError, match=f"frame_{ref:06d}.ply is missing"):
        export_rig(results_dir)
    assert main(["export", str(results_dir), "--format", "glb"]) == 2
    assert "--reference" in capsys.readouterr().err
    assert not (results_dir / "spine_rig.glb").exists()


def test_cli_export(results_dir, tmp_path_factory, capsys):
    from stage.cli import main

    assert main(["export", str(results_dir), "--format", "glb"]) == 0
    assert (results_dir / "spine_rig.glb").is_file()
    out = tmp_path_factory.mktemp("o") / "s.glb"
    assert main(["export", str(results_dir), "--format", "spine-glb", "--out", str(out)]) == 0
    assert out.is_file() and str(out) in capsys.readouterr().out


def test_export_to_a_directory_is_one_line_and_leaves_nothing_behind(results_dir, tmp_path, capsys):
    """``--out`` naming a directory: one line naming it and the file to give, for every format, before any work;
    ``export_rig(out=a directory)`` fails without leaving its temporary file (it left ``DIR.tmp``)."""
    from stage.cli import main

    target = tmp_path / "o" / "exports"
    target.mkdir(parents=True)
    for fmt, name in (("glb", "spine_rig.glb"), ("spine-glb", "spine.glb"), ("bvh", "rig.bvh")):
        assert main(["export", str(results_dir), "--format", fmt, "--out", str(target)]) == 2
        assert capsys.readouterr().err == (f"stage export: error: --out {target} is a directory: give the file to "
                                           f"write (e.g. {target / name})\n")
    with pytest.raises(IsADirectoryError):
        export_rig(results_dir, out=target)
    assert [p.name for p in (tmp_path / "o").iterdir()] == ["exports"] and not any(target.iterdir())


def test_an_export_that_cannot_be_written_leaves_the_earlier_file_whole(results_dir, tmp_path, monkeypatch, capsys):
    """Nothing lost: a disk that fails the write (ENOSPC when the bytes are flushed) leaves the file an earlier
    export wrote as it was, and no temporary file beside it, for each format of a results directory."""
    import errno
    import os

    from stage.cli import main

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    for fmt in ("glb", "spine-glb"):
        out = tmp_path / fmt / "model.glb"
        out.parent.mkdir()
        out.write_bytes(b"the earlier export")
        with monkeypatch.context() as m:
            m.setattr(os, "fsync", full)
            assert main(["export", str(results_dir), "--format", fmt, "--out", str(out)]) != 0
        assert out.read_bytes() == b"the earlier export" and [p.name for p in out.parent.iterdir()] == ["model.glb"]
        err = capsys.readouterr().err
        assert "No space left on device" in err and len(err.splitlines()) == 1, err


def test_export_without_spine_is_a_clear_error(tmp_path, capsys):
    from stage.cli import main

    (tmp_path / "meshes").mkdir()
    with pytest.raises(NoSpineError, match="no spine.json yet"):
        export_rig(tmp_path)
    assert main(["export", str(tmp_path)]) == 2
    assert "no spine.json yet" in capsys.readouterr().err


def test_invalid_input(tmp_path, results_dir, take):
    _, spine, v, f = take
    with pytest.raises(ValueError, match="model"):
        armature_to_glb(spine)
    with pytest.raises(ValueError, match="scale"):
        armature_to_glb(rigged_model(spine, v, f), scale=-1)
    with pytest.raises(ValueError, match="sections"):
        spine_tubes(armature_from_spine(spine), sections=2)
    with pytest.raises(ValueError):
        spine_to_glb({"format": "nope"})
    with pytest.raises(FileNotFoundError, match="results directory"):
        export_rig(tmp_path / "missing")
    with pytest.raises(ValueError, match="reference"):
        export_rig(results_dir, reference=999)
    (results_dir / "meshes" / f"frame_{FRAMES // 2:06d}.ply").unlink()
    with pytest.raises(FileNotFoundError, match="mesh frame_.*is missing"):
        export_rig(results_dir)
    # no meshes/ at all: the spine of a mesh sequence (`stage spines --meshes`); `stage process` would not make them
    import shutil

    shutil.rmtree(results_dir / "meshes")
    with pytest.raises(FileNotFoundError, match=r"has no meshes/ folder .*meshes/frame_\d{6}\.ply.*--format spine-glb"):
        export_rig(results_dir)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "spine.json").write_text(json.dumps({"format": "capture-stage/spine@1"}))
    with pytest.raises(ValueError, match="missing key"):
        export_rig(bad)
