"""`stage bench armature`'s measure of what the motion segmentation sees where the body is rigid."""

import numpy as np
import pytest

from stage.benchmarks.armature import _parts, segmentation_noise
from tests.pipeline.shapes import two_bars


def test_segmentation_noise_is_zero_within_a_rigid_part_and_grows_with_noise():
    """The hinged bar moved exactly: the distances and normals of one bar's samples do not change (0 up to
    float32 rounding) while those across the hinge do; noise on the vertices shows within the parts."""
    V, F, right = two_bars(T=4)
    exact = segmentation_noise(V, F, right.astype(int), n_samples=120)
    assert exact["dv_within"] < 1e-3 and exact["dn_within"] < 0.1
    assert exact["dv_across"] > 10 and exact["dn_across"] > 1
    assert 2 <= exact["below_small_motion"] <= 65
    noisy = V + np.random.default_rng(0).normal(scale=1.0, size=V.shape)  # 1 mm on a 200 mm bar
    seen = segmentation_noise(noisy, F, right.astype(int), n_samples=120)
    assert seen["dv_within"] > 1 and seen["dn_within"] > exact["dn_within"] + 1


def test_true_parts_bend_when_any_joint_between_them_does():
    """A limb capsule no vertex lies nearest to (a neck hidden between body and head) leaves two joints between
    the body and the head: the head's part bends against the body when the hidden one's joint does. The
    slow reference: the joints between two parts listed by hand."""
    from types import SimpleNamespace

    creature = SimpleNamespace(limbs=[SimpleNamespace(name="head"), SimpleNamespace(name="leg")])
    names = ["head.0", "head.1", "leg.0", "leg.1", "leg.2"]
    raw = np.array([-1, -1, 1, 1, 16, 18, 18])  # no vertex on head.0 (the neck) nor on leg.1
    for bends in ([True, False, False, True, False], [False, False, True, False, False], [False] * 5):
        part, parent, bent = _parts(raw, creature, names, np.array(bends))
        assert part.tolist() == [0, 0, 1, 1, 2, 3, 3] and parent.tolist() == [-1, 0, 0, 2]
        by_hand = [False, bends[0] or bends[1], bends[2], bends[3] or bends[4]]
        assert bent.tolist() == by_hand


def test_invalid_input():
    V, F, right = two_bars(T=3)
    with pytest.raises(ValueError, match="parts"):
        segmentation_noise(V, F, right[:-1].astype(int))
    with pytest.raises(ValueError, match="one frame"):
        segmentation_noise(V[:1], F, right.astype(int))
