"""Synthetic board observations through known cameras (for tests and benchmarks).

Board poses are drawn around the point the cameras look at, each turned
towards a random camera with a random tilt, as a person waving a board in the
middle of a rig would; every camera that sees the board from the front gets the
projected corners plus Gaussian pixel noise. No images are rendered (see
``fake_cameras.boards`` for that).
"""

from __future__ import annotations

import numpy as np

from calib.boards import Board, Chessboard
from calib.calibration import Calibration
from calib.detect import Detection, default_min_corners

__all__ = ["rig_target", "random_board_poses", "synthetic_detections"]


def rig_target(calibration: Calibration) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis, (3,)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in calibration.cameras:
        d = c.R[2]  # optical axis in world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _rot_from_z(z: np.ndarray, angle: float) -> np.ndarray:
    z = z / np.linalg.norm(z)
    a = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(angle), np.sin(angle)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)  # columns: board axes in world


def random_board_poses(
    calibration: Calibration, board: Board, n: int, *, seed: int = 0, spread: float | None = None,
    max_tilt_deg: float = 40.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board -> world poses ``(R, t)`` around :func:`rig_target`."""
    rng = np.random.default_rng(seed)
    target = rig_target(calibration)
    centers = calibration.centers()
    dist = float(np.median(np.linalg.norm(centers - target, axis=1)))
    spread = 0.2 * dist if spread is None else float(spread)
    mid = board.object_points().mean(axis=0)
    out = []
    for _ in range(n):
        p = target + rng.uniform(-1, 1, 3) * spread
        cam = centers[rng.integers(len(centers))]
        toward = (cam - p) / np.linalg.norm(cam - p)
        tilt = np.deg2rad(rng.uniform(0, max_tilt_deg))
        axis = np.cross(toward, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        # rotate "toward" by tilt about axis (Rodrigues)
        k = axis
        v = toward * np.cos(tilt) + np.cross(k, toward) * np.sin(tilt) + k * (k @ toward) * (1 - np.cos(tilt))
        R = _rot_from_z(-v, rng.uniform(0, 2 * np.pi))  # board z points into the face, away from the viewer
        t = p - R @ mid
        out.append((R, t))
    return out


def synthetic_detections(
    calibration: Calibration,
    board: Board,
    poses: list[tuple[np.ndarray, np.ndarray]],
    *,
    noise_px: float = 0.3,
    seed: int = 0,
    max_angle_deg: float = 75.0,
    margin_px: float = 2.0,
) -> dict[str, list[Detection]]:
    """Project the board's corners in every pose through every camera that sees its face.

    Parameters
    ----------
    calibration : Calibration
        The true cameras.
    board : Chessboard or Charuco
    poses : list of (R (3, 3), t (3,))
        Board -> world poses; the frame number of a detection is the pose index.
    noise_px : float
        Standard deviation of the Gaussian noise added to each pixel coordinate.
    max_angle_deg : float
        A camera sees the board when the angle between the board's face normal
        and the direction to the camera is below this.

    Returns
    -------
    dict
        Camera name -> list of :class:`~calib.detect.Detection` (chessboards:
        all corners or nothing; ChArUco: the corners inside the image).
    """
    if noise_px < 0:
        raise ValueError(f"noise_px must be >= 0, got {noise_px}")
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    need = default_min_corners(board)
    out: dict[str, list[Detection]] = {c.name: [] for c in calibration.cameras}
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    for f, (R, t) in enumerate(poses):
        Xw = obj @ R.T + t
        normal = -R[:, 2]  # towards the viewer of the printed face
        mid = Xw.mean(axis=0)
        for c in calibration.cameras:
            to_cam = c.center - mid
            if normal @ to_cam / np.linalg.norm(to_cam) < cos_max:
                continue
            uv, z = c.project(Xw, return_depth=True)
            inside = (z > 0) & c.in_image(uv, margin=margin_px)
            if isinstance(board, Chessboard):
                if not inside.all():
                    continue
            if inside.sum() < need:
                continue
            ids = np.flatnonzero(inside)
            noisy = uv[ids] + rng.normal(0, noise_px, (ids.size, 2))
            out[c.name].append(Detection(ids=ids, corners=noisy, frame=f))
    return out
