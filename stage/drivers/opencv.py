"""``driver = "opencv"``: webcams, video files and image sequences through ``cv2.VideoCapture``.

One class, :class:`OpenCVCamera`, reads every source a rig (or ``stage import``)
can name in ``device``:

* a device index (``0``) or node (``"/dev/video2"``), opened with the V4L2
  backend on Linux;
* a network stream (``"rtsp://..."``, ``"http://..."``);
* a video file (``"take/cam0.avi"``);
* an image sequence: a printf pattern (``"cam0/img_%04d.png"``) or a directory
  of images, sorted by name; a single image is a one-frame sequence.

Live devices are configured with :meth:`OpenCVCamera.configure` (MJPG first, then
size, fps and manual exposure, the order V4L2 wants) and report what the device
actually granted. When the rig asks ``store = "jpeg"`` and the camera delivers
MJPG, the camera's own JPEG bytes are kept in :attr:`Frame.encoded`
(``CAP_PROP_CONVERT_RGB = 0`` makes V4L2 hand over the raw MJPEG buffer), and
the decoded image is in :attr:`Frame.image`. MJPG video files and JPEG image
sequences pass their bytes through the same way.

Timestamps: for devices the V4L2 buffer timestamp (``CAP_PROP_POS_MSEC``; the
kernel's ``CLOCK_MONOTONIC`` for UVC cameras), falling back to the host clock
when the backend gives none; for files ``index / fps``. ``exposure`` in the rig
is in milliseconds (V4L2 counts ``exposure_time_absolute`` in 100 µs units).
"""

from __future__ import annotations

import logging
import os
import re
import struct
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import cv2
import numpy as np

from stage.drivers.base import (
    CameraDisconnectedError,
    CameraError,
    CameraNotFoundError,
    Granted,
    unmirror,
)
from stage.frame import Frame
from stage.rig import CameraConfig

__all__ = ["OpenCVCamera", "Source", "classify_source", "fourcc_to_str", "expand_pattern", "IMAGE_SUFFIXES"]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm", ".exr", ".jp2"})
_JPEG_SUFFIXES = frozenset({".jpg", ".jpeg"})
_LIVE_KINDS = frozenset({"device", "stream"})
_MAX_FAILED_READS = 3  # consecutive failed reads before a live device counts as disconnected
_MAX_CORRUPT_FRAMES = 30  # consecutive undecodable (e.g. truncated MJPEG) frames before giving up
_V4L2_EXPOSURE_UNIT_MS = 0.1  # V4L2 exposure_time_absolute is in 100 µs units
_V4L2_EXPOSURE_MANUAL = 1  # V4L2_EXPOSURE_MANUAL in the exposure_auto menu
_HINT = "run `stage cameras` to list what is attached"

SourceKind = Literal["device", "stream", "video", "pattern", "directory", "image"]


@dataclass(frozen=True)
class Source:
    """What a camera config's ``device`` names.

    Parameters
    ----------
    kind : {"device", "stream", "video", "pattern", "directory", "image"}
    target : int or str
        Device index, device node / URL / file path, printf pattern or directory.
    """

    kind: SourceKind
    target: int | str

    @property
    def live(self) -> bool:
        """A device or network stream (as opposed to recorded footage)."""
        return self.kind in _LIVE_KINDS

    def describe(self) -> str:
        if self.kind == "device" and isinstance(self.target, int):
            return f"camera index {self.target}"
        return f"{self.kind} {self.target!s}"


def classify_source(device: int | str) -> Source:
    """Tell what a ``device`` setting names (no file or device access beyond ``stat``).

    Parameters
    ----------
    device : int or str
        Index, ``/dev/video*`` path, URL, printf pattern (one ``%d``-style field),
        directory, image or video file.

    Returns
    -------
    Source

    Raises
    ------
    ValueError
        ``device`` is not an int or a non-empty string, or is a pattern with
        other than one integer field.
    """
    if isinstance(device, bool) or not isinstance(device, (int, str)):
        raise ValueError(f"device must be an int index or a path string, got {type(device).__name__}")
    if isinstance(device, int):
        if device < 0:
            raise ValueError(f"device index must be >= 0, got {device}")
        return Source("device", device)
    text = device.strip()
    if not text:
        raise ValueError("device must not be empty")
    if text.isdigit():
        return Source("device", int(text))
    if "://" in text:
        return Source("stream", text)
    if text.startswith("/dev/"):
        return Source("device", text)
    if "%" in text:
        _pattern_regex(text)  # validates
        return Source("pattern", text)
    p = Path(text).expanduser()
    if p.is_dir():
        return Source("directory", str(p))
    if p.suffix.lower() in IMAGE_SUFFIXES:
        return Source("image", str(p))
    return Source("video", str(p))


_PRINTF = re.compile(r"%(0?)(\d*)d")


def _pattern_regex(pattern: str) -> tuple[Path, re.Pattern]:
    name = Path(pattern).name
    fields = _PRINTF.findall(name)
    if len(fields) != 1 or name.count("%") != 1 or "%" in str(Path(pattern).parent):
        raise ValueError(f"device pattern {pattern!r} must have exactly one integer field like %04d in the file name")
    zero, width = fields[0]
    m = _PRINTF.search(name)
    prefix, suffix = re.escape(name[: m.start()]), re.escape(name[m.end():])
    digits = rf"(\d{{{int(width)}}})" if zero and width else (r"( *\d+)" if width else r"(\d+)")
    return Path(pattern).parent, re.compile(rf"^{prefix}{digits}{suffix}$")


def expand_pattern(pattern: str) -> list[Path]:
    """Files matching a printf pattern such as ``img_%04d.png``, in numeric order.

    Parameters
    ----------
    pattern : str
        Path whose file name holds one ``%d`` / ``%0Nd`` field.

    Returns
    -------
    list of Path
        Existing files, sorted by the number in the field (empty when none match).
    """
    folder, rx = _pattern_regex(pattern)
    if not folder.is_dir():
        return []
    hits = []
    for entry in folder.iterdir():
        m = rx.match(entry.name)
        if m and entry.is_file():
            hits.append((int(m.group(1)), entry))
    return [p for _, p in sorted(hits)]


def _list_images(directory: Path) -> list[Path]:
    return sorted(
        (p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: p.name,
    )


def fourcc_to_str(code: float | int) -> str:
    """``CAP_PROP_FOURCC`` value -> four characters (``""`` when unknown)."""
    try:
        value = int(code)
    except (TypeError, ValueError):
        return ""
    if value <= 0:
        return ""
    text = struct.pack("<I", value & 0xFFFFFFFF).decode("latin-1")
    return text.strip("\x00 ") if text.isprintable() else ""


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's own stderr warnings while probing sources (we raise clear errors instead)."""
    logging_mod = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging_mod is None:
        yield
        return
    old = logging_mod.getLogLevel()
    logging_mod.setLogLevel(logging_mod.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        logging_mod.setLogLevel(old)


def _node_state(node: str) -> Literal["ok", "missing", "denied"]:
    """Whether a device node exists and is readable and writable by us."""
    if not os.path.exists(node):
        return "missing"
    return "ok" if os.access(node, os.R_OK | os.W_OK) else "denied"


def _backend_available(api: int) -> bool:
    try:
        return api in cv2.videoio_registry.getBackends()
    except (AttributeError, cv2.error):
        return False


def _to_bgr(arr: np.ndarray) -> np.ndarray:
    if arr.ndim == 2:
        return cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    if arr.shape[2] == 4:
        return cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    if arr.shape[2] == 1:
        return cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    return arr


def _decode_jpeg(data: np.ndarray | bytes) -> np.ndarray | None:
    buf = np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray)) else data.reshape(-1)
    if buf.size < 4 or buf[0] != 0xFF or buf[1] != 0xD8:
        return None
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return img


class OpenCVCameraConfig(CameraConfig):
    """A ``cv2.VideoCapture`` source: device index, ``/dev/video*`` path, video file or image sequence."""

    driver: Literal["opencv"]
    device: int | str = 0
    exposure: float | None = None  # manual exposure in milliseconds; None = auto
    mjpg: bool = True
    loop: bool = False


class OpenCVCamera:
    """A ``cv2.VideoCapture`` camera: device, stream, video file or image sequence.

    Parameters
    ----------
    config : OpenCVCameraConfig
        The rig's camera entry. ``fps`` None means "the device's / file's own rate"
        (30 for image sequences); :func:`stage.drivers.registry.open_driver` fills
        it from the rig.

    Notes
    -----
    ``open -> configure -> grab ... -> close``; also a context manager. ``grab``
    raises :class:`CameraDisconnectedError` when a device stops delivering
    (``_MAX_FAILED_READS`` failed reads in a row) or a file ends (unless
    ``loop``). ``Frame.index`` counts the frames this source delivered
    (OpenCV's V4L2 backend does not expose the driver's sequence number).
    """

    config_model = OpenCVCameraConfig

    def __init__(self, config: OpenCVCameraConfig) -> None:
        if not isinstance(config, OpenCVCameraConfig):
            raise ValueError(f"config must be an OpenCVCameraConfig, got {type(config).__name__}")
        self.config = config
        self.camera_id = config.id
        self.source = classify_source(config.device)
        self._cap: cv2.VideoCapture | None = None
        self._files: list[Path] | None = None
        self._granted: Granted | None = None
        self._count = 0
        self._pos = 0  # next file of a sequence
        self._failed = self._corrupt = 0
        self._last_ts = -1
        self._passthrough = False  # frames arrive as JPEG bytes
        self._fps = 0.0
        self._manual_exposure = False
        self._levels_at = -(10**18)  # when exposure and gain were last read (host ns)
        self._level_cache: tuple[float | None, float | None] = (None, None)

    # -- lifecycle ----------------------------------------------------------
    def __enter__(self) -> "OpenCVCamera":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"OpenCVCamera({self.camera_id!r}, {self.source.describe()})"

    @property
    def is_open(self) -> bool:
        return self._cap is not None or self._files is not None

    def open(self) -> None:
        """Open the source.

        Raises
        ------
        CameraNotFoundError
            The device, file, directory or pattern does not exist, holds no
            images, or cannot be opened (permissions, unsupported codec).
        """
        if self.is_open:
            return
        kind, target = self.source.kind, self.source.target
        who = f"camera {self.camera_id!r}"
        if kind in ("pattern", "directory", "image"):
            if kind == "pattern":
                files = expand_pattern(str(target))
                if not files:
                    raise CameraNotFoundError(f"{who}: no images match the pattern {target!s}")
            elif kind == "directory":
                files = _list_images(Path(target))
                if not files:
                    raise CameraNotFoundError(
                        f"{who}: directory {target!s} holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})"
                    )
            else:
                if not Path(target).is_file():
                    raise CameraNotFoundError(f"{who}: image {target!s} not found")
                files = [Path(target)]
            self._files = files
            self._pos = 0
        elif kind == "video":
            if not Path(target).is_file():
                raise CameraNotFoundError(f"{who}: video file {target!s} not found")
            api = cv2.CAP_FFMPEG if _backend_available(cv2.CAP_FFMPEG) else cv2.CAP_ANY
            with _quiet_opencv():
                cap = cv2.VideoCapture(str(target), api)
            if not cap.isOpened():
                cap.release()
                raise CameraNotFoundError(f"{who}: cannot open video file {target!s} (unsupported or corrupt)")
            self._cap = cap
        elif kind == "stream":
            with _quiet_opencv():
                cap = cv2.VideoCapture(str(target), cv2.CAP_ANY)
            if not cap.isOpened():
                cap.release()
                raise CameraNotFoundError(f"{who}: cannot open stream {target!s}")
            self._cap = cap
        else:
            self._cap = self._open_device(target)
        self._count = 0
        self._failed = self._corrupt = 0
        self._last_ts = -1
        log.debug("%s: opened %s", self.camera_id, self.source.describe())

    def _open_device(self, target: int | str) -> cv2.VideoCapture:
        who = f"camera {self.camera_id!r}"
        linux = sys.platform.startswith("linux")
        node = f"/dev/video{target}" if isinstance(target, int) else str(target)
        if linux or not isinstance(target, int):
            state = _node_state(node)
            if state == "missing":
                raise CameraNotFoundError(f"{who}: no video device {node} ({_HINT})")
            if state == "denied":
                raise CameraNotFoundError(
                    f"{who}: no permission to open {node}; add yourself to the 'video' group "
                    f"(sudo usermod -aG video $USER, then log in again)"
                )
        api = cv2.CAP_V4L2 if linux else cv2.CAP_ANY
        with _quiet_opencv():
            cap = cv2.VideoCapture(target if isinstance(target, int) else node, api)
        if not cap.isOpened():
            cap.release()
            raise CameraNotFoundError(
                f"{who}: cannot open {node} as a capture device (busy in another program, "
                f"or a metadata node rather than the camera's video node; {_HINT})"
            )
        return cap

    def close(self) -> None:
        """Release the source (idempotent)."""
        if self._cap is not None:
            self._cap.release()
        self._cap = None
        self._files = None
        self._granted = None
        self._passthrough = False

    # -- configure ----------------------------------------------------------
    def configure(self) -> Granted:
        """Apply the config and report what the source actually delivers.

        Returns
        -------
        Granted
            Size, fps, pixel format (fourcc or ``"BGR"``) and exposure (ms) read
            back from the device; ``extra`` holds ``source``, ``backend`` and
            ``store`` (``"jpeg"`` when frames carry the camera's own bytes).
        """
        if not self.is_open:
            self.open()
        if self._files is not None:
            granted = self._configure_sequence()
        elif self.source.live:
            granted = self._configure_device()
        else:
            granted = self._configure_video()
        self._granted = granted
        self._fps = granted.fps
        return granted

    def _explicit(self, name: str) -> bool:
        return name in self.config.model_fields_set

    def _warn_size(self, width: int, height: int) -> None:
        cfg = self.config
        if (self._explicit("width") or self._explicit("height")) and (width, height) != (cfg.width, cfg.height):
            log.warning(
                "%s: requested %dx%d, %s delivers %dx%d",
                self.camera_id, cfg.width, cfg.height, self.source.describe(), width, height,
            )

    def _configure_sequence(self) -> Granted:
        assert self._files is not None
        first = self._read_file(self._files[0])[0]
        h, w = first.shape[:2]
        self._warn_size(w, h)
        fps = float(self.config.fps or 30.0)
        jpeg = self.config.store == "jpeg" and all(p.suffix.lower() in _JPEG_SUFFIXES for p in self._files)
        self._passthrough = jpeg
        self._first_size = (w, h)
        return Granted(
            width=w, height=h, fps=fps, pixel_format="JPEG" if jpeg else "BGR",
            extra={"source": self.source.kind, "backend": "imread", "frames": len(self._files),
                   "store": "jpeg" if jpeg else "raw"},
        )

    def _configure_video(self) -> Granted:
        cap = self._cap
        assert cap is not None
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if not np.isfinite(fps) or fps <= 0:
            fps = float(self.config.fps or 30.0)
        if self._explicit("fps") and self.config.fps and abs(fps - self.config.fps) > 0.01 * self.config.fps:
            log.warning("%s: requested %.3g fps, the file is %.3g fps; timestamps follow the file",
                        self.camera_id, self.config.fps, fps)
        self._warn_size(w, h)
        fourcc = fourcc_to_str(cap.get(cv2.CAP_PROP_FOURCC))
        jpeg = False
        if self.config.store == "jpeg" and fourcc.upper() in ("MJPG", "JPEG", "MJPEG"):
            # FFmpeg raw mode: read() returns the demuxed packet, i.e. each frame's JPEG bytes
            jpeg = bool(cap.set(cv2.CAP_PROP_FORMAT, -1))
        self._passthrough = jpeg
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        return Granted(
            width=w, height=h, fps=fps, pixel_format=fourcc or "BGR",
            extra={"source": "video", "backend": cap.getBackendName(), "frames": n, "fourcc": fourcc,
                   "store": "jpeg" if jpeg else "raw"},
        )

    def _configure_device(self) -> Granted:
        cap = self._cap
        assert cap is not None
        cfg = self.config
        backend = cap.getBackendName()
        with _quiet_opencv():
            if cfg.mjpg:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*"MJPG"))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)
            if cfg.fps:
                cap.set(cv2.CAP_PROP_FPS, cfg.fps)
            if cfg.exposure is not None:
                manual = cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _V4L2_EXPOSURE_MANUAL)
                value = round(cfg.exposure / _V4L2_EXPOSURE_UNIT_MS) if backend == "V4L2" else cfg.exposure
                if not (manual and cap.set(cv2.CAP_PROP_EXPOSURE, value)):
                    log.warning("%s: the device refused manual exposure %.3g ms", self.camera_id, cfg.exposure)
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            fourcc = fourcc_to_str(cap.get(cv2.CAP_PROP_FOURCC))
            exposure = None
            if cfg.exposure is not None:
                raw = cap.get(cv2.CAP_PROP_EXPOSURE)
                if raw is not None and raw >= 0:
                    exposure = raw * _V4L2_EXPOSURE_UNIT_MS if backend == "V4L2" else float(raw)
            jpeg = False
            if cfg.store == "jpeg":
                if fourcc == "MJPG":
                    jpeg = bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0))
                else:
                    log.info("%s: store = 'jpeg' but the device delivers %s, not MJPG; frames are stored raw",
                             self.camera_id, fourcc or "an unknown format")
        if not np.isfinite(fps) or fps <= 0:
            fps = float(cfg.fps or 30.0)
        if (w, h) != (cfg.width, cfg.height):
            log.warning("%s: requested %dx%d, the device granted %dx%d", self.camera_id, cfg.width, cfg.height, w, h)
        if cfg.fps and abs(fps - cfg.fps) > 0.01 * cfg.fps:
            log.warning("%s: requested %.3g fps, the device granted %.3g fps", self.camera_id, cfg.fps, fps)
        if cfg.mjpg and fourcc and fourcc != "MJPG":
            log.warning("%s: requested MJPG, the device delivers %s (more USB bandwidth; see `stage cameras`)", self.camera_id, fourcc)
        if cfg.exposure is not None and exposure is not None and abs(exposure - cfg.exposure) > max(0.05 * cfg.exposure, 0.1):
            log.warning("%s: requested exposure %.3g ms, the device granted %.3g ms", self.camera_id, cfg.exposure, exposure)
        self._passthrough = jpeg
        self._manual_exposure = exposure is not None
        extra = {"source": self.source.kind, "backend": backend, "fourcc": fourcc, "store": "jpeg" if jpeg else "raw"}
        gain = self._read_gain()
        if gain is not None:
            extra.update(gain=gain, gain_unit=f"{backend} gain")
        return Granted(width=w, height=h, fps=fps, pixel_format=fourcc or "BGR", exposure=exposure, extra=extra)

    def _read_gain(self) -> float | None:
        """The device's gain (``CAP_PROP_GAIN``, in the backend's units), or None where it has none
        (OpenCV answers -1 for a control the device lacks, 0 where the backend reads none)."""
        with _quiet_opencv():
            raw = self._cap.get(cv2.CAP_PROP_GAIN)
        return float(raw) if raw is not None and np.isfinite(raw) and raw > 0 else None

    def _read_exposure_ms(self) -> float | None:
        """The device's exposure in ms while it is manual (an auto exposure's V4L2 control holds the
        last value set, not the sensor's), else None."""
        if not self._manual_exposure:
            return None
        with _quiet_opencv():
            raw = self._cap.get(cv2.CAP_PROP_EXPOSURE)
        if raw is None or not np.isfinite(raw) or raw < 0:
            return None
        return raw * _V4L2_EXPOSURE_UNIT_MS if self._cap.getBackendName() == "V4L2" else float(raw)

    def _levels(self, host_ns: int) -> tuple[float | None, float | None]:
        """(exposure ms, gain) of a device, read again at most once a second (one ioctl each)."""
        if host_ns - self._levels_at >= 1_000_000_000:
            self._levels_at = host_ns
            self._level_cache = (self._read_exposure_ms(), self._read_gain())
        return self._level_cache

    # -- grab ---------------------------------------------------------------
    def grab(self) -> Frame:
        """Block until the next frame and return it.

        Raises
        ------
        CameraError
            The camera is not open.
        CameraDisconnectedError
            The device stopped delivering, or a file ended (unless ``loop``).
        """
        if not self.is_open:
            raise CameraError(f"camera {self.camera_id!r} is not open; call open() and configure() first")
        if self._granted is None:
            self.configure()
        if self._files is not None:
            image, encoded = self._grab_file()
            host = time.monotonic_ns()
            ts = self._file_timestamp()
        else:
            image, encoded, host, ts = self._grab_capture()
        exposure_ms, gain = self._levels(host) if self.source.live else (None, None)
        frame = Frame(
            image=image, camera_id=self.camera_id, index=self._count, timestamp_ns=ts,
            host_timestamp_ns=host, encoded=encoded, exposure_ms=exposure_ms, gain=gain,
        )
        self._count += 1
        return unmirror(frame) if self.config.mirror else frame

    def _file_timestamp(self) -> int:
        return int(round(self._count * 1e9 / self._fps))

    def _read_file(self, path: Path) -> tuple[np.ndarray, bytes | None]:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise CameraDisconnectedError(f"camera {self.camera_id!r}: cannot read {path}: {exc.strerror}") from None
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise CameraError(f"camera {self.camera_id!r}: {path} is not a readable image")
        return img, data

    def _grab_file(self) -> tuple[np.ndarray, bytes | None]:
        assert self._files is not None
        if self._pos >= len(self._files):
            if not self.config.loop:
                raise CameraDisconnectedError(
                    f"camera {self.camera_id!r}: end of file sequence after {len(self._files)} images ({self.source.target})"
                )
            self._pos = 0
        path = self._files[self._pos]
        self._pos += 1
        img, data = self._read_file(path)
        if (img.shape[1], img.shape[0]) != self._first_size:
            raise CameraError(
                f"camera {self.camera_id!r}: {path.name} is {img.shape[1]}x{img.shape[0]}, "
                f"the sequence started at {self._first_size[0]}x{self._first_size[1]}"
            )
        return img, (data if self._passthrough else None)

    def _grab_capture(self) -> tuple[np.ndarray, bytes | None, int, int]:
        cap = self._cap
        assert cap is not None
        live = self.source.live
        looped = False
        while True:
            ok, arr = cap.read()
            host = time.monotonic_ns()
            image, encoded = self._convert(arr) if ok and arr is not None and arr.size else (None, None)
            if image is not None:
                self._failed = self._corrupt = 0
                break
            if live and ok:  # delivered but undecodable: a truncated MJPEG frame (USB bandwidth), drop it
                self._corrupt += 1
                log.debug("%s: dropped an undecodable frame (%d in a row)", self.camera_id, self._corrupt)
                if self._corrupt < _MAX_CORRUPT_FRAMES:
                    continue
                raise CameraDisconnectedError(
                    f"camera {self.camera_id!r}: {self.source.describe()} delivers only undecodable frames "
                    f"({self._corrupt} in a row); the USB bus is probably oversubscribed ({_HINT})"
                )
            if not live:
                if ok:  # a frame that does not decode: skip it like a device would drop it
                    log.warning("%s: skipping an undecodable frame in %s", self.camera_id, self.source.target)
                    continue
                if self.config.loop and self._count > 0 and not looped:
                    looped = True
                    cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                    continue
                raise CameraDisconnectedError(
                    f"camera {self.camera_id!r}: end of file {self.source.target} after {self._count} frames"
                )
            self._failed += 1
            if self._failed >= _MAX_FAILED_READS:
                raise CameraDisconnectedError(
                    f"camera {self.camera_id!r}: {self.source.describe()} stopped delivering frames "
                    f"({self._failed} failed reads after {self._count} frames); check the cable and the "
                    f"USB bus load ({_HINT})"
                )
            log.debug("%s: read failed (%d in a row)", self.camera_id, self._failed)
        if live:
            msec = cap.get(cv2.CAP_PROP_POS_MSEC)
            ts = int(round(msec * 1e6)) if msec and np.isfinite(msec) and msec > 0 else -1
            if ts <= self._last_ts:  # no (or a non-monotonic) device clock: use the host's
                ts = host
            self._last_ts = ts
        else:
            ts = self._file_timestamp()
        return image, encoded, host, ts

    def _convert(self, arr: np.ndarray) -> tuple[np.ndarray | None, bytes | None]:
        if self._passthrough and arr.dtype == np.uint8 and (arr.ndim == 1 or arr.shape[0] == 1):
            img = _decode_jpeg(arr)
            if img is None:
                return None, None
            return img, arr.tobytes()
        if arr.dtype != np.uint8:
            arr = cv2.convertScaleAbs(arr, alpha=255.0 / 65535.0) if arr.dtype == np.uint16 else arr.astype(np.uint8)
        return _to_bgr(arr), None
