"""Tracking with a rig as the articulated prior (pipeline.armature_track, pipeline.track_armature.track_with_armature).

The fast take: the simulated quadruped filmed at 5 frames a second (6 cameras, 320x240, 8 frames,
11.7 mm voxels), so its limbs move 3 voxels a frame or more (its true surface points: 95th percentile
of the steps over 4 voxels). Tracked again with the rig built from its first tracking (the tracking alone) as the
prior (``stage track --armature-rounds 1``), every frame's template vertices must lie within 2 voxels
(mean) and 4 voxels (95th percentile) of their true points
(``fake_cameras.surface_motion.tracking_errors``). Figures, also of the larger fast takes and of a
rig of the true motion, in docs/tracking.md ("Fast motion: the armature as the articulated prior").
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import pickle
from types import SimpleNamespace

import numpy as np
import pytest

from fake_cameras.mesh_motion import mesh_sequence
from pipeline.armature import build_armature
from pipeline.armature_track import ArmatureTracker, fit_pose_to_surface, surface_residual
from pipeline.geodesic import largest_component
from pipeline.mesh_primitives import vertex_normals
from pipeline.tracking import TemplateTracker

FAST = dict(n_cameras=6, frames=8, size=(320, 240), seed=3, fps=5.0)


@pytest.fixture(scope="module")
def sequence():
    ms = mesh_sequence("quadruped", frames=8, duration=0.7, voxel=14.0)  # 0.1 s a frame
    _, faces, kept = largest_component(ms.vertices[0], ms.faces, warn=False)  # a rig is of one connected part
    ms = SimpleNamespace(vertices=ms.vertices[:, kept], faces=faces)
    rig = build_armature(ms.vertices, ms.faces, reference=0)
    return ms, rig


def test_pose_on_the_surface_matches_the_fit_by_correspondence(sequence):
    """The articulated ICP on frame t's surface, started from frame t-1's pose, lands where the
    least squares with known correspondences puts the rig (within a fifth of the 14 mm voxel, mean)."""
    ms, rig = sequence
    for t in (2, 7):
        X = ms.vertices[t]
        pose, res = fit_pose_to_surface(rig.model, rig.fit.poses[t - 1], X, vertex_normals(X, ms.faces), gate=20.0)
        gap = np.linalg.norm(rig.model.deform(pose) - rig.posed(t), axis=1).mean()
        start_gap = np.linalg.norm(rig.posed(t - 1) - rig.posed(t), axis=1).mean()
        assert gap <= 0.2 * 14.0, (t, gap, start_gap)
        assert res == pytest.approx(surface_residual(rig.model.deform(pose), X, gate=20.0))


def test_posed_subset_is_the_posed_mesh_at_those_rows(sequence):
    """The ICP's posed subset and its normals, from the faces around it alone, equal the whole posed
    mesh's vertices and vertex normals at those rows."""
    _, rig = sequence
    m, pose = rig.model, rig.fit.poses[5]
    S, vn = m.posed_subset(pose, 300)
    full = m.deform(pose)
    rows = m.subset(300)
    np.testing.assert_allclose(S, full[rows], rtol=0, atol=1e-9)
    np.testing.assert_allclose(vn, vertex_normals(full, m.faces)[rows], rtol=0, atol=1e-12)


def test_surface_residual_exact():
    V = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    X = np.array([[0.0, 0, 1.0], [0.0, 0, 50.0]])
    # vertices -> points: 1 and sqrt(101) clipped at 5; points -> vertices: 1 and 50 clipped at 5
    assert surface_residual(V, X, gate=5.0) == pytest.approx((1 + 5) / 2 + (1 + 5) / 2)


def test_anchor_pulls_every_vertex():
    """With a huge anchor weight the fit ends on the anchor; with weight 0 it is the plain fit."""
    ms = mesh_sequence("starfish", frames=2, voxel=14.0)
    V, F = ms.vertices[0], ms.faces
    tr = TemplateTracker(V, F)
    X = ms.vertices[1]
    N = vertex_normals(X, F)
    target = V + np.array([3.0, -2.0, 1.0])
    far = tr.fit(X, N, previous=V, anchor=(target, 1e9))
    assert np.abs(far.vertices - target).max() < 1e-3
    plain, zero = tr.fit(X, N, previous=V), tr.fit(X, N, previous=V, anchor=(target, 0.0))
    assert np.allclose(plain.vertices, zero.vertices, atol=1e-6)


def test_invalid_input(sequence):
    ms, rig = sequence
    X = ms.vertices[1]
    N = vertex_normals(X, ms.faces)
    pose = rig.fit.poses[0]
    with pytest.raises(ValueError, match="model"):
        fit_pose_to_surface(object(), pose, X, N, gate=10.0)
    with pytest.raises(ValueError, match="start"):
        fit_pose_to_surface(rig.model, "pose", X, N, gate=10.0)
    with pytest.raises(ValueError, match="points"):
        fit_pose_to_surface(rig.model, pose, X[:, :2], N, gate=10.0)
    with pytest.raises(ValueError, match="gate"):
        fit_pose_to_surface(rig.model, pose, X, N, gate=0.0)
    with pytest.raises(ValueError, match="rounds"):
        fit_pose_to_surface(rig.model, pose, X, N, gate=10.0, rounds=0)
    with pytest.raises(ValueError, match="marks"):
        fit_pose_to_surface(rig.model, pose, X, N, gate=10.0, marks=(np.array([0, len(X) + 5]), X[:2]))
    with pytest.raises(ValueError, match="marks"):
        fit_pose_to_surface(rig.model, pose, X, N, gate=10.0, marks=(np.array([0]), X[:2]))
    with pytest.raises(ValueError, match="gate"):
        surface_residual(X, X, gate=-1.0)
    with pytest.raises(ValueError, match="vertices"):
        surface_residual(X[:0], X, gate=1.0)
    tr = TemplateTracker(ms.vertices[0], ms.faces)
    with pytest.raises(ValueError, match="tracker"):
        ArmatureTracker(object(), rig.model)
    with pytest.raises(ValueError, match="model"):
        ArmatureTracker(tr, object())
    with pytest.raises(ValueError, match="weight"):
        ArmatureTracker(tr, rig.model, weight=0.0)
    small = TemplateTracker(*_two_triangles())
    with pytest.raises(ValueError, match="connectivity"):
        ArmatureTracker(small, rig.model)
    with pytest.raises(ValueError, match="candidates"):
        ArmatureTracker(tr, rig.model).fit(X, N, previous=ms.vertices[0], candidates=[])
    with pytest.raises(ValueError, match="candidates"):
        ArmatureTracker(tr, rig.model).fit(X, N, previous=ms.vertices[0], candidates=[pose, "pose"])
    with pytest.raises(ValueError, match="anchor"):
        tr.fit(X, N, previous=ms.vertices[0], anchor=(X[:3], 1.0))
    with pytest.raises(ValueError, match="anchor weight"):
        tr.fit(X, N, previous=ms.vertices[0], anchor=(ms.vertices[0], -1.0))
    with pytest.raises(ValueError, match="anchor"):
        tr.fit(X, N, previous=ms.vertices[0], anchor=ms.vertices[0])


def _two_triangles():
    return np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), np.array([[0, 1, 2], [1, 3, 2]])


@pytest.fixture(scope="module")
def fast_take(tmp_path_factory):
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take

    sim = simulate_take("quadruped", **FAST)
    root = tmp_path_factory.mktemp("fast_quadruped")
    res = root / "results"
    process_take(record_take(sim, root / "quadruped.h5"), res, executor=None)
    process_take(root / "quadruped.h5", res, steps=("track",), executor=None)
    return sim, res


class _PicklingThreads(cf.ThreadPoolExecutor):
    """A thread pool whose tasks go through pickle first, as a process pool's do; counts them."""

    submitted = 0

    def submit(self, fn, /, *args, **kwargs):
        self.submitted += 1
        return super().submit(*pickle.loads(pickle.dumps((fn, *args))), **kwargs)


@pytest.mark.slow
def test_fast_take_tracked_with_its_rig(fast_take):
    """``stage track --armature-rounds 2`` on the fast take: the armature built from the default
    tracking, every frame tracked again with it, built again from that tracking and tracked again when
    it explains the surfaces better (the paper's track, refit, repeat); every frame within 2 voxels
    (mean) and 4 (95th percentile)."""
    from fake_cameras.surface_motion import surface_point_tracks, tracking_errors
    from pipeline.meshio import load_mesh
    from pipeline.track_armature import track_with_armature

    sim, res = fast_take
    voxel = float(json.loads((res / "grid.json").read_text())["voxel"])
    ref = int(json.loads((res / "tracked" / "track.json").read_text())["reference_frame"])
    V0, _ = load_mesh(res / "tracked" / f"{ref:06d}.ply", largest=False)
    truth = surface_point_tracks(sim.creature, V0, [sim.times[ref], *sim.times])[1:]
    steps = np.linalg.norm(np.diff(truth, axis=0), axis=2) / voxel
    assert np.percentile(steps, 95) >= 3.0  # the take is fast: 3 voxels a frame or more at the 95th percentile
    with _PicklingThreads(max_workers=1) as ex:  # one half of every round aside, its task pickled as a process pool's
        rep = track_with_armature(res, rounds=2, executor=ex)
    assert ex.submitted >= 1  # (the halves depend only on the reference frame: the same frames as in order)
    assert rep["rig_rounds"] >= 1 and rep["rig_prior"]["rounds"][0]["segments"] > 1
    assert {r["armature"] for r in rep["rig_prior"]["rounds"]} == {"tracking"}  # (the spine's round is opt-in)
    err, vols, _ = tracking_errors(sim.creature, sim.times, res)
    # every frame within 2 voxels on average and 4 at the 95th percentile (the figures, with the prior and
    # without: docs/tracking.md, "Accuracy")
    assert err.mean(axis=1).max() <= 2.0, err.mean(axis=1)
    assert np.percentile(err, 95, axis=1).max() <= 4.0, np.percentile(err, 95, axis=1)
    assert np.all(np.abs(vols - 1) <= 0.1), vols


@pytest.mark.slow
def test_the_spine_rig_of_a_take_is_bound_to_its_tracked_template(fast_take):
    """``track_with_armature(spine=True)``'s first armature: the take's spine rig (two bones an axis) on the
    tracked template at the reference frame, its limb vertices each on a bone of their own limb."""
    from pipeline.armature_files import load_sequence, tracked_meshes
    from pipeline.spine_format import read_spine
    from pipeline.track_armature_models import SPINE_BONES, _spine_rig
    from pipeline.track_frames import surface_meshes

    sim, res = fast_take
    frames, _ = surface_meshes(res, "meshes")
    vs, faces, _ = load_sequence(tracked_meshes(res))
    refi = frames.index(int(json.loads((res / "tracked" / "track.json").read_text())["reference_frame"]))
    model = _spine_rig(res, frames, vs[refi], faces, refi)
    spine = read_spine(res / "spine.json")
    assert model.skeleton.n_parts == 1 + SPINE_BONES * len(spine.axes)
    np.testing.assert_array_equal(model.vertices, vs[refi])
    assert _spine_rig(res, frames[:-1], vs[refi], faces, refi) is None  # a spine of other frames: built from the tracking


CENTRE, RADIUS = np.array([0.0, 0.0, 300.0]), 150.0


def _sphere_results(root, frames=4, truth=False):
    """The turning sphere of the carving tests (6 cameras at 160x120), with a 10 mm grid (``truth``: and its true
    vertices per frame)."""
    from pipeline.volume import Grid
    from tests.pipeline.tracking_takes import turning_sphere_results

    res, true = turning_sphere_results(root, frames=frames, size=(160, 120))
    (res / "grid.json").write_text(json.dumps(Grid(lo=CENTRE - 200, shape=(40, 40, 40), voxel=10.0).to_dict()))
    return (res, true) if truth else res


def _sphere_error(path):
    from pipeline.meshio import load_mesh

    v, _ = load_mesh(path, largest=False)
    return np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS) / 10.0  # voxels


def test_cli_armature_rounds_on_a_turning_sphere(tmp_path, capsys):
    """``stage track RESULTS --armature-rounds 1`` on a rigid turning sphere: one segment, the frames tracked
    again, every vertex still on the sphere (within a voxel), the rounds recorded. The turn itself the
    surface cannot show: the armature's pose stays put (all of the turn left), unless the colour tracks
    pull it (``colour=True``, with the rigid armature given; measured 0.25, 0.41 of the turn left on frames 1, 2)."""
    from pipeline.armature_fit import articulated_model
    from pipeline.armature_skeleton import ArticulatedSkeleton
    from pipeline.meshio import load_mesh
    from pipeline.track_armature import track_with_armature
    from stage.cli import main

    res, truth = _sphere_results(tmp_path, frames=3, truth=True)

    def left():
        return [np.linalg.norm(load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)[0] - truth[k], axis=1).mean()
                / np.linalg.norm(truth[k] - truth[0], axis=1).mean() for k in (1, 2)]

    assert main(["track", str(res), "--armature-rounds", "1", "--workers", "0", "--no-progress"]) == 0
    assert "articulated prior: 1 round (armature segments: 1;" in capsys.readouterr().out
    rep = json.loads((res / "tracked" / "track.json").read_text())
    assert rep["rig_rounds"] == 1 and sorted(rep["frames"]) == ["0", "1", "2"] and not rep["rig_prior"]["colour_tracks"]
    assert all("rig_residual_mm" in rep["frames"][k] for k in ("1", "2"))
    for k in range(3):
        assert _sphere_error(res / "tracked" / f"{k:06d}.ply").mean() < 1.0
    assert min(left()) > 0.9
    V0, F0 = load_mesh(res / "tracked" / "000000.ply", largest=False)
    rigid = articulated_model(V0, F0, ArticulatedSkeleton(  # the root and one bone to an auxiliary joint
        names=("root", "aux0"), parents=np.array([-1, 0]), rest=np.stack([CENTRE, CENTRE + [0.0, 0.0, RADIUS]]),
        articulation=np.array([False, False]), segment_pairs=(None, None), part=np.array([0, 0]), part_joint=np.array([0]),
        part_parent=np.array([-1]), bones=np.array([[0, 1]])))
    assert track_with_armature(res, rigid, colour=True)["rig_prior"]["colour_tracks"]
    assert max(left()) <= 0.65, left()
    for k in range(3):
        assert _sphere_error(res / "tracked" / f"{k:06d}.ply").mean() < 1.0
    # tracking again without the rig starts over: other settings
    assert main(["-q", "track", str(res), "--workers", "0", "--armature-rounds", "0"]) == 0
    assert json.loads((res / "tracked" / "track.json").read_text())["rig_rounds"] == 0
    # one round is the default
    assert main(["-q", "track", str(res), "--workers", "0"]) == 0
    assert json.loads((res / "tracked" / "track.json").read_text())["rig_rounds"] == 1


def test_armature_rounds_take_the_templates_labels_for_their_patches_and_armature(tmp_path, monkeypatch, caplog):
    """``track_with_armature(labels=)``: the template fit's patches follow the labels (the body one patch) in
    this process and in the worker's half, and the round's armature is built with them as its limbs;
    ``labels="spine"`` of a tracking with the spine's labels takes the ones it wrote (``tracked/labels.npy``)."""
    import trimesh

    import pipeline.armature as armature
    import pipeline.track as track
    import pipeline.track_armature as ta
    import pipeline.track_armature_round as tr
    from pipeline.results import atomic_write_bytes, ply_bytes

    t = trimesh.creation.icosphere(subdivisions=2, radius=60.0)
    for k in range(3):
        atomic_write_bytes(tmp_path / "meshes" / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [3.0 * k, 0, 0], t.faces))
    (tmp_path / "spine.json").write_text('{"frames": 3}')
    ref = t.vertices + [3.0, 0, 0]  # a spine's stand-in: reference frame 1, so both halves have frames
    fake = SimpleNamespace(vertices=ref, faces=t.faces, deform=lambda i: ref + [3.0 * (i - 1), 0, 0])
    monkeypatch.setattr(track, "spine_model", lambda *a: (1, fake))
    monkeypatch.setattr(tr, "spine_model", lambda *a: (1, fake))
    upper = np.where(t.vertices[:, 2] > 0, 0, -1)
    track.track_results(tmp_path, labels=upper)
    patches, limbs = [], []
    real_tracker, real_build = ta.TemplateTracker, armature.build_armature

    class Recorder(real_tracker):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            patches.append(self.patches)

    def build(*a, **k):
        limbs.append(k.get("limbs"))
        return real_build(*a, **k)

    monkeypatch.setattr(ta, "TemplateTracker", Recorder)
    monkeypatch.setattr(tr, "TemplateTracker", Recorder)  # (the worker's half)
    monkeypatch.setattr(armature, "build_armature", build)
    with cf.ThreadPoolExecutor(max_workers=1) as ex:
        rep = ta.track_with_armature(tmp_path, rounds=1, labels=lambda v, f, frame: upper, executor=ex)
    assert rep["rig_prior"]["patch_labels"] == "given" and rep["rig_rounds"] == 1 and rep["reference_frame"] == 1
    assert len(patches) == 2 and all(np.array_equal(p, patches[0]) for p in patches)  # here and the worker's half
    assert len(set(patches[0][upper < 0])) == 1 and not set(patches[0][upper < 0]) & set(patches[0][upper == 0])
    assert len(limbs) == 1 and np.array_equal(limbs[0].limb, upper) and limbs[0].names == ("limb0",)
    with pytest.raises(ValueError, match="labels"):
        ta.track_with_armature(tmp_path, labels=upper[1:])
    import pipeline.spine_format as spine_format

    monkeypatch.setattr(spine_format, "read_spine", lambda path: SimpleNamespace(frame_count=2))
    rep = ta.track_with_armature(tmp_path, rounds=1, labels=upper, parts="limbs")  # no usable spine: the motion's
    assert rep["rig_prior"]["parts"] == "motion" and len(limbs) == 2
    # labels="spine" of a tracking with the spine's labels: the ones it wrote (tracked/labels.npy), though the spine
    # gives none now (as with `stage track --template`, its labels are not the tracked template's)
    path = tmp_path / "tracked" / "track.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "patch_labels": "spine"}))
    rep = ta.track_with_armature(tmp_path, rounds=1, labels="spine")
    assert rep["rig_prior"]["patch_labels"] == "spine" and np.array_equal(patches[-1], patches[0])
    (tmp_path / "tracked" / "labels.npy").write_bytes(b"\x93NUMPY")  # truncated: one line, computed again (none here)

    def no_spine(path):
        raise spine_format.SpineFormatError(f"{path}: not a spine")

    monkeypatch.setattr(spine_format, "read_spine", no_spine)
    with caplog.at_level(logging.WARNING):
        rep = ta.track_with_armature(tmp_path, rounds=1, labels="spine")
    assert rep["rig_prior"]["patch_labels"] is None
    assert sum("labels.npy cannot be read" in r.getMessage() for r in caplog.records) == 1


def test_armature_round_from_the_labels_and_the_spines_limb_axes(tmp_path, monkeypatch):
    """``parts="limbs"`` with ``labels="spine"``: the round's armature is cut by ``limb_segments`` from the labels with
    every frame's surface (``template_labels(surfaces=)``, the limbs' roots given back by ``root_tubes``) along the
    spine's limb axes, the body one part hung above every limb's chain, every vertex on its own part; no motion
    segmentation."""
    import pipeline.armature as armature
    import pipeline.limb_segments as limb_segments
    import pipeline.track as track
    import pipeline.track_armature as ta
    from pipeline.armature_files import load_sequence, tracked_meshes
    from pipeline.meshio import load_mesh
    from pipeline.spine_format import read_spine
    from pipeline.template_labels import root_tubes, template_labels
    from tests.pipeline.tracking_takes import creature_spine_results

    creature_spine_results(tmp_path)
    track.track_results(tmp_path, labels="spine")
    cut, models = [], []
    real_cut, real_armature = limb_segments.limb_segments, ta._limb_rig

    def record(*a, **k):
        cut.append((a, k))
        return real_cut(*a, **k)

    def rig(*a, **k):
        models.append(real_armature(*a, **k))
        return models[-1]

    monkeypatch.setattr(limb_segments, "limb_segments", record)
    monkeypatch.setattr(ta, "_limb_rig", rig)
    monkeypatch.setattr(armature, "build_armature", lambda *a, **k: pytest.fail("the motion's armature was built"))
    vs, faces, _ = load_sequence(tracked_meshes(tmp_path))
    rep = ta.track_with_armature(tmp_path, rounds=1, labels="spine", parts="limbs")
    assert rep["rig_prior"]["parts"] == "limbs" and rep["rig_prior"]["rounds"][0]["armature"] == "limbs"
    ref = rep["reference_frame"]
    surfaces = [load_mesh(tmp_path / "meshes" / f"frame_{k:06d}.ply", largest=False)[0] for k in range(3)]
    (tracked, labels, axes), kw = cut[0]
    assert np.array_equal(labels, root_tubes(vs[ref], faces, template_labels(tmp_path, vs[ref], faces, reference=ref,
                                                                        surfaces=surfaces)))
    spine = read_spine(tmp_path / "spine.json")
    assert len(axes) == len(spine.limb_ids) and all(np.allclose(a, spine.axes[lid][ref]) for a, lid in zip(axes, spine.limb_ids))
    model = models[0][0]
    seg = real_cut(tracked, labels, axes, **kw)
    assert model.skeleton.n_parts == seg.max() + 1 and model.skeleton.part_parent[0] == -1
    from pipeline.track_frames import read_round_segments  # the kept round's segments, for the armature's cuts

    assert np.array_equal(read_round_segments(tmp_path, rep, len(vs[ref])), seg) and "cut" not in rep["rig_prior"]["rounds"][0]
    assert np.array_equal(model.vertex_parts[:, 0] == 0, labels == -1)  # the body one part, the root


def test_cli_armature_parts_reach_the_rounds(tmp_path, monkeypatch, capsys):
    """``stage track RESULTS --labels --armature-rounds 1 --armature-parts limbs`` runs the rounds with
    ``parts="limbs"`` and the labels; without the flag, ``parts="motion"``."""
    import pipeline.carve as carve
    import pipeline.track_armature as ta
    from stage.cli import main

    calls = []
    report = {"frames": {}, "vertices": 8, "gamma": 0.05, "gate_mm": 10.0, "solver": "cg", "skipped": []}
    monkeypatch.setattr(carve, "track_with_carving", lambda *a, **k: report)
    rounds = {**report, "rig_rounds": 1, "rig_prior": {"rounds": [{"armature": "limbs", "segments": 7, "residual_mm": 1.5}]}}
    monkeypatch.setattr(ta, "track_with_armature", lambda src, **k: calls.append(k) or rounds)
    (tmp_path / "meshes").mkdir()
    for extra in (["--armature-parts", "limbs"], []):
        assert main(["-q", "track", str(tmp_path), "--labels", "--armature-rounds", "1", *extra]) == 0
        assert "armature segments: 7 from the limbs" in capsys.readouterr().out
    assert [(k["parts"], k["labels"], k["rounds"]) for k in calls] == [("limbs", "spine", 1), ("motion", "spine", 1)]


def test_segment_armature_invalid_input():
    from pipeline.armature_track import segment_armature

    model, part = _tube()
    v, f = model.vertices, model.faces
    with pytest.raises(ValueError, match="vertices"):
        segment_armature(v[:, :2], f, part, np.array([-1, 0]))
    with pytest.raises(ValueError, match="faces"):
        segment_armature(v, f + len(v), part, np.array([-1, 0]))
    with pytest.raises(ValueError, match="segments"):
        segment_armature(v, f, part[1:], np.array([-1, 0]))
    with pytest.raises(ValueError, match="segments"):
        segment_armature(v, f, part * 2, np.array([-1, 0, 0]))  # segment 1 has no vertex
    with pytest.raises(ValueError, match="parents"):
        segment_armature(v, f, part, np.array([-1, -1]))
    with pytest.raises(ValueError, match="parents"):
        segment_armature(v, f, np.r_[part[:-1], 2], np.array([-1, 2, 1]))  # 1 and 2 a cycle
    with pytest.raises(ValueError, match="motion"):
        segment_armature(v, f, part, np.array([-1, 0]), motion=v[None, :5])
    with pytest.raises(ValueError, match="reference"):
        segment_armature(v, f, part, np.array([-1, 0]), motion=np.stack([v, v]), reference=2)


def test_track_with_rig_invalid_input(tmp_path, capsys):
    from pipeline.track_armature import track_with_armature
    from stage.cli import main

    res = tmp_path  # a results directory not tracked (the options are checked first)
    with pytest.raises(ValueError, match="rounds"):
        track_with_armature(res, rounds=0)
    with pytest.raises(ValueError, match="rounds"):
        track_with_armature(res, rounds="many")
    with pytest.raises(ValueError, match="lambda_thr"):
        track_with_armature(res, lambda_thr=1.5)
    with pytest.raises(ValueError, match="model"):
        track_with_armature(res, model=object())
    with pytest.raises(ValueError, match="spine"):
        track_with_armature(res, spine="yes")
    with pytest.raises(ValueError, match="parts"):
        track_with_armature(res, parts="bones")
    with pytest.raises(FileNotFoundError, match="stage track"):
        track_with_armature(res)  # not tracked yet
    with pytest.raises(SystemExit):  # argparse: "must be a count >= 0 or 'auto'"
        main(["-q", "track", str(res), "--armature-rounds", "-1"])
    # one armature round is the default: its rules speak when the rounds are turned off
    assert main(["-q", "track", str(res), "--spine-armature", "--armature-rounds", "0"]) == 2
    assert "--spine-armature needs --armature-rounds" in capsys.readouterr().err
    assert main(["-q", "track", str(res), "--armature-parts", "limbs", "--labels", "--armature-rounds", "0"]) == 2
    assert "--armature-parts 'limbs' needs --armature-rounds (" in capsys.readouterr().err  # what to add, alone
    assert main(["-q", "track", str(res), "--armature-parts", "limbs", "--armature-rounds", "1"]) == 2
    assert "--armature-parts 'limbs' needs --labels (" in capsys.readouterr().err
    assert main(["-q", "track", str(res), "--armature-parts", "limbs"]) == 2  # the default round, without labels
    assert "--armature-parts 'limbs' needs --labels (" in capsys.readouterr().err
    assert main(["-q", "track", str(res), "--armature-parts", "limbs", "--armature-rounds", "0"]) == 2
    assert "--armature-parts 'limbs' needs --armature-rounds and --labels (" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: "invalid choice"
        main(["-q", "track", str(res), "--armature-parts", "bones"])


def _tube(rings: int = 9, per: int = 8, length: float = 80.0, radius: float = 6.0):
    """A tube along x of ``rings`` rings of ``per`` vertices, bound to two parts that meet halfway (a joint)."""
    from pipeline.armature_fit import ArticulatedModel
    from pipeline.armature_skeleton import ArticulatedSkeleton

    a = np.linspace(0, 2 * np.pi, per, endpoint=False)
    xs = np.linspace(0, length, rings)
    v = np.concatenate([np.c_[np.full(per, x), radius * np.cos(a), radius * np.sin(a)] for x in xs])
    f = []
    for r in range(rings - 1):
        for i in range(per):
            p, q = r * per + i, r * per + (i + 1) % per
            f += [[p, q, q + per], [p, q + per, p + per]]
    sk = ArticulatedSkeleton(names=("root", "joint1", "aux0"), parents=np.array([-1, 0, 1]),
                             rest=np.array([[0.0, 0, 0], [length / 2, 0, 0], [length, 0, 0]]),
                             articulation=np.array([False, True, False]), segment_pairs=(None,) * 3,
                             part=np.array([0, 1, 1]), part_joint=np.array([0, 1]), part_parent=np.array([-1, 0]),
                             bones=np.array([[0, 1], [1, 2]]))
    part = (v[:, 0] > length / 2).astype(np.int64)
    return ArticulatedModel(v, np.array(f), sk, part[:, None], np.ones((len(v), 1))), part


def _rot(axis, angle):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * angle).as_matrix()


def test_segment_armature_turns_every_segment_about_its_centre_of_rotation():
    """A tube of three rigid segments in a chain, each turning about a pivot 4 mm into the next segment past
    the middle of their two boundary rings: with the motion every joint is its centre of rotation (to 0.05 mm), without it the
    ring's centroid; every vertex moves with its own segment's part alone, and the true motion's per-part
    poses skin every frame exactly."""
    from pipeline.armature_track import segment_armature

    model, _ = _tube(rings=13, length=120.0)
    v, f = model.vertices, model.faces
    seg = np.searchsorted([45.0, 85.0], v[:, 0])  # rings at x = 0, 10, .. 120: the boundaries' rings at 40, 50 and 80, 90
    pivots = np.array([[49.0, 0, 0], [89.0, 0, 0]])
    T = 6
    frames = np.empty((T, len(v), 3))
    for t in range(T):  # the root's rigid motion, then every segment turned about its pivot (ball joints)
        G = [(_rot([0, 0, 1], 0.1 * t), np.array([2.0 * t, 0, 0]))]
        for j, axis in enumerate(([np.cos(t), np.sin(t), 0.5], [0.5, np.cos(2 * t), np.sin(2 * t)])):
            R = G[-1][0] @ _rot(axis, 0.2 + 0.1 * t * (j + 1))
            c = pivots[j]
            G.append((R, G[-1][0] @ c + G[-1][1] - R @ c))
        frames[t] = np.stack([G[s][0] @ x + G[s][1] for x, s in zip(v, seg)])
        if t == 0:  # the pivots where the rest frame has them
            at_rest = np.stack([G[j][0] @ c + G[j][1] for j, c in enumerate(pivots)])
    arm = segment_armature(frames[0], f, seg, np.array([-1, 0, 1]), motion=frames, reference=0)
    assert arm.skeleton.n_parts == 3 and list(arm.skeleton.part_parent) == [-1, 0, 1]
    assert np.abs(arm.pivots[1:] - at_rest).max() < 0.05
    assert arm.influences.shape == (len(v), 1) and np.array_equal(arm.vertex_parts[:, 0], seg)
    assert np.allclose(arm.weights, 1.0)
    from pipeline.armature_fit import Pose
    from pipeline.rigid_parts import rigid_motions

    motions = [rigid_motions(frames[:, seg == s]) for s in range(3)]
    for t in (1, T - 1):  # the segments' own rigid motions skin every vertex with its segment's alone
        pose = Pose(np.stack([m[0][t] for m in motions]), np.stack([m[1][t] for m in motions]))
        assert np.abs(arm.deform(pose) - frames[t]).max() < 1e-9
    still = segment_armature(v, f, seg, np.array([-1, 0, 1]))
    assert np.allclose(still.pivots[1:], [[45.0, 0, 0], [85.0, 0, 0]], atol=1e-9)


def test_a_body_piece_that_does_not_move_with_the_body_becomes_a_limb():
    """``parts="limbs"``: a piece the labels give the body (an arm the spine has no axis for) that the body's motion
    carries off the surfaces becomes a limb of its own, its axis from where it meets the body to its far end; a body
    that moves as one gains nothing."""
    import pipeline.track_armature_labels as tl

    tube, _ = _tube(rings=13, length=120.0)
    v, f = tube.vertices, tube.faces
    other = v[:16] + [0.0, 40.0, 0]  # a labelled limb of two rings beside it
    V = np.vstack([v, other])
    F = np.vstack([f, _tube(rings=2, length=10.0)[0].faces + len(v)])
    labels = np.r_[np.full(len(v), -1), np.zeros(len(other), dtype=np.int64)]
    axes = [np.array([[0.0, 40, 0], [10.0, 40, 0]])]
    arm = v[:, 0] >= 90.0  # turns about (90, 0, 0) while the rest stands
    T = 4
    frames = np.repeat(V[None], T, axis=0)
    for t in range(T):
        R = _rot([0, 0, 1], 0.6 * t)
        frames[t, :len(v)][arm] = (v[arm] - [90.0, 0, 0]) @ R.T + [90.0, 0, 0]
    out, ax = tl._unclaimed_limbs(frames, F, labels, axes, list(frames), reference=0)
    assert len(ax) == 2 and set(out[:len(v)][~arm]) == {-1} and np.array_equal(out[len(v):], labels[len(v):])
    new = out == 1
    assert new[:len(v)][v[:, 0] >= 110.0].all() and not new[:len(v)][v[:, 0] < 90.0].any()  # its far rings
    assert 90.0 <= ax[1][0, 0] <= 110.0 and ax[1][1, 0] == 120.0
    still, ax2 = tl._unclaimed_limbs(np.repeat(V[None], T, axis=0), F, labels, axes, [V] * T, reference=0)
    assert np.array_equal(still, labels) and len(ax2) == 1


def test_a_body_piece_is_not_fused_with_the_labelled_limb_it_moves_with():
    """``parts="limbs"``: a piece of the body that moves with the labelled limb beside it (a thigh's root the labels
    give the body, which a forearm touches) is not taken into the new limb that turns on its own beyond it; the new
    limb starts where the piece leaves that limb's motion (exact rigid motions, the surfaces the frames themselves)."""
    import pipeline.track_armature_labels as tl

    tube, _ = _tube(rings=25, length=240.0)
    v, f = tube.vertices, tube.faces
    side, _ = _tube(rings=3, length=20.0)
    other = side.vertices + [150.0, 20.0, 0]  # a labelled limb beside the tube's rings at x = 150, 160, 170
    V, F = np.vstack([v, other]), np.vstack([f, side.faces + len(v)])
    labels = np.r_[np.full(len(v), -1), np.zeros(len(other), dtype=np.int64)]
    axes = [np.array([[150.0, 20, 0], [170.0, 20, 0]])]
    touch = (v[:, 0] >= 150.0) & (v[:, 0] < 180.0)  # moves with the labelled limb
    arm = v[:, 0] >= 180.0  # and beyond it turns about (180, 0, 0) too; the rest stands
    frames = np.repeat(V[None], 4, axis=0)
    for t in range(4):
        shift = np.array([0.0, 0.0, 30.0 * t])
        frames[t, len(v):] = other + shift
        frames[t, :len(v)][touch] = v[touch] + shift
        frames[t, :len(v)][arm] = (v[arm] - [180.0, 0, 0]) @ _rot([0, 1, 0], 0.6 * t).T + [180.0, 0, 0] + shift
    out, ax = tl._unclaimed_limbs(frames, F, labels, axes, list(frames), reference=0)
    assert len(ax) == 2 and np.array_equal(out[len(v):], labels[len(v):])
    new = out[:len(v)] == 1
    assert not new[~arm].any() and new[v[:, 0] >= 200.0].all()  # the far rings, nothing of the piece beside the limb
    assert 180.0 <= ax[1][0, 0] <= 200.0 and ax[1][1, 0] == 240.0


def test_marks_turn_a_round_part_the_surface_cannot():
    """A tube's half turned about its own axis by one vertex spacing lies on the same surface (the
    residual is 0): the ICP alone keeps the turn; with marks (where the images say half of its
    vertices went) the half turns back to its place. Reference: the rest shape, exact."""
    from scipy.spatial.transform import Rotation

    from pipeline.armature_fit import _forward
    from pipeline.armature_track import mark_points, mark_residual

    model, part = _tube()
    X, N = model.vertices, vertex_normals(model.vertices, model.faces)
    turned = _forward(model, np.eye(3), np.zeros(3), np.stack([np.eye(3), Rotation.from_rotvec([np.pi / 4, 0, 0]).as_matrix()]))
    start_gap = np.linalg.norm(model.deform(turned) - X, axis=1)[part == 1].mean()
    assert surface_residual(model.deform(turned), X, gate=10.0) == pytest.approx(0.0, abs=1e-9) and start_gap > 4.0
    alone, _ = fit_pose_to_surface(model, turned, X, N, gate=10.0)
    assert np.linalg.norm(model.deform(alone) - X, axis=1)[part == 1].mean() > 0.9 * start_gap
    ids = np.flatnonzero(part == 1)[::2]  # half of the turned part's vertices followed
    marks = (ids, X[ids])
    assert mark_residual(model.deform(turned), marks, gate=100.0) == pytest.approx(start_gap)
    pose, _ = fit_pose_to_surface(model, turned, X, N, gate=10.0, marks=marks)
    # measured 0.017 of the turn left after the six rounds (0.15 with the targets moved halfway to the marks)
    assert np.linalg.norm(model.deform(pose) - X, axis=1)[part == 1].mean() < 0.05 * start_gap
    # tracks as the cameras give them: two rays through every followed vertex -> the same marks
    rays = np.tile([[0.0, 0.6, 0.8], [0.6, 0.8, 0.0]], (len(ids), 1))
    tr = (np.repeat(ids, 2), np.repeat(X[ids], 2, axis=0) + 30.0 * rays, rays)
    mv, mx = mark_points(tr, len(X))
    assert np.array_equal(mv, ids) and np.allclose(mx, X[ids]) and mark_points((ids[:0], X[:0], X[:0]), len(X)) is None


def test_ray_points_equal_a_per_vertex_reference():
    from pipeline.colour_tracks import ray_points

    rng = np.random.default_rng(5)
    n = 12
    truth = rng.normal(size=(n, 3)) * 50
    idx = np.r_[np.arange(n), np.arange(0, n, 2), np.arange(0, n, 3)]  # 1..3 rays a vertex
    rays = rng.normal(size=(len(idx), 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    targets = truth[idx] + rng.normal(size=(len(idx), 3)) + rays * rng.uniform(-40, 40, (len(idx), 1))
    ok, x = ray_points(idx, targets, rays, n)
    for v in range(n):
        t = np.flatnonzero(idx == v)
        assert ok[v] == (len(t) >= 2)
        if ok[v]:
            P = [np.eye(3) - np.outer(rays[j], rays[j]) for j in t]
            assert np.allclose(x[v], np.linalg.solve(sum(P), sum(p @ targets[j] for p, j in zip(P, t))))
