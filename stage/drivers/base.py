"""The one small driver interface every camera implements."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from stage.frame import Frame

__all__ = [
    "CameraDriver",
    "Granted",
    "CameraError",
    "CameraNotFoundError",
    "CameraDisconnectedError",
    "DriverUnavailableError",
    "unmirror",
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


def unmirror(frame: Frame) -> Frame:
    """The frame of a camera that delivers mirrored images, flipped back left-right.

    The camera's own encoded bytes describe the mirrored image, so they are dropped
    (the store encodes the flipped image).
    """
    image = np.ascontiguousarray(frame.image[:, ::-1])
    depth = None if frame.depth is None else np.ascontiguousarray(frame.depth[:, ::-1])
    return dataclasses.replace(frame, image=image, depth=depth, encoded=None)
