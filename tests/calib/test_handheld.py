"""A simulated hand-held board take (fake_cameras.handheld): six webcams round a room, one
delivering mirrored images, one mounted sideways, the board on a small part of each image.

Corners are the true projections plus Gaussian noise (0.3 px); the mirroring camera's are
made on its flipped-back images, as detection makes them (the flipped-image path itself is
tested on rendered images below). Default settings: ``intrinsics="prior"``.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.intrinsics import coverage_fraction
from calib.rig import calibrate_rig, resolve_flipped
from calib.synthetic import synthetic_detections
from fake_cameras.handheld import HANDHELD_BOARD, handheld_poses, handheld_rig, render_handheld

N_FRAMES = 200  # about 30 s of a 6 fps webcam take


@pytest.fixture(scope="module")
def take():
    truth, mirrored = handheld_rig()
    poses = handheld_poses(truth, HANDHELD_BOARD, N_FRAMES, seed=1)
    dets = synthetic_detections(truth, HANDHELD_BOARD, [(T[:3, :3], T[:3, 3]) for T in poses], noise_px=0.3,
                                seed=2, max_angle_deg=70.0)
    return truth, mirrored, poses, dets


@pytest.fixture(scope="module")
def solved(take):
    truth, mirrored, _, dets = take
    return calibrate_rig(dets, {c.name: c.size for c in truth}, HANDHELD_BOARD, cameras=truth.names,
                         flipped=mirrored)


def test_take_is_hand_held_like(take):
    truth, _, _, dets = take
    for cam in truth:
        cover = coverage_fraction(np.concatenate([d.corners for d in dets[cam.name]]), cam.size)
        assert cover <= 0.75, cam.name  # the image corners stay empty
        for d in dets[cam.name]:
            w, h = np.ptp(d.corners, axis=0)
            assert w * h <= 0.25 * cam.width * cam.height  # the board covers at most a quarter of the image
    frames = {}
    for ds in dets.values():
        for d in ds:
            frames[d.frame] = frames.get(d.frame, 0) + 1
    assert max(frames.values()) <= 4  # never the whole rig at once


def test_focal_and_principal_point_with_default_prior(solved, take):
    truth = take[0]
    assert solved.evaluation["mode"] == "prior"
    for est, tru in zip(solved.calibration, truth):
        np.testing.assert_allclose([est.K[0, 0], est.K[1, 1]], [tru.K[0, 0], tru.K[1, 1]], rtol=0.01,
                                   err_msg=est.name)
        assert np.linalg.norm(est.K[:2, 2] - tru.K[:2, 2]) < 5.0, est.name


def test_mirrored_and_sideways_cameras(solved, take):
    truth, mirrored, *_ = take
    assert solved.evaluation["mirrored"] == mirrored == ["cam_1"]
    assert solved.calibration["cam_1"].meta.get("mirror") is True
    assert not solved.calibration["cam_0"].meta.get("mirror")
    # the relative pose of the sideways camera (rolled 90 degrees) is right
    a, b = solved.calibration["cam_3"], solved.calibration["cam_0"]
    ta, tb = truth["cam_3"], truth["cam_0"]
    R_est, R_true = a.R @ b.R.T, ta.R @ tb.R.T
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_true) - 1) / 2, -1, 1)))
    assert angle < 0.5
    d_est = np.linalg.norm(a.center - b.center)
    assert d_est == pytest.approx(np.linalg.norm(ta.center - tb.center), rel=0.01)


def test_board_seen_from_behind_is_told_from_a_mirror(take):
    """A camera that delivers the true image but sees the board from behind (through the print)
    also finds it only in the flipped image; the rig tells the two apart."""
    truth, _, _, dets = take
    from calib.rig import _unflip

    # detection on the flipped image of such a camera gives the flipped coordinates of the true corners
    behind = dict(dets)
    behind["cam_1"] = _unflip(dets["cam_1"], truth["cam_1"].width)
    out, mirrored, notes = resolve_flipped(behind, {c.name: c.size for c in truth}, HANDHELD_BOARD, ["cam_1"],
                                           truth.names, 6)
    assert mirrored == [] and "from behind" in notes[0]
    for a, b in zip(out["cam_1"], dets["cam_1"]):  # back in the coordinates of the images as delivered
        np.testing.assert_allclose(a.corners, b.corners, atol=1e-9)


def test_mirrored_images_are_found_and_flagged(tmp_path):
    """Rendered frames: the mirroring camera's board is found only once flipped, the CLI says so."""
    import cv2

    from stage.cli.calibrate import detect_images

    truth, _ = handheld_rig(3, mirrored=(1,), sideways=())
    poses = handheld_poses(truth, HANDHELD_BOARD, 200, seed=3)
    obj = HANDHELD_BOARD.object_points()
    # frames the two first cameras both see well
    keep = []
    for k, T in enumerate(poses):
        X = obj @ T[:3, :3].T + T[:3, 3]
        ok = all(truth[i].in_image(truth[i].project(X), margin=4).all()
                 and (truth[i].center - T[:3, 3]) @ -T[:3, 2] > 0 for i in (0, 1))
        if ok:
            keep.append(k)
    keep = keep[:5]
    assert len(keep) >= 4
    sub = truth.__class__(truth.cameras[:2], units="mm")
    imgs = render_handheld(sub, HANDHELD_BOARD, poses[keep], seed=4)
    for name, frames in imgs.items():
        (tmp_path / name).mkdir()
        for i, img in enumerate(frames):
            cv2.imwrite(str(tmp_path / name / f"{i:03d}.png"), img)
    dets, sizes, flipped, notes = detect_images(tmp_path, HANDHELD_BOARD, progress=False)
    assert flipped == ["cam_1"] and len(dets["cam_1"]) >= 4
    assert any(n.startswith("cam_1 delivers mirrored images") for n in notes)
    # the flipped detections are where the true (unmirrored) camera projects the corners
    d = dets["cam_1"][0]
    true_uv = truth["cam_1"].project(obj[d.ids] @ poses[keep[d.frame]][:3, :3].T + poses[keep[d.frame]][:3, 3])
    assert np.median(np.linalg.norm(d.corners - true_uv, axis=1)) < 0.5
    # forced mirror = false: a clear error naming the camera, nothing returned
    from calib.intrinsics import CalibrationError

    with pytest.raises(CalibrationError, match="cam_1.*mirror = false.*flipped"):
        detect_images(tmp_path, HANDHELD_BOARD, progress=False, mirror=["cam_1=false"])


def test_mirrored_camera_in_a_take(tmp_path):
    """The same check on a take (stage calibrate TAKE.h5): frames of one camera mirrored."""
    from stage import store
    from stage.cli.calibrate import detect_take_flipped
    from stage.frame import Frame

    truth, _ = handheld_rig(3, mirrored=(1,), sideways=())
    poses = handheld_poses(truth, HANDHELD_BOARD, 200, seed=3)
    obj = HANDHELD_BOARD.object_points()
    keep = [k for k, T in enumerate(poses)
            if all(truth[i].in_image(truth[i].project(obj @ T[:3, :3].T + T[:3, 3]), margin=4).all()
                   and (truth[i].center - T[:3, 3]) @ -T[:3, 2] > 0 for i in (0, 1))][:4]
    sub = truth.__class__(truth.cameras[:2], units="mm")
    imgs = render_handheld(sub, HANDHELD_BOARD, poses[keep], seed=5)
    take = tmp_path / "board.h5"
    with store.TakeWriter(take, [store.CameraSpec(n, 640, 480) for n in imgs], fps=6) as w:
        for k in range(len(keep)):
            w.write_set({n: Frame(np.repeat(imgs[n][k][:, :, None], 3, axis=2), n, k, k * 10**8, k * 10**8)
                         for n in imgs})
    dets, sizes, cams, flipped, notes = detect_take_flipped(take, HANDHELD_BOARD, progress=False)
    assert flipped == ["cam_1"] and len(dets["cam_1"]) >= 3 and any("cam_1" in n for n in notes)
