"""Spines through the whole pipeline on the simulated rig.

Simulated takes (8 cameras, 640x480, 30 frames = one gait cycle at 30 fps) of the starfish
and the quadruped are keyed, carved, meshed, skeletonized and corresponded by
:func:`pipeline.process.process_take`, and the resulting ``spine.json`` is scored against
the simulator's ground truth with :func:`fake_cameras.evaluate.evaluate_spine`.

Size = diagonal of the bounding box of the true limb axes and tips over the take.
Stated tolerances: K = the true limb count; every limb's tip within 3 % of
the size of its true tip in >= 95 % of frames; identities consistent in 100 % of
frames; mean distance between spine limb axes and true limb axes <= 2 % of the size,
measured on the limbs, i.e. outside the creature's body (the spine's junctions lie
inside the body by construction, Brostow et al. 2004 §4.3, while the true axes start
at the limbs' attachments: see the docstring of ``fake_cameras.evaluate``).

The takes and their results are built once per test process (:mod:`tests.pipeline.spine_takes`).
"""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.creatures import Pose
from fake_cameras.evaluate import evaluate_spine, limb_axis_distance, resample_polyline
from tests.pipeline.spine_takes import GROUP, N_FRAMES, run

TRUE_LIMBS = {"starfish": 5, "quadruped": 6}

pytestmark = pytest.mark.xdist_group(GROUP)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["starfish", "quadruped"])
def test_whole_pipeline_spine_accuracy(name, tmp_path_factory):
    r = run(name, tmp_path_factory)
    sim, spine, acc = r["sim"], r["spine"], r["acc"]
    assert r["res"].frames == N_FRAMES and r["res"].empty_frames == []
    assert spine["frame_count"] == N_FRAMES == len(spine["frames"])
    # K equals the true limb count
    assert acc["K"] == acc["true_limbs"] == len(sim.limb_names) == TRUE_LIMBS[name]
    # each tip within 3 % of size of its true tip in >= 95 % of frames (per limb; unseen counts as a miss)
    names = list(sim.limb_names)
    true_tips = sim.tip_array()
    for limb, true_limb in acc["match"].items():
        S = np.array([fr["tips"][limb] if fr["tips"][limb] is not None else [np.nan] * 3 for fr in spine["frames"]], float)
        err = np.linalg.norm(S - true_tips[:, names.index(true_limb)], axis=1) / acc["size"]
        assert np.mean(np.nan_to_num(err, nan=np.inf) <= 0.03) >= 0.95, (limb, true_limb, err)
    assert acc["tip_within_tol"] >= 0.95
    # identities consistent in 100 % of frames, and every true limb has its own spine limb
    assert acc["identity_consistent"] == 1.0
    assert sorted(acc["match"].values()) == sorted(names)
    # mean distance from spine limb axes to true limb axes (outside the body) <= 2 % of size;
    # measured 0.3 % (starfish) and 0.6 % (quadruped); whole axes incl. the body: 1.9 % / 3.8 %
    assert acc["limb_axis_skipped"] == 0
    assert acc["limb_axis_error_mean"] <= 0.02, acc["limb_axis_error_mean"]


def _stick_pose() -> Pose:
    """A body sphere (radius 50 at the origin) with one straight limb along +x to x = 200."""
    return Pose(
        p0=np.array([[0.0, 0, 0], [30.0, 0, 0]]),
        p1=np.array([[0.0, 0, 0], [190.0, 0, 0]]),
        r0=np.array([50.0, 12.0]),
        r1=np.array([50.0, 10.0]),
        limb=np.array([-1, 0]),
        names=("limb",),
    )


def test_limb_axis_distance_ignores_the_body_and_sees_offsets():
    pose = _stick_pose()
    true_axis = np.array([[30.0, 0, 0], [200.0, 0, 0]])
    # a spine limb from a junction at the body centre: the stretch inside the body is ignored
    from_centre = np.array([[0.0, 0, 0], [100.0, 0, 0], [200.0, 0, 0]])
    assert limb_axis_distance(from_centre, true_axis, pose, step=1.0) == pytest.approx(0.0, abs=1e-9)
    # the same limb displaced by 7 mm outside the body: 7 mm both ways
    shifted = from_centre + [0.0, 7.0, 0.0]
    assert limb_axis_distance(shifted, true_axis, pose, step=1.0) == pytest.approx(7.0, abs=0.05)
    # a limb that stops halfway is penalised by the true limb's uncovered half (symmetric measure)
    half = np.array([[0.0, 0, 0], [125.0, 0, 0]])
    # outside part of the true axis: x in [50, 200]; x > 125 is on average 37.5 mm away; weight 1/2
    assert limb_axis_distance(half, true_axis, pose, step=0.5) == pytest.approx(0.5 * 0.5 * 37.5, rel=0.02)
    # a limb entirely inside the body has nothing to compare
    assert limb_axis_distance(np.array([[0.0, 0, 0], [20.0, 0, 0]]), true_axis, pose, step=1.0) is None


def test_resample_polyline_spacing_and_invalid_input():
    q = np.array([[0.0, 0, 0], [10.0, 0, 0], [10.0, 5, 0]])
    p = resample_polyline(q, 1.0)
    assert np.allclose(p[0], q[0]) and np.allclose(p[-1], q[-1])
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= 1.0 + 1e-12
    assert len(p) == 16
    with pytest.raises(ValueError, match="step"):
        resample_polyline(q, 0.0)
    with pytest.raises(ValueError, match="polyline"):
        resample_polyline(np.zeros((0, 3)), 1.0)


def test_invalid_input():
    pose = _stick_pose()
    frame = {"tips": {"limb0": [200.0, 0, 0]}, "axes": {"limb0": [[0.0, 0, 0], [200.0, 0, 0]]}}
    spine = {"graph": {"limbs": ["limb0"]}, "frames": [frame]}
    tips = np.array([[[200.0, 0, 0]]])
    axes = {"limb": np.array([[[30.0, 0, 0], [200.0, 0, 0]]])}
    acc = evaluate_spine(spine, tips, axes, ["limb"], poses=[pose])
    assert acc["limb_axis_error_mean"] == pytest.approx(0.0, abs=1e-9) and acc["axis_error_mean"] > 0.05
    assert evaluate_spine(spine, tips, axes, ["limb"])["limb_axis_error_mean"] is None
    with pytest.raises(ValueError, match="poses"):
        evaluate_spine(spine, tips, axes, ["limb"], poses=[pose, pose])
    with pytest.raises(ValueError, match="step"):
        limb_axis_distance(axes["limb"][0], axes["limb"][0], pose, step=-1.0)
