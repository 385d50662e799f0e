"""A rig's calibration: an ordered set of :class:`~calib.camera.Camera` objects."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from calib.camera import Camera

__all__ = ["Calibration"]


@dataclass(frozen=True, eq=False)
class Calibration:
    """Cameras of one rig in a common world frame.

    Parameters
    ----------
    cameras : tuple of Camera
        In rig order; names must be unique.
    units : str
        Unit of the world frame and of every ``t`` ("mm" for our rigs).
    meta : dict
        Free-form provenance (method, errors, board, date...), JSON-serializable.
    """

    cameras: tuple[Camera, ...]
    units: str = "mm"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if not cams:
            raise ValueError("cameras must not be empty")
        for c in cams:
            if not isinstance(c, Camera):
                raise ValueError(f"cameras must hold Camera objects, got {type(c).__name__}")
        names = [c.name for c in cams]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"cameras: duplicate camera names {sorted(dup)}")
        object.__setattr__(self, "cameras", cams)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for c in self.cameras:
                if c.name == key:
                    return c
            raise KeyError(f"no camera named {key!r} (cameras: {', '.join(self.names)})")
        return self.cameras[key]

    def centers(self) -> np.ndarray:
        """(C, 3) camera centres."""
        return np.stack([c.center for c in self.cameras])

    def reprojection_error_px(self) -> dict[str, float]:
        """What the calibration says of its own accuracy: each camera's reprojection error, pixels.

        0 for every camera of a calibration that holds the true cameras (``meta["exact"]``, a
        simulator's); else, per camera, the RMS error on the board frames held out of the fit
        (``meta["held_out_rms_px"]``, :func:`calib.rig.calibrate_rig`), on all frames
        (``all_frames_rms_px``) or on the frames fitted (``per_camera_rms_px``), else the
        camera's own ``meta["error"]`` (caliscope's RMS, :func:`calib.formats.read_caliscope_toml`),
        the first one recorded. Cameras it records nothing of are left out (``{}`` for most
        imported calibrations).
        """
        if self.meta.get("exact") is True:
            return {n: 0.0 for n in self.names}
        tables = [{c.name: c.meta.get("error") for c in self.cameras}]
        tables += [self.meta.get(k) for k in ("per_camera_rms_px", "all_frames_rms_px", "held_out_rms_px")]
        out: dict[str, float] = {}
        for table in tables:  # the last one recorded wins
            if isinstance(table, dict):
                out.update({n: float(v) for n, v in table.items() if n in self.names and _pixels(v)})
        return {n: out[n] for n in self.names if n in out}

    def to_dict(self) -> dict:
        return {
            "format": "capture-stage/calibration@1",
            "units": self.units,
            "cameras": [c.to_dict() for c in self.cameras],
            "meta": dict(self.meta),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Calibration":
        if not isinstance(data, dict) or "cameras" not in data:
            raise ValueError("calibration dictionary needs a 'cameras' list")
        unknown = sorted(set(data) - {"format", "units", "cameras", "meta"})
        if unknown:
            raise ValueError(f"calibration: unknown keys {unknown} (known: format, units, cameras, meta)")
        return cls(
            cameras=tuple(Camera.from_dict(c) for c in data["cameras"]),
            units=str(data.get("units", "mm")),
            meta=dict(data.get("meta", {})),
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return self.units == other.units and self.cameras == other.cameras


def _pixels(v) -> bool:
    """Whether ``v`` is a finite, non-negative number (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v)) and v >= 0
