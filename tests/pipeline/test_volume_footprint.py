"""pipeline.volume.pixel_footprint: the size of a pixel at a point, per camera."""

import numpy as np
import pytest

from fake_cameras.dome import make_dome
from pipeline.volume import pixel_footprint


def test_footprint_is_one_pixel_of_image_motion():
    cal = make_dome(6, size=(480, 360), seed=0, distortion=False)
    p = np.array([10.0, -20.0, 300.0])
    fp = pixel_footprint(cal, p)[:, 0]
    for cam, f in zip(cal, fp):
        # move the point by one footprint across the optical axis: its image moves by one pixel
        step = cam.R.T @ np.array([f, 0.0, 0.0])
        uv = cam.project(np.stack([p, p + step]))
        assert np.linalg.norm(uv[1] - uv[0]) == pytest.approx(1.0, rel=0.02)
    behind = cal[0].center + (cal[0].center - p)  # behind camera 0
    assert np.isnan(pixel_footprint(cal, behind)[0, 0])


def test_invalid_input():
    cal = make_dome(4, size=(160, 120), seed=0)
    with pytest.raises(ValueError, match="calibration"):
        pixel_footprint("cams", [0, 0, 0])
    with pytest.raises(ValueError, match="finite"):
        pixel_footprint(cal, [0, np.nan, 0])
