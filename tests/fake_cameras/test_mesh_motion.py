"""The simulated creatures' joints over time (fake_cameras.mesh_motion.true_joints)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fake_cameras.creatures import make_creature
from fake_cameras.mesh_motion import mesh_sequence, true_joints


def test_true_joints_are_the_posed_sequences_joints():
    """At a posed sequence's times: its joint names, positions and articulating joints, exactly; a joint
    articulates when its parts turn against each other by more than ``min_bend``."""
    ms = mesh_sequence("starfish", frames=4, voxel=14.0)
    names, J, art = true_joints(make_creature("starfish"), ms.times)
    assert names == ms.joint_names and J.shape == ms.joints.shape
    np.testing.assert_allclose(J, ms.joints, atol=1e-9)
    assert np.array_equal(art, ms.articulates)
    assert not true_joints(make_creature("starfish"), ms.times[:1])[2].any()  # one instant: nothing turns
    assert true_joints(make_creature("starfish"), ms.times, min_bend=0.0)[2].all()
    assert not true_joints(make_creature("starfish"), ms.times, min_bend=math.pi)[2].any()


def test_invalid_input():
    cr = make_creature("starfish")
    with pytest.raises(ValueError, match="times"):
        true_joints(cr, [])
    with pytest.raises(ValueError, match="times"):
        true_joints(cr, [0.0, float("nan")])
    with pytest.raises(ValueError, match="min_bend"):
        true_joints(cr, [0.0, 0.1], min_bend=-1.0)
