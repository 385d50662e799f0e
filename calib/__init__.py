"""Camera model and calibration of capture-stage rigs."""

from calib.calibration import Calibration
from calib.camera import Camera, pixel_rays, project_points

__all__ = ["Camera", "Calibration", "project_points", "pixel_rays"]
