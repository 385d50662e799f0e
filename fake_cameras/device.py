"""A simulated camera device behind the driver interface (``driver = "fake"``).

Frames are rendered ahead (:func:`fake_cameras.take.simulate_take`, or the board
views of :func:`fake_cameras.boards.render_board_views` for a board subject; cached
on disk and shared by every camera of the process) and replayed in real time:
frame ``k`` is captured at ``epoch + k / fps`` on the host's monotonic clock and
shows scene frame ``k mod F``. ``grab()`` sleeps until the next capture time.
The cameras of one rig share the epoch, like a genlocked rig: it is set one
start-up lead (:data:`START_LEAD_NS`) after the first ``grab()`` of a capture
(a capture = from the first of the rig's cameras opened to the last closed), so
every camera's first frame, sequence number 0, shows scene frame 0 and a take
of ``F`` frame sets films the scene once from its start. An explicit
``epoch_ns`` replaces that (a rig whose clock has run since then).

Like a real device each camera

* stamps frames with its own clock: ``timestamp_ns`` = true capture time +
  ``clock_offset_ms`` + Gaussian jitter (``jitter_ms``);
* numbers frames with its own sequence counter (from 0 at ``open``), so a
  dropped frame leaves a gap;
* drops frames at random (``drop_rate``) and when the reader falls more than
  ``buffer`` frames behind (the oldest frames are overwritten);
* delivers its images flipped left-right when its ``mirror_mode`` is on (a
  webcam's mirror mode); ``mirror = true`` on the camera flips them back at
  capture, as the other drivers do (:func:`~stage.drivers.base.unmirror`);
* disconnects after ``disconnect_after`` delivered frames, or at the next grab after
  :meth:`FakeCamera.unplug` (:class:`~stage.drivers.base.CameraDisconnectedError`);
* refuses to open a simulated index the rig does not have
  (:class:`~stage.drivers.base.CameraNotFoundError`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import threading
import time
from typing import Annotated, Callable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from stage.drivers.base import CameraDisconnectedError, CameraError, CameraNotFoundError, Granted, unmirror
from stage.drivers.registry import register_driver
from stage.frame import Frame
from stage.rig import CameraConfig, Rig

__all__ = ["FakeCamera", "FakeCameraConfig", "Simulation", "take_for_rig", "START_LEAD_NS"]

log = logging.getLogger(__name__)

#: the first frame of a capture is due this long after the first grab of any of its cameras,
#: so that the grabber threads, started one after the other, all begin with frame 0
START_LEAD_NS = 200_000_000


class FakeCameraConfig(CameraConfig):
    """A camera of the simulated rig (``driver = "fake"`` in a rig file)."""

    driver: Literal["fake"]
    index: Annotated[int, Field(ge=0)] = 0
    clock_offset_ms: float = 0.0
    jitter_ms: Annotated[float, Field(ge=0)] = 0.0
    drop_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    disconnect_after: Annotated[int, Field(ge=0)] | None = None
    depth: bool = False
    # the simulated webcam's mirror mode: it delivers its images flipped left-right (``mirror = true``
    # tells the stage so, and capture flips them back)
    mirror_mode: bool = False


class Simulation(BaseModel):
    """The rig file's ``[simulation]`` table: what the simulated rig films (required with ``driver = "fake"``
    cameras)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    subject: Literal["starfish", "quadruped", "biped", "tailed_quadruped", "board-chessboard", "board-charuco", "empty"] = "starfish"
    n_cameras: Annotated[int, Field(ge=4, le=24)] = 12
    frames: Annotated[int, Field(ge=1)] = 30
    seed: int = 0
    noise: Annotated[float, Field(ge=0)] = 2.0


_TAKES: dict = {}
_TAKES_LOCK = threading.Lock()


class _Session:
    """The shared epoch of one rig's open cameras (None until the first grab)."""

    def __init__(self) -> None:
        self.n_open = 0
        self.epoch: int | None = None


_SESSIONS: dict[int, _Session] = {}
_SESSIONS_LOCK = threading.Lock()


#: the arrays of fake_cameras.boards.BoardViews kept in the disk cache
_BOARD_ARRAYS = ("images", "poses", "object_points", "corners_3d", "corners_2d", "visible")
#: bump when the board views' rendering changes: invalidates cached views
BOARD_RENDER_VERSION = 1


def _board_source(kind: str, calibration, frames: int, seed: int, noise: float, volume):
    from calib.boards import Charuco, Chessboard
    from fake_cameras.boards import BoardViews, board_poses, floor_pose, render_board_views
    from fake_cameras.take import RENDER_VERSION, cached_render

    board = (
        Chessboard(corners=(9, 6), square_mm=50.0)
        if kind == "board-chessboard"
        else Charuco(squares=(7, 5), square_mm=70.0, marker_mm=52.0, dictionary="DICT_4X4_50")
    )
    # view 0: the board lying on the floor at the world origin (it defines the world frame
    # when calibrating with world_frame=0); the rest move through most of the volume, where
    # the subject will be (a calibration only holds where the board has been)
    waved = board_poses(board, calibration, max(frames - 1, 0), seed=seed, volume=volume, spread=0.9)
    poses = np.concatenate([floor_pose()[None], waved])[:frames]
    # rendered once per machine: the views' arrays are kept in the simulator's disk cache
    # (fake_cameras.take.cache_dir) under every input of the rendering
    key = json.dumps({
        "kind": "board-views", "version": [RENDER_VERSION, BOARD_RENDER_VERSION], "board": board.to_dict(),
        "calibration": calibration.to_dict(), "frames": int(frames), "seed": int(seed), "noise": float(noise),
        "volume": [list(volume.center), list(volume.size)],
        "poses": hashlib.sha1(np.round(poses, 6).tobytes()).hexdigest(),
    }, sort_keys=True, default=float)

    def render() -> dict:
        bv = render_board_views(board, calibration, frames, seed=seed, noise_sigma=noise, volume=volume, poses=poses)
        return {name: getattr(bv, name) for name in _BOARD_ARRAYS}

    arrays = cached_render(key, render, names=_BOARD_ARRAYS)
    return BoardViews(board=board, calibration=calibration, **arrays)


def take_for_rig(rig: Rig, *, size: tuple[int, int], fps: float, depth: bool = False):
    """The rendered frames a rig's ``[simulation]`` films (memoized per process).

    Returns
    -------
    SimulatedTake or fake_cameras.boards.BoardViews
        Anything with ``images (F, C, H, W, 3)``, optional ``depth`` and ``calibration``.
    """
    sim = rig.table("simulation")
    if sim is None:
        raise ValueError("rig: fake cameras need a [simulation] table")
    key = (sim.subject, sim.n_cameras, sim.frames, float(fps), tuple(size), sim.seed, bool(depth), sim.noise,
           tuple(rig.volume.center), tuple(rig.volume.size))
    with _TAKES_LOCK:
        hit = _TAKES.get(key)
        if hit is not None:
            return hit
        from fake_cameras.dome import make_dome
        from fake_cameras.take import simulate_take

        if sim.subject.startswith("board-"):
            cal = make_dome(sim.n_cameras, size=size, volume=rig.volume, seed=sim.seed)
            src = _board_source(sim.subject, cal, sim.frames, sim.seed, sim.noise, rig.volume)
        else:
            src = simulate_take(
                sim.subject, n_cameras=sim.n_cameras, frames=sim.frames, fps=fps, size=size, seed=sim.seed,
                depth=depth, noise_sigma=sim.noise, volume=rig.volume,
            )
        _TAKES[key] = src
        return src


class FakeCamera:
    """A simulated camera (implements :class:`stage.drivers.base.CameraDriver`).

    Parameters
    ----------
    config : FakeCameraConfig
        ``index`` picks the camera of the simulated dome; ``clock_offset_ms``,
        ``jitter_ms``, ``drop_rate``, ``disconnect_after`` and ``depth`` as in
        the module docstring.
    rig : stage.rig.Rig, optional
        Its ``[simulation]`` says what is filmed (needed unless ``take`` is given);
        ``rig.fps`` is used when the camera has no ``fps`` of its own.
    take : SimulatedTake or BoardViews, optional
        Replay these frames instead of simulating the rig's subject.
    epoch_ns : int, optional
        Monotonic time of frame 0 (default: :data:`START_LEAD_NS` after the first grab of
        the capture, shared by the cameras of ``rig``, or of ``take`` without a rig).
    seed : int, optional
        Seeds drops and jitter (default: derived from the camera index).
    buffer : int, optional
        Frames the device holds for a slow reader before it overwrites them.
    latency_ms : float, optional
        Delay between capture and delivery to the host.
    clock, sleep : callables, optional
        ``time.monotonic_ns`` and ``time.sleep`` (replace them to test without waiting).
    """

    config_model = FakeCameraConfig

    def __init__(
        self,
        config: FakeCameraConfig,
        rig: Rig | None = None,
        *,
        take=None,
        epoch_ns: int | None = None,
        seed: int | None = None,
        buffer: int = 4,
        latency_ms: float = 2.0,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
    ):
        if not isinstance(config, FakeCameraConfig):
            raise ValueError(f"config must be a FakeCameraConfig, got {type(config).__name__}")
        if rig is not None and not isinstance(rig, Rig):
            raise ValueError(f"rig must be a stage.rig.Rig or None, got {type(rig).__name__}")
        if take is None and (rig is None or rig.table("simulation") is None):
            raise ValueError("rig: a fake camera needs a rig with a [simulation] table (or a take to replay)")
        if take is not None and not hasattr(take, "images"):
            raise ValueError(f"take must be a SimulatedTake or BoardViews, got {type(take).__name__}")
        if int(buffer) < 1:
            raise ValueError(f"buffer must be >= 1, got {buffer!r}")
        self.config = config
        self.camera_id = config.id
        self.rig = rig
        self.fps = float(config.fps or (rig.fps if rig is not None else None) or getattr(take, "fps", 30.0))
        self.period_ns = int(round(1e9 / self.fps))
        self._take = take
        self._epoch = None if epoch_ns is None else int(epoch_ns)
        self._shared_epoch = epoch_ns is None
        self._session: _Session | None = None
        self._rng = np.random.default_rng(config.index + 7919 if seed is None else seed)
        self._buffer = int(buffer)
        self._latency_ns = int(latency_ms * 1e6)
        self._clock = clock
        self._sleep = sleep
        self._opened = False
        self._configured = False
        self._k = None  # next capture number
        self._k0 = 0
        self.delivered = 0
        self.dropped = 0
        self._unplugged = threading.Event()

    # -- driver protocol ---------------------------------------------------------
    def open(self) -> None:
        """Connect to the simulated device (renders or loads its frames)."""
        if self._take is None:
            self._take = take_for_rig(
                self.rig, size=(self.config.width, self.config.height), fps=self.fps, depth=self.config.depth
            )
        n_cams = self._take.images.shape[1]
        if self.config.index >= n_cams:
            raise CameraNotFoundError(
                f"camera {self.camera_id!r}: simulated camera index {self.config.index} does not exist "
                f"(the simulated rig has {n_cams} cameras, indices 0..{n_cams - 1})"
            )
        h, w = self._take.images.shape[2:4]
        if (w, h) != (self.config.width, self.config.height):
            raise CameraError(
                f"camera {self.camera_id!r}: the simulated frames are {w}x{h}, "
                f"the rig asks for {self.config.width}x{self.config.height}"
            )
        if self.config.depth and getattr(self._take, "depth", None) is None:
            raise CameraError(f"camera {self.camera_id!r}: depth requested but the simulated take has no depth")
        if self._shared_epoch:
            self._join_session()
        self._opened = True
        self._k = None
        self.delivered = 0
        self.dropped = 0

    def _join_session(self) -> None:
        """Share the epoch of the rig's other open cameras (a new capture when none is open)."""
        key = id(self.rig) if self.rig is not None else id(self._take)
        with _SESSIONS_LOCK:
            if self._session is None:
                self._session = _SESSIONS.setdefault(key, _Session())
                self._session.n_open += 1
            self._epoch = self._session.epoch

    def _leave_session(self) -> None:
        key = id(self.rig) if self.rig is not None else id(self._take)
        with _SESSIONS_LOCK:
            if self._session is None:
                return
            self._session.n_open -= 1
            if self._session.n_open <= 0 and _SESSIONS.get(key) is self._session:
                del _SESSIONS[key]
            self._session = None

    def _start_clock(self, now: int) -> None:
        """The shared epoch: set by the first grab of the capture, one lead ahead."""
        with _SESSIONS_LOCK:
            if self._session.epoch is None:
                self._session.epoch = int(now) + START_LEAD_NS
            self._epoch = self._session.epoch

    def configure(self) -> Granted:
        """What the simulated device grants: exactly the requested settings."""
        if not self._opened:
            raise CameraError(f"camera {self.camera_id!r}: open() before configure()")
        self._configured = True
        return Granted(
            width=self.config.width,
            height=self.config.height,
            fps=self.fps,
            pixel_format="BGR",
            has_depth=bool(self.config.depth),
            extra={"simulated": True, "index": self.config.index},
        )

    def grab(self) -> Frame:
        """Block until the next frame is delivered and return it."""
        if not self._opened:
            raise CameraError(f"camera {self.camera_id!r}: grab() on a closed camera")
        if self._unplugged.is_set():
            self._opened = False
            raise CameraDisconnectedError(f"camera {self.camera_id!r}: simulated USB unplug")
        lim = self.config.disconnect_after
        if lim is not None and self.delivered >= lim:
            self._opened = False
            raise CameraDisconnectedError(
                f"camera {self.camera_id!r}: simulated disconnect after {lim} frames (disconnect_after)"
            )
        now = self._clock()
        if self._k is None:
            if self._session is not None:
                self._start_clock(now)
            self._k = max(0, -(-(now - self._epoch) // self.period_ns))
            self._k0 = self._k
        while True:
            # frames the reader was too slow for are overwritten in the device buffer
            newest = (now - self._epoch - self._latency_ns) // self.period_ns
            oldest_kept = newest - self._buffer + 1
            if self._k < oldest_kept:
                self.dropped += oldest_kept - self._k
                self._k = oldest_kept
            due = self._epoch + self._k * self.period_ns + self._latency_ns
            if due > now:
                self._sleep((due - now) / 1e9)
                now = self._clock()
                continue
            k = self._k
            self._k += 1
            if self.config.drop_rate > 0 and self._rng.random() < self.config.drop_rate:
                self.dropped += 1
                continue
            break
        take = self._take
        F = take.images.shape[0]
        idx = self.config.index
        image = np.array(take.images[k % F, idx])
        depth = None
        if self.config.depth:
            depth = np.array(take.depth[k % F, idx])
        capture = self._epoch + k * self.period_ns
        jitter = self._rng.normal(0.0, self.config.jitter_ms * 1e6) if self.config.jitter_ms > 0 else 0.0
        ts = int(capture + self.config.clock_offset_ms * 1e6 + jitter)
        self.delivered += 1
        if self.config.mirror_mode:  # what the device delivers
            image = np.ascontiguousarray(image[:, ::-1])
            depth = None if depth is None else np.ascontiguousarray(depth[:, ::-1])
        frame = Frame(
            image=image,
            camera_id=self.camera_id,
            index=int(k - self._k0),
            timestamp_ns=ts,
            host_timestamp_ns=int(self._clock()),
            depth=depth,
        )
        return unmirror(frame) if self.config.mirror else frame

    def close(self) -> None:
        self._opened = False
        self._leave_session()

    # -- extras -------------------------------------------------------------------
    def unplug(self) -> None:
        """Pull the simulated cable: the next (or the waiting) grab raises CameraDisconnectedError."""
        self._unplugged.set()

    @property
    def calibration(self):
        """The true calibration of the simulated rig (after :meth:`open`), its cameras named as the rig
        file names them: each simulated camera of the rig under its ``id`` (the simulated camera at its
        ``index``), in the rig's order; without a rig, the simulated take's own names."""
        if self._take is None:
            return None
        cal = self._take.calibration
        if self.rig is None:
            return cal
        from calib.calibration import Calibration

        cams = [dataclasses.replace(cal.cameras[c.index], name=c.id) for c in self.rig.cameras
                if isinstance(c, FakeCameraConfig) and c.index < len(cal.cameras)]
        return Calibration(cameras=tuple(cams), units=cal.units, meta=dict(cal.meta)) if cams else None

    def scene_frame(self, index: int) -> int:
        """Scene frame shown by device sequence number ``index``."""
        return (self._k0 + int(index)) % self._take.images.shape[0]

    def __enter__(self) -> "FakeCamera":
        self.open()
        self.configure()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FakeCamera({self.camera_id!r}, index={self.config.index}, {self.config.width}x{self.config.height}@{self.fps:g})"


# rig cameras with driver = "fake" are these (stage.drivers.open_driver finds them once this module is imported)
register_driver("fake", FakeCamera, needs_rig=True, table=("simulation", Simulation))
