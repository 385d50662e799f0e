"""The control room's server side: previews, board guidance, and what the page reads.

:class:`ControlRoom` wraps a running :class:`stage.session.StageSession`:

* **previews**: each camera's latest frame downscaled (``preview_width``), optionally with
  its backdrop mask tinted in (the rig's keying mode, :mod:`stage.keying`, model estimated
  on the camera's first preview) and the board corners of the board session drawn on it,
  encoded as JPEG once per new frame and option set, whatever the number of viewers;
* **board session** (:class:`BoardSession`): the board detected (:func:`calib.detect.detect_board`)
  on every camera of the latest frame set a few times a second, in its own thread; per camera
  a coverage map of where corners were seen and the number of distinct views
  (:func:`calib.detect.view_change` over ``min_change``), per camera pair the views both saw
  (the links the bundle adjustment needs); "enough views" when every camera has
  ``min_views`` and the pairs with ``min_shared`` shared views connect every camera;
* the figures of every MJPEG stream: open streams and the latency from a frame's grab to its
  bytes being sent (p50 / p99 of the last ones).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import cv2
import numpy as np

__all__ = ["ControlRoom", "BoardSession", "disk_state", "image_figures", "DISK_LOW_MINUTES", "DISK_FULL_MINUTES",
           "CLIPPED_PCT", "DARK_LEVEL"]

log = logging.getLogger(__name__)

#: coverage map cells across x and y
COVERAGE_CELLS = (8, 6)
#: minutes of recording left (at the rig's raw data rate) under which the page warns, and says the disk is almost full
DISK_LOW_MINUTES, DISK_FULL_MINUTES = 10.0, 2.0


#: a picture with more of its pixels clipped (a channel at 250 or more) than this percentage is called overexposed
CLIPPED_PCT = 2.0
#: a picture whose median luma (0-255) is under this is called dark
DARK_LEVEL = 30.0
#: the level and clipped share are taken on every ``W // IMAGE_FIGURES_WIDTH``-th pixel (about this many across)
IMAGE_FIGURES_WIDTH = 320
#: the sharpness is taken on at most this many pixels square in the middle of the picture, at full resolution
SHARPNESS_CROP = 256
#: seconds between two measures of one camera's picture (:meth:`ControlRoom.figures`)
IMAGE_FIGURES_PERIOD_S = 1.0


def image_figures(image: np.ndarray) -> dict[str, Any]:
    """Exposure and focus as the picture itself shows them, whatever the driver reports.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        BGR.

    Returns
    -------
    dict
        ``level``: the median luma (0-255); ``clipped_pct``: the percentage of pixels with a channel at 250 or
        more (both over every ``W // IMAGE_FIGURES_WIDTH``-th pixel across and down); ``sharpness``: the
        variance of the luma's Laplacian (3x3, ``cv2.Laplacian``) over the picture's central half (where the
        subject is), at most its middle ``SHARPNESS_CROP`` pixels square, at full resolution: a figure to turn
        the focus ring up to (it depends on what is in view: compare it on one view, not across cameras);
        ``exposure``: ``"overexposed"`` (more than :data:`CLIPPED_PCT` % clipped), ``"dark"`` (level under
        :data:`DARK_LEVEL`) or None.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or min(img.shape[:2]) < 4:
        raise ValueError(f"image must be an (H, W, 3) uint8 array of at least 4x4, got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    step = max(1, w // IMAGE_FIGURES_WIDTH)
    sub = img[::step, ::step]  # every step-th pixel: the level and the clipped share without averaging highlights away
    level = float(np.median(cv2.cvtColor(sub, cv2.COLOR_BGR2GRAY)))
    clipped = float((sub >= 250).any(axis=2).mean() * 100.0)
    ch, cw = min(h - 2 * (h // 4), SHARPNESS_CROP), min(w - 2 * (w // 4), SHARPNESS_CROP)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    centre = cv2.cvtColor(np.ascontiguousarray(img[y0:y0 + ch, x0:x0 + cw]), cv2.COLOR_BGR2GRAY)
    sharpness = float(cv2.Laplacian(centre, cv2.CV_64F, ksize=1).var())
    exposure = "overexposed" if clipped > CLIPPED_PCT else "dark" if level < DARK_LEVEL else None
    return {"level": level, "clipped_pct": clipped, "sharpness": sharpness, "exposure": exposure}


def disk_state(disk: dict[str, Any]) -> dict[str, str | None]:
    """What the page says of the takes' disk: ``level`` None, ``"low"`` (under :data:`DISK_LOW_MINUTES` of
    recording left) or ``"full"`` (under :data:`DISK_FULL_MINUTES`), and its ``message``."""
    if not isinstance(disk, dict):
        raise ValueError(f"disk must be a dict (StageSession.disk), got {type(disk).__name__}")
    left = disk.get("minutes_left")
    if left is None or left >= DISK_LOW_MINUTES:
        return {"level": None, "message": None}
    if left < DISK_FULL_MINUTES:
        return {"level": "full", "message": f"disk almost full: {left:.1f} min of recording left; "
                                            "free space where takes are written before recording"}
    return {"level": "low", "message": f"disk low: {left:.0f} min of recording left at the rig's data rate"}


class _Keyers:
    """Per camera: the backdrop keying parameters, estimated once on a preview image."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self._params: dict[str, Any] = {}
        self.errors: dict[str, str] = {}
        self._lock = threading.Lock()

    def mask(self, cid: str, image: np.ndarray) -> np.ndarray | None:
        from stage.keying import KeyingError, KeyParams, estimate_model, key_one

        with self._lock:
            p = self._params.get(cid)
        if p is None:
            if cid in self.errors:
                return None
            b = self.rig.backdrop
            try:
                p = estimate_model(image[None], params=KeyParams(mode=b.key_mode, backdrop_color=b.color))
            except (KeyingError, ValueError) as exc:
                self.errors[cid] = str(exc)
                log.warning("camera %s: no backdrop model for the mask overlay: %s", cid, exc)
                return None
            with self._lock:
                self._params[cid] = p
        try:
            mask, _, _, _ = key_one(image, p)
        except (KeyingError, ValueError):
            return None
        return mask


def _downscale(image: np.ndarray, width: int) -> tuple[np.ndarray, float]:
    h, w = image.shape[:2]
    if w <= width:
        return image, 1.0
    s = width / w
    return cv2.resize(image, (width, max(1, round(h * s))), interpolation=cv2.INTER_AREA), s


class BoardSession:
    """Live board detection over the latest frame sets, with coverage and view counts.

    Parameters
    ----------
    session : StageSession
    board : Chessboard or Charuco
    min_views : int
        Distinct views each camera needs.
    min_shared : int
        Views two cameras must share for their pair to count as a link.
    min_change : float
        A view counts when its corners moved by this fraction of the image diagonal from every
        view counted before (:func:`calib.detect.view_change`).
    rate_hz : float
        Frame sets examined per second.
    """

    def __init__(self, session, board, *, min_views: int = 8, min_shared: int = 3, min_change: float = 0.02,
                 rate_hz: float = 6.0) -> None:
        if min_views < 1 or min_shared < 1:
            raise ValueError("min_views and min_shared must be >= 1")
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        self.session, self.board = session, board
        self.min_views, self.min_shared, self.min_change = int(min_views), int(min_shared), float(min_change)
        self.period = 1.0 / float(rate_hz)
        ids = session.ids
        self.ids = ids
        self._lock = threading.Lock()
        self.latest: dict[str, Any] = {c: None for c in ids}  # camera -> (frame, (N, 2) corners or None) or None
        self.kept: dict[str, list] = {c: [] for c in ids}
        self.coverage = {c: np.zeros(COVERAGE_CELLS[::-1], np.int64) for c in ids}
        self.shared = np.zeros((len(ids), len(ids)), np.int64)
        self.sets_examined = 0
        self.version = 0  # bumps with every examined set
        self.take: str | None = None
        self.job: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="board-session", daemon=True)
        self.started = time.time()

    def start(self) -> "BoardSession":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _loop(self) -> None:
        last_index = None
        while not self._stop.is_set():
            t0 = time.monotonic()
            fs = self.session.latest_set()
            if fs is not None and fs.index != last_index:
                last_index = fs.index
                try:
                    self.examine(fs.frames)
                except Exception:  # a detector failure must not end the session's guidance silently
                    log.exception("board detection failed on set %d", fs.index)
            self._stop.wait(max(0.0, self.period - (time.monotonic() - t0)))

    def examine(self, frames: dict) -> None:
        """Detect the board in one frame set's images and count views, coverage and shared views."""
        from calib.detect import detect_board, view_change

        seen: list[int] = []
        found: dict[str, Any] = {}
        for i, cid in enumerate(self.ids):
            f = frames.get(cid)
            det = None if f is None else detect_board(f.image, self.board)
            found[cid] = None if f is None else (f, None if det is None else det.corners)
            if det is None:
                continue
            h, w = f.image.shape[:2]
            kept = self.kept[cid]
            novel = all(view_change(det, k, (w, h)) > self.min_change for k in kept)
            if novel:
                kept.append(det)
                seen.append(i)
                cx = np.clip((det.corners[:, 0] / w * COVERAGE_CELLS[0]).astype(int), 0, COVERAGE_CELLS[0] - 1)
                cy = np.clip((det.corners[:, 1] / h * COVERAGE_CELLS[1]).astype(int), 0, COVERAGE_CELLS[1] - 1)
                with self._lock:
                    np.add.at(self.coverage[cid], (cy, cx), 1)
        with self._lock:
            self.latest = found
            self.sets_examined += 1
            self.version += 1
            det_idx = [i for i, c in enumerate(self.ids) if found[c] is not None and found[c][1] is not None]
            for a in det_idx:
                for b in det_idx:
                    if a != b and (a in seen or b in seen):
                        self.shared[a, b] += 1

    def examined(self, cid: str) -> tuple[Any, np.ndarray | None] | None:
        """(frame, corners or None) of camera ``cid`` in the last examined set, or None."""
        with self._lock:
            return self.latest.get(cid)

    def enough(self) -> tuple[bool, str]:
        """Whether the views suffice, and what is missing when they do not."""
        views = {c: len(self.kept[c]) for c in self.ids}
        short = [c for c, n in views.items() if n < self.min_views]
        link = self.shared >= self.min_shared
        reached = {0}
        frontier = [0]
        while frontier:
            a = frontier.pop()
            for b in np.flatnonzero(link[a]):
                if int(b) not in reached:
                    reached.add(int(b))
                    frontier.append(int(b))
        apart = [c for i, c in enumerate(self.ids) if i not in reached]
        if not short and not apart:
            return True, "enough views: every camera has its views and the pairs link every camera"
        msg = []
        if short:
            msg.append(f"{len(short)} camera(s) need more views ({', '.join(short[:6])}{'...' if len(short) > 6 else ''})")
        if apart:
            msg.append(f"{len(apart)} camera(s) share too few views with the others ({', '.join(apart[:6])})")
        return False, "; ".join(msg)

    def status(self) -> dict[str, Any]:
        with self._lock:
            ok, why = self.enough()
            return {
                "running": self.running, "take": self.take, "job": self.job,
                "min_views": self.min_views, "min_shared": self.min_shared, "sets_examined": self.sets_examined,
                "views": {c: len(self.kept[c]) for c in self.ids},
                "detected": {c: (self.latest.get(c) or (None, None))[1] is not None for c in self.ids},
                "coverage": {c: self.coverage[c].tolist() for c in self.ids},
                "shared": self.shared.tolist(), "cameras": list(self.ids),
                "enough": ok, "message": why, "board": self.board.to_dict(),
            }


class ControlRoom:
    """What the control room page needs from a running session.

    Parameters
    ----------
    session : StageSession
        Opened.
    board : Board, optional
        The calibration board of board sessions (``stage serve --board``).
    calibration : Calibration, optional
        For the live 3-D preview; default: the one the cameras' drivers know (the simulator's).
        A calibration the session makes (its board session's job) or is given later
        (:meth:`use_calibration`) replaces it.
    calibrations : CalibrationLibrary, optional
        Where the calibration jobs put their results (the app sets it to its own).
    preview_width : int
        Previews are downscaled to at most this width.
    preview_fps : float
        Frames per second each preview stream sends.
    """

    def __init__(self, session, *, board=None, calibration=None, preview_width: int = 320,
                 preview_fps: float = 5.0, calibrations=None) -> None:
        if preview_width < 16:
            raise ValueError(f"preview_width must be >= 16, got {preview_width!r}")
        if not 0 < preview_fps <= 60:
            raise ValueError(f"preview_fps must be in (0, 60], got {preview_fps!r}")
        self.session = session
        self.board = board
        self.preview_width = int(preview_width)
        self.preview_fps = float(preview_fps)
        self.keyers = _Keyers(session.rig)
        self._cache: dict[tuple, tuple[int, bytes, int]] = {}
        self._measured: dict[str, tuple[int, float, dict | None]] = {}  # camera -> (seq, when, image figures)
        self._lock = threading.Lock()
        self.streams = 0
        self.latency_ns: collections.deque = collections.deque(maxlen=2000)
        self.encode_s: collections.deque = collections.deque(maxlen=2000)
        self.board_session: BoardSession | None = None
        self.closing = threading.Event()  # set when the server shuts down: preview streams end
        self.live3d = None
        self.calibrations = calibrations
        self._calibration = calibration
        self.calibration_source = "the calibration given (--calibration)" if calibration is not None else None
        self.calibration_version = 0  # grows with every calibration the session makes or is given
        self._adopted: str | None = None  # the board session's job whose calibration is in use

    # -- calibration for the 3-D preview -----------------------------------------------------------
    def calibration(self):
        """The calibration the 3-D preview uses: the newest the session made (its board session's
        calibration job, once finished) or was given (:meth:`use_calibration`, ``--calibration``),
        else the drivers' own (the simulator's), or None."""
        self._adopt_board_calibration()
        if self._calibration is not None:
            return self._calibration
        for drv in self.session.drivers.values():
            cal = getattr(drv, "calibration", None)
            if cal is not None and hasattr(cal, "names"):
                self.calibration_source = "the cameras' own calibration"
                return cal
        return None

    def take_calibration(self) -> tuple[Any, str]:
        """The calibration a take recorded now stores (the 3-D preview's, :meth:`calibration`, cut to the
        rig's cameras in rig order) and what the page says of it; ``(None, why)`` when there is none or
        it lacks one of the rig's cameras (such a take cannot be processed until it is calibrated)."""
        from calib.calibration import Calibration

        cal = self.calibration()
        if cal is None:
            return None, ("takes are recorded without a calibration (none yet): run a board session and "
                          "calibrate, or start stage serve with --calibration CAL")
        missing = [c for c in self.session.ids if c not in cal.names]
        if missing:
            return None, (f"takes are recorded without a calibration: {self.calibration_source} has no camera "
                          f"{', '.join(missing)}")
        cut = Calibration(cameras=tuple(cal[c] for c in self.session.ids), units=cal.units, meta=dict(cal.meta))
        return cut, f"takes are recorded with {self.calibration_source}"

    def use_calibration(self, calibration, source: str) -> None:
        """Make ``calibration`` the 3-D preview's from now on (its worker starts again with it)."""
        with self._lock:
            self._calibration = calibration
            self.calibration_source = source
            self.calibration_version += 1
        log.info("the 3-D preview uses %s", source)

    def _adopt_board_calibration(self) -> None:
        """The board session's calibration, once its job has saved it (the newest the session made)."""
        bs, lib = self.board_session, self.calibrations
        job = getattr(bs, "job", None)
        if job is None or job == self._adopted or lib is None or not lib.exists(job):
            return
        self._adopted = job
        try:
            cal = lib.load(job)
        except (OSError, ValueError, LookupError) as exc:  # damaged or gone: said, the preview keeps its own
            log.warning("calibration %s of the board session cannot be read: %s", job, exc)
            return
        self.use_calibration(cal, f"calibration {job} (board session)")

    # -- previews ------------------------------------------------------------------------------
    def preview(self, cid: str, *, mask: bool = False, board: bool = True, quality: int = 75) -> tuple[int, bytes | None, int]:
        """(frame sequence number, JPEG or None before the first frame, grab time ns) of one camera."""
        seq, frame = self.session.latest(cid)
        if frame is None:
            return seq, None, 0
        bs = self.board_session
        show_board = board and bs is not None and bs.running
        corners = None
        if show_board:
            # during a board session a tile shows the frame the board was looked for in, with the
            # corners found (half a second old at most): corners drawn on a newer frame would be off
            hit = bs.examined(cid)
            if hit is not None and frame.host_timestamp_ns - hit[0].host_timestamp_ns < 500_000_000:
                frame, corners = hit
        key = (cid, bool(mask), bs.version if show_board else -1, int(quality))
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None and hit[0] == seq:
            return hit
        t0 = time.perf_counter()
        img, scale = _downscale(frame.image, self.preview_width)
        if mask:
            m = self.keyers.mask(cid, img)
            if m is not None:
                img = img.copy()
                img[m] = (0.5 * img[m] + 0.5 * np.array([255, 0, 255])).astype(np.uint8)
        if show_board:
            if corners is not None:
                img = img.copy() if img is frame.image else img
                for x, y in np.asarray(corners) * scale:
                    cv2.circle(img, (int(round(x)), int(round(y))), 2, (0, 0, 255), -1, lineType=cv2.LINE_AA)
        ok, buf = cv2.imencode(".jpg", img, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
        if not ok:
            raise ValueError(f"camera {cid}: the preview could not be encoded")
        out = (seq, buf.tobytes(), int(frame.host_timestamp_ns))
        with self._lock:
            self._cache[key] = out
            self.encode_s.append(time.perf_counter() - t0)
        return out

    def _image_figures(self, cid: str) -> dict[str, Any] | None:
        """:func:`image_figures` of a camera's latest picture, measured at most once per
        :data:`IMAGE_FIGURES_PERIOD_S` whatever the number of pages asking; None before its first frame."""
        seq, frame = self.session.latest(cid)
        now = time.monotonic()
        with self._lock:
            hit = self._measured.get(cid)
        if hit is not None and (hit[0] == seq or now - hit[1] < IMAGE_FIGURES_PERIOD_S):
            return hit[2]
        out = None if frame is None else image_figures(frame.image)
        with self._lock:
            self._measured[cid] = (seq, now, out)
        return out

    def stream_opened(self) -> None:
        with self._lock:
            self.streams += 1

    def stream_closed(self) -> None:
        with self._lock:
            self.streams -= 1

    def sent(self, grab_ns: int) -> None:
        """A preview of a frame grabbed at ``grab_ns`` (host monotonic) was handed to the network."""
        self.latency_ns.append(time.monotonic_ns() - int(grab_ns))

    def latency_ms(self) -> dict[str, float | None]:
        v = np.asarray(list(self.latency_ns), dtype=np.float64) / 1e6
        if v.size == 0:
            return {"p50": None, "p99": None, "n": 0}
        return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "n": int(v.size)}

    # -- board session -------------------------------------------------------------------------
    def start_board(self, *, min_views: int = 8, min_shared: int = 3) -> BoardSession:
        if self.board is None:
            raise ValueError("no calibration board: start stage serve with --board BOARD.toml")
        if self.board_session is not None and self.board_session.running:
            self.board_session.stop()
        self.board_session = BoardSession(self.session, self.board, min_views=min_views,
                                          min_shared=min_shared).start()
        return self.board_session

    def stop_board(self) -> None:
        if self.board_session is not None:
            self.board_session.stop()

    def close(self) -> None:
        self.closing.set()
        self.stop_board()
        if self.live3d is not None:
            self.live3d.stop()

    def figures(self) -> dict[str, Any]:
        f = self.session.figures()
        f["disk"] = {**f["disk"], **disk_state(f["disk"])}
        for c in f["cameras"]:
            c["image"] = self._image_figures(c["id"])
        cal, said = self.take_calibration()
        f["take_calibration"] = {"calibrated": cal is not None, "message": said}
        f["previews"] = {"streams": self.streams, "latency_ms": self.latency_ms(), "fps": self.preview_fps,
                         "width": self.preview_width}
        return f
