"""The opencv driver: video files, image sequences, and (emulated) V4L2 devices through one class."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from fake_cameras.device import FakeCameraConfig
from stage.drivers import opencv as ocv
from stage.drivers.base import CameraDisconnectedError, CameraDriver, CameraError, CameraNotFoundError
from stage.drivers.opencv import OpenCVCamera, OpenCVCameraConfig, classify_source, expand_pattern, fourcc_to_str
from stage.drivers.registry import open_driver
from stage.rig import parse_rig

W, H, N = 160, 120, 20


def pattern_image(i: int) -> np.ndarray:
    """Frame ``i``: flat grey level ``10 * i`` with a white block whose column encodes ``i``."""
    img = np.full((H, W, 3), 10 * i, np.uint8)
    x = 4 + 7 * i
    img[40:80, x : x + 6] = 255
    return img


def decoded_index(img: np.ndarray) -> int:
    """Recover ``i`` from a (possibly JPEG-degraded) pattern image: the block's column."""
    cols = img[40:80].mean(axis=(0, 2))
    x = int(np.argmax(cols > 200))
    return round((x - 4) / 7)


def cfg(device, **kw) -> OpenCVCameraConfig:
    return OpenCVCameraConfig(id="cam0", driver="opencv", device=device, **kw)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "take.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (W, H))
    assert writer.isOpened()
    for i in range(N):
        writer.write(pattern_image(i))
    writer.release()
    return path


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seq")
    for i in range(5):
        assert cv2.imwrite(str(folder / f"img_{i:04d}.png"), pattern_image(i))
    (folder / "notes.txt").write_text("not an image")
    return folder


def test_video_file_frames_in_order(video):
    cam = OpenCVCamera(cfg(str(video)))
    assert isinstance(cam, CameraDriver)
    cam.open()
    granted = cam.configure()
    assert (granted.width, granted.height) == (W, H)
    assert granted.fps == pytest.approx(25.0)
    assert granted.pixel_format == "MJPG"
    frames = [cam.grab() for _ in range(N)]
    with pytest.raises(CameraDisconnectedError, match="end of file"):
        cam.grab()
    cam.close()
    assert [f.index for f in frames] == list(range(N))
    assert [decoded_index(f.image) for f in frames] == list(range(N))
    # file time = index / fps, exactly
    assert [f.timestamp_ns for f in frames] == [round(i * 1e9 / 25.0) for i in range(N)]
    for i, f in enumerate(frames):
        assert f.image.shape == (H, W, 3) and f.image.dtype == np.uint8 and f.camera_id == "cam0"
        assert abs(float(f.image[:30].mean()) - 10 * i) < 4  # JPEG keeps the flat level
        assert f.encoded is None
    hosts = [f.host_timestamp_ns for f in frames]
    assert hosts == sorted(hosts)


def test_video_file_jpeg_passthrough_is_the_files_bytes(video):
    with OpenCVCamera(cfg(str(video), store="jpeg")) as cam:
        granted = cam.configure()
        assert granted.extra["store"] == "jpeg"
        frames = [cam.grab() for _ in range(N)]
    for i, f in enumerate(frames):
        assert f.encoded[:2] == b"\xff\xd8"
        # the decoded image is the decode of exactly those bytes
        again = cv2.imdecode(np.frombuffer(f.encoded, np.uint8), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(again, f.image)
        assert decoded_index(f.image) == i


def test_video_loop_continues_index_and_time(video):
    with OpenCVCamera(cfg(str(video), loop=True)) as cam:
        frames = [cam.grab() for _ in range(N + 3)]
    assert [decoded_index(f.image) for f in frames] == list(range(N)) + [0, 1, 2]
    assert [f.index for f in frames] == list(range(N + 3))
    ts = np.diff([f.timestamp_ns for f in frames])
    assert np.all(ts > 0)


def test_image_sequence_pattern_and_directory(sequence):
    pattern = str(sequence / "img_%04d.png")
    assert [p.name for p in expand_pattern(pattern)] == [f"img_{i:04d}.png" for i in range(5)]
    for device in (pattern, str(sequence)):
        with OpenCVCamera(cfg(device, fps=10)) as cam:
            granted = cam.configure()
            assert (granted.width, granted.height, granted.fps) == (W, H, 10)
            frames = [cam.grab() for _ in range(5)]
            with pytest.raises(CameraDisconnectedError, match="end of file"):
                cam.grab()
        for i, f in enumerate(frames):
            np.testing.assert_array_equal(f.image, pattern_image(i))  # PNG is lossless
            assert f.index == i and f.timestamp_ns == i * 100_000_000


def test_jpeg_directory_keeps_file_bytes(tmp_path):
    data = []
    for i in range(3):
        ok, buf = cv2.imencode(".jpg", pattern_image(i))
        (tmp_path / f"{i:02d}.jpg").write_bytes(buf.tobytes())
        data.append(buf.tobytes())
    with OpenCVCamera(cfg(str(tmp_path), store="jpeg")) as cam:
        assert cam.configure().extra["store"] == "jpeg"
        assert [cam.grab().encoded for _ in range(3)] == data


def test_requested_size_differs_from_file_warns(video, caplog):
    with caplog.at_level(logging.WARNING, logger="stage.drivers.opencv"):
        with OpenCVCamera(cfg(str(video), width=640, height=480)) as cam:
            granted = cam.configure()
    assert (granted.width, granted.height) == (W, H)
    assert "requested 640x480" in caplog.text and f"{W}x{H}" in caplog.text


def test_missing_sources_are_clear_errors(tmp_path):
    for device, match in [
        (99, r"/dev/video99.*stage cameras"),
        ("/dev/video99", r"/dev/video99.*stage cameras"),
        (str(tmp_path / "nope.avi"), "video file .*nope.avi not found"),
        (str(tmp_path / "none_%03d.png"), "no images match"),
        (str(tmp_path), "holds no images"),
    ]:
        cam = OpenCVCamera(cfg(device))
        with pytest.raises(CameraNotFoundError, match=match):
            cam.open()
        assert not cam.is_open


def test_corrupt_video_is_not_found_error(tmp_path):
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"RIFF\x00\x00garbage" * 10)
    with pytest.raises(CameraNotFoundError, match="cannot open video file"):
        OpenCVCamera(cfg(str(bad))).open()


# -- a V4L2 device, emulated: the same class, the device code path -------------------------------


class FakeV4L2Capture:
    """Emulates what OpenCV's V4L2 backend does with a UVC webcam.

    It grants only 640x480 (whatever is asked), 30 fps, MJPG when asked; with
    ``CONVERT_RGB = 0`` it returns the raw MJPEG buffer as a (1, N) uint8 array;
    ``POS_MSEC`` is the buffer timestamp; after ``fail_after`` frames reads fail.
    """

    fail_after = 10**9
    corrupt_at: frozenset = frozenset()

    def __init__(self, target, api):
        assert api == cv2.CAP_V4L2
        self.props = {cv2.CAP_PROP_FOURCC: float(cv2.VideoWriter.fourcc(*"YUYV")), cv2.CAP_PROP_FPS: 30.0,
                      cv2.CAP_PROP_CONVERT_RGB: 1.0, cv2.CAP_PROP_AUTO_EXPOSURE: 3.0, cv2.CAP_PROP_EXPOSURE: 156.0,
                      cv2.CAP_PROP_GAIN: 32.0}
        self.n = 0
        self.msec = 0.0

    def isOpened(self):
        return True

    def getBackendName(self):
        return "V4L2"

    def set(self, prop, value):
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return True  # silently keeps 640x480
        if prop == cv2.CAP_PROP_FPS:
            return True  # keeps 30
        if prop == cv2.CAP_PROP_EXPOSURE:
            self.props[prop] = float(2 * int(value / 2 + 0.5))  # rounds to its step of 2
            return True
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return 640.0
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            return 480.0
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.msec
        return self.props.get(prop, -1.0)

    def read(self):
        if self.n >= self.fail_after:
            return False, None
        img = np.full((480, 640, 3), 7 * self.n % 256, np.uint8)
        self.msec = 5_000_000.0 + self.n * 1000.0 / 30.0 + (33.4 if self.n >= 3 else 0.0)  # a driver drop after 3
        self.n += 1
        if self.props[cv2.CAP_PROP_CONVERT_RGB] == 0 and fourcc_to_str(self.props[cv2.CAP_PROP_FOURCC]) == "MJPG":
            if self.n - 1 in self.corrupt_at:  # what a starved USB bus delivers
                return True, np.frombuffer(b"\xff\xd8\xff\x00" + bytes(60), np.uint8).reshape(1, -1)
            ok, buf = cv2.imencode(".jpg", img)
            return True, buf.reshape(1, -1)
        return True, img

    def release(self):
        pass


@pytest.fixture
def fake_v4l2(monkeypatch):
    monkeypatch.setattr(ocv.sys, "platform", "linux")
    monkeypatch.setattr(ocv, "_node_state", lambda node: "ok" if node == "/dev/video4" else "missing")
    monkeypatch.setattr(ocv.cv2, "VideoCapture", FakeV4L2Capture)
    FakeV4L2Capture.fail_after = 10**9
    FakeV4L2Capture.corrupt_at = frozenset()
    return FakeV4L2Capture


def test_device_reports_what_it_granted(fake_v4l2, caplog):
    cam = OpenCVCamera(cfg(4, width=1280, height=720, fps=60, exposure=10.1, store="jpeg"))
    with caplog.at_level(logging.WARNING, logger="stage.drivers.opencv"):
        cam.open()
        granted = cam.configure()
    assert (granted.width, granted.height, granted.fps) == (640, 480, 30.0)
    assert granted.pixel_format == "MJPG"
    assert granted.exposure == pytest.approx(10.2)  # 101 units of 100 us rounded by the device to 102
    assert cam._cap.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1  # manual
    assert "granted 640x480" in caplog.text and "granted 30 fps" in caplog.text
    frames = [cam.grab() for _ in range(5)]
    cam.close()
    for i, f in enumerate(frames):
        assert f.encoded is not None and f.encoded[:2] == b"\xff\xd8"
        assert f.image.shape == (480, 640, 3)
        assert abs(float(f.image.mean()) - 7 * i) < 2
    # exposure and gain: granted, and read again from the device (at most once a second) with the frames
    assert granted.extra["gain"] == 32.0 and granted.extra["gain_unit"] == "V4L2 gain"
    assert all(f.exposure_ms == pytest.approx(10.2) and f.gain == 32.0 for f in frames)
    # the device clock (V4L2 buffer timestamps), not the host's, in ns
    ts = np.array([f.timestamp_ns for f in frames])
    assert ts[0] == 5_000_000_000_000
    np.testing.assert_allclose(np.diff(ts) / 1e6, [33.333, 33.333, 66.733, 33.333], atol=1e-3)


def test_device_in_auto_exposure_without_a_gain_control(fake_v4l2):
    cam = OpenCVCamera(cfg(4, width=640, height=480, fps=30))
    cam.open()
    del cam._cap.props[cv2.CAP_PROP_GAIN]  # OpenCV answers -1 for a control the device lacks
    granted = cam.configure()
    f = cam.grab()
    cam.close()
    assert granted.exposure is None and "gain" not in granted.extra  # auto: the control holds a stale value
    assert f.exposure_ms is None and f.gain is None


def test_device_disconnect_after_repeated_failures(fake_v4l2):
    fake_v4l2.fail_after = 4
    with OpenCVCamera(cfg("/dev/video4")) as cam:
        cam.configure()
        for _ in range(4):
            assert cam.grab().encoded is None  # store = "raw": no bytes kept
        with pytest.raises(CameraDisconnectedError, match="stopped delivering frames"):
            cam.grab()


def test_device_drops_undecodable_mjpeg_frames(fake_v4l2):
    fake_v4l2.corrupt_at = frozenset({1, 2})
    with OpenCVCamera(cfg(4, store="jpeg")) as cam:
        cam.configure()
        frames = [cam.grab() for _ in range(3)]
    # device frames 1 and 2 were garbage: delivered are 0, 3, 4 (by their grey level 7 * n)
    assert [round(float(f.image.mean()) / 7) for f in frames] == [0, 3, 4]
    assert all(f.encoded[:2] == b"\xff\xd8" for f in frames)


def test_registry_opens_opencv_with_rig_fps(video):
    rig = parse_rig({"fps": 12.5, "cameras": [{"id": "v", "driver": "opencv", "device": str(video)}]})
    drv = open_driver(rig.cameras[0], rig)
    assert isinstance(drv, OpenCVCamera) and drv.camera_id == "v" and drv.config.fps == 12.5


def test_invalid_input(tmp_path, video):
    with pytest.raises(ValueError, match="OpenCVCameraConfig"):
        OpenCVCamera({"id": "x", "device": 0})
    with pytest.raises(ValueError, match="exactly one integer field"):
        OpenCVCamera(cfg(str(tmp_path / "a_%d_%d.png")))
    with pytest.raises(ValueError, match="device index"):
        classify_source(-1)
    with pytest.raises(ValueError, match="device must be"):
        classify_source(1.5)
    with pytest.raises(ValueError, match="empty"):
        classify_source("  ")
    with pytest.raises(CameraError, match="not open"):
        OpenCVCamera(cfg(str(video))).grab()
    with pytest.raises(ValueError, match="camera config"):
        open_driver({"driver": "opencv"})
    with pytest.raises(ValueError, match="rig must be"):
        open_driver(cfg(0), rig={"fps": 30})
    with pytest.raises(ValueError, match="fake cameras need the rig"):
        open_driver(FakeCameraConfig(id="f", driver="fake"))
    assert classify_source("3") == ocv.Source("device", 3)
    assert classify_source("rtsp://cam/1").kind == "stream"
    assert fourcc_to_str(0) == "" and fourcc_to_str(cv2.VideoWriter.fourcc(*"MJPG")) == "MJPG"
