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


def test_reprojection_error_px_says_what_the_calibration_measured():
    assert Calibration(_cams()).reprojection_error_px() == {}  # imported: nothing known
    assert Calibration(_cams(), meta={"exact": True}).reprojection_error_px() == {"c0": 0.0, "c1": 0.0, "c2": 0.0}
    meta = {"per_camera_rms_px": {"c0": 0.3, "c1": 0.4, "c2": 0.5},
            "held_out_rms_px": {"c0": 0.6, "c1": float("nan"), "zz": 1.0}}
    # held out where measured, else the fit's own; a non-finite figure or an unknown camera is ignored
    assert Calibration(_cams(), meta=meta).reprojection_error_px() == {"c0": 0.6, "c1": 0.4, "c2": 0.5}
    # a figure that is not a number is ignored, as is a table that is not one
    odd = {"all_frames_rms_px": {"c0": "0.2", "c1": True, "c2": -1.0}, "held_out_rms_px": [0.1]}
    assert Calibration(_cams(), meta=odd).reprojection_error_px() == {}
    assert Calibration(_cams(), meta={"exact": "yes"}).reprojection_error_px() == {}
    # a camera's own figure (caliscope's RMS) where the calibration's tables say nothing of it
    cams = list(_cams())
    cams[1] = Camera(cams[1].name, cams[1].K, cams[1].dist, cams[1].R, cams[1].t, cams[1].size, meta={"error": 0.7})
    got = Calibration(tuple(cams), meta={"held_out_rms_px": {"c0": 0.6}}).reprojection_error_px()
    assert got == {"c0": 0.6, "c1": 0.7}


def test_invalid_input():
    with pytest.raises(ValueError, match="cameras"):
        Calibration(())
    with pytest.raises(ValueError, match="duplicate"):
        Calibration(_cams(1) + _cams(1))
    with pytest.raises(KeyError, match="no camera named"):
        Calibration(_cams())["zz"]
    with pytest.raises(ValueError, match="cameras"):
        Calibration.from_dict({"units": "mm"})
