import numpy as np
import pytest

from calib import Calibration, Camera


def _cams(n=3):
    return tuple(
        Camera(f"c{i}", np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5), np.eye(3),
               [i * 100.0, 0, 1000], (640, 480))
        for i in range(n)
    )


def test_roundtrip_and_lookup():
    cal = Calibration(_cams(), meta={"method": "test"})
    again = Calibration.from_dict(cal.to_dict())
    assert again == cal and again.names == ["c0", "c1", "c2"]
    assert cal["c1"] is cal[1]
    np.testing.assert_allclose(cal.centers()[:, 0], [0, -100, -200])


def test_invalid_input():
    with pytest.raises(ValueError, match="cameras"):
        Calibration(())
    with pytest.raises(ValueError, match="duplicate"):
        Calibration(_cams(1) + _cams(1))
    with pytest.raises(KeyError, match="no camera named"):
        Calibration(_cams())["zz"]
    with pytest.raises(ValueError, match="cameras"):
        Calibration.from_dict({"units": "mm"})
