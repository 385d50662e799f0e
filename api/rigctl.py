"""The rig as the API sees it: its cameras, one capture at a time in the background, previews.

Captures go through :mod:`stage.capture` and write a take into
``DATA/takes/<take>.h5``; previews open one camera through
:func:`stage.drivers.open_driver`, grab a frame and close it. With a running stage
session (``stage serve --rig``) the cameras are the session's: captures record from
it and previews are its latest frames (nothing opens a camera a second time).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from api.errors import ConflictError, NotFoundError, UnavailableError
from api.paths import check_take_id, inside

__all__ = ["CaptureManager", "CaptureState"]

log = logging.getLogger(__name__)


@dataclass
class CaptureState:
    """The current (or last) capture."""

    state: str = "idle"  # idle | capturing | done | failed | stopped
    take: str | None = None
    frames: int | None = None
    duration_s: float | None = None
    started: float | None = None
    finished: float | None = None
    frames_written: int = 0
    error: str | None = None
    result: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class CaptureManager:
    """One background capture at a time on the rig of ``rig_path``.

    Parameters
    ----------
    rig_path : Path
        The rig TOML file.
    takes_dir : Path
        Where takes are written.
    driver_factory : callable, optional
        ``(config, rig) -> CameraDriver``; default :func:`stage.drivers.open_driver`.
    session : StageSession, optional
        A running stage session: captures record from its cameras.
    take_calibration : callable, optional
        ``() -> (Calibration or None, message)``: what a take recorded from the session stores
        (:meth:`api.control.ControlRoom.take_calibration`); None: no calibration.
    """

    def __init__(self, rig_path: Path, takes_dir: Path, *, driver_factory: Any = None, session: Any = None,
                 take_calibration: Any = None) -> None:
        if take_calibration is not None and not callable(take_calibration):
            raise ValueError(f"take_calibration must be callable, got {type(take_calibration).__name__}")
        self.session = session  # a running stage.session.StageSession, or None
        self.take_calibration = take_calibration
        self.driver_factory = driver_factory  # (config, rig) -> CameraDriver; default stage.drivers.open_driver
        self.rig_path = Path(rig_path)
        self.takes_dir = Path(takes_dir)
        self._state = CaptureState()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- rig ---------------------------------------------------------------------------------
    def rig(self):
        """The validated rig (raises :class:`UnavailableError` when there is no rig file)."""
        import stage.drivers  # noqa: F401 (the built-in drivers register their camera models)
        from stage.rig import load_rig

        if self.session is not None:
            return self.session.rig
        if not self.rig_path.is_file():
            raise UnavailableError("no rig file: put rig.toml in the data root or set the 'rig' setting")
        return load_rig(self.rig_path)

    @property
    def busy(self) -> bool:
        if self.session is not None:
            return self.session.recording_active
        return self._thread is not None and self._thread.is_alive()

    def describe(self) -> dict[str, Any]:
        """Rig name, fps, volume and cameras with their state (``idle`` or ``capturing``)."""
        rig = self.rig()
        cam_state = "capturing" if self.busy else "idle"
        cams = []
        for c in rig.cameras:
            d = c.model_dump(mode="json")
            d["state"] = cam_state
            cams.append(d)
        return {
            "name": rig.name,
            "fps": rig.fps,
            "volume": rig.volume.model_dump(mode="json"),
            "backdrop": rig.backdrop.model_dump(mode="json"),
            "cameras": cams,
            "capture": self.status(),
        }

    def status(self) -> dict[str, Any]:
        if self.session is not None:
            return self._session_status()
        with self._lock:
            return self._state.to_dict()

    def _session_status(self) -> dict[str, Any]:
        rec = self.session.recording()
        st = {"idle": "idle", "recording": "capturing"}.get(rec.get("state"), rec.get("state"))
        res = rec.get("result") or {}
        if st == "done" and res.get("stopped") == "stopped":
            st = "stopped"
        return CaptureState(state=st, take=rec.get("take"), started=rec.get("started"), finished=rec.get("finished"),
                            frames_written=int(rec.get("frames_written") or 0), error=rec.get("error"),
                            result={k: v for k, v in res.items() if k != "sync"}).to_dict()

    # -- preview -----------------------------------------------------------------------------
    def preview(self, camera_id: str, *, quality: int = 80) -> bytes:
        """A JPEG from one camera, grabbed now (refused while a capture runs), or the session's latest frame."""
        rig = self.rig()
        conf = next((c for c in rig.cameras if c.id == camera_id), None)
        if conf is None:
            raise NotFoundError(f"no camera {camera_id!r} in the rig (cameras: {', '.join(c.id for c in rig.cameras)})")
        if self.session is not None:
            _, frame = self.session.latest(camera_id)
            if frame is None:
                raise UnavailableError(f"camera {camera_id!r} has delivered no frame ({self.session.cameras[camera_id].state})")
            return _jpeg(frame.image, quality)
        if self.busy:
            raise ConflictError("a capture is running; previews are off until it ends")
        drv = self._factory()(conf, rig)
        drv.open()
        try:
            drv.configure()
            frame = drv.grab()
        finally:
            drv.close()
        return _jpeg(frame.image, quality)

    def _factory(self) -> Any:
        if self.driver_factory is not None:
            return self.driver_factory
        try:
            from stage.drivers import open_driver
        except ImportError as exc:
            raise UnavailableError(f"camera drivers are not available ({exc})") from None
        return open_driver

    # -- capture -----------------------------------------------------------------------------
    def start(self, *, take: str, frames: int | None = None, duration_s: float | None = None) -> dict[str, Any]:
        """Start capturing ``frames`` frame sets (or ``duration_s`` seconds) into take ``take``."""
        check_take_id(take, name="take")
        if (frames is None) == (duration_s is None):
            raise ValueError("give exactly one of frames or duration_s")
        if frames is not None and frames < 1:
            raise ValueError("frames must be >= 1")
        if duration_s is not None and not (0 < duration_s <= 24 * 3600):
            raise ValueError("duration_s must be in (0, 86400]")
        rig = self.rig()
        out = inside(self.takes_dir, f"{take}.h5")
        if out.exists():
            raise ConflictError(f"take {take!r} already exists")
        if self.session is not None:
            return self._session_start(out, take, frames, duration_s)
        try:
            from stage.capture import capture_take
        except ImportError as exc:
            raise UnavailableError(f"capturing needs stage.capture ({exc})") from None
        drivers = None
        if self.driver_factory is not None:
            drivers = {c.id: self.driver_factory(c, rig) for c in rig.cameras}
        with self._lock:
            if self.busy:
                raise ConflictError(f"a capture is already running (take {self._state.take!r})")
            self._stop.clear()
            self._state = CaptureState(state="capturing", take=take, frames=frames, duration_s=duration_s,
                                       started=time.time())
            self._thread = threading.Thread(target=self._run, args=(capture_take, rig, out, frames, duration_s, drivers),
                                            name="capture", daemon=True)
            self._thread.start()
            return self._state.to_dict()

    def _session_start(self, out: Path, take: str, frames: int | None, duration_s: float | None) -> dict[str, Any]:
        from stage.session import RecordingBusyError

        try:
            cal = None if self.take_calibration is None else self.take_calibration()[0]
            self.session.start_recording(out, take=take, frames=frames, duration_s=duration_s, calibration=cal)
        except (RecordingBusyError, FileExistsError) as exc:
            raise ConflictError(str(exc)) from None
        return self.status()

    def stop(self) -> dict[str, Any]:
        """Ask the running capture to stop (the take keeps what was written)."""
        if not self.busy:
            raise ConflictError("no capture is running")
        if self.session is not None:
            self.session.stop_recording(wait=None)
            return self.status()
        self._stop.set()
        return self.status()

    def wait(self, timeout: float | None = None) -> None:
        if self.session is not None:
            self.session.wait_recording(timeout)
            return
        th = self._thread
        if th is not None:
            th.join(timeout)

    def _on_set(self, n: int) -> None:
        with self._lock:
            self._state.frames_written = int(n)

    def _run(self, capture_take: Any, rig: Any, out: Path, frames: int | None, duration_s: float | None,
             drivers: Any) -> None:
        try:
            result = capture_take(rig, out, frames=frames, duration_s=duration_s, drivers=drivers,
                                  stop=self._stop, on_set=self._on_set)
            state, err = ("stopped" if result.stopped in ("stopped", "interrupted") else "done"), None
        except Exception as exc:  # a capture failure becomes the state's error; the server goes on
            if isinstance(exc, OSError):  # a full disk, a device gone: one line, not a traceback
                log.error("capture into %s failed: %s", out.name, exc)
            else:
                log.exception("capture into %s failed", out.name)
            result, state, err = None, "failed", f"{type(exc).__name__}: {exc}".replace(str(out.parent), "DATA/takes")
        with self._lock:
            self._state.state = state
            self._state.error = err
            self._state.finished = time.time()
            if result is not None:
                self._state.frames_written = int(result.sets)
                self._state.result = {"sets": int(result.sets), "frames": dict(result.frames),
                                      "duration_s": float(result.duration_s), "fps": float(result.fps),
                                      "stopped": str(result.stopped), "disconnected": dict(result.disconnected),
                                      "drops": {k: int(v) for k, v in result.drops.items()}}


def _jpeg(image: Any, quality: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise ValueError("could not encode the preview")
    return buf.tobytes()
