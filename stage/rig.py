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
    layers = ["volume"]   # optional: volume, graphcut (docs/keying.md)

    [[cameras]]
    id = "cam0"
    driver = "opencv"
    device = "/dev/video0"
    width = 640
    height = 480

Unknown keys and bad values raise :class:`RigError` naming the key.

Every camera entry is validated against the config model of its ``driver``: each driver declares
its model (a subclass of :class:`CameraConfig`) and registers it with the driver
(:func:`stage.drivers.registry.register_driver`, which calls :func:`register_camera_config`). A
driver may also own a top-level table of the rig file (the simulator's ``[simulation]``), required
when one of its cameras is in the rig. This module knows no driver: ``opencv`` and ``depthai``
register when :mod:`stage.drivers` is imported, others when their package is (``fake`` with
:mod:`fake_cameras`); a camera of a driver not registered is a clear error naming the known ones.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, ValidationError, field_validator, model_validator

__all__ = [
    "RigError",
    "check_plane",
    "Volume",
    "Backdrop",
    "CameraConfig",
    "register_camera_config",
    "registered_camera_configs",
    "camera_config",
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
    """How the stage's silhouettes are keyed (docs/keying.md).

    ``layers`` combine with any mode: ``volume`` (pixels whose rays miss the capture volume
    are background), ``graphcut`` (a per-camera graph cut seeded by the keyer's sure
    background and a first hull's projection: walls, lights, people outside the volume drop
    out where the backdrop does not fill the view).
    """

    key_mode: Literal["chroma", "luma", "plate"] = "chroma"
    color: Literal["green", "blue", "black", "white"] = "green"
    layers: tuple[Literal["volume", "graphcut"], ...] | None = None


class CameraConfig(_Strict):
    """The settings every camera of a rig file has; a driver's config model subclasses it with its own
    keys and a ``driver: Literal["name"]`` field."""

    id: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")]
    driver: str
    width: Annotated[int, Field(gt=0, le=16384)] = 640
    height: Annotated[int, Field(gt=0, le=16384)] = 480
    fps: Annotated[float, Field(gt=0, le=1000)] | None = None
    store: Literal["raw", "jpeg"] = "raw"
    # the camera delivers mirrored images (a webcam's mirror mode): frames are flipped back at capture
    mirror: bool = False


#: driver name -> its camera config model, and the rig-file table it owns (name, model) or None
_CAMERA_CONFIGS: dict[str, tuple[type[CameraConfig], tuple[str, type[BaseModel]] | None]] = {}


def register_camera_config(driver: str, model: type[CameraConfig], *,
                           table: tuple[str, type[BaseModel]] | None = None) -> None:
    """Validate rig cameras with ``driver = driver`` against ``model``.

    Parameters
    ----------
    driver : str
        The ``driver`` value of a rig camera entry.
    model : type
        A subclass of :class:`CameraConfig`.
    table : (str, type), optional
        A top-level table of the rig file this driver owns and its pydantic model (the
        simulator's ``("simulation", Simulation)``); required when the rig has a camera of
        this driver, read with :meth:`Rig.table`.
    """
    if not isinstance(driver, str) or not driver:
        raise ValueError(f"driver must be a non-empty string, got {driver!r}")
    if not (isinstance(model, type) and issubclass(model, CameraConfig)):
        raise ValueError(f"model must be a subclass of stage.rig.CameraConfig, got {model!r}")
    if table is not None:
        name, table_model = table
        if not isinstance(name, str) or name in Rig.model_fields or not (
                isinstance(table_model, type) and issubclass(table_model, BaseModel)):
            raise ValueError(f"table must be (a new top-level key, a pydantic model), got {table!r}")
    _CAMERA_CONFIGS[driver] = (model, table)


def registered_camera_configs() -> list[str]:
    """The drivers whose cameras a rig file may hold now."""
    return sorted(_CAMERA_CONFIGS)


def camera_config(data: Any) -> CameraConfig:
    """One rig camera entry validated against the config model of its ``driver``.

    Raises
    ------
    ValueError
        No registered driver of that name (the message names the known ones).
    pydantic.ValidationError
        The entry does not fit the driver's model.
    """
    if isinstance(data, CameraConfig):
        return data
    driver = data.get("driver") if isinstance(data, dict) else None
    if driver not in _CAMERA_CONFIGS:
        hint = " (the simulator's driver registers itself when fake_cameras is imported)" if driver == "fake" else ""
        raise ValueError(f"unknown driver {driver!r}{hint}; known: {registered_camera_configs()}")
    return _CAMERA_CONFIGS[driver][0].model_validate(data)


def _tables() -> dict[str, tuple[str, type[BaseModel]]]:
    """Top-level table name -> (the driver owning it, its model)."""
    return {t[0]: (d, t[1]) for d, (_, t) in _CAMERA_CONFIGS.items() if t is not None}


class Rig(_Strict):
    """A validated rig file. The top-level tables drivers own (:func:`register_camera_config`) are
    read with :meth:`table`."""

    model_config = ConfigDict(extra="allow", frozen=True)  # the drivers' tables; any other key is refused

    name: str = "rig"
    fps: Annotated[float, Field(gt=0, le=1000)] = 30.0
    sync_tolerance_ms: Annotated[float, Field(gt=0)] | None = None
    volume: Volume = Volume()
    support_plane: tuple[float, float, float, float] | None = None
    backdrop: Backdrop = Backdrop()
    cameras: list[SerializeAsAny[CameraConfig]] = Field(default_factory=list)

    @field_validator("cameras", mode="before")
    @classmethod
    def _typed_cameras(cls, v: Any) -> Any:
        return [camera_config(c) for c in v] if isinstance(v, list) else v

    @model_validator(mode="before")
    @classmethod
    def _typed_tables(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        tables = _tables()
        unknown = sorted(k for k in data if k not in cls.model_fields and k not in tables)
        if unknown:
            raise ValueError(f"unknown key {unknown[0]!r}")
        return {k: tables[k][1].model_validate(v) if k in tables and not isinstance(v, BaseModel) else v
                for k, v in data.items()}

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
        for name, (driver, _) in _tables().items():
            if any(c.driver == driver for c in self.cameras) and self.table(name) is None:
                raise ValueError(f"{name}: {driver} cameras need a [{name}] table")
        return self

    def table(self, name: str) -> BaseModel | None:
        """The validated top-level table ``name`` a driver owns (e.g. ``[simulation]``), or None."""
        return (self.__pydantic_extra__ or {}).get(name)

    @property
    def tolerance_ns(self) -> int:
        """Frame-set grouping tolerance: the configured one, else half a frame period."""
        if self.sync_tolerance_ms is not None:
            return int(self.sync_tolerance_ms * 1e6)
        return int(0.5e9 / self.fps)


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


def _error_lines(exc: ValidationError, prefix: tuple = ()) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in (*prefix, *err["loc"]))
        if err["type"] == "extra_forbidden":
            lines.append(f"  unknown key {loc!r}")
        else:
            lines.append(f"  {loc or '(top level)'}: {err['msg'].removeprefix('Value error, ')}")
    return lines


def _typed_parts(data: dict) -> tuple[dict, list[str]]:
    """``data`` with every camera and driver table validated by its own model, and the error lines
    of those that are not (located in the file: ``cameras.1.device``, ``simulation.frames``)."""
    out, lines = dict(data), []
    cams = data.get("cameras")
    if isinstance(cams, list):
        typed = []
        for i, cam in enumerate(cams):
            try:
                typed.append(camera_config(cam))
            except ValidationError as exc:
                lines += _error_lines(exc, ("cameras", i))
            except ValueError as exc:
                lines.append(f"  cameras.{i}.driver: {exc}")
        out["cameras"] = typed
    tables = _tables()
    for key in data:
        if key in tables:
            try:
                out[key] = tables[key][1].model_validate(data[key])
            except ValidationError as exc:
                lines += _error_lines(exc, (key,))
        elif key not in Rig.model_fields:
            lines.append(f"  unknown key {key!r}")
    return out, lines


def parse_rig(data: dict, *, source: str = "rig") -> Rig:
    """Validate a rig dictionary (as read from TOML); every camera against the config model of its
    ``driver``. Raises :class:`RigError` listing every bad key."""
    if not isinstance(data, dict):
        raise RigError(f"{source}: invalid rig file\n  (top level): must be a table, got {type(data).__name__}")
    typed, lines = _typed_parts(data)
    if not lines:
        try:
            return Rig.model_validate(typed)
        except ValidationError as exc:
            lines = _error_lines(exc)
    raise RigError("\n".join([f"{source}: invalid rig file", *lines]))


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
