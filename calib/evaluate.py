"""How good a rig calibration is on board detections it may never have seen.

:func:`reprojection_errors` fits one rigid board pose per frame set (jointly
over every camera that saw the board, the cameras held fixed) and measures the
reprojection error per camera. Applied to frame sets the calibration did not
use, this is the held-out error of :func:`calib.rig.calibrate_rig`; applied to
another program's calibration on the same detections, it compares the two on
equal terms.

:func:`projection_uncertainty` propagates a camera's intrinsics covariance to
pixels at the image centre and corners (the figure mrcal reports, here for the
intrinsics given the camera's pose): the semi-major axis of the 1-sigma
ellipse of the projection of a fixed point seen at that pixel.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares

from calib.boards import Board, Charuco, Chessboard
from calib.bundle import project_batch, rodrigues_batch
from calib.calibration import Calibration
from calib.camera import Camera, undistort_normalized
from calib.detect import Detection

__all__ = ["reprojection_errors", "projection_uncertainty", "UNCERTAINTY_POINTS"]

# image positions (fractions of width, height) where the uncertainty is reported
UNCERTAINTY_POINTS = {"centre": (0.5, 0.5), "top-left": (0.0, 0.0), "top-right": (1.0, 0.0),
                      "bottom-left": (0.0, 1.0), "bottom-right": (1.0, 1.0)}


def _initial_pose(cam: Camera, det: Detection, obj: np.ndarray):
    """Board -> world pose from one camera's view (IPPE), or None."""
    import cv2

    op = obj[det.ids].reshape(-1, 1, 3)
    ip = det.corners.reshape(-1, 1, 2)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(op, ip, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return None
    if n == 0:
        return None
    best = int(np.argmin(np.asarray(errs).ravel()))
    Rcb, _ = cv2.Rodrigues(rvecs[best])
    tcb = tvecs[best].ravel()
    R = cam.R.T @ Rcb
    t = cam.R.T @ (tcb - cam.t)
    return cv2.Rodrigues(R)[0].ravel(), t


def reprojection_errors(
    calibration: Calibration,
    detections: Mapping[str, Sequence[Detection]],
    board: Board,
    *,
    frames: Sequence[int] | None = None,
    min_corners: int = 4,
) -> dict:
    """Reprojection error of a fixed calibration, one fitted board pose per frame set.

    Parameters
    ----------
    calibration : Calibration
        Cameras (held fixed), in the board's unit.
    detections : mapping str -> sequence of Detection
        Per camera; equal ``frame`` numbers are one frame set (one board pose).
    board : Chessboard or Charuco
    frames : sequence of int, optional
        Only these frame sets (default: every frame with a detection).
    min_corners : int
        Views with fewer corners are ignored.

    Returns
    -------
    dict
        ``per_camera``: name -> ``{"rms": px, "corners": int, "views": int, "sum_sq": px^2}``
        (``sum_sq`` lets results of several folds be pooled); ``rms``: over every corner;
        ``frames``: frame sets evaluated.
    """
    if not isinstance(calibration, Calibration):
        raise ValueError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if not isinstance(detections, Mapping):
        raise ValueError("detections must map camera names to sequences of Detection")
    unknown = sorted(set(detections) - set(calibration.names))
    if unknown:
        raise ValueError(f"detections: camera(s) {unknown} are not in the calibration ({calibration.names})")
    obj = board.object_points()
    want = None if frames is None else {int(f) for f in frames}
    by_frame: dict[int, list[tuple[int, Detection]]] = {}
    for ci, cam in enumerate(calibration.cameras):
        for d in detections.get(cam.name, ()):
            if d is None or len(d) < min_corners or (want is not None and int(d.frame) not in want):
                continue
            by_frame.setdefault(int(d.frame), []).append((ci, d))
    intr = np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist] for c in calibration.cameras])
    Rc = np.stack([c.R for c in calibration.cameras])
    tc = np.stack([c.t for c in calibration.cameras])
    sq = np.zeros(len(calibration))
    cnt = np.zeros(len(calibration), np.int64)
    views = np.zeros(len(calibration), np.int64)
    n_sets = 0
    for f in sorted(by_frame):
        views_f = by_frame[f]
        ci0, d0 = max(views_f, key=lambda v: len(v[1]))
        x0 = _initial_pose(calibration.cameras[ci0], d0, obj)
        if x0 is None:
            continue
        oc = np.concatenate([np.full(len(d), ci) for ci, d in views_f])
        X = np.concatenate([obj[d.ids] for _, d in views_f])
        uv = np.concatenate([d.corners for _, d in views_f])

        def resid(p, oc=oc, X=X, uv=uv):
            Xw = X @ rodrigues_batch(p[:3])[0].T + p[3:]
            Xc = np.einsum("mij,mj->mi", Rc[oc], Xw) + tc[oc]
            return (project_batch(Xc, intr[oc]) - uv).ravel()

        sol = least_squares(resid, np.concatenate(x0), method="lm", x_scale="jac")
        r2 = np.sum(sol.fun.reshape(-1, 2) ** 2, axis=1)
        np.add.at(sq, oc, r2)
        np.add.at(cnt, oc, 1)
        for ci, _ in views_f:
            views[ci] += 1
        n_sets += 1
    per = {}
    for ci, name in enumerate(calibration.names):
        per[name] = {"rms": float(np.sqrt(sq[ci] / cnt[ci])) if cnt[ci] else float("nan"),
                     "corners": int(cnt[ci]), "views": int(views[ci]), "sum_sq": float(sq[ci])}
    total = int(cnt.sum())
    return {"per_camera": per, "rms": float(np.sqrt(sq.sum() / total)) if total else float("nan"), "frames": n_sets}


def _intrinsics_jacobian(xy: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """(N, 2, 9) derivative of the pixel of normalized points ``xy`` w.r.t. ``fx, fy, cx, cy, k1..k3``."""
    fx, fy, _, _, k1, k2, p1, p2, k3 = intr
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    J = np.zeros((xy.shape[0], 2, 9))
    J[:, 0, 0], J[:, 1, 1] = xd, yd
    J[:, 0, 2], J[:, 1, 3] = 1.0, 1.0
    J[:, 0, 4], J[:, 1, 4] = fx * x * r2, fy * y * r2
    J[:, 0, 5], J[:, 1, 5] = fx * x * r2**2, fy * y * r2**2
    J[:, 0, 6], J[:, 1, 6] = fx * 2 * x * y, fy * (r2 + 2 * y * y)
    J[:, 0, 7], J[:, 1, 7] = fx * (r2 + 2 * x * x), fy * 2 * x * y
    J[:, 0, 8], J[:, 1, 8] = fx * x * r2**3, fy * y * r2**3
    return J


def projection_uncertainty(camera: Camera, covariance: np.ndarray) -> dict:
    """1-sigma projection uncertainty (px) at the image centre and corners.

    Parameters
    ----------
    camera : Camera
    covariance : (9, 9) float ndarray
        Of ``fx, fy, cx, cy, k1, k2, p1, p2, k3``; NaN rows / columns (parameters
        held fixed) count as exactly known.

    Returns
    -------
    dict
        Position name (:data:`UNCERTAINTY_POINTS`) -> px, the square root of the
        largest eigenvalue of the projection's 2 x 2 covariance.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (9, 9):
        raise ValueError(f"covariance must have shape (9, 9), got {cov.shape}")
    cov = np.where(np.isfinite(cov), cov, 0.0)
    w, h = camera.size
    pix = np.array([[fx * (w - 1), fy * (h - 1)] for fx, fy in UNCERTAINTY_POINTS.values()])
    K = camera.K
    yd = (pix[:, 1] - K[1, 2]) / K[1, 1]
    xd = (pix[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    xy = undistort_normalized(np.stack([xd, yd], axis=1), camera.dist)
    intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *camera.dist])
    J = _intrinsics_jacobian(xy, intr)
    S = J @ cov @ J.transpose(0, 2, 1)
    worst = np.sqrt(np.maximum(np.linalg.eigvalsh(S)[:, -1], 0.0))
    return {name: float(v) for name, v in zip(UNCERTAINTY_POINTS, worst)}
