"""Calibrate a whole rig from board detections: intrinsics per camera, then all together.

This is the entry point the CLI and the demo use::

    result = calibrate_rig(detections, sizes, board)
    result.calibration          # calib.Calibration, mm, world = a board pose (z up)
    print(result.report())

Detection (from images, takes or videos) is the caller's business (see
:mod:`calib.detect`); this module only takes arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from calib.boards import Board, Charuco, Chessboard
from calib.calibration import Calibration
from calib.detect import Detection
from calib.extrinsics import ExtrinsicsResult, calibrate_extrinsics
from calib.intrinsics import CalibrationError, IntrinsicsResult, calibrate_intrinsics

__all__ = ["RigCalibration", "calibrate_rig"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """Result of :func:`calibrate_rig`."""

    calibration: Calibration
    intrinsics: dict  # name -> IntrinsicsResult
    extrinsics: ExtrinsicsResult | None

    @property
    def warnings(self) -> list[str]:
        w = [x for r in self.intrinsics.values() for x in r.warnings]
        if self.extrinsics is not None:
            w += list(self.extrinsics.warnings)
        return w

    def report(self) -> str:
        lines = ["intrinsics (per camera, Zhang):"]
        lines += ["  " + r.summary().replace("\n", "\n  ") for r in self.intrinsics.values()]
        if self.extrinsics is not None:
            lines.append("extrinsics (bundle adjustment of all cameras):")
            lines.append("  " + self.extrinsics.report().replace("\n", "\n  "))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "intrinsics": {k: v.to_dict() for k, v in self.intrinsics.items()},
            "extrinsics": self.extrinsics.to_dict() if self.extrinsics is not None else None,
        }


def calibrate_rig(
    detections: Mapping[str, Sequence[Detection]],
    sizes: Mapping[str, tuple[int, int]],
    board: Board,
    *,
    cameras: Sequence[str] | None = None,
    world: str = "board",
    world_frame: int | None = None,
    optimize_intrinsics: bool = True,
    fix_k3: bool = False,
    reject_outliers: bool = True,
    min_views: int = 4,
    solver: str = "lm",
    max_intrinsic_views: int | None = 40,
) -> RigCalibration:
    """Intrinsics of every camera (:func:`calib.intrinsics.calibrate_intrinsics`), then
    one bundle adjustment of the rig (:func:`calib.extrinsics.calibrate_extrinsics`).

    Parameters
    ----------
    detections : mapping str -> sequence of Detection
        Per camera; equal ``frame`` numbers mean the same moment.
    sizes : mapping str -> (int, int)
        Image ``(width, height)`` per camera.
    board : Chessboard or Charuco
    cameras : sequence of str, optional
        Rig order (default: the order of ``sizes``).
    world, world_frame, optimize_intrinsics, solver
        See :func:`calib.extrinsics.calibrate_extrinsics`.
    fix_k3, reject_outliers, min_views
        See :func:`calib.intrinsics.calibrate_intrinsics`.
    max_intrinsic_views : int or None
        Views per camera for the initial per-camera intrinsics (evenly spaced);
        the bundle adjustment then refines them with every view.

    Returns
    -------
    RigCalibration
        With a single camera only the intrinsics (camera at the origin).

    Raises
    ------
    CalibrationError
        Naming every camera that has too few views or cannot be connected, with
        what to do. Nothing is written anywhere.
    """
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if not isinstance(detections, Mapping) or not isinstance(sizes, Mapping):
        raise ValueError("detections and sizes must be mappings keyed by camera name")
    names = list(cameras) if cameras is not None else list(sizes)
    if not names:
        raise ValueError("cameras: no cameras to calibrate")
    missing = [n for n in names if n not in sizes]
    if missing:
        raise ValueError(f"sizes: no image size for camera(s) {missing}")
    intr: dict[str, IntrinsicsResult] = {}
    problems: list[str] = []
    bad: list[str] = []
    for n in names:
        dets = [d for d in detections.get(n, ()) if d is not None]
        try:
            intr[n] = calibrate_intrinsics(dets, board, tuple(sizes[n]), name=n, fix_k3=fix_k3,
                                           reject_outliers=reject_outliers, min_views=min_views,
                                           max_views=max_intrinsic_views)
        except CalibrationError as exc:
            if not dets:
                problems.append(
                    f"camera {n}: the board was never detected; check that {n} sees the board and that the board "
                    f"file matches the print (corners = INNER corners; ChArUco squares, dictionary, legacy flag)"
                )
            else:
                problems.append(str(exc))
            bad.append(n)
    if problems:
        raise CalibrationError("; ".join(problems), cameras=bad)
    if len(names) == 1:
        cam = intr[names[0]].camera()
        return RigCalibration(Calibration((cam,), units="mm", meta={"method": "intrinsics only"}), intr, None)
    # rejected outlier views are left out of the bundle adjustment as well
    kept = {}
    for n in names:
        rej = set(intr[n].rejected)
        kept[n] = [d for d in detections.get(n, ()) if d is not None and d.frame not in rej]
    ext = calibrate_extrinsics(
        kept, [intr[n].camera() for n in names], board, world=world, world_frame=world_frame,
        optimize_intrinsics=optimize_intrinsics, solver=solver,
        fixed_intrinsics=("k3",) if fix_k3 else (),  # what the intrinsics held, the bundle keeps
    )
    meta = dict(ext.calibration.meta)
    meta["per_camera_rms_px"] = dict(ext.per_camera_rms)
    meta["board_geometry_error_mm"] = {k: v for k, v in ext.geometry.items() if np.isfinite(v)}
    calib = Calibration(ext.calibration.cameras, units="mm", meta=meta)
    return RigCalibration(calib, intr, ext)
