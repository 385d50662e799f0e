"""Spines end to end on meshes: real horse/cat, simulated creatures, hard frames, bad input.

Creature size in the simulated tests = diagonal of the bounding box of the
creature's capsules in the first frame.
"""

from __future__ import annotations

import contextlib
import json
import logging
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from pipeline.correspond import NoLimbsError
from pipeline.frame_skeleton import FrameSkeleton, SpineParams, frame_skeleton
from pipeline.geodesic import edge_graph, geodesic_distance, mesh_edges, vertex_areas
from pipeline.meshio import load_mesh, mesh_paths
from pipeline.spine import build_spine
from pipeline.spine_format import FORMAT, Spine, SpineFormatError, read_spine, validate_spine_dict, write_spine
from pipeline.spine_meshes import spine_from_meshes
from tests.conftest import shared_dataset

FPS = 30.0


# --------------------------------------------------------------------------- building blocks


def mesh_pose(pose, voxel):
    """Marching-cubes mesh of a simulated pose's signed distance field."""
    from skimage.measure import marching_cubes

    lo, hi = pose.bounds()
    lo = lo - 2 * voxel
    hi = hi + 2 * voxel
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    g = [lo[i] + voxel * np.arange(n[i]) for i in range(3)]
    v, f, _, _ = marching_cubes(pose.grid_sdf(g), 0.0, spacing=(voxel,) * 3)
    return v + lo, f


def polyline_distance(P, Q):
    """Distance from each point of P (n, 3) to the polyline Q (m, 3)."""
    a, b = Q[:-1], Q[1:]
    ab = b - a
    t = np.clip(((P[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12)[None], 0, 1)
    return np.linalg.norm(P[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(1)


def sphere_mesh(r=1.0, sub=3):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(m.vertices), np.asarray(m.faces)


_SIM: dict = {}


def simulated(name, frames=24, **kw):
    key = (name, frames, tuple(sorted(kw.items())))
    if key not in _SIM:
        from fake_cameras.creatures import make_creature

        c = make_creature(name, **kw)
        poses = [c.pose(i / FPS) for i in range(frames)]
        lo, hi = poses[0].bounds()
        size = float(np.linalg.norm(hi - lo))
        meshes = [mesh_pose(p, size / 56) for p in poses]
        frames_sk = [frame_skeleton(v, f) for v, f in meshes]
        _SIM[key] = (c, poses, size, frames_sk)
    return _SIM[key]


def limb_map(spine, poses, names):
    """Spine limb k -> creature limb name, by nearest true tip in the reference frame."""
    r = spine.meta["references"][0]
    T = np.array([poses[r].tips[n] for n in names])
    d = np.linalg.norm(spine.tips[r][:, None] - T[None], axis=2)
    m = d.argmin(1)
    assert len(set(m.tolist())) == spine.K
    return [names[i] for i in m]


# --------------------------------------------------------------------------- real meshes


@pytest.fixture(scope="module")
def horse():
    d = shared_dataset("horse_gallop")
    # the first 24 of the 48 frames: the take is one 24-frame gait cycle twice (frames k and k + 24
    # agree to 1e-4 of the mesh's units), so these are the whole motion at half the cost
    paths = mesh_paths(d / "0*.obj")[:24]
    meshes = [load_mesh(p) for p in paths]
    frames = [frame_skeleton(v, f) for v, f in meshes]
    return meshes, frames


def test_horse_gallop_six_limbs_on_same_body_part(horse):
    """K = 6, and the vertex nearest each spine tip stays on the same body part in >= 95 % of frames.

    Same body part: the nearest vertex of the tip in frame t lies within a geodesic
    radius of 0.1 sqrt(area) (about a hoof's length) of the reference frame's tip
    vertex, measured on the reference mesh (vertex ids correspond across frames).
    """
    meshes, frames = horse
    assert len(frames) == 24
    spine = build_spine(frames, fps=FPS, units="m")
    assert spine.K == 6
    r = spine.meta["references"][0]
    v, f = meshes[r]
    g = edge_graph(v, mesh_edges(f))
    radius = 0.1 * np.sqrt(vertex_areas(v, f).sum())
    ref_vert = [int(np.argmin(np.linalg.norm(v - spine.tips[r, k], axis=1))) for k in range(6)]
    D = geodesic_distance(g, np.array(ref_vert))
    same = np.zeros((len(frames), 6), dtype=bool)
    for t, (vt, _) in enumerate(meshes):
        for k in range(6):
            if np.all(np.isfinite(spine.tips[t, k])):
                nv = int(np.argmin(np.linalg.norm(vt - spine.tips[t, k], axis=1)))
                same[t, k] = D[k, nv] < radius
    assert same.mean(axis=0).min() >= 0.95, same.mean(axis=0)  # measured 1.0 for every limb (24 frames; 48 as well)


def test_cat_poses_six_tips_every_pose():
    d = shared_dataset("cat_poses")
    for p in mesh_paths(d / "0*.obj"):
        fs = frame_skeleton(*load_mesh(p))
        assert fs.n_tips == 6, p.name


# --------------------------------------------------------------------------- simulated creatures


@pytest.mark.slow
@pytest.mark.parametrize("name", ["starfish", "quadruped"])
def test_simulated_creature_accuracy(name):
    """K = true limb count; tips within 3 % of size in >= 95 % of frames; identities 100 %;
    mean distance between spine axes and true limb axes <= 2 % of size.

    The axis distance is measured from the true limb axis to the spine's axis of
    that limb (the spine's junction is a metanode inside the body, while the true
    axis starts at the limb's attachment on the body surface, so the spine axis
    is longer at its junction end by construction).
    """
    c, poses, size, frames = simulated(name)
    spine = build_spine(frames, fps=FPS, units="mm")
    assert spine.K == len(c.names)
    names = limb_map(spine, poses, c.names)
    T = len(poses)
    true_tips = np.array([[p.tips[n] for n in names] for p in poses])
    err = np.linalg.norm(spine.tips - true_tips, axis=2) / size
    ok = np.nan_to_num(err, nan=np.inf) <= 0.03
    assert ok.mean(axis=0).min() >= 0.95, err
    # identities: every seen tip is nearest to its own true tip
    for t in range(T):
        allt = np.array([poses[t].tips[n] for n in names])
        seen = np.all(np.isfinite(spine.tips[t]), axis=1)
        nearest = np.linalg.norm(spine.tips[t][:, None] - allt[None], axis=2).argmin(1)
        assert np.array_equal(nearest[seen], np.arange(spine.K)[seen]), t
    dists = []
    for t in range(T):
        for k, n in enumerate(names):
            ax = spine.axes[f"limb{k}"][t]
            if np.all(np.isfinite(ax)):
                dists.append(polyline_distance(poses[t].axes[n], ax).mean())
    assert np.mean(dists) / size <= 0.02, np.mean(dists) / size


@pytest.mark.slow
def test_hard_frames_tuck_and_spur():
    """Two limbs tucked for a few frames and a one-frame spurious bump: K stays right,
    the hidden limb is null (never given another limb's identity)."""
    c, poses, size, frames = simulated("quadruped", frames=18, tuck=(0.2, 0.3), spur=(0.45, 0.45 + 1 / FPS))
    spine = build_spine(frames, fps=FPS, units="mm")
    assert spine.K == 6
    counts = spine.meta["tip_counts"]
    assert max(counts) >= 6
    names = limb_map(spine, poses, c.names)
    for t in range(len(poses)):
        allt = np.array([poses[t].tips[n] for n in names])
        for k in range(6):
            if np.all(np.isfinite(spine.tips[t, k])):
                d = np.linalg.norm(allt - spine.tips[t, k], axis=1)
                # a seen tip is its own limb (or, while tucked, the partner it is pressed against)
                near = int(d.argmin())
                partner = set(c.tuck_pair) if names[k] in c.tuck_pair else {names[k]}
                assert names[near] in partner or d[k] <= 0.05 * size, (t, k, names[near])
    tucked = [t for t in range(len(poses)) if counts[t] < 6]
    for t in tucked:  # a limb is missing there: exactly the missing count are null
        assert np.sum(~np.all(np.isfinite(spine.tips[t]), axis=1)) >= 6 - counts[t]


# --------------------------------------------------------------------------- bad input


def test_sphere_has_no_tips_and_take_raises():
    v, f = sphere_mesh()
    fs = frame_skeleton(v, f)
    assert fs.n_tips == 0
    with pytest.raises(NoLimbsError):
        build_spine([fs, fs])


def test_empty_frame_one_frame_take_and_multicomponent(caplog):
    c, poses, size, frames = simulated("starfish", frames=4)
    empty = frame_skeleton(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    assert empty.n_tips == 0 and empty.n_faces == 0
    spine = build_spine([frames[0], empty, frames[1]], fps=FPS)
    assert spine.frame_count == 3 and spine.K == 5
    assert np.all(np.isnan(spine.tips[1]))
    d = spine.to_dict()
    assert all(x is None for x in d["frames"][1]["tips"].values())
    one = build_spine([frames[0]], fps=FPS)
    assert one.K == 5 and one.frame_count == 1
    # multi-component: a far-away sphere is dropped with a warning, tips unchanged
    pose = poses[0]
    v, f = mesh_pose(pose, size / 56)
    sv, sf = sphere_mesh(r=size / 20, sub=2)
    v2 = np.vstack([sv + np.array([3 * size, 0, 0]), v])
    f2 = np.vstack([sf, f + len(sv)])
    with caplog.at_level(logging.WARNING):
        fs = frame_skeleton(v2, f2)
    assert "connected parts" in caplog.text
    assert fs.n_tips == 5
    np.testing.assert_allclose(fs.tips, frames[0].tips, atol=1e-9)
    assert np.all(fs.tip_vertices >= len(sv))  # numbered in the input mesh


def test_nonmanifold_mesh_is_accepted():
    v, f = sphere_mesh(sub=2)
    # a fin sharing one edge with the sphere: non-manifold edge
    e = f[0, :2]
    v2 = np.vstack([v, v[e].mean(0) * 3])
    f2 = np.vstack([f, [[e[0], e[1], len(v)]]])
    fs = frame_skeleton(v2, f2)
    assert fs.n_tips <= 1


# --------------------------------------------------------------------------- format and driver


def test_write_read_roundtrip_and_validation(tmp_path):
    c, poses, size, frames = simulated("starfish", frames=4)
    spine = build_spine(frames, fps=FPS, units="mm")
    p = write_spine(tmp_path / "out" / "spine.json", spine)
    d = json.loads(p.read_text())
    assert d["format"] == FORMAT and d["frame_count"] == 4 and len(d["frames"]) == 4
    assert set(d["graph"]["limbs"]) == set(d["frames"][0]["tips"])
    for k in d["graph"]["limbs"]:
        ax = d["frames"][0]["axes"][k]
        # from junction to tip
        assert np.allclose(ax[-1], d["frames"][0]["tips"][k])
        assert np.allclose(ax[0], d["frames"][0]["junctions"][d["graph"]["parents"][k]])
    back = read_spine(p)
    np.testing.assert_allclose(back.tips, spine.tips)
    for k in spine.axes:
        np.testing.assert_allclose(back.axes[k], spine.axes[k])
    bad = dict(d, format="x")
    with pytest.raises(SpineFormatError):
        validate_spine_dict(bad)
    bad = json.loads(p.read_text())
    bad["graph"]["parents"]["j0"] = "limb0"
    with pytest.raises(SpineFormatError):
        validate_spine_dict(bad)
    bad = json.loads(p.read_text())
    bad["frames"][1]["index"] = 0
    with pytest.raises(SpineFormatError):
        validate_spine_dict(bad)
    bad = json.loads(p.read_text())
    bad["frames"][0]["tips"]["limb0"] = [1, 2]
    with pytest.raises(SpineFormatError):
        validate_spine_dict(bad)
    (tmp_path / "junk.json").write_text("{")
    with pytest.raises(SpineFormatError):
        read_spine(tmp_path / "junk.json")


def test_frame_skeleton_dict_roundtrip():
    c, poses, size, frames = simulated("starfish", frames=4)
    fs = frames[0]
    back = FrameSkeleton.from_dict(json.loads(json.dumps(fs.to_dict())))
    np.testing.assert_allclose(back.tips, fs.tips)
    np.testing.assert_allclose(back.limb_points, fs.limb_points)
    assert back.topology() == fs.topology()
    assert len(back.skeletons) == fs.n_tips


@pytest.mark.parametrize("pool", [False, True])
def test_what_a_mesh_sequences_frames_warn_of_is_said_once_per_kind(tmp_path, caplog, pool):
    """A sequence whose frames 0, 1 and 3 hold a speck beside the subject and whose frame 2 is empty: each kind is
    said once, naming its frames (not one line per frame, nor from a worker process's own log), and the spine is
    that of the frames without the specks (the largest part kept)."""
    import trimesh

    c, poses, size, frames = simulated("starfish", frames=4)
    clean, specked = tmp_path / "clean", tmp_path / "specked"
    for d in (clean, specked):
        d.mkdir()
    for i, p in enumerate(poses[:4]):
        v, f = mesh_pose(p, size / 40) if i != 2 else (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
        trimesh.Trimesh(v, f, process=False).export(clean / f"{i:04d}.ply")
        if i != 2:
            speck = trimesh.creation.icosphere(subdivisions=1, radius=size / 50)
            v, f = np.vstack([v, speck.vertices + v.max(0) + size / 5]), np.vstack([f, speck.faces + len(v)])
        trimesh.Trimesh(v, f, process=False).export(specked / f"{i:04d}.ply")
    in_memory = [load_mesh(q, largest=False) for q in sorted(specked.glob("*.ply"))]  # (numbered as given)
    said = []
    with ProcessPoolExecutor(2) if pool else contextlib.nullcontext() as ex:
        for meshes in (str(specked / "*.ply"), in_memory):
            caplog.clear()
            with caplog.at_level(logging.INFO):
                got = spine_from_meshes(meshes, executor=ex)
            said.append([r.getMessage() for r in caplog.records
                         if r.levelno >= logging.INFO and r.name.startswith("pipeline")])
            b = spine_from_meshes(str(clean / "*.ply"))
            assert got.K == b.K == 5
            np.testing.assert_allclose(got.tips, b.tips)
    assert said == [["skeletons: faces in other connected parts dropped (the largest part kept) (3 frames: 0, 1, 3)",
                     "skeletons: empty frame (no faces) (1 frame: 2)"]] * 2, said


def test_spine_from_meshes_parallel_matches_serial(tmp_path):
    import trimesh

    c, poses, size, frames = simulated("starfish", frames=4)
    paths = []
    for i, p in enumerate(poses[:3]):
        v, f = mesh_pose(p, size / 40)
        q = tmp_path / f"{i:04d}.ply"
        trimesh.Trimesh(v, f, process=False).export(q)
        paths.append(q)
    with ProcessPoolExecutor(2) as ex:
        a = spine_from_meshes(str(tmp_path / "*.ply"), executor=ex, fps=24, units="mm")
    b = spine_from_meshes([load_mesh(q) for q in paths], fps=24, units="mm")
    assert a.K == b.K == 5 and a.fps == 24
    np.testing.assert_allclose(a.tips, b.tips)


def test_invalid_input():
    v, f = sphere_mesh(sub=1)
    with pytest.raises(ValueError, match="vertices"):
        frame_skeleton(np.zeros((4, 2)), f)
    with pytest.raises(ValueError, match="faces"):
        frame_skeleton(v, f + 1000)
    with pytest.raises(ValueError, match="params"):
        frame_skeleton(v, f, params={"n_bins": 10})
    with pytest.raises(ValueError):
        SpineParams(n_bins=0)
    with pytest.raises(ValueError, match="frames"):
        build_spine([])
    with pytest.raises(ValueError, match="fps"):
        build_spine([FrameSkeleton.empty()], fps=0)
    with pytest.raises(ValueError, match="spine"):
        write_spine("/tmp/x.json", {"format": FORMAT})
    with pytest.raises(FileNotFoundError):
        read_spine("/nonexistent/spine.json")
    with pytest.raises(FileNotFoundError):
        spine_from_meshes("/nonexistent/*.obj")
    with pytest.raises(ValueError, match="executor"):
        spine_from_meshes([(v, f)], executor=2)
    with pytest.raises(SpineFormatError):
        Spine.from_dict({"format": FORMAT})


# --------------------------------------------------------------------------- a limb ending in near-equal maxima


def forked_take(frames=8):
    """The forked capsule (tests/pipeline/shapes.py) over a take: bump A stands still, bump B
    wobbles by 0.08 (of the radius-0.5 body), and which of the two is higher swaps every frame."""
    from tests.pipeline.shapes import forked_capsule

    return [forked_capsule(heights=(0.45, 0.43) if t % 2 else (0.43, 0.45),
                           b_offset=0.04 * np.array([np.cos(2.1 * t), np.sin(2.1 * t)])) for t in range(frames)]


def test_limb_with_near_equal_maxima_keeps_its_most_consistent_tip():
    """Each frame's highest bump swaps; the spine keeps bump A (the one still in the limb's frame) in
    every frame, and an alternate standing in equals the frame computed with it as the tip."""
    from pipeline.frame_skeleton import LIMB_FRACTIONS, with_alternates
    from pipeline.skeleton import grow_skeleton, limb_points

    meshes = forked_take()
    frames = [frame_skeleton(v, f) for v, f in meshes]
    assert all(len(fr.alternates) == 1 for fr in frames)
    spine = build_spine(frames, fps=FPS)
    assert spine.K == 2
    k = int(np.argmax(spine.tips[0][:, 2]))
    # measured 0.0022 at most (bump A's tip vertex against its centre); bump B lies 0.56 away
    np.testing.assert_allclose(spine.tips[:, k, :2], np.tile([0.28, 0.0], (len(frames), 1)), atol=0.05)
    b_higher = [t for t, fr in enumerate(frames) if fr.tips[np.argmax(fr.tips[:, 2]), 0] < 0]
    assert len(b_higher) >= 2 and spine.meta["tip_alternates"] == {f"limb{k}": b_higher}
    # stand-in: tip, skeleton and the rings the other skeleton records are those of the alternate
    for t in (0, 1):  # in frame 1 the alternate's ring in the other tip's skeleton is not the tip's
        v, f = meshes[t]
        fr = frames[t]
        alt = fr.alternates[0]
        got = with_alternates(fr, [0])
        e = mesh_edges(f)
        tips = fr.tip_vertices.copy()
        tips[alt.tip] = alt.vertex
        for j, s in enumerate(got.skeletons):
            ref = grow_skeleton(v, e, edge_graph(v, e), int(tips[j]), tips=tips, seed=j,
                                min_bin_width=float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()),
                                weights=vertex_areas(v, f))
            np.testing.assert_array_equal(s.tip_nodes, ref.tip_nodes)
            # measured 0 (nodes and limb points: the same computation); 1e-12 allows summation order only
            np.testing.assert_allclose(s.nodes, ref.nodes, atol=1e-12)
            # every tip's limb points, not only the swapped tip's: the other limb ends at its new ring
            np.testing.assert_allclose(got.limb_points[j], limb_points(ref, got.tips[j], LIMB_FRACTIONS), atol=1e-12)
        np.testing.assert_allclose(got.tips[alt.tip], v[alt.vertex])


def test_alternates_survive_the_stored_records():
    """Alternates and clear tips survive the JSON dict and the skeleton record; a record without
    clear tips (an older format) reads as not known."""
    from pipeline.process.records import load_skeleton, skeleton_bytes

    fr = frame_skeleton(*forked_take(1)[0])
    assert len(fr.alternates) == 1
    for back in (FrameSkeleton.from_dict(json.loads(json.dumps(fr.to_dict()))), None):
        if back is None:
            import tempfile
            from pathlib import Path

            with tempfile.TemporaryDirectory() as d:
                p = Path(d) / "r.npz"
                p.write_bytes(skeleton_bytes({"index": 0, "status": "ok", "skeleton": fr}))
                back = load_skeleton(p)["skeleton"]
        a, b = fr.alternates[0], back.alternates[0]
        assert back.clear.dtype == bool and back.clear.tolist() == fr.clear.tolist()  # the clear tips too
        assert (a.tip, a.vertex) == (b.tip, b.vertex)
        np.testing.assert_array_equal(a.rings, b.rings)
        np.testing.assert_array_equal(a.alt_rings, b.alt_rings)
        np.testing.assert_allclose(a.skeleton.nodes, b.skeleton.nodes)
        np.testing.assert_allclose(a.limb_points, b.limb_points)
    from dataclasses import replace

    assert FrameSkeleton.from_dict({**fr.to_dict(), "clear": None}).clear is None
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "old.npz"
        p.write_bytes(skeleton_bytes({"index": 0, "status": "ok", "skeleton": replace(fr, clear=None)}))
        assert load_skeleton(p)["skeleton"].clear is None
