"""Camera drivers behind one small interface (:class:`CameraDriver`).

``open_driver(config, rig)`` creates the driver a rig camera entry names
(``fake``, ``opencv``, ``depthai``); vendor SDKs load only when such a camera is
opened.
"""

from stage.drivers.base import (
    CameraDisconnectedError,
    CameraDriver,
    CameraError,
    CameraNotFoundError,
    DriverUnavailableError,
    Granted,
)
from stage.drivers.registry import open_driver

__all__ = [
    "CameraDriver",
    "Granted",
    "CameraError",
    "CameraNotFoundError",
    "CameraDisconnectedError",
    "DriverUnavailableError",
    "open_driver",
]
