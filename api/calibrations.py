"""Calibrations under ``DATA/calibrations/<id>.json`` and the job work that makes one from a take.

Two ways to get one:

* ``source="take"``: the calibration stored in the take (simulated takes and
  imported takes carry one) is copied at once;
* ``source="board"``: a background job (kind ``calibrate``) runs helper D's rig
  calibration on the board views of the take.

Downloads convert with :func:`calib.formats.write_calibration` (JSON, aniposelib
TOML, OpenCV YAML).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import uuid
from pathlib import Path
from typing import Any, Callable

from api.errors import NotFoundError, UnavailableError
from api.paths import JOB_ID, check_id, inside

__all__ = ["CalibrationLibrary", "calibrate_take_work", "FORMATS", "MEDIA"]

log = logging.getLogger(__name__)

FORMATS = ("json", "toml", "yaml")
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
        if self.dir.is_dir():
            for p in sorted(self.dir.glob("*.json"), key=lambda p: p.stat().st_mtime):
                try:
                    check_id(p.stem, pattern=JOB_ID)
                    data = json.loads(p.read_text(encoding="utf-8"))
                except (ValueError, OSError):
                    continue
                meta = data.get("meta", {}) if isinstance(data, dict) else {}
                out.append({"id": p.stem, "cameras": [c.get("name") for c in data.get("cameras", [])],
                            "units": data.get("units"), "take": meta.get("take"), "source": meta.get("source"),
                            "created": p.stat().st_mtime})
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
        tmp = p.with_name(f".{p.name}.{uuid.uuid4().hex}.part")
        tmp.write_text(json.dumps(calib.to_dict(), indent=1), encoding="utf-8")
        os.replace(tmp, p)
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


def _find_rig_calibrator() -> Callable[..., Any]:
    """Helper D's calibrate-a-take entry point (names tried in order)."""
    import importlib

    for modname, fname in (("calib.take", "calibrate_take"), ("calib.rig", "calibrate_take"),
                           ("calib.pipeline", "calibrate_take"), ("calib.extrinsics", "calibrate_take"),
                           ("calib", "calibrate_take")):
        try:
            fn = getattr(importlib.import_module(modname), fname)
        except (ImportError, AttributeError):
            continue
        if callable(fn):
            return fn
    raise UnavailableError("calibrating from board views needs helper D's calib.calibrate_take (not available)")


def calibrate_take_work(calibrations_dir: Path) -> Callable[..., Any]:
    """Job work for kind ``calibrate``: board views of the take -> ``DATA/calibrations/<job>.json``."""

    def work(take: Path, out: Path, *, params: dict, progress: Callable[[str, int, int], None],
             cancel: threading.Event, job_id: str, take_id: str, **_: Any) -> dict:
        import inspect

        fn = _find_rig_calibrator()
        sig = inspect.signature(fn).parameters
        kw = {k: v for k, v in params.items() if k in sig}
        if "progress" in sig:
            kw["progress"] = progress
        if "cancel" in sig:
            kw["cancel"] = cancel
        result = fn(take, **kw)
        calib = getattr(result, "calibration", result)
        if not hasattr(calib, "to_dict"):
            raise ValueError("the calibrator returned no calibration")
        calib = type(calib)(cameras=calib.cameras, units=calib.units,
                            meta={**calib.meta, "take": take_id, "source": "board"})
        CalibrationLibrary(calibrations_dir).save(calib, job_id)
        return {"calibration": job_id, "links": {"json": f"/calibrations/{job_id}.json"}}

    return work
