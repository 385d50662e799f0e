"""Create the driver a rig camera entry asks for.

The built-in drivers (``opencv``, ``depthai``) load on first use, so ``import stage``
never imports a vendor SDK. Other drivers register themselves with
:func:`register_driver` when their module is imported: the simulated rig's ``fake``
driver does so in :mod:`fake_cameras.device` (the ``stage`` CLI imports it), so the
ground floor never imports the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from stage.drivers.base import CameraDriver, DriverUnavailableError
from stage.rig import DepthAICameraConfig, FakeCameraConfig, OpenCVCameraConfig

if TYPE_CHECKING:  # pragma: no cover
    from stage.rig import CameraConfig, Rig

__all__ = ["open_driver", "register_driver", "registered_drivers"]


def _opencv() -> type:
    from stage.drivers.opencv import OpenCVCamera

    return OpenCVCamera


def _depthai() -> type:
    from stage.drivers.depthai_driver import DepthAICamera

    return DepthAICamera


#: driver name -> (loader of the class, whether the class takes the rig as second argument)
_DRIVERS: dict[str, tuple[Callable[[], type], bool]] = {
    "opencv": (_opencv, False),
    "depthai": (_depthai, False),
}

_CONFIG_TYPES = (FakeCameraConfig, OpenCVCameraConfig, DepthAICameraConfig)


def register_driver(name: str, cls: type, *, needs_rig: bool = False) -> None:
    """Make ``cls`` the driver of rig cameras with ``driver = name``.

    Parameters
    ----------
    name : str
        The ``driver`` value of a rig camera entry.
    cls : type
        ``cls(config)`` (or ``cls(config, rig)`` with ``needs_rig``) is a :class:`CameraDriver`.
    needs_rig : bool
        The driver is created with the whole rig too.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    if not isinstance(cls, type):
        raise ValueError(f"cls must be a class, got {cls!r}")
    _DRIVERS[name] = (lambda: cls, bool(needs_rig))


def registered_drivers() -> list[str]:
    """Names of the drivers :func:`open_driver` can create now."""
    return sorted(_DRIVERS)


def _driver_class(name: str) -> tuple[type, bool]:
    if name not in _DRIVERS:
        hint = " (it registers itself when fake_cameras is imported)" if name == "fake" else ""
        raise DriverUnavailableError(f"driver {name!r} is not registered{hint}; known: {registered_drivers()}")
    load, needs_rig = _DRIVERS[name]
    try:
        return load(), needs_rig
    except ImportError as exc:
        raise DriverUnavailableError(
            f"driver {name!r} cannot load: {exc} (install the package it needs; see docs/hardware.md)"
        ) from exc


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
        The driver's vendor library is missing, or no driver of that name is registered.
    """
    from stage.rig import Rig

    if not isinstance(config, _CONFIG_TYPES):
        raise ValueError(f"config must be a rig camera config, got {type(config).__name__}")
    if rig is not None and not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig or None, got {type(rig).__name__}")
    if config.fps is None and rig is not None:
        config = config.model_copy(update={"fps": rig.fps})
    if isinstance(config, FakeCameraConfig) and rig is None:
        raise ValueError("rig: fake cameras need the rig (its [simulation] table)")
    cls, needs_rig = _driver_class(config.driver)
    return cls(config, rig) if needs_rig else cls(config)
