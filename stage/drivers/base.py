"""The one small driver interface every camera implements."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from stage.frame import Frame

__all__ = [
    "CameraDriver",
    "Granted",
    "CameraError",
    "CameraNotFoundError",
    "CameraDisconnectedError",
    "DriverUnavailableError",
]


class CameraError(RuntimeError):
    """Base class of camera failures; the message says which camera and what to do."""


class CameraNotFoundError(CameraError):
    """The configured device is not attached (or not readable)."""


class CameraDisconnectedError(CameraError):
    """The device stopped delivering frames mid-take."""


class DriverUnavailableError(CameraError):
    """The driver's vendor library is not installed or cannot load."""


@dataclass(frozen=True)
class Granted:
    """What a device actually granted after :meth:`CameraDriver.configure`.

    Devices often ignore or round requested settings; the rig records these values.
    """

    width: int
    height: int
    fps: float
    pixel_format: str = "BGR"
    exposure: float | None = None
    has_depth: bool = False
    extra: dict = field(default_factory=dict)


@runtime_checkable
class CameraDriver(Protocol):
    """open -> configure -> grab ... -> close.

    ``grab`` blocks until the next frame and returns it; it raises
    :class:`CameraDisconnectedError` when the device is gone and
    :class:`StopIteration`-free ``None`` is never returned.
    """

    camera_id: str

    def open(self) -> None: ...

    def configure(self) -> Granted: ...

    def grab(self) -> Frame: ...

    def close(self) -> None: ...
