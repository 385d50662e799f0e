"""Armatures from motion (Tzionas & Gall 2016, section 4): real and simulated subjects, files, bad input.

Measured (this machine, see docs/armature-format.md for the figures): the pipe's articulation,
the simulated creatures' recall/precision and vertex errors, the horse's legs and playback.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pipeline.armature import (
    armature_counts,
    armature_dict,
    build_armature,
    bvh_text,
    counted,
)
from pipeline.armature_files import armature_summary, load_sequence, remove_armature, write_armature
from pipeline.armature_fit import fit_frame
from tests.conftest import SHARED_DATA
from tests.pipeline.bvh import parse_bvh

DATA = SHARED_DATA
PIPE = DATA / "tzionas_pipe" / "pipe.npz"
HORSE = DATA / "horse_gallop"


def _articulation_scores(rig, true_joints, articulates, size, tol=0.05):
    """Recall and precision of articulations within ``tol`` of size (median distance over frames)."""
    sk = rig.skeleton
    found = rig.fit.joints[:, sk.articulation]
    true = true_joints[:, articulates]
    if found.shape[1] == 0:
        return 0.0, 0.0, np.zeros((0, true.shape[1]))
    D = np.median(np.linalg.norm(found[:, :, None] - true[:, None, :], axis=3), axis=0) / size
    return float((D.min(0) < tol).mean()), float((D.min(1) < tol).mean()), D


# --------------------------------------------------------------------------- the pipe


@pytest.fixture(scope="module")
def pipe():
    if not PIPE.is_file():
        pytest.skip(f"real data not found: {PIPE} (../shared/data is absent)")
    d = np.load(PIPE)
    rig = build_armature(d["vertices"], d["faces"], units="mm", frame_indices=d["frame_index"])
    return d, rig


def test_pipe_has_one_articulation_at_the_hand_made_joint(pipe):
    d, rig = pipe
    sk = rig.skeleton
    assert int(sk.articulation.sum()) == 1
    size = float(np.linalg.norm(np.ptp(d["vertices"][0], axis=0)))
    found = rig.fit.joints[:, sk.articulation][:, 0]
    err = np.linalg.norm(found - d["joints"][:, 1], axis=1)  # joint 1: the hand-made articulation
    # the joint within 5 % of the bounding-box diagonal, the fit within 3 mm (the pipe's figures:
    # docs/armature-format.md)
    assert np.median(err) <= 0.05 * size
    assert rig.fit.errors.mean() <= 3.0


def test_pipe_fit_matches_the_slow_least_squares(pipe):
    """Gauss-Newton reaches the minimum a general optimiser finds (one frame)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from pipeline.armature_fit import Pose, _forward

    d, rig = pipe
    m = rig.model
    t = 45
    y = np.asarray(d["vertices"][t], dtype=np.float64)
    pose, err = fit_frame(m, y, rig.fit.poses[t - 1], iterations=30)
    P = m.skeleton.n_parts

    def resid(x):
        loc = Rotation.from_rotvec(x[6:].reshape(P - 1, 3)).as_matrix()
        local = np.concatenate([np.eye(3)[None], loc])
        pz = _forward(m, Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], local)
        return (m.deform(Pose(pz.R, pz.t)) - y).ravel()

    p0 = rig.fit.poses[t - 1]
    x0 = np.r_[Rotation.from_matrix(p0.R[0]).as_rotvec(), p0.t[0],
               np.concatenate([Rotation.from_matrix(p0.R[0].T @ p0.R[p]).as_rotvec() for p in range(1, P)])]
    ref = least_squares(resid, x0, method="lm", xtol=1e-10, ftol=1e-10)
    ref_sse = float((ref.fun**2).sum())
    sse = float(((m.deform(pose) - y) ** 2).sum())
    assert sse <= ref_sse * 1.01 + 1e-9


# --------------------------------------------------------------------------- simulated creatures


@pytest.fixture(scope="module", params=["starfish", "quadruped", "biped"])
def creature(request):
    from fake_cameras.mesh_motion import mesh_sequence

    # the template in the scanning pose (the biped's arms held away from its torso)
    ms = mesh_sequence(request.param, frames=40)
    # small motion of small parts: the paper's setting for it (section 5)
    rig = build_armature(ms.vertices, ms.faces, lambda_thr=0.98)
    return request.param, ms, rig


def test_simulated_creatures_articulations_and_error(creature):
    name, ms, rig = creature
    recall, precision, _ = _articulation_scores(rig, ms.joints, ms.articulates, ms.size)
    # recall and precision 0.7, the fit within 1 % of the size;
    # every creature's figures: docs/armature-format.md
    assert recall >= 0.7
    assert precision >= 0.7
    assert rig.fit.errors.mean() <= 0.01 * ms.size


# --------------------------------------------------------------------------- the horse and the files


@pytest.fixture(scope="module")
def horse(tmp_path_factory):
    if not HORSE.is_dir():
        pytest.skip(f"real data not found: {HORSE} (../shared/data is absent)")
    # the first 24 of the 48 frames: the take is one 24-frame gait cycle twice (frames k and k + 24
    # agree to 1e-4 of the mesh's units), so these are the whole motion at half the cost
    paths = sorted(HORSE.glob("0*.obj"))[:24]
    V, F, numbers = load_sequence(paths)
    rig = build_armature(V, F, units="m", fps=24.0, frame_indices=numbers)
    out = tmp_path_factory.mktemp("horse_rig")
    write_armature(rig, out)
    return V, F, rig, out


def test_horse_legs_have_two_segments(horse):
    from scipy.spatial import cKDTree

    from pipeline.frame_skeleton import frame_skeleton

    V, F, rig, _ = horse
    rest = V[rig.reference]
    m = frame_skeleton(rest, F).merged()
    axes = [a for a in m.tip_axes if a is not None]
    hooves = sorted(range(len(axes)), key=lambda i: axes[i][-1][1])[:4]  # y is up: the four lowest tips
    pts = np.vstack(axes)
    owner = np.concatenate([np.full(len(a), i) for i, a in enumerate(axes)])
    _, near = cKDTree(pts).query(rest)
    lab = rig.segmentation.labels
    for h in hooves:
        leg = owner[near] == h
        counts = np.bincount(lab[leg])
        assert (counts >= 0.05 * leg.sum()).sum() >= 2, f"leg {h}: segments {counts[counts > 0]}"


def test_horse_rig_plays_back(horse):
    import pygltflib
    import trimesh
    from scipy.spatial.transform import Rotation

    V, F, rig, out = horse
    doc = json.loads((out / "rig.json").read_text())
    assert doc["format"] == "capture-stage/rig@1" and doc["frame_count"] == len(V)
    g = pygltflib.GLTF2().load(str(out / "rig.glb"))
    assert len(g.skins) == 1 and len(g.skins[0].joints) == len(doc["joints"])
    assert len(g.animations) == 1
    scene = trimesh.load(str(out / "rig.glb"))
    assert len(scene.geometry) >= 1
    joints, rows = parse_bvh((out / "rig.bvh").read_text())
    assert len(joints) == len(doc["joints"])
    assert sorted(j["name"] for j in joints) == sorted(j["name"] for j in doc["joints"])
    # forward kinematics of the BVH reproduces rig.json's joint positions
    t = len(V) // 2
    pos, rot, col = {}, {}, 0
    for j in joints:
        vals = rows[t, col : col + len(j["channels"])]
        col += len(j["channels"])
        R = Rotation.from_euler("ZXY", vals[-3:], degrees=True).as_matrix()
        if j["parent"] is None:
            pos[j["name"]], rot[j["name"]] = vals[:3], R
        else:
            par = joints[j["parent"]]["name"]
            pos[j["name"]] = pos[par] + rot[par] @ np.asarray(j["offset"])
            rot[j["name"]] = rot[par] @ R
    ref = doc["frames"][t]["joints"]
    size = doc["size"]
    for name, p in pos.items():
        assert np.linalg.norm(p - np.asarray(ref[name])) < 1e-4 * size
    # posed frames in the template's vertex order
    assert len(list((out / "posed").glob("*.ply"))) == len(V)
    lab = np.load(out / "segments.npy")
    assert lab.shape == (V.shape[1],)
    # 5 % of the size: a deforming, not only articulated, body (its figures: docs/armature-format.md)
    assert np.mean(doc["fit"]["vertex_error_percent"]) < 5.0


# --------------------------------------------------------------------------- bad input


def test_rigid_sequence_gives_one_segment_and_a_message(caplog, tmp_path):
    from fake_cameras.mesh_motion import mesh_sequence

    ms = mesh_sequence("quadruped", frames=6, voxel=14.0)
    V = np.repeat(ms.vertices[:1], 6, axis=0) + np.linspace(0, 50, 6)[:, None, None]
    with caplog.at_level(logging.WARNING):
        rig = build_armature(V, ms.faces)
    assert rig.segmentation.n_segments == 1
    assert int(rig.skeleton.articulation.sum()) == 0
    assert "nothing bends" in caplog.text
    assert rig.fit.errors.max() < 1e-6 * ms.size
    write_armature(rig, tmp_path)
    assert len(parse_bvh(bvh_text(rig))[0]) == len(armature_dict(rig)["joints"])


def test_one_frame_sequence():
    from fake_cameras.mesh_motion import mesh_sequence

    ms = mesh_sequence("starfish", frames=1, voxel=14.0)
    with pytest.raises(ValueError, match="one frame: an armature is found from how the subject moves"):
        build_armature(ms.vertices, ms.faces)


def test_several_components_are_a_clear_error(pipe, caplog):
    """A second, separate part: an error naming the parts (an armature is found for one connected subject);
    a speck apart from the subject (surface debris, under 0.5 % of the vertices) follows its nearest bone."""
    import trimesh

    d, _ = pipe
    V = np.asarray(d["vertices"][:3], dtype=np.float64)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    bv = np.asarray(ball.vertices) + V[0].mean(0) + np.array([0.0, 0.0, 150.0])
    V2 = np.concatenate([V, np.repeat(bv[None], len(V), axis=0)], axis=1)
    F2 = np.concatenate([d["faces"], np.asarray(ball.faces) + V.shape[1]])
    with pytest.raises(ValueError, match=f"faces: the mesh has 2 connected parts \\({V.shape[1]}, {len(bv)} vertices\\)"):
        build_armature(V2, F2)
    # a speck (a tetrahedron) and a vertex in no face
    tet = trimesh.creation.icosphere(subdivisions=0, radius=2.0)
    sv = np.asarray(tet.vertices) + V[0].mean(0) + np.array([0.0, 0.0, 150.0])
    V3 = np.concatenate([V, np.repeat(sv[None], len(V), axis=0), V[:, :1] + 500.0], axis=1)
    F3 = np.concatenate([d["faces"], np.asarray(tet.faces) + V.shape[1]])
    with caplog.at_level(logging.WARNING):
        rig = build_armature(V3, F3, n_samples=200)
    assert "1 speck apart from the subject (12 vertices" in caplog.text
    assert rig.segmentation.labels.shape == (V3.shape[1],)
    assert np.isfinite(rig.posed(1)).all()


def test_invalid_input(tmp_path, monkeypatch):
    import pipeline.armature as armature
    from pipeline.results import ply_bytes

    V = np.random.default_rng(0).normal(size=(2, 10, 3))
    F = np.array([[0, 1, 2], [2, 3, 4]])
    with pytest.raises(ValueError, match="fps"):
        build_armature(V, F, fps=0)
    with monkeypatch.context() as m:  # the rest frame is checked before the segmentation's work
        m.setattr(armature, "motion_segmentation", lambda *a, **k: pytest.fail("segmented before checking reference"))
        for bad in (2, -1):
            with pytest.raises(ValueError, match=r"reference must be within 0\.\.1, got"):
                build_armature(V, F, reference=bad)
    with pytest.raises(ValueError, match="frame_indices"):
        build_armature(V, F, frame_indices=[1, 2, 3])
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match="whole_crossing_paths must be True or False"):
            build_armature(V, F, whole_crossing_paths=bad)
    with pytest.raises(ValueError, match="shape"):
        build_armature(V[0], F)
    # files whose vertex counts differ: not a sequence with shared connectivity
    (tmp_path / "000000.ply").write_bytes(ply_bytes(V[0], F))
    (tmp_path / "000001.ply").write_bytes(ply_bytes(V[1][:8], F[:1]))
    with pytest.raises(ValueError, match="track"):
        load_sequence(sorted(tmp_path.glob("*.ply")))
    # the counts of the rig's summaries
    for bad in (-1, 1.5, "2", True, None):
        with pytest.raises(ValueError, match="n must be a count"):
            counted(bad, "joint")
    for bad in ("", "  ", 3, None):
        with pytest.raises(ValueError, match="noun"):
            counted(1, bad)
    with pytest.raises(ValueError, match="segments"):
        armature_counts(-1, 0, 0)
    with pytest.raises(ValueError, match="articulations"):
        armature_counts(1, 0.5, 2)
    with pytest.raises(ValueError, match="joints"):
        armature_counts(1, 1, "2")
    assert armature_counts(np.int64(2), 1, 3) == "2 segments, 1 articulation, 3 joints"  # numpy integers count
    # armature_summary: a path; a file that is no rig.json gives None
    with pytest.raises(ValueError, match="path must be a path"):
        armature_summary(None)
    assert armature_summary(tmp_path / "absent.json") is None and armature_summary(tmp_path / "000000.ply") is None
    # remove_armature: a path to a directory, which need not exist
    with pytest.raises(ValueError, match="out_dir must be a path"):
        remove_armature(None)
    with pytest.raises(ValueError, match="out_dir must be a rig directory"):
        remove_armature(tmp_path / "000000.ply")
    assert (tmp_path / "000000.ply").is_file() and remove_armature(tmp_path / "absent") is False


def test_scan_opening_opens_only_limbs_that_touch_the_body():
    from fake_cameras.creatures import make_creature
    from fake_cameras.mesh_motion import scan_opening

    def angles(name):
        return {k: np.degrees(np.arccos(np.clip((np.trace(A) - 1) / 2, -1, 1))) for k, A in scan_opening(make_creature(name)).items()}

    assert max(angles("starfish").values()) == 0.0  # arms already clear
    b = angles("biped")
    assert 20.0 <= b["arm_l"] <= 90.0 and 20.0 <= b["arm_r"] <= 90.0  # arms hang against the torso
    assert b["head"] == 0.0  # attached end-on: no angle clears it
    with pytest.raises(ValueError, match="step"):
        scan_opening(make_creature("biped"), step=0.0)


def test_deform_matches_the_per_influence_blend(creature):
    """The blended affine maps give the textbook LBS sum over influences."""
    _, ms, rig = creature
    m = rig.model
    pose = rig.fit.poses[len(rig.fit.poses) // 2]
    vp = m.vertex_parts
    ref = np.zeros_like(m.vertices)
    for k in range(vp.shape[1]):
        ref += m.weights[:, k, None] * (np.einsum("vij,vj->vi", pose.R[vp[:, k]], m.vertices) + pose.t[vp[:, k]])
    np.testing.assert_allclose(m.deform(pose), ref, rtol=0, atol=1e-9 * ms.size)
    rows = np.arange(0, len(ref), 7)
    np.testing.assert_allclose(m.deform(pose, rows), ref[rows], rtol=0, atol=1e-9 * ms.size)


def test_constant_velocity_prediction_is_exact_on_constant_velocity_motion(creature):
    from scipy.spatial.transform import Rotation

    from pipeline.armature_fit import _forward, predict_pose

    _, _, rig = creature
    m = rig.model
    P = m.skeleton.n_parts
    om = np.random.default_rng(1).normal(scale=0.1, size=(P, 3))
    v = np.array([3.0, -2.0, 1.0])
    c = m.pivots[0]

    def pose_at(s):
        R = Rotation.from_rotvec(s * om).as_matrix()
        return _forward(m, R[0], c + s * v - R[0] @ c, R)

    pred = predict_pose(m, pose_at(1.0), pose_at(0.0))
    truth = pose_at(2.0)
    np.testing.assert_allclose(pred.R, truth.R, atol=1e-9)
    np.testing.assert_allclose(pred.t, truth.t, atol=1e-6)


# --------------------------------------------------------------------------- the same creature, varied motion

_VARIED = [
    # (creature, frames, periods of the slowest limb): coarse, twice as fast a frame, and dense (the
    # segmentation's frame-rate invariance: test_motion_segmentation's five times the frame rate)
    ("biped", 16, 1.0),
    ("biped", 32, 2.0),
    ("quadruped", 100, 1.0),
]


@pytest.mark.parametrize("name, frames, periods", _VARIED)
def test_varied_frame_rate_and_speed_give_a_stable_rig(name, frames, periods):
    """Frame counts, frame rates and speeds of one simulated motion: the articulations found stay put."""
    from fake_cameras.creatures import make_creature
    from fake_cameras.mesh_motion import mesh_sequence

    period = 1.0 / min(lb.freq for lb in make_creature(name).limbs)
    ms = mesh_sequence(name, frames=frames, duration=periods * period, voxel=10.0, dtype=np.float32)
    rig = build_armature(ms.vertices, ms.faces, lambda_thr=0.98)
    recall, precision, _ = _articulation_scores(rig, ms.joints, ms.articulates, ms.size)
    # the bounds of test_simulated_creatures_articulations_and_error (figures: docs/armature-format.md)
    assert recall >= 0.7
    assert precision >= 0.7
    assert rig.fit.errors.mean() <= 0.01 * ms.size


# --------------------------------------------------------------------------- joints from the segments' motion


def _rigid_about(pivot, axis, angles):
    """(R (T, 3, 3), t (T, 3)) of rotations by ``angles`` about ``axis`` through ``pivot``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.outer(angles, axis)).as_matrix()
    return R, pivot - np.einsum("tij,j->ti", R, pivot)


def test_joint_residual_recovers_a_shared_pivot():
    from scipy.spatial.transform import Rotation

    from pipeline.armature_skeleton import joint_residual

    T = 30
    body = (np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3)))
    pivot = np.array([10.0, -5.0, 3.0])
    # a ball joint: rotations about changing axes through the pivot
    rv = np.c_[np.linspace(0.0, 0.5, T), np.linspace(0.0, 0.7, T), 0.2 * np.sin(np.linspace(0.0, 3.0, T))]
    R = Rotation.from_rotvec(rv).as_matrix()
    ball = (R, pivot - np.einsum("tij,j->ti", R, pivot))
    res, c = joint_residual(body, ball, pivot + np.array([4.0, 0.0, 0.0]), ridge=1e-9)
    assert res < 1e-6 and np.linalg.norm(c - pivot) < 1e-4
    # a hinge: the pivot is free along the axis and stays at the centroid's foot on it
    hinge = _rigid_about(pivot, np.array([0.0, 0.0, 1.0]), np.linspace(0.0, 0.6, T))
    centroid = pivot + np.array([1.0, 0.0, 7.0])
    res, c = joint_residual(body, hinge, centroid)
    assert res < 1e-2
    np.testing.assert_allclose(c, pivot + np.array([0.0, 0.0, 7.0]), atol=0.1)
    # two limbs turning about points 30 apart (siblings in contact): no shared pivot
    other = _rigid_about(pivot + np.array([30.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.linspace(0.0, 0.6, T))
    res, _ = joint_residual(hinge, other, pivot)
    assert res > 3.0


def test_touching_segments_are_not_jointed():
    """Three segments adjacent in a cycle: the pair whose motion shares no pivot is a contact."""
    from pipeline.armature_skeleton import _kinematic_tree

    cand = [((0, 1), None, 1.0), ((0, 2), None, 1.0), ((1, 2), None, 1.0)]
    kept = _kinematic_tree(cand, {(0, 1): 0.1, (0, 2): 0.2, (1, 2): 9.0})
    assert sorted(c[0] for c in kept) == [(0, 1), (0, 2)]
    assert len(_kinematic_tree(cand[:1], {(0, 1): 0.0})) == 1


def test_an_undefined_joint_in_a_frame_still_gives_valid_files(pipe, tmp_path, caplog):
    """A frame whose pose is unusable (a zero rotation, unknown joint positions): null in rig.json, the
    previous frame's motion in the BVH and the GLB."""
    import pygltflib

    from pipeline.armature_fit import FitResult, Pose

    _, rig = pipe
    poses = list(rig.fit.poses[:6])
    joints = rig.fit.joints[:6].copy()
    bad = poses[3]
    R = bad.R.copy()
    R[-1] = 0.0  # the last part's rotation is undefined
    poses[3] = Pose(R, bad.t.copy())
    joints[4, -1] = np.nan  # a joint position unknown in another frame
    from dataclasses import replace

    broken = replace(rig, fit=FitResult(poses, rig.fit.errors[:6].copy(), joints), frame_indices=rig.frame_indices[:6])
    with caplog.at_level(logging.WARNING):
        text = bvh_text(broken)
    assert "undefined" in caplog.text
    parsed, rows = parse_bvh(text)
    assert len(parsed) == broken.skeleton.n_joints and rows.shape[0] == 6 and np.all(np.isfinite(rows))
    doc = armature_dict(broken)
    assert doc["frames"][4]["joints"][broken.skeleton.names[-1]] is None
    write_armature(broken, tmp_path)
    g = pygltflib.GLTF2().load(str(tmp_path / "rig.glb"))
    assert len(g.animations) == 1


def test_tracked_meshes_are_the_six_digit_frames_only(tmp_path):
    """``tracked/NNNNNN.ply`` in frame order; a user's file beside them is not read as a frame."""
    from pipeline.armature_files import NoTrackingError, tracked_meshes

    (tmp_path / "tracked").mkdir()
    (tmp_path / "tracked" / "1_fixed.ply").write_text("the user's")
    with pytest.raises(NoTrackingError, match="no tracked/NNNNNN.ply"):
        tracked_meshes(tmp_path)
    for k in (2, 0, 1):
        (tmp_path / "tracked" / f"{k:06d}.ply").write_text("")
    assert [p.name for p in tracked_meshes(tmp_path)] == ["000000.ply", "000001.ply", "000002.ply"]


# --------------------------------------------------------------------------- the cow: motion it was not developed on

COW = DATA / "cow_poses"


def test_cow_articulations_against_its_rigging_skeleton():
    """The cow's 7 poses against its hand-made rigging skeleton (scored as docs/armature-format.md says: within
    5 % of size, median over the poses; recall over the articulations that bend >= 10 degrees)."""
    if not COW.is_dir():
        pytest.skip(f"real data not found: {COW} (../shared/data is absent)")
    from pipeline.armature_score import articulation_bends, articulation_scores

    V, F, _ = load_sequence(sorted(COW.glob("cow-*.obj")))
    sk = np.load(COW / "skeleton.npz")
    J, par = sk["joints"], sk["parents"]
    art = np.array([par[j] >= 0 and (par == j).any() for j in range(len(par))])
    bending = art & (articulation_bends(J, par) >= 10.0)
    hub = art | (np.bincount(par[par >= 0], minlength=len(par)) >= 2)  # the root joins four bones
    rig = build_armature(V, F)
    s = articulation_scores(rig.fit.joints[:, rig.skeleton.articulation], J, size=rig.size, articulates=hub,
                            bending=bending)
    # recall and precision 0.7, the fit within 1.5 % of the size (figures: docs/armature-format.md)
    assert s["recall"] >= 0.7
    assert s["precision"] >= 0.7
    assert rig.fit.errors.mean() <= 0.015 * rig.size


def test_a_joint_that_barely_bends_keeps_the_boundary_placement_and_says_so():
    """The hinged bar: bent by 60 degrees the joint moves to the centre of rotation (the hinge at the
    origin); bent by a fifth of a degree, with 0.5 mm of tracking noise, the centre is ill-determined and the
    joint stays at the boundary's centroid on the curve skeleton, which rig.json says."""
    from pipeline.armature_skeleton import articulated_skeleton
    from tests.pipeline.shapes import two_bars

    V, F, right = two_bars(12)
    lab = right.astype(np.int64)
    sk = articulated_skeleton(V[0], F, lab, motion=V, reference=0)
    j = int(np.flatnonzero(sk.articulation)[0])
    assert sk.placement[j]["method"] == "centre of rotation" and sk.placement[j]["bend_degrees"] == pytest.approx(60, abs=0.5)
    assert np.linalg.norm(sk.rest[j][:2]) < 1.0  # the hinge axis is z through the origin
    ang = np.radians(np.linspace(0, 0.2, 12))
    W = np.repeat(V[:1], 12, axis=0)
    for t, a in enumerate(ang):
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        W[t, right] = V[0, right] @ R.T
    W = W + np.random.default_rng(0).normal(scale=0.5, size=W.shape)
    sk = articulated_skeleton(V[0], F, lab, motion=W, reference=0)
    j = int(np.flatnonzero(sk.articulation)[0])
    pl = sk.placement[j]
    assert pl["method"] == "boundary" and "ill-determined" in pl["reason"] and pl["uncertainty"] > 1.0
    rig = build_armature(W, F, n_samples=300)
    doc = armature_dict(rig)
    for jd in doc["joints"]:
        assert ("placement" in jd) == (jd["kind"] == "joint")


def _far_hinge(degrees: float):
    """Two bars (12 frames) whose right half (x > 0) turns by ``degrees`` about a z axis through (-30, 0, 0),
    inside the left half, 30 mm from where they meet: -> V, F, right, the motion W (12, n, 3), the pivot."""
    from tests.pipeline.shapes import two_bars

    V, F, right = two_bars(12)
    W = np.repeat(V[:1], 12, axis=0)
    pivot = np.array([-30.0, 0.0, 0.0])
    for t, a in enumerate(np.radians(np.linspace(0, degrees, 12))):
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        W[t, right] = (V[0, right] - pivot) @ R.T + pivot
    return V, F, right, W, pivot


def test_a_determined_centre_of_rotation_away_from_the_boundary_is_the_joint():
    """The bar's right half (x > 0) turns by 60 degrees about a z axis through (-30, 0, 0), inside the left
    half, 30 mm from where the two segments meet (the boundary's radius is about 12 mm), as a limb whose
    template touches the body along its length turns about a shoulder away from that boundary: the joint is
    the centre of rotation, not the boundary's centroid."""
    from pipeline.armature_skeleton import articulated_skeleton

    V, F, right, W, pivot = _far_hinge(60)
    sk = articulated_skeleton(V[0], F, right.astype(np.int64), motion=W, reference=0)
    j = int(np.flatnonzero(sk.articulation)[0])
    assert sk.placement[j]["method"] == "centre of rotation", sk.placement[j]
    assert np.linalg.norm(sk.rest[j][:2] - pivot[:2]) < 1.0  # measured: on the axis


def test_a_centre_beside_a_sheet_pushed_into_the_body_is_the_joint():
    """The far hinge (the bar's right half turns by 60 degrees about a z axis through (-30, 0, 0), 30 mm inside the
    left half from where the labels start the right one), with a small closed box pushed into the left half 3 mm
    beside the hinge, as a tracked limb pressed into the body: the hinge's eight nearest vertices lie on that box and
    their outward normals all face it, yet it lies inside the surface (winding number 1). The joint is the centre of
    rotation, at the hinge to within 1 mm (measured 0.1 mm; the boundary is 37 mm from it)."""
    import trimesh
    from scipy.spatial import cKDTree

    from pipeline.armature_skeleton import CurveSkeleton, articulated_skeleton
    from pipeline.mesh_primitives import outward_normals

    V, F, right, W, pivot = _far_hinge(60)
    box = trimesh.creation.box(extents=(8.0, 8.0, 6.0))
    for _ in range(3):
        box = box.subdivide()
    bv = np.asarray(box.vertices) + pivot + np.array([0.0, 0.0, 6.0])  # z from 3 to 9, inside the bar (|z| < 10)
    n = V.shape[1]
    rest = np.concatenate([V[0], bv])
    faces = np.concatenate([F, np.asarray(box.faces) + n])
    motion = np.concatenate([W, np.repeat(bv[None], len(W), axis=0)], axis=1)  # it moves with the left half
    labels = np.concatenate([right, np.zeros(len(bv), bool)]).astype(np.int64)
    _, nn = cKDTree(rest).query(pivot, k=8)
    assert (nn >= n).all()
    normals = outward_normals(rest, faces)
    assert ((((pivot - rest[nn]) * normals[nn]).sum(1) > 0)).all()  # every nearest normal faces the hinge
    line = np.c_[np.linspace(-100.0, 100.0, 41), np.zeros(41), np.zeros(41)]
    curve = CurveSkeleton(line, np.c_[np.arange(40), np.arange(1, 41)])
    sk = articulated_skeleton(rest, faces, labels, curve, motion=motion, reference=0)
    j = int(np.flatnonzero(sk.articulation)[0])
    assert int(sk.articulation.sum()) == 1
    assert sk.placement[j]["method"] == "centre of rotation", sk.placement[j]
    assert np.linalg.norm(sk.rest[j] - pivot) < 1.0


def test_an_uncertain_centre_beyond_the_boundary_is_drawn_towards_it():
    """The same far hinge turned by 20 degrees with 2 mm of noise on every vertex: the centre is uncertain by a
    quarter of the boundary's radius (more than PIVOT_FAR_UNCERTAINTY), so the joint is the centre drawn towards the
    boundary's point, nearer the hinge than the boundary (measured 3.2 mm from it, 30 mm before); the drawn centre
    equals the stacked least-squares problem solved by lstsq (slow reference) and the pivot without
    noise (up to a ridge of 1e-6 mm)."""
    from pipeline.armature_skeleton import _drawn_centre, articulated_skeleton
    from pipeline.rigid_parts import rigid_motions

    V, F, right, W, pivot = _far_hinge(20)
    X = W + np.random.default_rng(0).normal(scale=2.0, size=W.shape)
    sk = articulated_skeleton(V[0], F, right.astype(np.int64), motion=X, reference=0)
    j = int(np.flatnonzero(sk.articulation)[0])
    assert sk.placement[j]["method"] == "centre of rotation, drawn to the boundary", sk.placement[j]
    assert np.linalg.norm(sk.rest[j][:2] - pivot[:2]) < 6.0
    (Ra, ta), (Rb, tb) = rigid_motions(X[:, ~right]), rigid_motions(X[:, right])
    point = np.array([0.0, 1.0, 2.0])
    got = _drawn_centre((Ra, ta), (Rb, tb), point, residual=3.0, radius=12.0)
    w = np.sqrt(len(Ra)) * 3.0 / 12.0
    A = np.concatenate([*(Ra - Rb), w * np.eye(3)])
    rhs = np.concatenate([*(tb - ta), w * point])
    np.testing.assert_allclose(got, np.linalg.lstsq(A, rhs, rcond=None)[0], atol=1e-9)
    (Ra, ta), (Rb, tb) = rigid_motions(W[:, ~right]), rigid_motions(W[:, right])
    exact = _drawn_centre((Ra, ta), (Rb, tb), point, residual=1e-6, radius=12.0)
    np.testing.assert_allclose(exact[:2], pivot[:2], atol=1e-6)


def _l_bar():
    """A watertight L-shaped bar 2 x 2 thick: along x from -1 to 11 (y within -1..1), then along y up to 11 (x within
    9..11); z within -1..1."""
    L = np.array([(-1, -1), (11, -1), (11, 11), (9, 11), (9, 1), (-1, 1)], float)
    v = np.vstack([np.c_[L, np.full(6, -1.0)], np.c_[L, np.full(6, 1.0)]])
    cap = [(4, 5, 0), (4, 0, 1), (4, 1, 2), (4, 2, 3)]
    f = [*cap, *((a + 6, c + 6, b + 6) for a, b, c in cap)]
    for i in range(6):
        j = (i + 1) % 6
        f += [(i, j, j + 6), (i, j + 6, i + 6)]
    return v, np.array(f)


def test_a_bone_whose_curve_path_leaves_the_mesh_is_not_split_with_whole_crossing_paths():
    """The L bar's axis as its curve skeleton, one segment: one bone from end to end, whose chord cuts the corner out
    of the bar. Its curve inside the bar: split where the chord leaves (more than the two ends), with or without
    ``whole_crossing_paths``. The curve's corner pushed out below the bar (as a ragged surface's curve skeleton
    leaves it): every split bone still leaves the mesh and is split again (today's rule, the tracking's rounds);
    with ``whole_crossing_paths`` the bone stays whole (root and one end), no split can bring it inside."""
    from pipeline.armature_skeleton import CurveSkeleton, articulated_skeleton, segment_hits_mesh

    v, f = _l_bar()
    labels = np.zeros(len(v), dtype=np.int64)
    edges = np.array([(0, 1), (1, 2), (2, 3), (3, 4)])
    inside = np.array([(0, 0, 0), (5, 0, 0), (10, 0, 0), (10, 5, 0), (10, 10, 0)], float)
    outside = inside.copy()
    outside[2] = (10, -3, 0)
    assert segment_hits_mesh(inside[0], inside[4], v, f)
    assert not any(segment_hits_mesh(inside[j], inside[j + 1], v, f) for j in range(4))
    assert segment_hits_mesh(outside[1], outside[2], v, f)

    def joints(points, whole):
        sk = articulated_skeleton(v, f, labels, CurveSkeleton(points, edges), refine_joints=False,
                                  whole_crossing_paths=whole)
        assert not sk.articulation.any()
        return sk.n_joints, sk.rest

    (n_in, rest_in), (n_in_whole, rest_in_whole) = joints(inside, False), joints(inside, True)
    assert n_in == n_in_whole > 2
    np.testing.assert_array_equal(rest_in, rest_in_whole)
    assert joints(outside, False)[0] > 2
    n_out, rest_out = joints(outside, True)
    assert n_out == 2
    np.testing.assert_allclose(sorted(map(tuple, rest_out)), [(0, 0, 0), (10, 10, 0)], atol=1e-9)


def test_the_armature_step_leaves_crossing_bones_whole_and_the_tracking_rounds_do_not(tmp_path, monkeypatch):
    """``whole_crossing_paths``: on in the armature step (``armature_results``), off in the tracking's armature
    rounds (``_rig_of``, the tracking's prior), and ``build_armature`` passes it on to the skeleton (default off)."""
    import pipeline.armature as armature
    import pipeline.armature_files as armature_files
    from pipeline.results import ply_bytes
    from pipeline.track_armature_models import _rig_of

    seen = []

    def stop(*a, **k):
        seen.append(k.get("whole_crossing_paths", False))
        raise RuntimeError("stop")

    V = np.random.default_rng(0).normal(size=(2, 10, 3))
    F = np.array([[0, 1, 2], [2, 3, 4]])
    with monkeypatch.context() as m:
        m.setattr(armature, "articulated_skeleton", stop)
        for kw in ({}, {"whole_crossing_paths": True}):
            with pytest.raises(RuntimeError, match="stop"):
                build_armature(V, F, reference=0, parts=np.zeros(10, dtype=np.int64), **kw)
    assert seen == [False, True]
    seen.clear()
    (tmp_path / "tracked").mkdir()
    for i in range(2):
        (tmp_path / "tracked" / f"{i:06d}.ply").write_bytes(ply_bytes(V[i], F))
    monkeypatch.setattr(armature_files, "build_armature", stop)
    monkeypatch.setattr(armature, "build_armature", stop)
    for call in (lambda: armature_files.armature_results(tmp_path, limbs=None), lambda: _rig_of(V, F, [0, 1], 0, 0.7)):
        with pytest.raises(RuntimeError, match="stop"):
            call()
    assert seen == [True, False]
