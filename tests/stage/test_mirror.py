"""Cameras that deliver mirrored images: ``mirror = true`` flips their frames back at capture
(the drivers) and at import (a calibration camera with ``meta["mirror"]``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.calibration import Calibration
from calib.camera import Camera
from stage.drivers.base import unmirror
from stage.drivers.opencv import OpenCVCamera, OpenCVCameraConfig
from stage.frame import Frame
from stage.importer import import_take
from stage.rig import parse_rig
from stage.store import TakeReader


def _img(k: int) -> np.ndarray:
    img = np.zeros((24, 32, 3), np.uint8)
    img[:, : 4 + k] = 200  # a bar on the left: flipping moves it right
    return img


def test_unmirror_flips_image_and_depth_and_drops_bytes():
    depth = np.arange(24 * 32, dtype=np.uint16).reshape(24, 32)
    f = Frame(_img(0), "c", 0, 0, 0, depth=depth, encoded=b"jpeg")
    g = unmirror(f)
    np.testing.assert_array_equal(g.image, _img(0)[:, ::-1])
    np.testing.assert_array_equal(g.depth, depth[:, ::-1])
    assert g.encoded is None and g.index == f.index


def test_opencv_driver_flips_a_mirroring_camera(tmp_path):
    for k in range(2):
        cv2.imwrite(str(tmp_path / f"{k:02d}.png"), _img(k))
    for mirror in (False, True):
        cfg = OpenCVCameraConfig(id="cam0", driver="opencv", device=str(tmp_path), mirror=mirror)
        with OpenCVCamera(cfg) as cam:
            cam.configure()
            got = [cam.grab().image for _ in range(2)]
        for k, img in enumerate(got):
            np.testing.assert_array_equal(img, _img(k)[:, ::-1] if mirror else _img(k))


def test_rig_file_mirror_flag():
    rig = parse_rig({"cameras": [{"id": "a", "driver": "opencv", "device": 0, "mirror": True},
                                 {"id": "b", "driver": "opencv", "device": 1}]})
    assert [c.mirror for c in rig.cameras] == [True, False]
    with pytest.raises(ValueError, match="mirror"):
        parse_rig({"cameras": [{"id": "a", "driver": "opencv", "device": 0, "mirror": "sometimes"}]})


def test_import_flips_a_mirroring_camera(tmp_path):
    for name in ("a", "b"):
        (tmp_path / "imgs" / name).mkdir(parents=True)
        for k in range(2):
            cv2.imwrite(str(tmp_path / "imgs" / name / f"{k:02d}.png"), _img(k))
    K = [[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]
    cams = (Camera("a", K=K, dist=np.zeros(5), R=np.eye(3), t=np.zeros(3), size=(32, 24), meta={"mirror": True}),
            Camera("b", K=K, dist=np.zeros(5), R=np.eye(3), t=[100.0, 0, 0], size=(32, 24)))
    out = import_take(tmp_path / "imgs", Calibration(cams), tmp_path / "take.h5", storage="raw")
    with TakeReader(out.path) as r:
        for k in range(2):
            s = r.frame_set(k)
            np.testing.assert_array_equal(s["a"], _img(k)[:, ::-1])
            np.testing.assert_array_equal(s["b"], _img(k))
