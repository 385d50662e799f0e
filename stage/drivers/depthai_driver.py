"""``driver = "depthai"``: Luxonis OAK cameras through the depthai v3 API.

Each :class:`DepthAICamera` owns one device and one pipeline (several OAKs are
several cameras in the rig; ``device`` names one by its id, ``None`` takes the
first that is still free). The pipeline films the colour socket (``CAM_A`` by
default) and, with ``depth = true``, computes stereo depth from ``CAM_B``/``CAM_C``
aligned to the colour image (``StereoDepth.inputAlignTo`` on RVC2, an
``ImageAlign`` node on RVC4); a ``Sync`` node pairs colour and depth on the
device, so each :class:`~stage.frame.Frame` carries both. With
``store = "jpeg"`` the device's ``VideoEncoder`` (MJPEG) produces the bytes the
take keeps, and the host decodes them once for ``Frame.image``.

Timestamps are the device's capture times. By default (``clock="synced"``) they
are ``ImgFrame.getTimestamp()``: the device clock mapped onto the host's
monotonic clock by depthai's continuous time sync, so several OAKs share one
time base; ``clock="device"`` gives the raw ``getTimestampDevice()``.

The message -> Frame conversion (:func:`frame_from_messages`) and the factory
calibration -> :class:`calib.camera.Camera` conversion (:func:`factory_camera`)
are plain functions, testable with host-built ``dai.ImgFrame`` and
``dai.CalibrationHandler`` objects. depthai is imported only when one of them
runs or a camera opens (``import stage`` does not import it).
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np

from stage.drivers.base import (
    CameraDisconnectedError,
    CameraError,
    CameraNotFoundError,
    DriverUnavailableError,
    Granted,
    unmirror,
)
from stage.frame import Frame
from stage.rig import CameraConfig

if TYPE_CHECKING:  # pragma: no cover
    from calib.camera import Camera

__all__ = [
    "DepthAICamera",
    "frame_from_messages",
    "factory_camera",
    "fit_five_coefficients",
    "list_devices",
    "timedelta_to_ns",
    "import_depthai",
    "NO_DEVICE_HINT",
]

log = logging.getLogger(__name__)

NO_DEVICE_HINT = (
    "no OAK device found; check the USB connection (a USB 3 port and cable for full speed) and the "
    "udev rules (echo 'SUBSYSTEM==\"usb\", ATTRS{idVendor}==\"03e7\", MODE=\"0666\"' | "
    "sudo tee /etc/udev/rules.d/80-movidius.rules && sudo udevadm control --reload-rules && "
    "sudo udevadm trigger); in a container pass -v /dev/bus/usb:/dev/bus/usb; run `stage cameras`"
)

Clock = Literal["synced", "device"]
_STEREO_SIZE = (640, 400)  # mono sensors of OAK-D (OV9282) at their 400p mode
_COLOR_TYPES = ("BGR888i", "BGR888p", "RGB888i", "RGB888p", "NV12", "NV21", "YUV420p", "YUV422i", "YUV422p", "YUV444p", "YUV444i")
_GRAY_TYPES = ("GRAY8", "RAW8", "YUV400p")
_DEPTH_TYPES = ("RAW16", "GRAY16")


def import_depthai() -> Any:
    """Import depthai v3 or raise :class:`DriverUnavailableError` saying what to install."""
    try:
        import depthai as dai
    except ImportError as exc:
        raise DriverUnavailableError(
            f"the depthai driver needs the depthai package (v3): pip install 'depthai>=3' ({exc})"
        ) from None
    if not hasattr(getattr(dai, "node", None), "Camera") or not hasattr(dai.node.Camera, "requestOutput"):
        raise DriverUnavailableError(
            f"the depthai driver needs depthai v3, found {getattr(dai, '__version__', 'unknown')}: "
            "pip install -U 'depthai>=3'"
        )
    return dai


def timedelta_to_ns(td: _dt.timedelta) -> int:
    """Exact integer nanoseconds of a ``datetime.timedelta`` (depthai's timestamp type)."""
    if not isinstance(td, _dt.timedelta):
        raise ValueError(f"timestamp must be a datetime.timedelta, got {type(td).__name__}")
    return ((td.days * 86_400 + td.seconds) * 1_000_000 + td.microseconds) * 1_000


def _type_name(msg: Any) -> str:
    try:
        return msg.getType().name
    except AttributeError:
        return ""


def _is_encoded_frame(msg: Any) -> bool:
    return hasattr(msg, "getProfile") and hasattr(msg, "getFrameType")


def _decode_jpeg(data: np.ndarray, camera_id: str) -> np.ndarray:
    buf = np.ascontiguousarray(np.asarray(data, dtype=np.uint8).reshape(-1))
    if buf.size < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        raise ValueError(f"camera {camera_id!r}: encoded frame is not JPEG/MJPEG (use profile MJPEG)")
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"camera {camera_id!r}: a JPEG frame from the device does not decode")
    return img


def _color_image(msg: Any, camera_id: str) -> tuple[np.ndarray, bytes | None]:
    """(BGR image, encoded bytes or None) of an ImgFrame / EncodedFrame."""
    if _is_encoded_frame(msg):
        profile = msg.getProfile().name
        if profile not in ("JPEG", "MJPEG"):
            raise ValueError(
                f"camera {camera_id!r}: {profile} frames cannot be decoded one by one; "
                "configure the VideoEncoder with profile MJPEG"
            )
        data = np.asarray(msg.getData(), dtype=np.uint8)
        return _decode_jpeg(data, camera_id), data.tobytes()
    kind = _type_name(msg)
    if kind == "BITSTREAM":
        data = np.asarray(msg.getData(), dtype=np.uint8)
        return _decode_jpeg(data, camera_id), data.tobytes()
    if kind in _COLOR_TYPES:
        img = msg.getCvFrame()
    elif kind in _GRAY_TYPES:
        img = cv2.cvtColor(np.ascontiguousarray(msg.getCvFrame()), cv2.COLOR_GRAY2BGR)
    else:
        raise ValueError(f"camera {camera_id!r}: unsupported colour frame type {kind or type(msg).__name__}")
    img = np.ascontiguousarray(img)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"camera {camera_id!r}: {kind} frame converted to {img.dtype} {img.shape}, not BGR")
    return img, None


def _depth_image(msg: Any, shape: tuple[int, int], camera_id: str) -> np.ndarray:
    kind = _type_name(msg)
    if kind not in _DEPTH_TYPES:
        raise ValueError(f"camera {camera_id!r}: depth frame must be RAW16 (millimetres), got {kind or type(msg).__name__}")
    depth = np.asarray(msg.getFrame())
    if depth.dtype != np.uint16:
        depth = depth.view(np.uint16) if depth.dtype.itemsize == 1 else depth.astype(np.uint16)
    depth = depth.reshape(msg.getHeight(), msg.getWidth())
    if depth.shape != shape:
        # aligned depth at another resolution (size rounding on the device): nearest neighbour keeps mm values
        depth = cv2.resize(depth, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(depth)


def frame_from_messages(
    camera_id: str,
    img_frame: Any,
    depth_frame: Any = None,
    *,
    host_ns: int,
    clock: Clock = "synced",
) -> Frame:
    """Turn the device's messages into a :class:`Frame`.

    Parameters
    ----------
    camera_id : str
    img_frame : dai.ImgFrame or dai.EncodedFrame
        Colour: ``BGR888i``/``BGR888p``/``RGB888*``/``NV12`` (and other YUV),
        ``GRAY8``, or JPEG bytes (an MJPEG ``EncodedFrame`` or a ``BITSTREAM``
        ImgFrame from ``VideoEncoder``), kept in ``Frame.encoded``.
    depth_frame : dai.ImgFrame, optional
        ``RAW16`` depth in millimetres aligned to the colour image; resized
        (nearest neighbour) when its size differs.
    host_ns : int
        ``time.monotonic_ns()`` when the messages arrived.
    clock : {"synced", "device"}
        ``"synced"``: ``getTimestamp()`` (device clock on the host's time base);
        ``"device"``: ``getTimestampDevice()``.

    Returns
    -------
    Frame
        ``index`` = the colour frame's sequence number.

    Raises
    ------
    ValueError
        Bad arguments or a frame type that is not an image / not depth.
    """
    if not isinstance(camera_id, str) or not camera_id:
        raise ValueError("camera_id must be a non-empty string")
    if clock not in ("synced", "device"):
        raise ValueError(f"clock must be 'synced' or 'device', got {clock!r}")
    if isinstance(host_ns, bool) or not isinstance(host_ns, (int, np.integer)):
        raise ValueError(f"host_ns must be an int (time.monotonic_ns()), got {type(host_ns).__name__}")
    if img_frame is None or not hasattr(img_frame, "getSequenceNum"):
        raise ValueError(f"img_frame must be a depthai ImgFrame or EncodedFrame, got {type(img_frame).__name__}")
    image, encoded = _color_image(img_frame, camera_id)
    depth = None
    if depth_frame is not None:
        if not hasattr(depth_frame, "getFrame"):
            raise ValueError(f"depth_frame must be a depthai ImgFrame, got {type(depth_frame).__name__}")
        depth = _depth_image(depth_frame, image.shape[:2], camera_id)
    stamp = img_frame.getTimestamp() if clock == "synced" else img_frame.getTimestampDevice()
    exposure_ms, iso = _exposure(img_frame)
    return Frame(
        image=image,
        camera_id=camera_id,
        index=int(img_frame.getSequenceNum()),
        timestamp_ns=timedelta_to_ns(stamp),
        host_timestamp_ns=int(host_ns),
        depth=depth,
        encoded=encoded,
        exposure_ms=exposure_ms,
        gain=iso,
    )


def _exposure(img_frame: Any) -> tuple[float | None, float | None]:
    """The frame's exposure time (ms) and ISO sensitivity as the sensor set them
    (``getExposureTime`` / ``getSensitivity`` of an ``ImgFrame`` or ``EncodedFrame``); None where
    the message has none (0: a frame the sensor did not stamp, e.g. one built on the host)."""
    if not hasattr(img_frame, "getExposureTime"):
        return None, None
    exposure_ms = timedelta_to_ns(img_frame.getExposureTime()) / 1e6
    iso = float(img_frame.getSensitivity()) if hasattr(img_frame, "getSensitivity") else 0.0
    return (exposure_ms if exposure_ms > 0 else None), (iso if iso > 0 else None)


# -- factory calibration -------------------------------------------------------------------------


def fit_five_coefficients(
    K: np.ndarray, dist: np.ndarray, size: tuple[int, int], *, fisheye: bool = False, grid: int = 25
) -> tuple[np.ndarray, float]:
    """Best ``k1 k2 p1 p2 k3`` for a lens described by a richer model.

    OAK factory calibrations use OpenCV's rational model (14 coefficients) or
    the fisheye model (4); our one camera model has five. The image is sampled
    on a ``grid`` x ``grid`` pixel lattice, undistorted with the full model, and
    the five coefficients that map those rays back onto the same pixels are
    solved by linear least squares (the model is linear in them).

    Parameters
    ----------
    K : (3, 3) float ndarray
    dist : (N,) float ndarray
        4, 5, 8, 12 or 14 OpenCV coefficients (or 4 fisheye ``k1..k4``).
    size : (int, int)
        ``(width, height)``.
    fisheye : bool
        ``dist`` is the fisheye model.
    grid : int
        Samples per axis (>= 4).

    Returns
    -------
    dist5 : (5,) float ndarray
    rms_px : float
        RMS reprojection difference between the fitted and the full model over
        the grid, in pixels (how good a first guess this is).
    """
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a 3x3 intrinsics matrix with positive focal lengths, got shape {K.shape}")
    allowed = (4,) if fisheye else (4, 5, 8, 12, 14)
    if dist.size not in allowed:
        raise ValueError(f"dist must have {' or '.join(map(str, allowed))} coefficients, got {dist.size}")
    w, h = (int(s) for s in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"size must be (width, height) > 0, got {size}")
    if int(grid) < 4:
        raise ValueError(f"grid must be >= 4, got {grid}")
    u, v = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    if fisheye:
        und = cv2.fisheye.undistortPoints(pix, K, dist).reshape(-1, 2)
    else:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        und = cv2.undistortPoints(pix, K, dist, criteria=crit).reshape(-1, 2)
    ok = np.all(np.isfinite(und), axis=1)
    x, y = und[ok, 0], und[ok, 1]
    xd = (pix[ok, 0, 0] - K[0, 2]) / K[0, 0]
    yd = (pix[ok, 0, 1] - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    # x_d - x = x (k1 r2 + k2 r4 + k3 r6) + 2 p1 x y + p2 (r2 + 2 x^2);  y likewise
    ax = np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1)
    ay = np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)
    A = np.vstack([ax * K[0, 0], ay * K[1, 1]])  # weight residuals in pixels
    b = np.concatenate([(xd - x) * K[0, 0], (yd - y) * K[1, 1]])
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    rms = float(np.sqrt(np.mean((A @ coef - b) ** 2) * 2)) if b.size else float("nan")
    return coef.astype(np.float64), rms


def factory_camera(
    calibration: Any,
    socket: str = "CAM_A",
    *,
    size: tuple[int, int],
    name: str,
) -> "Camera":
    """A first-guess :class:`calib.camera.Camera` from an OAK's factory calibration.

    Parameters
    ----------
    calibration : dai.CalibrationHandler
        ``device.readCalibration()``.
    socket : {"CAM_A", "CAM_B", "CAM_C"}
    size : (int, int)
        ``(width, height)`` of the stream (intrinsics are scaled and cropped to it
        the way ``requestOutput``'s default crop mode does).
    name : str
        Camera id in the rig.

    Returns
    -------
    Camera
        Intrinsics and distortion (rational/fisheye models refit to five
        coefficients; ``meta["distortion_fit_rms_px"]`` says how well), pose =
        identity (the world frame is this camera's until the rig is calibrated).
    """
    from calib.camera import Camera

    dai = import_depthai()
    if not isinstance(calibration, dai.CalibrationHandler):
        raise ValueError(f"calibration must be a depthai CalibrationHandler, got {type(calibration).__name__}")
    if socket not in ("CAM_A", "CAM_B", "CAM_C", "CAM_D"):
        raise ValueError(f"socket must be CAM_A..CAM_D, got {socket!r}")
    w, h = (int(s) for s in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"size must be (width, height) > 0, got {size}")
    sock = getattr(dai.CameraBoardSocket, socket)
    try:
        K = np.asarray(calibration.getCameraIntrinsics(sock, w, h), dtype=np.float64)
        dist = np.asarray(calibration.getDistortionCoefficients(sock), dtype=np.float64)
        model = calibration.getDistortionModel(sock).name
    except RuntimeError as exc:
        raise CameraError(f"camera {name!r}: the device holds no factory calibration for {socket}: {exc}") from None
    fisheye = model == "Fisheye"
    if model not in ("Perspective", "Fisheye"):
        raise CameraError(f"camera {name!r}: {socket} uses the {model} lens model, which has no pinhole first guess")
    if not fisheye and dist.size >= 5 and not np.any(dist[5:]):
        dist5, rms = dist[:5].copy(), 0.0
    else:
        dist5, rms = fit_five_coefficients(K, dist, (w, h), fisheye=fisheye)
        if rms > 1.0:
            log.warning(
                "%s: the %s lens model fits our 5-coefficient model only to %.1f px RMS; calibrate this camera",
                name, model, rms,
            )
    meta = {
        "source": "depthai factory calibration",
        "socket": socket,
        "distortion_model": model,
        "distortion_full": [float(d) for d in dist],
        "distortion_fit_rms_px": rms,
    }
    return Camera(name=name, K=K, dist=dist5, R=np.eye(3), t=np.zeros(3), size=(w, h), meta=meta)


# -- devices -------------------------------------------------------------------------------------


def list_devices() -> list[dict]:
    """OAK devices depthai can see and that are free (USB and PoE).

    Returns
    -------
    list of dict
        ``{"id", "name", "state", "protocol", "platform"}`` per device.

    Raises
    ------
    DriverUnavailableError
        depthai v3 is not installed.
    """
    dai = import_depthai()
    out = []
    for info in dai.Device.getAllAvailableDevices():
        out.append(
            {
                "id": info.getDeviceId(),
                "name": info.name,
                "state": getattr(info.state, "name", str(info.state)),
                "protocol": getattr(info.protocol, "name", str(info.protocol)),
                "platform": getattr(info.platform, "name", str(info.platform)),
            }
        )
    return out


class DepthAICameraConfig(CameraConfig):
    """A Luxonis OAK camera through depthai v3."""

    driver: Literal["depthai"]
    device: str | None = None  # device id (MxId) or IP; None = first available
    depth: bool = True
    socket: Literal["CAM_A", "CAM_B", "CAM_C"] = "CAM_A"


class DepthAICamera:
    """One OAK camera: colour plus aligned stereo depth, device-synced timestamps.

    Parameters
    ----------
    config : DepthAICameraConfig
    clock : {"synced", "device"}
        See :func:`frame_from_messages`.
    timeout_s : float
        ``grab`` raises :class:`CameraDisconnectedError` when no frame arrives
        for this long (default: 2 s plus ten frame periods).
    """

    config_model = DepthAICameraConfig

    def __init__(self, config: DepthAICameraConfig, *, clock: Clock = "synced", timeout_s: float | None = None) -> None:
        if not isinstance(config, DepthAICameraConfig):
            raise ValueError(f"config must be a DepthAICameraConfig, got {type(config).__name__}")
        if clock not in ("synced", "device"):
            raise ValueError(f"clock must be 'synced' or 'device', got {clock!r}")
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.config = config
        self.camera_id = config.id
        self.clock: Clock = clock
        self._timeout_s = timeout_s
        self._dai: Any = None
        self._device: Any = None
        self._pipeline: Any = None
        self._queue: Any = None
        self._synced = False
        self._granted: Granted | None = None

    def __repr__(self) -> str:
        return f"DepthAICamera({self.camera_id!r}, device={self.config.device!r})"

    def __enter__(self) -> "DepthAICamera":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._device is not None

    @property
    def device(self) -> Any:
        """The ``dai.Device`` (None until opened)."""
        return self._device

    def open(self) -> None:
        """Connect to the configured OAK (or the first free one).

        Raises
        ------
        DriverUnavailableError
            depthai v3 is missing.
        CameraNotFoundError
            No OAK is attached, or none with the configured id.
        """
        if self.is_open:
            return
        dai = import_depthai()
        self._dai = dai
        infos = list(dai.Device.getAllAvailableDevices())  # fast; dai.Device() alone waits ~10 s for nothing
        want = self.config.device
        if not infos:
            raise CameraNotFoundError(f"camera {self.camera_id!r}: {NO_DEVICE_HINT}")
        if want is not None:
            match = [i for i in infos if want in (i.getDeviceId(), i.name)]
            if not match:
                ids = ", ".join(f"{i.getDeviceId()} ({i.name})" for i in infos)
                raise CameraNotFoundError(
                    f"camera {self.camera_id!r}: no free OAK device {want!r}; free devices: {ids}"
                )
            info = match[0]
        else:
            info = infos[0]
        try:
            self._device = dai.Device(info)
        except RuntimeError as exc:
            raise CameraNotFoundError(
                f"camera {self.camera_id!r}: cannot connect to OAK {info.getDeviceId()}: {exc} "
                "(in use by another program? udev rules? see docs/hardware.md)"
            ) from None
        log.info("%s: connected to OAK %s (%s)", self.camera_id, info.getDeviceId(), info.name)

    def configure(self) -> Granted:
        """Build and start the pipeline; report what the device delivers.

        Raises
        ------
        CameraError
            The device lacks the colour socket, or the stereo pair for depth.
        """
        if not self.is_open:
            self.open()
        if self._pipeline is not None:
            assert self._granted is not None
            return self._granted
        dai, dev, cfg = self._dai, self._device, self.config
        fps = float(cfg.fps or 30.0)
        size = (cfg.width, cfg.height)
        sockets = {s.name for s in dev.getConnectedCameras()}
        if cfg.socket not in sockets:
            raise CameraError(f"camera {self.camera_id!r}: the OAK has no {cfg.socket} camera (it has {sorted(sockets)})")
        if cfg.depth and not {"CAM_B", "CAM_C"} <= sockets:
            raise CameraError(f"camera {self.camera_id!r}: depth needs the CAM_B/CAM_C stereo pair; set depth = false")
        jpeg = cfg.store == "jpeg"
        sock = getattr(dai.CameraBoardSocket, cfg.socket)
        pipeline = dai.Pipeline(dev)
        cam = pipeline.create(dai.node.Camera).build(sock)
        color = cam.requestOutput(size, dai.ImgFrame.Type.NV12 if jpeg else dai.ImgFrame.Type.BGR888i, fps=fps)
        color_msgs = color
        if jpeg:
            enc = pipeline.create(dai.node.VideoEncoder).build(
                color, frameRate=fps, profile=dai.VideoEncoderProperties.Profile.MJPEG, quality=95
            )
            color_msgs = enc.out
        if cfg.depth:
            left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
            right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
            stereo = pipeline.create(dai.node.StereoDepth).build(
                left.requestOutput(_STEREO_SIZE, fps=fps),
                right.requestOutput(_STEREO_SIZE, fps=fps),
                presetMode=dai.node.StereoDepth.PresetMode.DEFAULT,
            )
            stereo.setLeftRightCheck(True)
            stereo.setDepthAlign(sock)
            if dev.getPlatform() == dai.Platform.RVC4:
                align = pipeline.create(dai.node.ImageAlign)
                stereo.depth.link(align.input)
                color.link(align.inputAlignTo)
                depth_out = align.outputAligned
            else:
                color.link(stereo.inputAlignTo)
                depth_out = stereo.depth
            sync = pipeline.create(dai.node.Sync)
            sync.setSyncThreshold(_dt.timedelta(seconds=0.5 / fps))
            color_msgs.link(sync.inputs["color"])
            depth_out.link(sync.inputs["depth"])
            queue = sync.out.createOutputQueue(maxSize=8, blocking=False)
        else:
            queue = color_msgs.createOutputQueue(maxSize=8, blocking=False)
        pipeline.start()
        self._pipeline, self._queue, self._synced = pipeline, queue, cfg.depth
        speed = getattr(dev.getUsbSpeed(), "name", "UNKNOWN")
        if speed in ("LOW", "FULL", "HIGH"):
            log.warning(
                "%s: the OAK runs on a USB 2 link (%s speed); use a USB 3 port and cable for full frame rates",
                self.camera_id, speed.lower(),
            )
        self._granted = Granted(
            width=size[0], height=size[1], fps=fps, pixel_format="MJPEG" if jpeg else "BGR", has_depth=cfg.depth,
            extra={"device_id": dev.getDeviceId(), "usb_speed": speed, "platform": dev.getPlatformAsString(),
                   "product": _safe(dev.getProductName), "store": "jpeg" if jpeg else "raw", "clock": self.clock,
                   "gain_unit": "ISO"},  # every frame says its exposure and sensitivity (frame_from_messages)
        )
        return self._granted

    def grab(self) -> Frame:
        """The next colour (+ depth) frame.

        Raises
        ------
        CameraError
            Not open.
        CameraDisconnectedError
            The device closed, crashed or sent nothing for ``timeout_s``.
        """
        if not self.is_open:
            raise CameraError(f"camera {self.camera_id!r} is not open; call open() and configure() first")
        if self._pipeline is None:
            self.configure()
        timeout = self._timeout_s or (2.0 + 10.0 / float(self.config.fps or 30.0))
        try:
            msg = self._queue.get(_dt.timedelta(seconds=timeout))
        except (RuntimeError, self._dai.MessageQueue.QueueException) as exc:
            raise CameraDisconnectedError(f"camera {self.camera_id!r}: the OAK stopped delivering: {exc}") from None
        host = time.monotonic_ns()
        if msg is None:
            closed = self._device.isClosed()
            raise CameraDisconnectedError(
                f"camera {self.camera_id!r}: no frame from the OAK for {timeout:.1f} s"
                + (" (device closed: unplugged?)" if closed else "")
            )
        if self._synced:
            frame = frame_from_messages(self.camera_id, msg["color"], msg["depth"], host_ns=host, clock=self.clock)
        else:
            frame = frame_from_messages(self.camera_id, msg, host_ns=host, clock=self.clock)
        return unmirror(frame) if self.config.mirror else frame

    def factory_camera(self) -> "Camera":
        """This device's factory calibration as a first-guess :class:`calib.camera.Camera`."""
        if not self.is_open:
            raise CameraError(f"camera {self.camera_id!r} is not open")
        return factory_camera(
            self._device.readCalibration(), self.config.socket,
            size=(self.config.width, self.config.height), name=self.camera_id,
        )

    def close(self) -> None:
        """Stop the pipeline and release the device (idempotent)."""
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError as exc:
                log.debug("%s: pipeline.stop: %s", self.camera_id, exc)
        if self._device is not None:
            try:
                self._device.close()
            except RuntimeError as exc:
                log.debug("%s: device.close: %s", self.camera_id, exc)
        self._pipeline = self._queue = self._device = None
        self._granted = None


def _safe(getter: Any) -> str | None:
    try:
        return str(getter())
    except RuntimeError:
        return None
