"""A hand-held board take on a small webcam-like rig, with ground truth.

Real calibration footage often looks like this: a handful of cameras round a room,
an operator walking a board about at chest height and turning it from camera to
camera, the board covering a small part of each image (a tenth to a quarter), so
that each camera sees the board in a few dozen frames and only two or three cameras
see it at once. Some webcams deliver mirrored images; some are mounted sideways.

:func:`handheld_rig` builds such a rig (true cameras, which of them mirror);
:func:`handheld_poses` the board's path; :func:`render_handheld` films it with
:func:`fake_cameras.boards.render_board`, flipping the images of the mirroring
cameras as their firmware would. The true camera of a mirroring webcam is the
model of the flipped-back (true) image.
"""

from __future__ import annotations

import math

import numpy as np

from calib.boards import Charuco, Chessboard
from calib.calibration import Calibration
from calib.camera import Camera
from fake_cameras.boards import render_board
from fake_cameras.dome import look_at

__all__ = ["handheld_rig", "handheld_poses", "render_handheld", "HANDHELD_BOARD"]

#: The board the take waves: 7 x 5 squares of 90 mm (630 x 450 mm).
HANDHELD_BOARD = Charuco((7, 5), 90.0, 68.0, dictionary="DICT_4X4_50")


def handheld_rig(
    n_cameras: int = 6,
    *,
    size: tuple[int, int] = (640, 480),
    mirrored: tuple[int, ...] = (1,),
    sideways: tuple[int, ...] = (3,),
    radius_mm: float = 1900.0,
    seed: int = 0,
) -> tuple[Calibration, list[str]]:
    """Webcams on a ring round the room, looking at its middle.

    Parameters
    ----------
    n_cameras : int
    size : (int, int)
        Image ``(width, height)``.
    mirrored, sideways : tuple of int
        Indices of the cameras that deliver mirrored images / are rolled 90 degrees.
    radius_mm : float
    seed : int

    Returns
    -------
    calibration : Calibration
        The true cameras (mm; the mirroring ones with ``meta["mirror"] = True``).
    mirrored : list of str
        Names of the mirroring cameras.
    """
    if n_cameras < 2:
        raise ValueError(f"n_cameras must be >= 2, got {n_cameras}")
    bad = [i for i in (*mirrored, *sideways) if not 0 <= i < n_cameras]
    if bad:
        raise ValueError(f"mirrored / sideways: camera indices {bad} out of range [0, {n_cameras})")
    rng = np.random.default_rng(seed)
    w, h = size
    target = np.array([0.0, 0.0, 1100.0])
    cams = []
    for i in range(n_cameras):
        a = 2 * math.pi * i / n_cameras + rng.uniform(-0.15, 0.15)
        c = np.array([radius_mm * math.cos(a), radius_mm * math.sin(a), 1400.0 + 500.0 * (i % 2)])
        R = look_at(c, target, roll=math.pi / 2 if i in sideways else 0.0)
        f = rng.uniform(0.85, 1.05) * w
        K = np.array([[f * rng.uniform(0.995, 1.005), 0, (w - 1) / 2 + rng.uniform(-12, 12)],
                      [0, f, (h - 1) / 2 + rng.uniform(-12, 12)], [0, 0, 1.0]])
        dist = np.array([rng.uniform(-0.25, -0.08), rng.uniform(0.0, 0.08), rng.normal(0, 5e-4), rng.normal(0, 5e-4),
                         0.0])
        meta = {"mirror": True} if i in mirrored else {}
        cams.append(Camera(f"cam_{i}", K=K, dist=dist, R=R, t=-R @ c, size=size, meta=meta))
    cal = Calibration(tuple(cams), units="mm", meta={"source": "fake_cameras.handheld"})
    return cal, [cams[i].name for i in mirrored]


def handheld_poses(calibration: Calibration, board: Chessboard | Charuco, n_frames: int, *,
                   seed: int = 0) -> np.ndarray:
    """(F, 4, 4) board -> world poses of an operator walking the board about and turning it.

    The board centre wanders (a smoothed random walk) within 0.5 m of the room's middle at
    chest height; the board turns slowly round the vertical (the operator turns from camera
    to camera), tilts by up to 30 degrees and rolls by up to 25 degrees.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = board.outline_mm
    mid = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    p = np.array([0.0, 0.0, 1100.0])
    vel = np.zeros(3)
    yaw = rng.uniform(0, 2 * math.pi)
    out = np.empty((int(n_frames), 4, 4))
    for k in range(int(n_frames)):
        vel = 0.7 * vel + rng.normal(0, 60.0, 3) * np.array([1.0, 1.0, 0.5])
        p = p + vel
        off = p - np.array([0.0, 0.0, 1100.0])
        off = np.clip(off, [-500, -500, -300], [500, 500, 300])
        p = np.array([0.0, 0.0, 1100.0]) + off
        yaw += rng.normal(0.35, 0.25)  # keeps turning one way, unevenly: every camera gets its turn
        tilt = math.radians(rng.uniform(-30, 30))
        roll = math.radians(rng.uniform(-25, 25))
        n = np.array([math.cos(yaw) * math.cos(tilt), math.sin(yaw) * math.cos(tilt), math.sin(tilt)])
        z = -n  # board z points into the printed face, away from the cameras it faces
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        x, y = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
        R = np.stack([x, y, z], axis=1)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p - R @ mid
        out[k] = T
    return out


def render_handheld(calibration: Calibration, board: Chessboard | Charuco, poses: np.ndarray, *, seed: int = 0,
                    noise_sigma: float = 2.0):
    """Film the board path with every camera: ``{name: [(H, W) uint8 grey image per frame]}``.

    Mirroring cameras (``meta["mirror"]``) deliver their images flipped left-right.
    """
    import cv2

    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (F, 4, 4), got {poses.shape}")
    rng = np.random.default_rng(seed)
    out: dict[str, list[np.ndarray]] = {c.name: [] for c in calibration}
    for T in poses:
        for cam in calibration:
            img = cv2.cvtColor(render_board(cam, T, board, rng=rng, noise_sigma=noise_sigma), cv2.COLOR_BGR2GRAY)
            if cam.meta.get("mirror"):
                img = np.ascontiguousarray(img[:, ::-1])
            out[cam.name].append(img)
    return out
