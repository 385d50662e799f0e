"""`stage bench calib --draws`: the reported uncertainties against the simulator's truth; the figures it prints
are those computed directly from `calibrate_rig` on the same draw."""

import numpy as np
import pytest

from stage.cli import main


def test_draws_print_the_chi_square_of_the_reported_covariances(capsys):
    from calib.rig import calibrate_rig
    from calib.synthetic import random_board_poses, synthetic_detections
    from fake_cameras.dome import make_dome
    from stage.benchmarks.calib import _board

    args = ["bench", "calib", "--draws", "1", "--views", "25", "--board", "charuco", "--seed", "5"]
    assert main(args) == 0
    rows = {line[:25].strip(): line[25:].split() for line in capsys.readouterr().out.splitlines()[2:4]}
    # the same draw, directly: chi-square of each camera's Zhang and rig intrinsics against their covariances
    truth, board = make_dome(12), _board("charuco")
    dist = float(np.median(np.linalg.norm(truth.centers() - truth.centers().mean(0), axis=1)))
    poses = random_board_poses(truth, board, 25, seed=5, spread=0.25 * dist)
    dets = synthetic_detections(truth, board, poses, noise_px=0.3, seed=5 + 10_000)
    res = calibrate_rig(dets, {c.name: c.size for c in truth}, board, cameras=truth.names)
    chi_z, chi_b, dof = 0.0, 0.0, 0
    for i, cam in enumerate(res.calibration.cameras):
        t = truth[cam.name]
        true = np.r_[t.K[0, 0], t.K[1, 1], t.K[0, 2], t.K[1, 2], t.dist]
        zhang = res.intrinsics[cam.name]
        free = np.isfinite(np.diag(zhang.covariance))
        rig = np.r_[cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], cam.dist]
        for est, cov, acc in ((zhang.params, zhang.covariance, "z"), (rig, res.extrinsics.meta["intrinsics_cov"][i], "b")):
            d = (est - true)[free]
            c = d @ np.linalg.solve(cov[np.ix_(free, free)], d)
            chi_z, chi_b = (chi_z + c, chi_b) if acc == "z" else (chi_z, chi_b + c)
        dof += int(free.sum())
    assert float(rows["own calibration (Zhang)"][-1]) == pytest.approx(chi_z / dof, abs=0.006)  # printed to 0.01
    assert float(rows["rig (bundle adjustment)"][-1]) == pytest.approx(chi_b / dof, abs=0.006)


def test_invalid_input(capsys):
    assert main(["bench", "calib", "--draws", "-1"]) == 2
    assert "--draws" in capsys.readouterr().err
