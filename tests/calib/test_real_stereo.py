"""Real images: OpenCV's 9x6 stereo sample (opencv_stereo_9x6)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boards import Chessboard
from calib.detect import detect_board
from calib.extrinsics import calibrate_extrinsics
from calib.intrinsics import calibrate_intrinsics
from tests.conftest import shared_dataset

BOARD = Chessboard((9, 6), 25.0)
FRAMES = [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14]


@pytest.fixture(scope="module")
def stereo():
    import cv2

    root = shared_dataset("opencv_stereo_9x6")
    out = {}
    for side in ("left", "right"):
        imgs = [cv2.imread(str(root / f"{side}{k:02d}.jpg")) for k in FRAMES]
        # the OpenCV sample's procedure: findChessboardCorners + cornerSubPix with an 11x11 window
        out[side] = [detect_board(im, BOARD, frame=k, method="classic", subpix_window=11)
                     for k, im in zip(FRAMES, imgs)]
        out[side + "_default"] = [detect_board(im, BOARD, frame=k) for k, im in zip(FRAMES, imgs)]
    return out


def test_left_matches_opencv_reference(stereo):
    """OpenCV's published reference (left_intrinsics.yml) and the RMS measured in the data README."""
    assert all(d is not None for d in stereo["left"])
    r = calibrate_intrinsics(stereo["left"], BOARD, (640, 480), name="left", fix_aspect_ratio=True,
                             reject_outliers=False)
    assert abs(r.K[0, 0] / 535.9157 - 1) < 0.005
    assert abs(r.K[0, 2] - 342.2832) < 2 and abs(r.K[1, 2] - 235.5708) < 2
    assert abs(r.rms - 0.4087) < 0.05
    # the reference's outlier view (left02, 1.18 px) is what the automatic rejection drops
    r2 = calibrate_intrinsics(stereo["left"], BOARD, (640, 480), name="left", fix_aspect_ratio=True)
    assert list(r2.rejected) == [2]
    assert r2.rms < r.rms
    assert abs(r2.K[0, 0] / 535.9157 - 1) < 0.005


def test_default_detector_is_at_least_as_good(stereo):
    r = calibrate_intrinsics(stereo["left_default"], BOARD, (640, 480), name="left", fix_aspect_ratio=True,
                             reject_outliers=False)
    assert r.rms <= 0.4087 and abs(r.K[0, 0] / 535.9157 - 1) < 0.005


def test_stereo_baseline_through_rig_pipeline(stereo):
    intr = {s: calibrate_intrinsics(stereo[s], BOARD, (640, 480), name=s) for s in ("left", "right")}
    dets = {s: [d for d in stereo[s] if d.frame not in intr[s].rejected] for s in ("left", "right")}
    res = calibrate_extrinsics(dets, [intr["left"].camera(), intr["right"].camera()], BOARD, world="camera")
    baseline = float(np.linalg.norm(res.calibration["right"].center))
    assert abs(baseline - 83.6) < 1.0, baseline
    c = res.calibration["right"].center
    assert c[0] > 80 and abs(c[1]) < 10 and abs(c[2]) < 10, c  # the right camera sits ~84 mm along +x
    assert res.rms < 0.5
    assert res.geometry["neighbor_rms"] < 0.5  # mm, on 25 mm squares
