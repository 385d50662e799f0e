"""Real footage: caliscope's 4-camera ChArUco session (``../shared/data/caliscope_4cam``).

Default settings only, exactly what ``stage calibrate --images DIR`` runs. The reference
is caliscope's own ``camera_array.toml`` — another program's estimate, not the truth —
so the geometry is compared at a few per cent, and the deciding figure is the held-out
reprojection error of both calibrations on the same detections (:mod:`calib.evaluate`).
One of the webcams sees the board only in the flipped image (the board is seen from
behind); it must be found, explained and calibrated.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calib.boards import load_board
from calib.evaluate import reprojection_errors
from calib.formats import in_units, read_calibration
from calib.rig import calibrate_rig
from tests.conftest import shared_dataset


@pytest.fixture(scope="module")
def session():
    root = shared_dataset("caliscope_4cam")
    from stage.cli.calibrate import detect_images

    board = load_board(root / "charuco.toml")  # caliscope's own board file
    assert board.squares == (4, 5) and board.square_mm == pytest.approx(54.0) and board.inverted
    dets, sizes, flipped, notes = detect_images(root / "extrinsic", board, progress=False)
    result = calibrate_rig(dets, sizes, board, cameras=list(sizes), flipped=flipped, holdout_folds=5)  # as the CLI
    ref = in_units(read_calibration(root / "camera_array.toml"), "mm")
    return board, result, ref, flipped, notes


def test_all_cameras_calibrated_and_connected(session):
    _, result, ref, flipped, notes = session
    assert result.calibration.names == ref.names
    assert flipped == ["cam_1"] and any("cam_1" in n for n in notes)
    assert any("from behind" in n for n in result.evaluation["flipped"])
    assert all(v >= 10 for v in result.extrinsics.per_camera_views.values())


def test_focal_lengths_within_3_percent(session):
    _, result, ref, *_ = session
    for ours, theirs in zip(result.calibration, ref):
        for i in (0, 1):
            assert ours.K[i, i] == pytest.approx(theirs.K[i, i], rel=0.03), ours.name


# Relative rotations within the 2 degrees, default flags. Measured 0.68-1.54 degrees: the default
# distortion model puts a weak zero-mean prior on p1, p2 (sigma 0.001) and k3 (sigma 0.5), so the
# tangential terms no longer slide along their 0.97-0.99 correlation with cx (the board covers 12-19 %
# of each image); without it (--distortion full) 1.29-2.37 degrees.
ROTATION_TOL_DEG = 2.0


def test_camera_distances_and_relative_rotations(session):
    _, result, ref, *_ = session
    ours, theirs = result.calibration, ref
    for a, b in itertools.combinations(range(len(ours)), 2):
        d_ours = np.linalg.norm(ours[a].center - ours[b].center)
        d_ref = np.linalg.norm(theirs[a].center - theirs[b].center)
        assert d_ours == pytest.approx(d_ref, rel=0.03), (ours[a].name, ours[b].name)
        Ro = ours[a].R @ ours[b].R.T
        Rr = theirs[a].R @ theirs[b].R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(Ro.T @ Rr) - 1) / 2, -1, 1)))
        assert angle < ROTATION_TOL_DEG, (ours[a].name, ours[b].name, angle)


def test_rotation_uncertainty_figures(session):
    """Both 1-sigma figures of the relative rotations are reported, and the folds' spread is the larger.

    With the default prior the folds' spread is 0.40-0.88 degrees per pair (0.79-1.75 without it); the
    remaining differences to caliscope (0.68-1.54 degrees) are 0.9-3.6 of those sigmas, so part of them
    is caliscope's own error or a bias of ours that these videos cannot show; the test does not claim
    more than what the figures support."""
    _, result, ref, *_ = session
    ev = result.evaluation
    folds, cov = ev["rotation_folds_deg"]["pairs"], ev["rotation_sigma_deg"]["pairs"]
    ours = result.calibration
    for a, b in itertools.combinations(range(len(ours)), 2):
        key = f"{ours[a].name} - {ours[b].name}"
        Ro, Rr = ours[a].R @ ours[b].R.T, ref[a].R @ ref[b].R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(Ro.T @ Rr) - 1) / 2, -1, 1)))
        assert 0 < cov[key] < folds[key] < 1.0 and angle < ROTATION_TOL_DEG, (key, angle, folds[key])
    table = result.report()
    assert "rotation deg vs" in table and "(covariance / folds)" in table
    # the folds vary far more than independent corner errors explain: the report says why
    assert any("errors shared by whole views dominate" in w for w in result.warnings)


def test_extrinsics_agree_given_caliscope_intrinsics(session):
    """With caliscope's intrinsics held, our extrinsics reproduce caliscope's relative rotations."""
    from calib.extrinsics import calibrate_extrinsics

    board, result, ref, *_ = session
    dets = result.evaluation["detections"]
    seen: dict[int, int] = {}
    for n in ref.names:
        for d in dets[n]:
            seen[d.frame] = seen.get(d.frame, 0) + 1
    linked = {n: [d for d in dets[n] if seen[d.frame] >= 2] for n in ref.names}
    ext = calibrate_extrinsics(linked, list(ref.cameras), board, optimize_intrinsics=False)
    ours = ext.calibration
    for a, b in itertools.combinations(range(len(ours)), 2):
        Ro, Rr = ours[a].R @ ours[b].R.T, ref[a].R @ ref[b].R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(Ro.T @ Rr) - 1) / 2, -1, 1)))
        assert angle < 1.0, (ours[a].name, ours[b].name, angle)


def test_auto_distortion_model(session):
    """--distortion auto: p1, p2 (and k3) held at zero where a camera's views do not support them."""
    board, result, ref, *_ = session
    auto = calibrate_rig(result.evaluation["detections"], {c.name: c.size for c in result.calibration}, board,
                         cameras=ref.names, distortion="auto")
    assert all(r.dropped for r in auto.intrinsics.values())
    ours = auto.calibration
    for a, b in itertools.combinations(range(len(ours)), 2):
        Ro, Rr = ours[a].R @ ours[b].R.T, ref[a].R @ ref[b].R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(Ro.T @ Rr) - 1) / 2, -1, 1)))
        assert angle < 2.0, (ours[a].name, ours[b].name, angle)
        assert np.linalg.norm(ours[a].center - ours[b].center) == pytest.approx(
            np.linalg.norm(ref[a].center - ref[b].center), rel=0.03)


def test_held_out_error_at_most_caliscope_on_same_detections(session):
    board, result, ref, *_ = session
    dets = result.evaluation["detections"]  # the detections in the coordinates of the images as delivered
    theirs = reprojection_errors(ref, dets, board)["per_camera"]
    ours = result.held_out_rms()
    for name in ref.names:
        assert np.isfinite(ours[name])
        assert ours[name] <= 1.1 * theirs[name]["rms"], (name, ours[name], theirs[name]["rms"])
    # the user reads the held-out line first
    assert result.report().splitlines()[1].startswith("held-out reprojection RMS")
