"""Camera model and calibration of capture-stage rigs."""

from calib.camera import Camera, pixel_rays, project_points
from calib.calibration import Calibration

__all__ = ["Camera", "Calibration", "project_points", "pixel_rays"]
