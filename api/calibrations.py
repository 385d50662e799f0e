"""Calibrations under ``DATA/calibrations/<id>.json`` and the job work that makes one from a take.

Two ways to get one:

* ``source="take"``: the calibration stored in the take (simulated takes and
  imported takes carry one) is copied at once;
* ``source="board"``: a background job (kind ``calibrate``) detects the board in every
  frame of the take and runs :func:`calib.rig.calibrate_rig` on all detections, with the
  defaults of ``stage calibrate``: the rig selects the views (every frame set seen by two or
  more cameras links them), intrinsics held by a prior from each camera's own calibration,
  5-fold held-out error in the report. Cameras whose board is found only in the flipped
  image are found by :func:`calib.take_detect.detect_take` (as ``stage calibrate`` does) and the
  rig decides whether each mirrors (``mirror = true`` in the calibration) or sees the board
  from behind; ``parameters.mirror`` forces it per camera.

Downloads convert with :func:`calib.formats.write_calibration` (JSON, aniposelib
TOML, OpenCV YAML).
"""

from __future__ import annotations

import json
import logging
import threading
import uuid
from pathlib import Path
from typing import Annotated, Any, Callable, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from api.errors import NotFoundError, UnavailableError
from api.jobs.runner import takes_warn
from api.paths import JOB_ID, check_id, confined_entries, inside
from calib.fileio import atomic_write, strict_json

__all__ = ["CalibrationLibrary", "CalibrateParams", "calibrate_take", "calibrate_take_work", "FORMATS", "MEDIA"]

log = logging.getLogger(__name__)

FORMATS = ("json", "toml", "yaml")
MIRROR_SPELLING = 'parameters.mirror.{camera} = "{value}"'  # the request field, in messages of calib.mirror
MEDIA = {"json": "application/json", "toml": "application/toml", "yaml": "application/x-yaml"}


class CalibrationLibrary:
    """Calibration files of one data root."""

    def __init__(self, calibrations_dir: Path) -> None:
        self.dir = Path(calibrations_dir).resolve()

    def _path(self, cal_id: str) -> Path:
        check_id(cal_id, pattern=JOB_ID, name="calibration id")
        return inside(self.dir, f"{cal_id}.json")

    def exists(self, cal_id: str) -> bool:
        return self._path(cal_id).is_file()

    def list(self) -> list[dict[str, Any]]:
        out = []
        for p in confined_entries(self.dir, "*.json", root=self.dir):
            try:
                check_id(p.stem, pattern=JOB_ID)
                data = json.loads(p.read_text(encoding="utf-8"))
                created = p.stat().st_mtime
            except (ValueError, OSError):
                continue
            if not isinstance(data, dict):
                continue
            meta = data.get("meta", {}) if isinstance(data.get("meta"), dict) else {}
            cams = data.get("cameras", []) if isinstance(data.get("cameras"), list) else []
            out.append({"id": p.stem, "cameras": [c.get("name") for c in cams if isinstance(c, dict)],
                        "units": data.get("units"), "take": meta.get("take"), "source": meta.get("source"),
                        "created": created})
        out.sort(key=lambda e: e["created"])
        return out

    def load(self, cal_id: str):
        from calib.calibration import Calibration

        p = self._path(cal_id)
        if not p.is_file():
            raise NotFoundError(f"no calibration {cal_id!r}")
        return Calibration.from_dict(json.loads(p.read_text(encoding="utf-8")))

    def save(self, calib, cal_id: str | None = None) -> str:
        cid = cal_id or uuid.uuid4().hex
        p = self._path(cid)
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, json.dumps(calib.to_dict(), indent=1))
        return cid

    def delete(self, cal_id: str) -> None:
        p = self._path(cal_id)
        if not p.is_file():
            raise NotFoundError(f"no calibration {cal_id!r}")
        p.unlink()

    def export(self, cal_id: str, fmt: str) -> bytes:
        """The calibration as ``fmt`` (json | toml | yaml) bytes."""
        if fmt not in FORMATS:
            raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
        calib = self.load(cal_id)
        if fmt == "json":
            return json.dumps(calib.to_dict(), indent=1).encode()
        from calib.formats import write_calibration

        tmp = self.dir / f".export-{uuid.uuid4().hex}.{fmt}"
        try:
            write_calibration(calib, tmp, format=fmt)
            return tmp.read_bytes()
        finally:
            tmp.unlink(missing_ok=True)

    def from_take(self, take_path: Path, take_id: str) -> str:
        """Copy the calibration stored in a take; return its new id."""
        from api.library import _open_reader

        with _open_reader(take_path) as r:
            cal = getattr(r, "calibration", None)
            cal = cal() if callable(cal) else cal
        if cal is None:
            raise NotFoundError(f"take {take_id!r} has no calibration stored; calibrate it from board views")
        cal = type(cal)(cameras=cal.cameras, units=cal.units, meta={**cal.meta, "take": take_id, "source": "take"})
        return self.save(cal)


class CalibrateParams(BaseModel):
    """Options of a calibration from board views (see ``stage calibrate --help``)."""

    model_config = ConfigDict(extra="forbid")
    board: dict[str, Any] = Field(description="board definition as in BOARD.toml, e.g. "
                                  "{type: chessboard, corners: [9, 6], square_mm: 25}")
    step: Annotated[int, Field(ge=1, le=1000)] = 1
    min_change: Annotated[float, Field(ge=0, le=1)] = 0.02
    world: Literal["board", "camera"] = "board"
    world_frame: Annotated[int, Field(ge=0)] | None = None
    fix_k3: bool = False
    distortion: Literal["prior", "full", "auto"] = Field("prior", description="per camera: prior fits all five "
                                                "distortion coefficients with a weak zero-mean prior on p1, p2 and k3; "
                                                "full fits them without one; auto holds p1, p2 and/or k3 at 0 where its views do "
                                                "not support them (as stage calibrate --distortion)")
    intrinsics: Literal["prior", "fixed", "free"] = "prior"
    holdout: Annotated[int, Field(ge=0, le=20)] = 5
    mirror: dict[str, Literal["auto", "true", "false"]] = Field(
        default_factory=dict, description="per camera: whether it delivers mirrored images (auto: decided from where "
        "the board is found, as stage calibrate --mirror CAM=auto|true|false); unnamed cameras: auto")

    @field_validator("holdout")
    @classmethod
    def _holdout(cls, v: int) -> int:
        if v == 1:
            raise ValueError("holdout must be 0 (none) or >= 2 folds")
        return v

    @field_validator("board")
    @classmethod
    def _board(cls, v: dict) -> dict:
        from calib.boards import parse_board

        parse_board(v)  # BoardError (a ValueError) names the bad key
        return v


def calibrate_take(take: Path, *, params: CalibrateParams, progress: Callable[[str, int, int], None] | None = None,
                   cancel: threading.Event | None = None, warn: Callable[[str], None] | None = None):
    """Detect the board in every camera's frames of ``take`` and calibrate the rig with
    :func:`calib.rig.calibrate_rig`; returns its ``RigCalibration``.

    Every detection goes to :func:`calib.rig.calibrate_rig`, which selects the views for the rig
    (thinning each camera alone would drop the frames that link the cameras).

    Parameters
    ----------
    take : Path
        The take (``.h5``) of the board waved through the rig.
    params : CalibrateParams
    progress : callable, optional
        ``progress(step, done, total)``: ``detect`` per frame set, then ``calibrate``.
    cancel : threading.Event, optional
        Set it to stop (between frame sets).
    warn : callable, optional
        ``warn(message)`` as each of the calibration's warnings is said (``calibrate_rig(warn=)``): a job keeps those
        said before the calibration fails.

    Raises
    ------
    ValueError
        Naming ``warn`` when it is not callable.
    InterruptedError
        When ``cancel`` is set.
    calib.intrinsics.CalibrationError
        Too few views / cameras that cannot be connected (a ValueError).
    """
    from calib.boards import parse_board
    from calib.rig import calibrate_rig
    from calib.take_detect import detect_take

    if warn is not None and not callable(warn):
        raise ValueError(f"warn must be a callable taking a message, or None, got {type(warn).__name__}")

    def on_set(done: int, total: int) -> None:
        if cancel is not None and cancel.is_set():
            raise InterruptedError("calibration cancelled")
        if progress is not None:
            progress("detect", done, total)

    board = parse_board(params.board)
    if cancel is not None and cancel.is_set():
        raise InterruptedError("calibration cancelled")
    detections, sizes, cams, flipped, notes = detect_take(take, board, step=params.step, mirror=params.mirror,
                                                          on_set=on_set, spelling=MIRROR_SPELLING)
    for line in dict.fromkeys(notes):
        log.info("calibrate %s: %s", take.name, line)
    result = calibrate_rig(detections, sizes, board, cameras=cams, world=params.world, world_frame=params.world_frame,
                           intrinsics=params.intrinsics, fix_k3=params.fix_k3, min_change=params.min_change,
                           distortion=params.distortion,
                           holdout_folds=params.holdout, flipped=flipped, warn=warn)
    if progress is not None:
        progress("calibrate", 1, 1)
    return result


def _find_rig_calibrator() -> Callable[..., Any]:
    """The calibrate-a-take function (needs ``calib.rig`` and ``calib.detect``)."""
    try:
        import calib.detect  # noqa: F401
        import calib.rig  # noqa: F401
    except ImportError as exc:
        raise UnavailableError(f"calibrating from board views is not available ({exc})") from None
    return calibrate_take


def calibrate_take_work(calibrations_dir: Path) -> Callable[..., Any]:
    """Job work for kind ``calibrate``: board views of the take -> ``DATA/calibrations/<job>.json``; the job's
    ``warn`` goes to the calibrator (when it takes one), so a calibration that fails keeps the warnings said before."""

    def work(take: Path, out: Path, *, params: dict, progress: Callable[[str, int, int], None],
             cancel: threading.Event, job_id: str, take_id: str, warn: Callable[[str], None] | None = None,
             **_: Any) -> dict:
        fn = _find_rig_calibrator()
        hook = {"warn": warn} if warn is not None and takes_warn(fn) else {}  # (kept as said: a failure keeps them)
        result = fn(take, params=CalibrateParams.model_validate(params), progress=progress, cancel=cancel, **hook)
        calib = getattr(result, "calibration", result)
        if not hasattr(calib, "to_dict"):
            raise ValueError("the calibrator returned no calibration")
        calib = type(calib)(cameras=calib.cameras, units=calib.units,
                            meta={**calib.meta, "take": take_id, "source": "board"})
        CalibrationLibrary(calibrations_dir).save(calib, job_id)
        if hasattr(result, "to_dict"):  # strict JSON: a figure with nothing to measure (a camera without
            # held-out views) is null, not NaN, which browsers' JSON.parse and other tools refuse
            (out / "report.json").write_text(strict_json(result.to_dict()), encoding="utf-8")
        said = list(dict.fromkeys(str(w) for w in getattr(result, "warnings", None) or ()))  # (the job's record's too)
        return {"calibration": job_id, "cameras": list(calib.names), "links": {"json": f"/calibrations/{job_id}.json"},
                "warnings": said}

    return work
