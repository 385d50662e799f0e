"""Intrinsic calibration of one camera from board views (Zhang 2000, via OpenCV).

``cv2.calibrateCameraExtended`` gives per-view reprojection errors and the
standard deviations of the parameters; views whose error is far above the rest
(a blurred or mis-detected board) are rejected and the camera re-solved. The
result carries a coverage measure (which part of the image the corners covered)
and plain-language warnings when views or coverage are too few.

Distortion model (``distortion="prior"``, the default): after the unregularised
Zhang solve, the camera is solved again for the maximum a posteriori: the
reprojection errors plus a zero-mean Gaussian prior on ``p1, p2`` (standard
deviation 0.001) and ``k3`` (0.5), weighted by the per-coordinate pixel noise of the
unregularised fit, so the objective is the negative log-posterior (the views' board
poses free, :func:`calib.bundle.bundle_adjust` with one camera). With the board on a
small part of the image, ``p1, p2`` are nearly degenerate with the principal point
(correlations of 0.97-0.99 on real webcam footage) and ``k3`` with ``k1, k2``: left
free they let the principal point wander along that valley, and every camera's
rotation with it. The prior removes only that freedom: where the views constrain a
term better than its prior, the data decide (a well-covered camera keeps its real
decentring). The widths are set by the image displacement they allow, not fitted to
any footage: decentring (Brown 1966's tangential terms) of an assembled lens displaces
points by a pixel or so, and ``p = 1e-3`` displaces the corner of an image with a
60-degree field of view by ``f p2 (r^2 + 2 x^2) ~ 0.7`` px (640 x 480, ``f = 550`` px);
``|k3| <= 0.5`` (one sigma) leaves ordinary, non-fisheye lenses their sixth-order term
and holds off the k3 of several units that narrow coverage produces (-3.4 on real
webcam footage). The simulated rigs' true decentring is within 0.001 and their k3 is 0. The
posterior covariance (prior included) is what the rig's bundle adjustment then uses as
its intrinsics prior. A sigma of ``inf`` gives the unregularised solve (``"full"``).

``distortion="auto"`` instead holds the tangential terms ``p1, p2`` and / or ``k3`` at
zero when the views do not support them. The test is the Bayesian information
criterion, evaluated from the full model by its Wald statistic: a set ``S`` of terms is
dropped when ``theta_S^T Cov_S^-1 theta_S < |S| ln N`` (``N`` pixel coordinates),
the largest margin winning, and the camera is solved again without it (Schwarz
1978; the Wald form is its usual large-sample approximation). A hard drop loses a
term too small for one camera's views that still matters to a rig whose bundle
adjustment sees many more (docs/calibration.md, "Real footage").

Reference: Z. Zhang, "A flexible new technique for camera calibration", IEEE
TPAMI 22(11), 2000.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from calib.boards import Board, Charuco, Chessboard
from calib.bundle import INTRINSIC_NAMES
from calib.camera import Camera
from calib.detect import Detection

__all__ = [
    "CalibrationError",
    "IntrinsicsResult",
    "calibrate_intrinsics",
    "coverage_fraction",
    "coverage_image",
    "MIN_VIEWS",
    "DISTORTION_MODES",
    "DISTORTION_SIGMA",
    "WARN_VIEWS",
    "WARN_COVERAGE",
]

log = logging.getLogger(__name__)

MIN_VIEWS = 4  # fewer views than this: refuse to calibrate
WARN_VIEWS = 10  # fewer views than this: warn
WARN_COVERAGE = 0.5  # fraction of the image grid cells with corners below which we warn
COVERAGE_GRID = (8, 6)
DISTORTION_MODES = ("prior", "full", "auto")
# Zero-mean prior standard deviations of the distortion terms a board on a small part of the image
# cannot separate from the principal point (p1, p2) or from k1, k2 (k3); see the module docstring.
DISTORTION_SIGMA = {"p1": 1e-3, "p2": 1e-3, "k3": 0.5}
_DROPPABLE = (("p1", "p2", "k3"), ("p1", "p2"), ("k3",))  # distortion terms the auto model may hold at zero


class CalibrationError(ValueError):
    """Calibration cannot proceed; the message names the camera and says what to do."""

    def __init__(self, message: str, *, cameras: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.cameras = tuple(cameras)


@dataclass(frozen=True, eq=False)
class IntrinsicsResult:
    """Intrinsics of one camera and how good they are.

    Attributes
    ----------
    name : str
    size : (int, int)
    K : (3, 3) float ndarray
    dist : (5,) float ndarray
    rms : float
        Reprojection RMS over the kept views (px).
    frames : (V,) int ndarray
        Frames of the kept views.
    per_view_rms : (V,) float ndarray
    rejected : dict
        Frame -> its per-view RMS, for views rejected as outliers.
    rvecs, tvecs : (V, 3) float ndarray
        Board -> camera pose of every kept view (mm).
    std : dict
        Standard deviations: ``fx, fy, cx, cy`` (px) and ``dist`` (5,).
    coverage : float
        Fraction of the image grid cells (8 x 6) that received a corner.
    warnings : tuple of str
    """

    name: str
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    rms: float
    frames: np.ndarray
    per_view_rms: np.ndarray
    rejected: dict
    rvecs: np.ndarray
    tvecs: np.ndarray
    std: dict
    coverage: float
    warnings: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
    covariance: np.ndarray | None = None  # (9, 9) fx, fy, cx, cy, k1..k3; NaN where held fixed
    held: tuple[str, ...] = ()  # distortion terms held at zero, here and in a bundle adjustment
    dropped: tuple[str, ...] = ()  # of those, the ones distortion="auto" found unsupported by the views

    @property
    def params(self) -> np.ndarray:
        """(9,) ``fx, fy, cx, cy, k1, k2, p1, p2, k3``."""
        return np.array([self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *self.dist], dtype=np.float64)

    def camera(self) -> Camera:
        """The camera at the origin (``R = I``, ``t = 0``)."""
        return Camera(self.name, K=self.K, dist=self.dist, R=np.eye(3), t=np.zeros(3), size=self.size)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "size": list(self.size),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "rms": self.rms,
            "views": int(len(self.frames)),
            "frames": self.frames.tolist(),
            "per_view_rms": self.per_view_rms.tolist(),
            "rejected": {str(k): v for k, v in self.rejected.items()},
            "std": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.std.items()},
            "coverage": self.coverage,
            "held_at_zero": list(self.held),
            "dropped_by_model_selection": list(self.dropped),
            "warnings": list(self.warnings),
        }

    def summary(self) -> str:
        s = self.std
        lines = [
            f"{self.name}: {len(self.frames)} views, RMS {self.rms:.3f} px, "
            f"f = ({self.K[0, 0]:.1f} ± {s['fx']:.1f}, {self.K[1, 1]:.1f} ± {s['fy']:.1f}) px, "
            f"c = ({self.K[0, 2]:.1f} ± {s['cx']:.1f}, {self.K[1, 2]:.1f} ± {s['cy']:.1f}) px, "
            f"coverage {100 * self.coverage:.0f}%"
        ]
        if self.dropped:
            lines.append(f"  distortion: {', '.join(self.dropped)} held at 0 (the views do not support them: "
                         "information criterion)")
        if self.rejected:
            lines.append(
                "  rejected outlier views: "
                + ", ".join(f"frame {k} ({v:.2f} px)" for k, v in sorted(self.rejected.items()))
            )
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def coverage_fraction(points: np.ndarray, size: tuple[int, int], *, grid: tuple[int, int] = COVERAGE_GRID) -> float:
    """Fraction of a ``grid`` of image cells that contain at least one of ``points`` ((N, 2) px)."""
    w, h = size
    gx, gy = grid
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if pts.size == 0:
        return 0.0
    ix = np.clip(((pts[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
    iy = np.clip(((pts[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
    occupied = np.zeros((gy, gx), bool)
    occupied[iy, ix] = True
    return float(occupied.mean())


def coverage_image(
    detections: Sequence[Detection], size: tuple[int, int], *, rejected: Sequence[int] = (),
    grid: tuple[int, int] = COVERAGE_GRID, title: str = ""
) -> np.ndarray:
    """Picture of where the corners fell: (H, W, 3) uint8 BGR, image-sized.

    Uncovered grid cells are tinted red; corners are dots (one colour per view,
    rejected views as grey crosses).
    """
    import cv2

    w, h = (int(s) for s in size)
    img = np.full((h, w, 3), 40, np.uint8)
    gx, gy = grid
    pts = np.concatenate([d.corners for d in detections], axis=0) if detections else np.zeros((0, 2))
    ix = np.clip(((pts[:, 0] + 0.5) / w * gx).astype(int), 0, gx - 1)
    iy = np.clip(((pts[:, 1] + 0.5) / h * gy).astype(int), 0, gy - 1)
    occupied = np.zeros((gy, gx), bool)
    occupied[iy, ix] = True
    for j in range(gy):
        for i in range(gx):
            x0, x1 = int(i * w / gx), int((i + 1) * w / gx)
            y0, y1 = int(j * h / gy), int((j + 1) * h / gy)
            if not occupied[j, i]:
                img[y0:y1, x0:x1] = (40, 40, 110)
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (80, 80, 80), 1)
    rej = set(int(r) for r in rejected)
    n = max(len(detections), 1)
    for k, d in enumerate(detections):
        hue = int(170 * k / n)
        color = cv2.cvtColor(np.uint8([[[hue, 220, 255]]]), cv2.COLOR_HSV2BGR)[0, 0].tolist()
        for u, v in d.corners:
            p = (int(round(u)), int(round(v)))
            if d.frame in rej:
                cv2.drawMarker(img, p, (160, 160, 160), cv2.MARKER_CROSS, 6, 1)
            else:
                cv2.circle(img, p, 2, color, -1, lineType=cv2.LINE_AA)
    text = f"{title}  coverage {100 * occupied.mean():.0f}%  views {len(detections) - len(rej)}"
    cv2.putText(img, text.strip(), (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def _object_image_points(detections: Sequence[Detection], board: Board):
    obj = board.object_points()
    objp = [obj[d.ids].astype(np.float32).reshape(-1, 1, 3) for d in detections]
    imgp = [d.corners.astype(np.float32).reshape(-1, 1, 2) for d in detections]
    return objp, imgp


def _initial_K(objp, imgp, size) -> np.ndarray:
    import cv2

    try:
        return cv2.initCameraMatrix2D(objp, imgp, tuple(size))
    except cv2.error:
        w, h = size
        f = float(max(w, h))
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def _check_inputs(board, size, min_views: int, outlier_factor: float) -> tuple[int, int]:
    """ValueError naming the bad parameter of :func:`calibrate_intrinsics`; the size as ints."""
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if len(size) != 2 or min(int(s) for s in size) <= 0:
        raise ValueError(f"size must be (width, height) > 0, got {size!r}")
    if min_views < 3:
        raise ValueError(f"min_views must be >= 3, got {min_views}")
    if outlier_factor <= 1:
        raise ValueError(f"outlier_factor must be > 1, got {outlier_factor}")
    return int(size[0]), int(size[1])


def _usable_views(detections, name: str, min_views: int, max_views: int | None) -> list[Detection]:
    """Views with >= 6 corners, at most ``max_views`` evenly spaced; CalibrationError when too few."""
    dets = [d for d in detections if d is not None]
    for d in dets:
        if not isinstance(d, Detection):
            raise ValueError(f"detections must hold Detection objects, got {type(d).__name__}")
    dets = [d for d in dets if len(d) >= 6]
    if max_views is not None:
        if max_views < min_views:
            raise ValueError(f"max_views must be >= min_views ({min_views}), got {max_views}")
        if len(dets) > max_views:
            pick = np.unique(np.round(np.linspace(0, len(dets) - 1, max_views)).astype(int))
            dets = [dets[i] for i in pick]
    if len(dets) < min_views:
        raise CalibrationError(
            f"camera {name}: only {len(dets)} usable board view(s), need at least {min_views} "
            f"(10-20 recommended): film the board in more positions and tilts in front of {name}",
            cameras=[name],
        )
    return dets


def _solve_rejecting(solve, dets: list[Detection], name: str, *, reject_outliers: bool, min_views: int,
                     outlier_factor: float, outlier_floor_px: float):
    """Solve, drop the views above ``max(outlier_factor * median, outlier_floor_px)``, re-solve
    (never below ``min_views``); returns (kept views, rejected frame -> RMS, the last solution)."""
    kept = list(dets)
    rejected: dict[int, float] = {}
    sol = solve(kept)
    while reject_outliers and len(kept) > min_views:
        per_view = sol[-1]
        med = float(np.median(per_view))
        thr = max(outlier_factor * med, outlier_floor_px)
        bad = np.flatnonzero(per_view > thr)
        bad = bad[np.argsort(-per_view[bad])][: len(kept) - min_views]
        if bad.size == 0:
            break
        for b in bad:
            rejected[kept[b].frame] = float(per_view[b])
        bad_set = set(bad.tolist())
        kept = [d for i, d in enumerate(kept) if i not in bad_set]
        log.debug("camera %s: rejected %d outlier view(s) above %.2f px", name, len(bad), thr)
        sol = solve(kept)
    return kept, rejected, sol


def _warnings(name: str, n_views: int, cov: float, std_in: np.ndarray, f_rel: float) -> list[str]:
    """What a user should know about one camera's intrinsics."""
    warnings = []
    if n_views < WARN_VIEWS:
        warnings.append(
            f"camera {name}: only {n_views} board views; 10-20 views at varied tilts give reliable intrinsics"
        )
    if cov < WARN_COVERAGE:
        warnings.append(
            f"camera {name}: board corners covered only {100 * cov:.0f}% of the image; move the board "
            "into the corners and edges of the view, or the lens distortion there is guessed"
        )
    if np.any(~np.isfinite(std_in[:9])):
        warnings.append(f"camera {name}: parameter uncertainty is undefined (degenerate views?)")
    if np.isfinite(f_rel) and f_rel > 0.01:
        warnings.append(
            f"camera {name}: focal length uncertain to {100 * f_rel:.1f}%; add views with the board tilted "
            "(30-45 degrees) towards the camera"
        )
    return warnings


def calibrate_intrinsics(
    detections: Sequence[Detection],
    board: Board,
    size: tuple[int, int],
    *,
    name: str = "camera",
    fix_aspect_ratio: bool = False,
    fix_k3: bool = False,
    zero_tangent: bool = False,
    reject_outliers: bool = True,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 0.5,
    min_views: int = MIN_VIEWS,
    K_guess: np.ndarray | None = None,
    max_views: int | None = None,
    distortion: str = "prior",
    distortion_sigma: dict | None = None,
) -> IntrinsicsResult:
    """Calibrate one camera's intrinsics from board detections (Zhang's method).

    Parameters
    ----------
    detections : sequence of Detection
        Views of the board (each with ``>= 6`` non-collinear corners).
    board : Chessboard or Charuco
    size : (int, int)
        Image ``(width, height)``.
    name : str
        Camera name (used in messages).
    fix_aspect_ratio : bool
        ``CALIB_FIX_ASPECT_RATIO`` (``fx / fy`` kept at the initial ratio 1). The MAP
        refinement of ``distortion="prior"`` frees ``fx`` and ``fy`` apart, so with this
        option the Zhang solution is kept as with ``"full"``.
    fix_k3, zero_tangent : bool
        Simpler distortion models for few views / mild lenses.
    reject_outliers : bool
        Drop views with a per-view RMS above ``max(outlier_factor * median,
        outlier_floor_px)`` and re-solve (repeatedly, never below ``min_views``).
    min_views : int
        Fewer usable views raise :class:`CalibrationError`.
    K_guess : (3, 3) ndarray, optional
        Initial intrinsics (``CALIB_USE_INTRINSIC_GUESS``).
    max_views : int, optional
        Use at most this many views, evenly spaced over the sequence (Zhang's
        method costs grow with the views; a rig's bundle adjustment uses them all).
    distortion : {"prior", "full", "auto"}
        ``"prior"`` (default): the five coefficients, with a zero-mean Gaussian prior of
        standard deviations ``distortion_sigma`` (maximum a posteriori; module
        docstring). ``"full"``: the five coefficients without a prior (less what
        ``fix_k3`` / ``zero_tangent`` hold). ``"auto"``: also hold ``p1, p2`` and / or
        ``k3`` at zero when the views do not support them (module docstring); the
        result's ``dropped`` names them.
    distortion_sigma : dict, optional
        With ``distortion="prior"``: prior standard deviation per distortion term
        (keys among ``k1, k2, p1, p2, k3``; ``inf`` or absent: no prior on it).
        Default :data:`DISTORTION_SIGMA`.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    CalibrationError
        Too few usable views (the message names the camera and what to do).
    """
    import cv2

    size = _check_inputs(board, size, min_views, outlier_factor)
    if distortion not in DISTORTION_MODES:
        raise ValueError(f"distortion must be one of {DISTORTION_MODES}, got {distortion!r}")
    sigmas = _check_sigma(DISTORTION_SIGMA if distortion_sigma is None else distortion_sigma)
    dets = _usable_views(detections, name, min_views, max_views)
    flags = _cv_flags(fix_aspect_ratio=fix_aspect_ratio, fix_k3=fix_k3, zero_tangent=zero_tangent)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)

    def solve(views: list[Detection]):
        objp, imgp = _object_image_points(views, board)
        K0, fl = _start(K_guess, objp, imgp, size, flags, fix_aspect_ratio=fix_aspect_ratio)
        out = cv2.calibrateCameraExtended(objp, imgp, size, K0, np.zeros(5), flags=fl, criteria=criteria)
        rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = out
        return rms, K, dist.ravel()[:5], rvecs, tvecs, std_in.ravel(), per_view.ravel()

    kept, rejected, (rms, K, dist, rvecs, tvecs, std_in, per_view) = _solve_rejecting(
        solve, dets, name, reject_outliers=reject_outliers, min_views=min_views, outlier_factor=outlier_factor,
        outlier_floor_px=outlier_floor_px)
    fixed = (("k3",) if fix_k3 else ()) + (("p1", "p2") if zero_tangent else ())
    if distortion == "prior" and not fix_aspect_ratio:  # the MAP refinement frees fx and fy apart
        K, dist, rvecs, tvecs, zcov, per_view, rms = _map_refine(kept, board, K, dist, rvecs, tvecs, fixed, sigmas)
        std_in = np.sqrt(np.diag(zcov))
        std_in[[INTRINSIC_NAMES.index(k) for k in fixed]] = 0.0  # held terms: 0, as OpenCV reports them
    else:
        zcov = _zhang_covariance(kept, board, K, dist, rvecs, tvecs, fixed)
    cov = coverage_fraction(np.concatenate([d.corners for d in kept], axis=0), size)
    std = {"fx": float(std_in[0]), "fy": float(std_in[1]), "cx": float(std_in[2]), "cy": float(std_in[3]),
           "dist": np.asarray(std_in[4:9], dtype=np.float64)}
    warnings = _warnings(name, len(kept), cov, std_in, std["fx"] / K[0, 0])
    for w in warnings:
        log.debug(w)  # in the result's warnings / report
    drop = _unsupported(K, dist, zcov, fixed, 2 * sum(len(d) for d in kept)) if distortion == "auto" else ()
    if drop:
        simpler = calibrate_intrinsics(kept, board, size, name=name, fix_aspect_ratio=fix_aspect_ratio,
                                       fix_k3=fix_k3 or "k3" in drop, zero_tangent=zero_tangent or "p1" in drop,
                                       reject_outliers=False, min_views=min_views, K_guess=K_guess, distortion="full")
        return dataclasses.replace(simpler, rejected=rejected, dropped=drop)
    return IntrinsicsResult(
        name=name,
        size=size,
        K=np.asarray(K, dtype=np.float64),
        dist=np.asarray(dist, dtype=np.float64),
        rms=float(rms),
        frames=np.array([d.frame for d in kept], dtype=np.int64),
        per_view_rms=np.asarray(per_view, dtype=np.float64),
        rejected=rejected,
        rvecs=np.asarray(rvecs, dtype=np.float64).reshape(-1, 3),
        tvecs=np.asarray(tvecs, dtype=np.float64).reshape(-1, 3),
        std=std,
        coverage=cov,
        warnings=tuple(warnings),
        covariance=zcov,
        held=fixed,
    )


def _start(K_guess, objp, imgp, size, flags: int, *, fix_aspect_ratio: bool) -> tuple[np.ndarray, int]:
    """The camera matrix OpenCV starts from and the flags that say so: the caller's guess, else the
    identity when the aspect ratio is held (OpenCV's own start), else Zhang's closed form."""
    import cv2

    if K_guess is not None:
        return np.asarray(K_guess, dtype=np.float64).reshape(3, 3).copy(), flags | cv2.CALIB_USE_INTRINSIC_GUESS
    if fix_aspect_ratio:
        return np.eye(3), flags
    return _initial_K(objp, imgp, size), flags | cv2.CALIB_USE_INTRINSIC_GUESS


def _cv_flags(*, fix_aspect_ratio: bool, fix_k3: bool, zero_tangent: bool) -> int:
    """OpenCV's calibration flags for the terms held."""
    import cv2

    flags = 0
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def _check_sigma(sigma) -> np.ndarray:
    """(5,) prior standard deviations of ``k1, k2, p1, p2, k3`` (inf: none) from ``distortion_sigma``."""
    names = INTRINSIC_NAMES[4:]
    if not isinstance(sigma, dict) or set(sigma) - set(names):
        raise ValueError(f"distortion_sigma must be a dict with keys among {names}, got {sigma!r}")
    out = np.array([float(sigma.get(k, np.inf)) for k in names])
    if np.any(np.isnan(out)) or np.any(out <= 0):
        raise ValueError(f"distortion_sigma values must be > 0 (inf: no prior), got {sigma!r}")
    return out


def _one_camera_problem(views, board, K, dist):
    """The bundle adjustment's arrays for one camera at the origin seeing ``views``: observation
    camera and board-pose indices, board points, pixels, and the (1, 9) intrinsics of K and dist."""
    obj = board.object_points()
    oc = np.concatenate([np.zeros(len(d), np.int64) for d in views])
    ob = np.concatenate([np.full(len(d), i) for i, d in enumerate(views)])
    op = np.concatenate([obj[d.ids] for d in views])
    ouv = np.concatenate([d.corners for d in views])
    intr = np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(dist).ravel()[:5]]])
    return oc, ob, op, ouv, intr


def _map_refine(views, board, K, dist, rvecs, tvecs, fixed, sigmas):
    """Maximum-a-posteriori intrinsics of one camera: reprojection errors plus a zero-mean Gaussian prior
    on the distortion terms (standard deviations ``sigmas``), started from the unregularised Zhang solution.

    The prior is weighted by that solution's per-coordinate pixel noise, so the objective is the negative
    log-posterior. Returns K, dist, rvecs, tvecs, the posterior (9, 9) covariance (prior included, NaN
    where held), per-view RMS and RMS (px)."""
    from calib.bundle import bundle_adjust

    oc, ob, op, ouv, intr = _one_camera_problem(views, board, K, dist)
    mean = intr.copy()
    mean[0, 4:] = 0.0
    var = np.concatenate([np.full(4, np.inf), sigmas ** 2])
    prior = np.diag(var)  # infinite variance: no prior row for that intrinsic
    kw = dict(intrinsics=intr, cam_rvec=np.zeros((1, 3)), cam_tvec=np.zeros((1, 3)),
              optimize_intrinsics=True, fixed_intrinsics=tuple(fixed), loss="linear")
    brv = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    btv = np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)
    r0 = bundle_adjust(oc, ob, op, ouv, board_rvec=brv, board_tvec=btv, max_nfev=1, **kw).residuals
    n_par = 9 - len(fixed) + 6 * len(views)
    noise = float(np.sqrt(np.sum(r0 ** 2) / max(r0.size - n_par, 1)))  # px per coordinate
    res = bundle_adjust(oc, ob, op, ouv, board_rvec=brv, board_tvec=btv, prior_cov=prior[None],
                        prior_scale=max(noise, 1e-6), prior_mean=mean, covariance=True, ftol=1e-14, **kw)
    p = res.intrinsics[0]
    K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
    sq = np.sum(res.residuals ** 2, axis=1)
    per_view = np.array([np.sqrt(np.mean(sq[ob == i])) for i in range(len(views))])
    return K, p[4:].copy(), res.board_rvec, res.board_tvec, res.intrinsics_cov[0], per_view, float(np.sqrt(np.mean(sq)))


def _unsupported(K, dist, cov, fixed, n_obs: int) -> tuple[str, ...]:
    """Distortion terms the views do not support (module docstring): the droppable set with the
    largest BIC margin ``|S| ln N - theta_S^T Cov_S^-1 theta_S`` when it is positive, else ()."""
    theta = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(dist).ravel()[:5]])
    best, margin = (), 0.0
    for S in _DROPPABLE:
        if set(S) & set(fixed):
            continue
        idx = [INTRINSIC_NAMES.index(k) for k in S]
        C = cov[np.ix_(idx, idx)]
        if not np.all(np.isfinite(C)):
            continue
        try:
            wald = float(theta[idx] @ np.linalg.solve(C, theta[idx]))
        except np.linalg.LinAlgError:
            continue
        m = len(S) * np.log(n_obs) - wald
        if m > margin:
            best, margin = S, m
    return best


def _zhang_covariance(views, board, K, dist, rvecs, tvecs, fixed) -> np.ndarray:
    """(9, 9) covariance of the intrinsics of a Zhang solve, with the full correlations.

    OpenCV reports only standard deviations; the bundle adjustment's Jacobian at the
    Zhang solution (one camera at the origin, the views' board poses free) gives the
    whole matrix, so a prior built from it keeps correlated terms (k1, k2, k3; fx, fy)
    together.
    """
    from calib.bundle import bundle_adjust

    oc, ob, op, ouv, intr = _one_camera_problem(views, board, K, dist)
    res = bundle_adjust(oc, ob, op, ouv, intrinsics=intr, cam_rvec=np.zeros((1, 3)), cam_tvec=np.zeros((1, 3)),
                        board_rvec=np.asarray(rvecs, dtype=np.float64).reshape(-1, 3),
                        board_tvec=np.asarray(tvecs, dtype=np.float64).reshape(-1, 3),
                        optimize_intrinsics=True, fixed_intrinsics=tuple(fixed), loss="linear", max_nfev=1,
                        covariance=True)
    return res.intrinsics_cov[0]
