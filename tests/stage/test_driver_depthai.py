"""The depthai driver: message -> Frame conversion with host-built depthai messages; no-device behaviour."""

from __future__ import annotations

import datetime as dt
import subprocess
import sys

import cv2
import numpy as np
import pytest

dai = pytest.importorskip("depthai", reason="depthai v3 is not installed")

from stage.drivers.base import CameraDisconnectedError, CameraError, CameraNotFoundError  # noqa: E402
from stage.drivers.depthai_driver import (  # noqa: E402
    DepthAICamera,
    DepthAICameraConfig,
    factory_camera,
    fit_five_coefficients,
    frame_from_messages,
    timedelta_to_ns,
)

W, H = 160, 120


def smooth_bgr() -> np.ndarray:
    """A smooth colour gradient (survives NV12's 2x2 chroma subsampling nearly exactly)."""
    y, x = np.mgrid[0:H, 0:W]
    return np.stack([x * 255 // (W - 1), y * 255 // (H - 1), 128 + 0 * x], axis=2).astype(np.uint8)


def img_msg(img: np.ndarray, kind, *, seq=7, device_s=12.5, synced_s=1000.25) -> "dai.ImgFrame":
    msg = dai.ImgFrame()
    msg.setCvFrame(img, kind)
    msg.setSequenceNum(seq)
    msg.setTimestampDevice(dt.timedelta(seconds=device_s))
    msg.setTimestamp(dt.timedelta(seconds=synced_s))
    return msg


def depth_msg(depth: np.ndarray) -> "dai.ImgFrame":
    msg = dai.ImgFrame()
    msg.setType(dai.ImgFrame.Type.RAW16)
    msg.setWidth(depth.shape[1])
    msg.setHeight(depth.shape[0])
    msg.setData(np.ascontiguousarray(depth).view(np.uint8).reshape(-1))
    return msg


@pytest.mark.parametrize("kind", ["BGR888i", "BGR888p", "RGB888i"])
def test_interleaved_and_planar_colour_exact(kind):
    img = smooth_bgr()
    img[10:20, 30:50] = (0, 0, 255)  # a red patch: channel order must survive
    f = frame_from_messages("oak", img_msg(img, getattr(dai.ImgFrame.Type, kind)), host_ns=123)
    np.testing.assert_array_equal(f.image, img)
    assert f.camera_id == "oak" and f.index == 7 and f.host_timestamp_ns == 123
    assert f.depth is None and f.encoded is None


def test_nv12_colour_matches_opencv_conversion():
    img = smooth_bgr()
    msg = img_msg(img, dai.ImgFrame.Type.NV12)
    f = frame_from_messages("oak", msg, host_ns=0)
    # reference: OpenCV's own NV12 -> BGR of the very bytes the message holds
    nv12 = np.asarray(msg.getData(), np.uint8).reshape(H * 3 // 2, W)
    ref = cv2.cvtColor(nv12, cv2.COLOR_YUV2BGR_NV12)
    assert np.abs(f.image.astype(int) - ref.astype(int)).max() <= 2
    assert np.abs(f.image.astype(int) - img.astype(int)).mean() < 3  # and it is the picture we sent


def test_gray_becomes_bgr():
    gray = smooth_bgr()[:, :, 0]
    f = frame_from_messages("oak", img_msg(gray, dai.ImgFrame.Type.GRAY8), host_ns=0)
    assert f.image.shape == (H, W, 3)
    for c in range(3):
        np.testing.assert_array_equal(f.image[:, :, c], gray)


def test_timestamps_both_clocks_exact_ns():
    msg = img_msg(smooth_bgr(), dai.ImgFrame.Type.BGR888i, device_s=12.5, synced_s=1000.25)
    assert frame_from_messages("oak", msg, host_ns=0).timestamp_ns == 1_000_250_000_000
    assert frame_from_messages("oak", msg, host_ns=0, clock="device").timestamp_ns == 12_500_000_000
    assert timedelta_to_ns(dt.timedelta(days=1, seconds=2, microseconds=3)) == 86_402_000_003_000


def test_colour_plus_aligned_depth():
    img = smooth_bgr()
    depth = (np.arange(H * W, dtype=np.uint32).reshape(H, W) * 7 % 10000).astype(np.uint16)
    f = frame_from_messages("oak", img_msg(img, dai.ImgFrame.Type.BGR888i), depth_msg(depth), host_ns=5)
    assert f.depth.dtype == np.uint16
    np.testing.assert_array_equal(f.depth, depth)


def test_depth_at_other_size_is_resized_nearest():
    img = smooth_bgr()
    small = np.repeat(np.repeat(np.arange(12, dtype=np.uint16).reshape(3, 4) * 500, 30, 0), 40, 1)[:H // 2, :W // 2]
    small = np.ascontiguousarray(small[:60, :80])
    f = frame_from_messages("oak", img_msg(img, dai.ImgFrame.Type.BGR888i), depth_msg(small), host_ns=0)
    assert f.depth.shape == (H, W)
    np.testing.assert_array_equal(f.depth[::2, ::2], small)  # exact 2x nearest neighbour keeps the mm values
    assert set(np.unique(f.depth)) <= set(np.unique(small))


class _Metered(dai.ImgFrame):
    """An ImgFrame as the sensor stamps it (depthai's Python API reads the exposure and the
    sensitivity of a frame but offers no setter: a host-built frame has 0 for both)."""

    def getExposureTime(self):
        return dt.timedelta(microseconds=8333)

    def getSensitivity(self):
        return 400


def test_exposure_and_iso_of_every_frame():
    img = smooth_bgr()
    plain = frame_from_messages("oak", img_msg(img, dai.ImgFrame.Type.BGR888i), host_ns=0)
    assert plain.exposure_ms is None and plain.gain is None  # stamped by no sensor
    msg = _Metered()
    msg.setCvFrame(img, dai.ImgFrame.Type.BGR888i)
    f = frame_from_messages("oak", msg, host_ns=0)
    assert f.exposure_ms == pytest.approx(8.333) and f.gain == 400
    np.testing.assert_array_equal(f.image, img)


def test_mjpeg_bytes_from_encoder():
    img = smooth_bgr()
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    enc = dai.EncodedFrame()
    enc.setProfile(dai.EncodedFrame.Profile.JPEG)
    enc.setData(jpg.reshape(-1))
    enc.setSequenceNum(3)
    enc.setTimestamp(dt.timedelta(milliseconds=40))
    f = frame_from_messages("oak", enc, host_ns=0)
    assert f.encoded == jpg.tobytes() and f.index == 3 and f.timestamp_ns == 40_000_000
    np.testing.assert_array_equal(f.image, cv2.imdecode(jpg, cv2.IMREAD_COLOR))
    # the same bytes in a BITSTREAM ImgFrame
    bit = dai.ImgFrame()
    bit.setType(dai.ImgFrame.Type.BITSTREAM)
    bit.setData(jpg.reshape(-1))
    assert frame_from_messages("oak", bit, host_ns=0).encoded == jpg.tobytes()


def test_factory_camera_from_calibration_handler():
    ch = dai.CalibrationHandler()
    K = [[800.0, 0.0, 640.0], [0.0, 805.0, 400.0], [0.0, 0.0, 1.0]]
    ch.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K, dai.Size2f(1280, 800))
    rational = [-0.10, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.004] + [0.0] * 6
    ch.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, rational)
    cam = factory_camera(ch, "CAM_A", size=(640, 400), name="oak")
    assert cam.name == "oak" and cam.size == (640, 400)
    np.testing.assert_allclose(cam.K, [[400, 0, 320], [0, 402.5, 200], [0, 0, 1]])
    np.testing.assert_array_equal(cam.R, np.eye(3))
    # the 5-coefficient fit reproduces the full model's pixels well inside the image
    assert cam.meta["distortion_fit_rms_px"] < 0.5
    pts = np.array([[0.1, -0.2, 1.0], [-0.3, 0.25, 1.0], [0.35, 0.3, 1.0]])
    full, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, np.array(rational))
    np.testing.assert_allclose(cam.project(pts), full.reshape(-1, 2), atol=1.0)
    # a plain 5-coefficient calibration passes through unchanged
    plain = [-0.1, 0.05, 0.001, -0.002, 0.01] + [0.0] * 9
    ch.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, plain)
    cam = factory_camera(ch, "CAM_A", size=(1280, 800), name="oak")
    np.testing.assert_allclose(cam.dist, plain[:5], atol=1e-7)
    assert cam.meta["distortion_fit_rms_px"] == 0.0


def test_fit_five_coefficients_recovers_a_five_coefficient_lens():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    d5 = np.array([-0.2, 0.08, 0.001, -0.0015, -0.01])
    fit, rms = fit_five_coefficients(K, np.concatenate([d5, np.zeros(9)]), (640, 480))
    np.testing.assert_allclose(fit, d5, atol=1e-6)
    assert rms < 1e-6


def test_no_device_is_a_clear_error():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is attached to this machine")
    cam = DepthAICamera(DepthAICameraConfig(id="oak", driver="depthai"))
    with pytest.raises(CameraNotFoundError, match="no OAK device found; check the USB connection.*udev"):
        cam.open()
    assert not cam.is_open
    with pytest.raises(CameraError, match="not open"):
        cam.grab()
    cam.close()  # harmless


def test_no_device_through_registry_and_cli(capsys):
    from stage.cli import main
    from stage.drivers.registry import open_driver
    from stage.rig import parse_rig

    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is attached to this machine")
    rig = parse_rig({"fps": 15, "cameras": [{"id": "oak", "driver": "depthai", "device": "1844301011"}]})
    drv = open_driver(rig.cameras[0], rig)
    assert isinstance(drv, DepthAICamera) and drv.config.fps == 15
    with pytest.raises(CameraNotFoundError, match="no OAK device found"):
        drv.open()
    from stage.discovery import discover

    others = not discover(depthai=False).empty
    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert "OAK devices (depthai)" not in out
    if not others:
        assert "no cameras found" in out and "no OAK reachable by depthai" in out


class FakeQueue:
    """Stands in for the started pipeline's output queue: MessageGroups, then silence."""

    def __init__(self, groups):
        self.groups = list(groups)
        self.timeouts = []

    def get(self, timeout):
        self.timeouts.append(timeout)
        return self.groups.pop(0) if self.groups else None


class FakeDevice:
    def isClosed(self):
        return True

    def close(self):
        pass


def test_grab_from_synced_colour_depth_groups():
    img = smooth_bgr()
    groups = []
    for seq in range(3):
        g = dai.MessageGroup()
        g["color"] = img_msg(img, dai.ImgFrame.Type.BGR888i, seq=seq, synced_s=10 + seq / 30)
        g["depth"] = depth_msg(np.full((H, W), 1000 + seq, np.uint16))
        groups.append(g)
    cam = DepthAICamera(DepthAICameraConfig(id="oak", driver="depthai", fps=30), timeout_s=0.01)
    # what configure() leaves behind, minus the hardware
    cam._dai, cam._device, cam._pipeline, cam._queue, cam._synced = dai, FakeDevice(), object(), FakeQueue(groups), True
    frames = [cam.grab() for _ in range(3)]
    assert [f.index for f in frames] == [0, 1, 2]
    assert [int(f.depth[0, 0]) for f in frames] == [1000, 1001, 1002]
    np.testing.assert_array_equal(np.diff([f.timestamp_ns for f in frames]), [33_333_000, 33_334_000])
    with pytest.raises(CameraDisconnectedError, match="no frame from the OAK.*unplugged"):
        cam.grab()
    cam._pipeline = None  # nothing to stop
    cam.close()
    assert not cam.is_open


def test_importing_stage_does_not_import_depthai():
    code = (
        "import sys, stage, stage.drivers, stage.drivers.registry, stage.discovery, stage.cli;"
        "stage.cli.build_parser(); print('depthai' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_invalid_input():
    img = img_msg(smooth_bgr(), dai.ImgFrame.Type.BGR888i)
    with pytest.raises(ValueError, match="camera_id"):
        frame_from_messages("", img, host_ns=0)
    with pytest.raises(ValueError, match="host_ns"):
        frame_from_messages("oak", img, host_ns=1.5)
    with pytest.raises(ValueError, match="clock"):
        frame_from_messages("oak", img, host_ns=0, clock="wall")
    with pytest.raises(ValueError, match="img_frame"):
        frame_from_messages("oak", np.zeros((2, 2, 3), np.uint8), host_ns=0)
    with pytest.raises(ValueError, match="depth frame must be RAW16"):
        frame_from_messages("oak", img, img, host_ns=0)
    with pytest.raises(ValueError, match="unsupported colour frame type RAW16"):
        frame_from_messages("oak", depth_msg(np.zeros((4, 4), np.uint16)), host_ns=0)
    h264 = dai.EncodedFrame()
    h264.setProfile(dai.EncodedFrame.Profile.AVC)
    h264.setData(np.zeros(16, np.uint8))
    with pytest.raises(ValueError, match="MJPEG"):
        frame_from_messages("oak", h264, host_ns=0)
    with pytest.raises(ValueError, match="timedelta"):
        timedelta_to_ns(1.0)
    with pytest.raises(ValueError, match="DepthAICameraConfig"):
        DepthAICamera({"id": "oak"})
    with pytest.raises(ValueError, match="clock"):
        DepthAICamera(DepthAICameraConfig(id="oak", driver="depthai"), clock="utc")
    with pytest.raises(ValueError, match="CalibrationHandler"):
        factory_camera(object(), size=(640, 400), name="oak")
    with pytest.raises(ValueError, match="socket"):
        factory_camera(dai.CalibrationHandler(), "CAM_Z", size=(640, 400), name="oak")
    with pytest.raises(CameraError, match="no factory calibration"):
        factory_camera(dai.CalibrationHandler(), "CAM_B", size=(640, 400), name="oak")
    with pytest.raises(ValueError, match="coefficients"):
        fit_five_coefficients(np.eye(3) * 500, np.zeros(6), (640, 480))
    with pytest.raises(ValueError, match="size"):
        fit_five_coefficients(np.diag([500.0, 500.0, 1.0]), np.zeros(5), (0, 480))
