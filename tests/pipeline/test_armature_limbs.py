"""The take's spine limbs as structure for an armature built from motion (pipeline.armature_limbs)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh


def _thighs(T: int = 12):
    """A plate (mm): the body (x < 0) and two limbs (x > 0, y > 0 and y < 0) that touch along y = 0. Both limbs
    swing about the one z axis through the origin, by different angles (thighs on the hip axis); the body
    shakes by 1 mm. -> vertices (T, V, 3), faces, segment labels (body 0, limbs 1 and 2)."""
    m = trimesh.creation.box(extents=(200, 200, 20))
    for _ in range(3):
        m = m.subdivide()
    v0 = np.asarray(m.vertices)
    lab = np.where(v0[:, 0] < 0, 0, np.where(v0[:, 1] > 0, 1, 2)).astype(np.int64)
    out = []
    for t in range(T):
        v = v0.copy()
        for s, a in ((1, 0.5 * t / T), (2, -0.3 * t / T)):
            c, n = np.cos(a), np.sin(a)
            v[lab == s] = v0[lab == s] @ np.array([[c, -n, 0], [n, c, 0], [0, 0, 1]]).T
        v[lab == 0] += np.array([np.sin(1.7 * t), np.cos(2.3 * t), 0.0])
        out.append(v)
    return np.asarray(out), np.asarray(m.faces), lab


def test_a_limb_is_not_hung_from_another_limb_it_touches():
    """The two limbs hinge on one axis, so their pair is the most joint-like (residual 0 against the body's
    1 mm): the kinematic tree alone hangs one limb from the other. With the spine's limbs both hang from
    the body and the limbs' pair is a contact."""
    from pipeline.armature_skeleton import _articulation_pairs

    V, F, lab = _thighs()
    plain, _, left = _articulation_pairs(V[0], F, lab, 3, V, 0)
    assert (1, 2) in [p for p, _, _ in plain] and left == []
    limbs = np.array([-1, 0, 1])[lab]  # body, limb0, limb1
    kept, _, left = _articulation_pairs(V[0], F, lab, 3, V, 0, limbs)
    assert sorted(p for p, _, _ in kept) == [(0, 1), (0, 2)]
    assert left == [(1, 2)]


def test_segment_limbs_is_the_majority_vote():
    from pipeline.armature_limbs import BODY, limb_pairs, segment_limbs

    lab = np.array([0, 0, 0, 1, 1, 2, 2, 2])
    limb = np.array([BODY, BODY, 0, 0, 0, 1, 1, BODY])
    sl = segment_limbs(lab, limb)
    np.testing.assert_array_equal(sl, [BODY, 0, 1])
    slow = [max(sorted(set(limb[lab == s])), key=lambda x: (limb[lab == s] == x).sum()) for s in range(3)]
    np.testing.assert_array_equal(sl, slow)
    assert limb_pairs([(0, 1), (0, 2), (1, 2)], sl) == {(1, 2)}


def test_vertex_limbs_takes_the_heaviest_bones_axis():
    """Two junctions (j0, j1) joined by the body's axis, a two-bone limb below each: a vertex lies on the
    limb of its heaviest bone, on the body when that bone is the body's or a limb's first (at a junction)."""
    from pipeline.armature_limbs import BODY, vertex_limbs
    from pipeline.armature_spine import RiggedModel, SpineArmature

    names = ("j0", "limb0.0", "limb0.1", "limb0.tip", "j1.0", "j1", "limb1.0", "limb1.1", "limb1.tip")
    element = ("j0", "limb0", "limb0", "limb0", "j1", "j1", "limb1", "limb1", "limb1")
    J = len(names)
    rig = SpineArmature(names=names, parents=np.array([-1, 0, 1, 2, 0, 4, 5, 6, 7]), element=element,
                        rest=np.zeros((J, 3)), bones=np.array([[1, 2], [2, 3], [4, 5], [6, 7], [7, 8]]),
                        rotations=np.zeros((1, J, 4)), translations=np.zeros((1, J, 3)), times=np.zeros(1),
                        frame_indices=np.zeros(1, dtype=np.int64), reference=0)
    joints = np.array([[2, 1], [4, 2], [7, 6], [1, 2], [6, 7]])  # heaviest first
    model = RiggedModel(np.zeros((5, 3)), np.array([[0, 1, 2]]), joints, np.full((5, 2), 0.5), rig)
    got = vertex_limbs(model)
    assert got.names == ("limb0", "limb1")
    np.testing.assert_array_equal(got.limb, [0, BODY, 1, BODY, BODY])


def test_invalid_input():
    from pipeline.armature_limbs import segment_limbs, vertex_limbs
    from pipeline.armature_skeleton import articulated_skeleton

    with pytest.raises(ValueError, match="RiggedModel"):
        vertex_limbs(object())
    with pytest.raises(ValueError, match="one entry per vertex"):
        segment_limbs([0, 1], [0])
    with pytest.raises(ValueError, match="BODY"):
        segment_limbs([0, 1], [0, -2])
    V, F, lab = _thighs(3)
    with pytest.raises(ValueError, match="limbs"):
        articulated_skeleton(V[0], F, lab, motion=V, limbs=np.zeros(3, dtype=np.int64))
    from pipeline.armature import build_armature

    with pytest.raises(ValueError, match="VertexLimbs"):
        build_armature(V, F, limbs=lab - 1)


def test_spine_limbs_without_a_usable_spine_is_none(tmp_path, caplog):
    """No spine.json: None (a mesh sequence); a damaged one: None and a warning saying the armature is built
    without the spine's limbs."""
    import logging

    from pipeline.armature_files import spine_limbs

    V, F, _ = _thighs(2)
    assert spine_limbs(tmp_path, V, F, np.arange(2)) is None
    (tmp_path / "spine.json").write_text("{not json")
    with caplog.at_level(logging.WARNING):
        assert spine_limbs(tmp_path, V, F, np.arange(2)) is None
    assert "without the spine's limbs" in caplog.text
