"""Rig files: TOML, validated with pydantic.

A rig file names the cameras (each with a driver and its settings), the capture
volume and the backdrop::

    name = "lab"
    fps = 30

    support_plane = [0, 0, 1, 0]  # optional: the plane the subject stands on, a x + b y + c z + d >= 0 kept

    [volume]            # millimetres, world frame of the calibration
    center = [0, 0, 375]
    size = [750, 750, 750]

    [backdrop]
    key_mode = "chroma"   # chroma | luma | plate

    [[cameras]]
    id = "cam0"
    driver = "opencv"
    device = "/dev/video0"
    width = 640
    height = 480

Unknown keys and bad values raise :class:`RigError` naming the key.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

__all__ = [
    "RigError",
    "check_plane",
    "Volume",
    "Backdrop",
    "FakeCameraConfig",
    "OpenCVCameraConfig",
    "DepthAICameraConfig",
    "CameraConfig",
    "Simulation",
    "Rig",
    "load_rig",
    "parse_rig",
]


class RigError(ValueError):
    """A rig file that cannot be used; the message names the key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Volume(_Strict):
    """Axis-aligned capture volume in world units (mm)."""

    center: tuple[float, float, float] = (0.0, 0.0, 375.0)
    size: tuple[float, float, float] = (750.0, 750.0, 750.0)

    @model_validator(mode="after")
    def _positive(self) -> "Volume":
        if min(self.size) <= 0:
            raise ValueError("volume.size must be positive in every axis")
        return self

    @property
    def bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        lo = tuple(c - s / 2 for c, s in zip(self.center, self.size))
        hi = tuple(c + s / 2 for c, s in zip(self.center, self.size))
        return lo, hi  # type: ignore[return-value]


class Backdrop(_Strict):
    key_mode: Literal["chroma", "luma", "plate"] = "chroma"
    color: Literal["green", "blue", "black", "white"] = "green"


class _CameraBase(_Strict):
    id: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")]
    width: Annotated[int, Field(gt=0, le=16384)] = 640
    height: Annotated[int, Field(gt=0, le=16384)] = 480
    fps: Annotated[float, Field(gt=0, le=1000)] | None = None
    store: Literal["raw", "jpeg"] = "raw"
    # the camera delivers mirrored images (a webcam's mirror mode): frames are flipped back at capture
    mirror: bool = False


class FakeCameraConfig(_CameraBase):
    """A camera of the simulated rig (``fake_cameras``)."""

    driver: Literal["fake"]
    index: Annotated[int, Field(ge=0)] = 0
    clock_offset_ms: float = 0.0
    jitter_ms: Annotated[float, Field(ge=0)] = 0.0
    drop_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    disconnect_after: Annotated[int, Field(ge=0)] | None = None
    depth: bool = False
    # the simulated webcam's mirror mode: it delivers its images flipped left-right (``mirror = true``
    # tells the stage so, and capture flips them back)
    mirror_mode: bool = False


class OpenCVCameraConfig(_CameraBase):
    """A ``cv2.VideoCapture`` source: device index, ``/dev/video*`` path, video file or image sequence."""

    driver: Literal["opencv"]
    device: int | str = 0
    exposure: float | None = None  # manual exposure in milliseconds; None = auto
    mjpg: bool = True
    loop: bool = False


class DepthAICameraConfig(_CameraBase):
    """A Luxonis OAK camera through depthai v3."""

    driver: Literal["depthai"]
    device: str | None = None  # device id (MxId) or IP; None = first available
    depth: bool = True
    socket: Literal["CAM_A", "CAM_B", "CAM_C"] = "CAM_A"


CameraConfig = Annotated[
    Union[FakeCameraConfig, OpenCVCameraConfig, DepthAICameraConfig], Field(discriminator="driver")
]


class Simulation(_Strict):
    """What the simulated rig films (used by ``driver = "fake"`` cameras)."""

    subject: Literal["starfish", "quadruped", "biped", "tailed_quadruped", "board-chessboard", "board-charuco", "empty"] = "starfish"
    n_cameras: Annotated[int, Field(ge=4, le=24)] = 12
    frames: Annotated[int, Field(ge=1)] = 30
    seed: int = 0
    noise: Annotated[float, Field(ge=0)] = 2.0


class Rig(_Strict):
    name: str = "rig"
    fps: Annotated[float, Field(gt=0, le=1000)] = 30.0
    sync_tolerance_ms: Annotated[float, Field(gt=0)] | None = None
    volume: Volume = Volume()
    support_plane: tuple[float, float, float, float] | None = None
    backdrop: Backdrop = Backdrop()
    simulation: Simulation | None = None
    cameras: list[CameraConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check(self) -> "Rig":
        ids = [c.id for c in self.cameras]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"cameras: duplicate camera ids {dup}")
        if not self.cameras:
            raise ValueError("cameras: a rig needs at least one camera")
        if self.support_plane is not None:
            check_plane(self.support_plane)  # the one rule for planes: finite, non-zero normal
        if any(c.driver == "fake" for c in self.cameras) and self.simulation is None:
            raise ValueError("simulation: fake cameras need a [simulation] table")
        return self

    @property
    def tolerance_ns(self) -> int:
        """Frame-set grouping tolerance: the configured one, else half a frame period."""
        if self.sync_tolerance_ms is not None:
            return int(self.sync_tolerance_ms * 1e6)
        return int(0.5e9 / self.fps)


_DRIVERS = {"fake", "opencv", "depthai"}


def check_plane(plane: Any, name: str = "support_plane") -> np.ndarray:
    """Validate a plane ``(a, b, c, d)`` (points with ``a x + b y + c z + d >= 0`` are above).

    Returns
    -------
    (4,) float ndarray
        The plane scaled so that ``(a, b, c)`` is a unit normal (``d`` is then the signed
        distance of the origin).
    """
    try:
        p = np.asarray(plane, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be four numbers (a, b, c, d)") from None
    if p.shape != (4,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be four finite numbers (a, b, c, d), got {plane!r}")
    n = float(np.linalg.norm(p[:3]))
    if n < 1e-12:
        raise ValueError(f"{name}: the normal (a, b, c) must not be zero")
    return p / n


def _format_errors(exc: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid rig file"]
    for err in exc.errors():
        parts = list(err["loc"])
        # drop the discriminator tag pydantic inserts after a camera's list index
        parts = [p for i, p in enumerate(parts) if not (i > 0 and isinstance(parts[i - 1], int) and p in _DRIVERS)]
        loc = ".".join(str(p) for p in parts)
        if err["type"] == "extra_forbidden":
            lines.append(f"  unknown key {loc!r}")
        else:
            lines.append(f"  {loc or '(top level)'}: {err['msg']}")
    return "\n".join(lines)


def parse_rig(data: dict, *, source: str = "rig") -> Rig:
    """Validate a rig dictionary (as read from TOML)."""
    try:
        return Rig.model_validate(data)
    except ValidationError as exc:
        raise RigError(_format_errors(exc, source)) from None


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig TOML file."""
    p = Path(path)
    if not p.is_file():
        raise RigError(f"{p}: rig file not found")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RigError(f"{p}: not valid TOML: {exc}") from None
    return parse_rig(data, source=str(p))
