"""A calibration that would be read wrongly is refused with the reason: a K whose last row is not
(0, 0, 1), a misspelt key (which would fall back to a default in silence)."""

import json

import numpy as np
import pytest

from calib.calibration import Calibration
from calib.camera import Camera
from calib.formats import read_calibration, write_calibration
from tests.calib.calibrations import random_calibration


def _cal():
    return random_calibration(n=2)


def test_k_with_a_wrong_last_row_is_refused(tmp_path):
    cal = _cal()
    d = cal.to_dict()
    d["cameras"][0]["K"][2][2] = 0.0
    with pytest.raises(ValueError, match=r"\[0, 0, 1\]"):
        Calibration.from_dict(d)
    path = write_calibration(cal, tmp_path / "c.json", format="json")
    data = json.loads(path.read_text())
    data["cameras"][1]["K"][2][0] = 3.0
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="intrinsic matrix"):
        read_calibration(path)
    toml = write_calibration(cal, tmp_path / "c.toml", format="toml")
    text = toml.read_text()
    last_row = "        0.0,\n        0.0,\n        1.0,\n"
    assert last_row in text
    toml.write_text(text.replace(last_row, "        0.0,\n        0.0,\n        0.0,\n", 1))
    with pytest.raises(ValueError, match="intrinsic matrix"):
        read_calibration(toml)


def test_unknown_keys_are_refused(tmp_path):
    cal = _cal()
    d = cal.to_dict()
    d["cameras"][0]["distortion"] = [0.1, 0, 0, 0, 0]  # misspelt "dist": would read as no distortion
    with pytest.raises(ValueError, match="unknown keys \\['distortion'\\]"):
        Calibration.from_dict(d)
    d = cal.to_dict()
    d["unit"] = "m"
    with pytest.raises(ValueError, match="unknown keys \\['unit'\\]"):
        Calibration.from_dict(d)
    toml = write_calibration(cal, tmp_path / "c.toml", format="toml")
    toml.write_text(toml.read_text().replace("distortions =", "distortion ="))
    with pytest.raises(ValueError, match="unknown keys"):
        read_calibration(toml)
    assert read_calibration(write_calibration(cal, tmp_path / "ok.toml", format="toml")) == cal


def test_invalid_input():
    cam = _cal().cameras[0]
    with pytest.raises(ValueError, match="dictionary"):
        Camera.from_dict([1, 2])
    K = np.array(cam.K)
    K[1, 0] = 5.0
    with pytest.raises(ValueError, match="intrinsic matrix"):
        Camera(name="c", K=K, dist=cam.dist, R=cam.R, t=cam.t, size=cam.size)
