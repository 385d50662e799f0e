"""Create the driver a rig camera entry asks for.

Vendor SDKs are imported only inside their driver, when a camera of that kind is
opened: ``import stage`` never imports depthai.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from stage.drivers.base import CameraDriver, DriverUnavailableError
from stage.rig import DepthAICameraConfig, FakeCameraConfig, OpenCVCameraConfig

if TYPE_CHECKING:  # pragma: no cover
    from stage.rig import CameraConfig, Rig

__all__ = ["open_driver", "DRIVERS"]

#: driver name -> (module, class) implementing it
DRIVERS: dict[str, tuple[str, str]] = {
    "fake": ("stage.drivers.fake", "FakeCamera"),
    "opencv": ("stage.drivers.opencv", "OpenCVCamera"),
    "depthai": ("stage.drivers.depthai_driver", "DepthAICamera"),
}

_CONFIG_TYPES = (FakeCameraConfig, OpenCVCameraConfig, DepthAICameraConfig)


def _driver_class(name: str) -> type:
    module_name, class_name = DRIVERS[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverUnavailableError(
            f"driver {name!r} cannot load: {exc} (install the package it needs; see docs/hardware.md)"
        ) from exc
    cls = getattr(module, class_name, None)
    if cls is None:
        raise DriverUnavailableError(f"driver {name!r}: {module_name} has no {class_name}")
    return cls


def open_driver(config: "CameraConfig", rig: "Rig | None" = None) -> CameraDriver:
    """The driver object for one camera of a rig (not yet opened).

    Parameters
    ----------
    config : FakeCameraConfig or OpenCVCameraConfig or DepthAICameraConfig
        One entry of ``rig.cameras``.
    rig : Rig, optional
        The rig it belongs to: a camera without its own ``fps`` takes the rig's,
        and simulated cameras need the rig's ``[simulation]``.

    Returns
    -------
    CameraDriver
        Call ``open()``, ``configure()``, then ``grab()``; ``close()`` at the end.

    Raises
    ------
    ValueError
        ``config`` is not a camera config, or ``rig`` is not a Rig.
    DriverUnavailableError
        The driver's vendor library is missing.
    """
    from stage.rig import Rig

    if not isinstance(config, _CONFIG_TYPES):
        raise ValueError(f"config must be a rig camera config, got {type(config).__name__}")
    if rig is not None and not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig or None, got {type(rig).__name__}")
    if config.fps is None and rig is not None:
        config = config.model_copy(update={"fps": rig.fps})
    if config.driver == "fake" and rig is None:
        raise ValueError("rig: fake cameras need the rig (its [simulation] table)")
    cls = _driver_class(config.driver)
    if config.driver == "fake":
        return cls(config, rig)
    return cls(config)
