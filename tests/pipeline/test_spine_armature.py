"""The take's spine rig as the armature mode's first armature (pipeline.track_armature_models.spine_armature)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.armature_fit import Pose
from pipeline.armature_spine import armature_from_spine, reference_frame, rigged_model
from pipeline.track_armature_models import SPINE_BONES, spine_armature
from tests.pipeline.creature_truth import creature_take, surface, true_spine


@pytest.fixture(scope="module")
def quadruped():
    _, poses = creature_take("quadruped", 6)
    spine = true_spine("quadruped", poses)
    ref = reference_frame(spine)
    v, f = surface(poses[ref], step=12.0)
    return poses[ref], spine, rigged_model(spine, v, f, reference=ref, segments=SPINE_BONES)


def test_parts_are_the_spine_bones_hung_as_its_joint_tree(quadruped):
    _, spine, rigged = quadruped
    rig = rigged.rig
    model = spine_armature(rigged)
    sk = model.skeleton
    assert sk.n_parts == 1 + len(rig.bones)  # the root and one part per bone: 2 per limb and per junction axis
    assert len(rig.bones) == SPINE_BONES * len(spine.axes)
    bone_joints = set(rig.bones[:, 0].tolist())
    for p in range(1, sk.n_parts):
        j = sk.part_joint[p]
        assert j in bone_joints and sk.part[j] == p
        a = rig.parents[j]  # the nearest bone joint above (or the root) drives its parent part
        while a > 0 and a not in bone_joints:
            a = rig.parents[a]
        assert sk.part_parent[p] == sk.part[a] and sk.part_parent[p] < p
    np.testing.assert_array_equal(model.bone_part, np.arange(1, sk.n_parts))


def test_every_vertex_moves_with_the_nearest_bone_of_its_axis(quadruped):
    pose, spine, rigged = quadruped
    rig = rigged.rig
    model = spine_armature(rigged)
    assert model.influences.shape[1] == 1 and np.all(model.weights == 1.0)
    bones = rig.bones
    for v in range(0, len(rigged.vertices), 7):  # a slow reference, vertex by vertex
        share: dict = {}
        for j, w in zip(rigged.joints[v], rigged.weights[v]):
            share[rig.element[j]] = share.get(rig.element[j], 0.0) + w
        own = max(share, key=share.get)
        best, bone = np.inf, None
        for b, (j0, j1) in enumerate(bones):
            if rig.element[j0] != own:
                continue
            a, c = rig.rest[j0], rig.rest[j1]
            t = np.clip(np.dot(rigged.vertices[v] - a, c - a) / np.dot(c - a, c - a), 0.0, 1.0)
            d = np.linalg.norm(rigged.vertices[v] - (a + t * (c - a)))
            if d < best:
                best, bone = d, b
        assert model.influences[v, 0] == bone
    # a limb's vertices move with a bone of that limb (the true limb: the nearest capsule's)
    label = pose.label_at(rigged.vertices)
    truth = np.array([pose.names[k] if k >= 0 else "" for k in label])
    limb = np.array([rig.element[j] for j in bones[model.influences[:, 0], 0]])
    on = np.isin(truth, spine.limb_ids)
    assert np.mean(limb[on] == truth[on]) >= 0.95


def test_a_pose_moves_every_vertex_rigidly_with_its_part(quadruped):
    _, _, rigged = quadruped
    model = spine_armature(rigged)
    P = model.skeleton.n_parts
    rng = np.random.default_rng(1)
    pose = Pose(Rotation.from_rotvec(rng.normal(scale=0.4, size=(P, 3))).as_matrix(), rng.normal(scale=20.0, size=(P, 3)))
    part = model.bone_part[model.influences[:, 0]]
    expected = np.einsum("vij,vj->vi", pose.R[part], model.vertices) + pose.t[part]
    np.testing.assert_allclose(model.deform(pose), expected, atol=1e-9)


def test_invalid_input(quadruped):
    _, spine, rigged = quadruped
    with pytest.raises(ValueError, match="rigged"):
        spine_armature(armature_from_spine(spine))
