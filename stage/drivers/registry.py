"""Create the driver a rig camera entry asks for, and register drivers.

A driver is a class implementing :class:`~stage.drivers.base.CameraDriver` that declares its rig
camera model in ``config_model`` (a subclass of :class:`stage.rig.CameraConfig` with
``driver: Literal["name"]``); :func:`register_driver` makes both known, so a rig file's camera is
validated against the model of its ``driver`` (:func:`stage.rig.parse_rig`) and opened by its
class. The built-in drivers (``opencv``, ``depthai``) register here when :mod:`stage.drivers` is
imported; their vendor SDKs load only when a camera opens (OpenCV is a dependency of the project).
Other drivers register themselves when their module is imported: the simulated rig's ``fake``
driver does so in :mod:`fake_cameras.device` (the ``stage`` CLI imports it), so the ground floor
never imports the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pydantic import BaseModel

from stage.drivers.base import CameraDriver, DriverUnavailableError
from stage.drivers.depthai_driver import DepthAICamera
from stage.drivers.opencv import OpenCVCamera
from stage.rig import CameraConfig, register_camera_config

if TYPE_CHECKING:  # pragma: no cover
    from stage.rig import Rig

__all__ = ["open_driver", "register_driver", "registered_drivers"]


#: driver name -> (its class, whether the class takes the rig as second argument)
_DRIVERS: dict[str, tuple[type, bool]] = {}


def register_driver(name: str, cls: type, *, needs_rig: bool = False,
                    table: tuple[str, type[BaseModel]] | None = None) -> None:
    """Make ``cls`` the driver of rig cameras with ``driver = name``.

    Parameters
    ----------
    name : str
        The ``driver`` value of a rig camera entry.
    cls : type
        ``cls(config)`` (or ``cls(config, rig)`` with ``needs_rig``) is a :class:`CameraDriver`;
        ``cls.config_model`` is the rig camera's model (a :class:`stage.rig.CameraConfig` subclass).
    needs_rig : bool
        The driver is created with the whole rig too.
    table : (str, type), optional
        A top-level table of the rig file the driver owns (:func:`stage.rig.register_camera_config`).
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    if not isinstance(cls, type):
        raise ValueError(f"cls must be a class, got {cls!r}")
    model = getattr(cls, "config_model", None)
    if not (isinstance(model, type) and issubclass(model, CameraConfig)):
        raise ValueError(f"cls.config_model must be a subclass of stage.rig.CameraConfig, got {model!r}")
    register_camera_config(name, model, table=table)
    _DRIVERS[name] = (cls, bool(needs_rig))


def registered_drivers() -> list[str]:
    """Names of the drivers :func:`open_driver` can create now."""
    return sorted(_DRIVERS)


def _driver_class(name: str) -> tuple[type, bool]:
    if name not in _DRIVERS:
        hint = " (it registers itself when fake_cameras is imported)" if name == "fake" else ""
        raise DriverUnavailableError(f"driver {name!r} is not registered{hint}; known: {registered_drivers()}")
    return _DRIVERS[name]


def open_driver(config: "CameraConfig", rig: "Rig | None" = None) -> CameraDriver:
    """The driver object for one camera of a rig (not yet opened).

    Parameters
    ----------
    config : stage.rig.CameraConfig
        One entry of ``rig.cameras`` (the config model of its driver).
    rig : Rig, optional
        The rig it belongs to: a camera without its own ``fps`` takes the rig's,
        and drivers registered with ``needs_rig`` (the simulator's) need it.

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

    if not isinstance(config, CameraConfig):
        raise ValueError(f"config must be a rig camera config, got {type(config).__name__}")
    if rig is not None and not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig or None, got {type(rig).__name__}")
    if config.fps is None and rig is not None:
        config = config.model_copy(update={"fps": rig.fps})
    cls, needs_rig = _driver_class(config.driver)
    if needs_rig and rig is None:
        raise ValueError(f"rig: {config.driver} cameras need the rig")
    return cls(config, rig) if needs_rig else cls(config)


register_driver("opencv", OpenCVCamera)
register_driver("depthai", DepthAICamera)
