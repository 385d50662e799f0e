"""Rendered boards are found by OpenCV's own detectors, at the true corner positions."""

import cv2
import numpy as np
import pytest

from calib.boards import Charuco, Chessboard
from fake_cameras.boards import board_poses, render_board_views
from fake_cameras.dome import make_dome


@pytest.fixture(scope="module")
def cal():
    return make_dome(4, seed=0)


def _frontal(bv, v, c, max_deg=50):
    cam = bv.calibration[c]
    to_cam = cam.center - bv.poses[v, :3, 3]
    cos = -(to_cam / np.linalg.norm(to_cam)) @ bv.poses[v, :3, 2]
    return bv.visible[v, c].all() and cos > np.cos(np.radians(max_deg))


@pytest.mark.slow
def test_chessboard_corners_are_detected_at_the_truth(cal):
    board = Chessboard(corners=(9, 6), square_mm=50.0)
    bv = render_board_views(board, cal, 4, seed=1)
    assert bv.images.shape == (4, 4, 480, 640, 3)
    errs = []
    for v in range(4):
        for c in range(4):
            if not _frontal(bv, v, c):
                continue
            gray = cv2.cvtColor(bv.images[v, c], cv2.COLOR_BGR2GRAY)
            flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            ok, cc = cv2.findChessboardCornersSB(gray, board.corners, flags=flags)
            assert ok, (v, c)
            cc = cc.reshape(-1, 2)
            true = bv.corners_2d[v, c]
            # the detector may start from either end of the grid
            e = min((np.linalg.norm(cc - true, axis=1), np.linalg.norm(cc[::-1] - true, axis=1)), key=np.max)
            errs.append(e)
    errs = np.concatenate(errs)
    assert errs.size >= 3 * board.n_corners
    assert np.median(errs) < 0.12
    assert np.percentile(errs, 90) < 0.3


@pytest.mark.slow
def test_charuco_corners_are_detected_at_the_truth(cal):
    board = Charuco(squares=(7, 5), square_mm=70.0, marker_mm=52.0, dictionary="DICT_4X4_50")
    bv = render_board_views(board, cal, 4, seed=1)
    det = cv2.aruco.CharucoDetector(board.to_cv())
    errs = []
    for v in range(4):
        for c in range(4):
            if not _frontal(bv, v, c):
                continue
            gray = cv2.cvtColor(bv.images[v, c], cv2.COLOR_BGR2GRAY)
            cc, ids, _, _ = det.detectBoard(gray)
            assert ids is not None and len(ids) >= 12, (v, c)
            errs.append(np.linalg.norm(cc.reshape(-1, 2) - bv.corners_2d[v, c][ids.ravel()], axis=1))
    errs = np.concatenate(errs)
    assert errs.size >= 40
    assert np.median(errs) < 0.12
    assert np.percentile(errs, 90) < 0.3


def test_ground_truth_geometry(cal):
    board = Chessboard(corners=(5, 4), square_mm=60.0)
    bv = render_board_views(board, cal, 3, seed=2, noise_sigma=0)
    V, C, N = bv.visible.shape
    assert (V, C, N) == (3, 4, 20)
    for v in range(V):
        R, t = bv.poses[v, :3, :3], bv.poses[v, :3, 3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
        assert np.allclose(bv.corners_3d[v], bv.object_points @ R.T + t)
        # corners of adjacent squares are one square apart in the world
        d = np.linalg.norm(np.diff(bv.corners_3d[v].reshape(4, 5, 3), axis=1), axis=2)
        assert np.allclose(d, 60.0)
        for c, cam in enumerate(cal):
            assert np.allclose(bv.corners_2d[v, c], cam.project(bv.corners_3d[v]))
    # every pose faces at least one camera; boards stay inside the volume
    assert bv.visible.any(axis=(1, 2)).all()
    assert np.all(np.abs(bv.corners_3d[..., :2]) < 375) and np.all((bv.corners_3d[..., 2] > 0) & (bv.corners_3d[..., 2] < 750))
    # cameras behind the board see only the studio (green)
    for v in range(V):
        for c in range(C):
            if not bv.visible[v, c].any():
                img = bv.images[v, c].astype(int)
                assert np.mean(img[..., 1] > img[..., 2] + 30) > 0.99


def test_invalid_input(cal):
    board = Chessboard(corners=(5, 4), square_mm=60.0)
    with pytest.raises(ValueError, match="board"):
        render_board_views({"type": "chessboard"}, cal, 2)
    with pytest.raises(ValueError, match="calibration"):
        render_board_views(board, "dome", 2)
    with pytest.raises(ValueError, match="n_views"):
        render_board_views(board, cal, 0)
    with pytest.raises(ValueError, match="noise_sigma"):
        render_board_views(board, cal, 1, noise_sigma=-1)
    with pytest.raises(ValueError, match="poses"):
        render_board_views(board, cal, 2, poses=np.eye(4)[None])
    with pytest.raises(ValueError, match="board"):
        board_poses("chessboard", cal, 2)


def test_board_poses_wander_through_volume():
    """Regression: a board nearly as large as the volume stayed within +-4 mm of its centre, so
    corners filled only the middle of every image and focal lengths came out 0.8 % off."""
    from stage.rig import Volume

    cal = make_dome(4, seed=0)
    vol = Volume()
    board = Charuco(squares=(7, 5), square_mm=70.0, marker_mm=52.0, dictionary="DICT_4X4_50")
    P = board_poses(board, cal, 60, seed=3, volume=vol, spread=0.9, close_fraction=0.0)
    x0, y0, x1, y1 = board.outline_mm
    mid = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    centres = np.einsum("vij,j->vi", P[:, :3, :3], mid) + P[:, :3, 3]
    half = np.asarray(vol.size) / 2
    rel = (centres - np.asarray(vol.center)) / half
    # uniform over +-0.9 of the half size: the spread of 60 draws is well above half of it
    assert np.all(rel[:, :2].std(axis=0) > 0.3)
    assert np.all(np.abs(rel[:, :2]) <= 0.9 + 1e-9)
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    low = (np.einsum("vij,nj->vni", P[:, :3, :3], outline) + P[:, None, :3, 3])[..., 2].min(axis=1)
    assert np.all(low >= board.square_mm - 1e-6)


def test_close_up_views_cover_every_camera_image():
    """Every camera gets close-up views (every third round) that carry its board corners
    into the edges of its image: with them the corners cover >= 50 % of a 10 x 8 grid of
    image cells in every camera (without them, the demo rig's cameras saw 31-46 %)."""
    from calib.intrinsics import coverage_fraction
    from stage.rig import Volume

    cal = make_dome(12, seed=0)
    board = Charuco(squares=(7, 5), square_mm=70.0, marker_mm=52.0, dictionary="DICT_4X4_50")
    obj = board.object_points()

    def coverage(P):
        out = []
        for c in cal:
            pts = []
            for T in P:
                X = obj @ T[:3, :3].T + T[:3, 3]
                uv, z = c.project(X, return_depth=True)
                inside = (z > 0) & np.all((uv >= 0) & (uv < np.asarray(c.size)), axis=1)
                if inside.all():  # the whole board in view (a chessboard needs all of it)
                    pts.append(uv)
            out.append(coverage_fraction(np.concatenate(pts) if pts else np.zeros((0, 2)), c.size))
        return np.array(out)

    far = coverage(board_poses(board, cal, 72, seed=3, volume=Volume(), spread=0.9, close_fraction=0.0))
    near = coverage(board_poses(board, cal, 72, seed=3, volume=Volume(), spread=0.9))
    assert near.min() >= 0.5 and near.mean() > far.mean() + 0.1, (far.round(2), near.round(2))
    with pytest.raises(ValueError, match="close_fraction"):
        board_poses(board, cal, 2, close_fraction=1.5)
