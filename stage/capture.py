"""Synchronized capture: every camera of a rig into one HDF5 take.

One grabber thread per camera pulls frames from its driver into a shared,
bounded queue (a full queue drops the frame and counts it: the writer could not
keep up); the main thread groups frames into frame sets
(:class:`stage.sync.StreamGrouper`) and stores every decided set
(:class:`stage.store.TakeWriter`, flushed per set).

A camera that disconnects (its driver raises, or it delivers nothing for
``stall_timeout_s``) is logged with a warning naming it, marked missing in the
rest of the take, and capture goes on with the others; when every camera is
gone capture stops. The take is closed cleanly in every case (also on Ctrl-C).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from stage.drivers.base import CameraDriver, CameraError, Granted
from stage.rig import Rig
from stage.store import CameraSpec, TakeWriter
from stage.sync import SetStatsAccumulator, StreamGrouper, SyncStats

__all__ = ["CaptureProgress", "CaptureResult", "TakeRecorder", "capture_take", "live_sync_window"]

log = logging.getLogger(__name__)

#: frame sets whose sync spread the live figures keep
SPREAD_WINDOW = 30


@dataclass(frozen=True)
class CaptureProgress:
    """Live figures for a progress bar.

    ``fps``: frame sets per second over the last second; ``drops``: camera
    slots missing in the sets so far (all cameras); ``queue_drops``: frames
    discarded because the writer fell behind.
    """

    sets: int
    target_sets: int | None
    elapsed_s: float
    duration_s: float | None
    fps: float
    drops: int
    queue_drops: int
    disconnected: tuple[str, ...]


@dataclass
class CaptureResult:
    """What a capture did."""

    path: Path
    sets: int
    frames: dict[str, int]
    duration_s: float
    fps: float
    stats: SyncStats
    stopped: str
    disconnected: dict[str, str] = field(default_factory=dict)
    queue_drops: dict[str, int] = field(default_factory=dict)
    granted: dict[str, Granted] = field(default_factory=dict)

    @property
    def drops(self) -> dict[str, int]:
        """Per camera: sets it is missing from plus frames the writer could not take."""
        return {c: self.stats.cameras[c].missing + self.queue_drops.get(c, 0) for c in self.frames}


class _Grabber(threading.Thread):
    def __init__(self, cid: str, driver: CameraDriver, q: "queue.Queue", stop: threading.Event, drops: dict) -> None:
        super().__init__(name=f"grab-{cid}", daemon=True)
        self.cid, self.driver, self.q, self.stop, self.drops = cid, driver, q, stop, drops

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                frame = self.driver.grab()
            except CameraError as exc:
                self.q.put(("gone", self.cid, str(exc)))
                return
            except Exception as exc:  # a driver bug must not kill the take silently
                self.q.put(("gone", self.cid, f"{type(exc).__name__}: {exc}"))
                return
            if frame.camera_id != self.cid:
                frame = _with_camera(frame, self.cid)
            try:
                self.q.put_nowait(("frame", self.cid, frame))
            except queue.Full:
                self.drops[self.cid] += 1


def _with_camera(frame: Any, cid: str) -> Any:
    from dataclasses import replace

    return replace(frame, camera_id=cid)


def _open_drivers(rig: Rig, drivers: Mapping[str, CameraDriver] | None) -> dict[str, CameraDriver]:
    if drivers is not None:
        missing = [c.id for c in rig.cameras if c.id not in drivers]
        if missing:
            raise ValueError(f"drivers: no driver for cameras {missing}")
        return {c.id: drivers[c.id] for c in rig.cameras}
    from stage.drivers.registry import open_driver

    return {c.id: open_driver(c, rig) for c in rig.cameras}


def _check_limits(frames: int | None, duration_s: float | None, stall_timeout_s: float, queue_seconds: float) -> None:
    """The stop condition and the stall and queue limits of a capture (ValueError naming the parameter)."""
    if frames is not None and (not isinstance(frames, int) or frames < 1):
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"duration_s must be positive, got {duration_s!r}")
    if stall_timeout_s <= 0 or queue_seconds <= 0:
        raise ValueError("stall_timeout_s and queue_seconds must be positive")


def capture_take(
    rig: Rig,
    out: str | os.PathLike,
    *,
    frames: int | None = None,
    duration_s: float | None = None,
    compression: str = "none",
    calibration: Any = None,
    drivers: Mapping[str, CameraDriver] | None = None,
    progress: Callable[[CaptureProgress], None] | None = None,
    on_set: Callable[[int], None] | None = None,
    overwrite: bool = False,
    stop: threading.Event | None = None,
    stall_timeout_s: float = 5.0,
    queue_seconds: float = 2.0,
) -> CaptureResult:
    """Capture a take from every camera of ``rig`` into ``out``.

    Parameters
    ----------
    rig : Rig
        The rig (cameras, fps, sync tolerance).
    out : path
        The take file to create.
    frames : int, optional
        Stop after this many frame sets.
    duration_s : float, optional
        Stop after this many seconds (at least one of ``frames``/``duration_s``).
    compression : {"none", "lz4", "gzip"}
        Filter of raw frames (see :class:`stage.store.TakeWriter`).
    calibration : Calibration, optional
        Stored in the take.
    drivers : mapping of camera id -> CameraDriver, optional
        Ready-made (not yet opened) drivers; default: ``open_driver`` for each rig camera.
    progress : callable, optional
        Called with a :class:`CaptureProgress` after every stored set.
    on_set : callable, optional
        Called with the number of sets stored (and flushed) so far.
    overwrite : bool
        Replace an existing take.
    stop : threading.Event, optional
        Set it to stop capturing early (the take is closed cleanly).
    stall_timeout_s : float
        A camera that delivers nothing for this long is treated as disconnected.
    queue_seconds : float
        Frames buffered between grabbers and writer (per camera, in seconds of video).

    Returns
    -------
    CaptureResult

    Raises
    ------
    ValueError
        Bad arguments; ``out`` exists (FileExistsError) without ``overwrite``.
    CameraError
        A camera cannot be opened (nothing is written then).
    """
    if not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig, got {type(rig).__name__}")
    if frames is None and duration_s is None:
        raise ValueError("give frames and/or duration_s: capture needs a stop condition")
    _check_limits(frames, duration_s, stall_timeout_s, queue_seconds)
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: take already exists (use --overwrite to replace it)")
    run = _Capture(rig, out, _open_drivers(rig, drivers), frames=frames, duration_s=duration_s,
                   stop=stop or threading.Event(), stall_timeout_s=stall_timeout_s, queue_seconds=queue_seconds,
                   progress=progress, on_set=on_set)
    return run.run(compression=compression, calibration=calibration, overwrite=overwrite)


class _Capture:
    """One capture, through its states in order (``state``):

    ``new`` -> ``opened`` (every camera open and configured) -> ``recording`` (the take
    file exists, grabbers run; frame sets are grouped and stored until a stop
    condition) -> ``draining`` (grabbers stopped; queued frames and open sets are
    stored) -> ``closed`` (cameras closed, take closed with its sync statistics).
    ``stopped`` says why recording ended: ``frames``, ``duration``, ``stopped``,
    ``all cameras disconnected`` or ``interrupted``.
    """

    def __init__(self, rig: Rig, out: Path, drivers: dict[str, CameraDriver], *, frames: int | None,
                 duration_s: float | None, stop: threading.Event, stall_timeout_s: float, queue_seconds: float,
                 progress: Callable[[CaptureProgress], None] | None, on_set: Callable[[int], None] | None,
                 sync_window: int = 30) -> None:
        self.rig, self.out, self.drivers = rig, out, drivers
        self.frames, self.duration_s, self.stall_timeout_s = frames, duration_s, stall_timeout_s
        self.progress, self.on_set, self.stop = progress, on_set, stop
        self.ids = list(drivers)
        period_ns = int(round(1e9 / rig.fps))
        # a late camera is waited for half a second (GIL or disk stalls), then marked missing
        self.grouper = StreamGrouper(self.ids, period_ns=period_ns, tolerance_ns=rig.tolerance_ns,
                                     timeout_ns=max(4 * period_ns, 500_000_000), window=sync_window)
        self.stored = SetStatsAccumulator(self.ids, period_ns=period_ns, tolerance_ns=rig.tolerance_ns)
        self.queue: queue.Queue = queue.Queue(maxsize=max(8, int(len(self.ids) * rig.fps * queue_seconds)))
        self.queue_drops = {c: 0 for c in self.ids}
        self.granted: dict[str, Granted] = {}
        self.disconnected: dict[str, str] = {}
        self.last_seen: dict[str, float] = {}
        self.threads: list[_Grabber] = []
        self.writer: TakeWriter | None = None
        self.n_sets = 0
        self.spreads: list[int] = []  # sync spread (ns) of the last stored sets
        self.last_set: Any = None  # the last stored frame set
        self.recent: list[float] = []  # times of the sets stored in the last second
        self.t0 = self.last_stats = time.monotonic()
        self.state = "new"
        self.stopped = "frames"

    # -- the run, top to bottom

    def run(self, *, compression: str, calibration: Any, overwrite: bool) -> CaptureResult:
        self.open_cameras()
        try:
            self.start_recording(compression=compression, calibration=calibration, overwrite=overwrite)
            done = self.record()
            if not done and self.stopped != "stopped":
                self.drain()
        except KeyboardInterrupt:
            self.stopped = "interrupted"
            log.warning("capture interrupted; closing the take with %d frame sets", self.n_sets)
        finally:
            stats = self.close()
        return self.result(stats)

    def open_cameras(self) -> None:
        """Open and configure every camera; on a failure close those already open (nothing is written)."""
        opened: list[str] = []
        try:
            for cid, d in self.drivers.items():
                d.open()
                opened.append(cid)
                self.granted[cid] = d.configure()
        except BaseException:
            for cid in opened:
                _close_quietly(cid, self.drivers[cid])
            raise
        for cfg in self.rig.cameras:
            g = self.granted[cfg.id]
            if (g.width, g.height) != (cfg.width, cfg.height):
                log.warning("camera %s: asked for %dx%d, the device granted %dx%d",
                            cfg.id, cfg.width, cfg.height, g.width, g.height)
        self.state = "opened"

    def start_recording(self, *, compression: str, calibration: Any, overwrite: bool) -> None:
        """Create the take file and start one grabber thread per camera."""
        g = self.granted
        specs = [CameraSpec(c.id, g[c.id].width, g[c.id].height, storage=c.store, depth=bool(g[c.id].has_depth))
                 for c in self.rig.cameras]
        self.writer = TakeWriter(
            self.out,
            specs,
            rig=self.rig.model_dump(mode="json"),
            calibration=calibration,
            compression=compression,
            fps=self.rig.fps,
            overwrite=overwrite,
            attrs={"granted": {c: vars(v) for c, v in g.items()}},
            expected_sets=self._expected_sets(),
        )
        self.t0 = self.last_stats = time.monotonic()
        self._start_grabbers()
        self.state = "recording"

    def _expected_sets(self) -> int | None:
        if self.frames is not None:
            return self.frames
        return int(self.duration_s * self.rig.fps) if self.duration_s is not None else None

    def _start_grabbers(self) -> None:
        self.threads = [_Grabber(c, self.drivers[c], self.queue, self.stop, self.queue_drops) for c in self.ids]
        for th in self.threads:
            th.start()

    def record(self) -> bool:
        """Group and store frame sets until a stop condition; True when the frame count is reached."""
        while True:
            reason = self._stop_reason()
            if reason is not None:
                self.stopped = reason
                return False
            if self._store(self._next_sets()):
                return True

    def drain(self) -> None:
        """Stop the grabbers, store what they delivered, then the sets still open."""
        self.state = "draining"
        self.stop.set()
        for th in self.threads:
            th.join(timeout=2.0)
        while True:
            try:
                kind, cid, payload = self.queue.get_nowait()
            except queue.Empty:
                break
            if kind == "frame" and cid not in self.disconnected:
                if self._store(self.grouper.push(payload, now_ns=time.monotonic_ns())):
                    break
        self._store(self.grouper.finish())

    def close(self) -> SyncStats:
        """Stop the grabbers, close every camera and the take (in every case, also on errors)."""
        self.stop.set()
        for th in self.threads:
            th.join(timeout=2.0)
        for cid in self.ids:
            _close_quietly(cid, self.drivers[cid])
        stats = self.stored.stats(self.grouper.stats())
        if self.writer is not None:
            self.writer.close(sync_stats=stats)
        self.state = "closed"
        return stats

    def result(self, stats: SyncStats) -> CaptureResult:
        elapsed = time.monotonic() - self.t0
        return CaptureResult(
            path=self.out,
            sets=self.n_sets,
            frames=self.writer.frame_counts() if self.writer is not None else {},
            duration_s=elapsed,
            fps=self.n_sets / elapsed if elapsed > 0 else 0.0,
            stats=stats,
            stopped=self.stopped,
            disconnected=self.disconnected,
            queue_drops=dict(self.queue_drops),
            granted=self.granted,
        )

    # -- recording, one step at a time

    def _stop_reason(self) -> str | None:
        if self.stop.is_set():
            return "stopped"
        if self.duration_s is not None and time.monotonic() - self.t0 >= self.duration_s:
            return "duration"
        if len(self.disconnected) == len(self.ids):
            return "all cameras disconnected"
        return None

    def _next_sets(self) -> list:
        """Take one event off the queue (or notice it is empty) and return the sets it completes."""
        try:
            kind, cid, payload = self.queue.get(timeout=0.05)
        except queue.Empty:
            return self._sets_on_idle()
        if kind == "frame" and cid not in self.disconnected:
            # "now" for timeouts is the frame's own arrival time: a backlog in the
            # queue (slow disk) must not time out sets whose frames are still queued
            self.last_seen[cid] = payload.host_timestamp_ns / 1e9
            return self.grouper.push(payload, now_ns=payload.host_timestamp_ns)
        if kind == "gone":
            return self._camera_gone(cid, payload)
        return []

    def _sets_on_idle(self) -> list:
        """The queue is empty: the wall clock is the truth (stalled cameras, timed-out sets)."""
        emitted: list = []
        now = time.monotonic()
        for c in self.ids:
            if c not in self.disconnected and now - self.last_seen.get(c, self.t0) > self.stall_timeout_s:
                emitted += self._camera_gone(c, f"no frame for {self.stall_timeout_s:g} s")
        return emitted + self.grouper.poll(time.monotonic_ns())

    def _camera_gone(self, cid: str, why: str) -> list:
        if cid in self.disconnected:
            return []
        self.disconnected[cid] = why
        log.warning("camera %s disconnected mid-take (%s); it is marked missing from now on", cid, why)
        return self.grouper.close_camera(cid, now_ns=time.monotonic_ns())

    def _store(self, sets: list) -> bool:
        """Write decided sets (up to the frame count); True once the frame count is reached."""
        for fs in sets:
            if self._enough():
                return True
            self.writer.write_set(dict(fs.frames.items()), time_ns=fs.time_ns)
            self.stored.add(fs)
            self.n_sets += 1
            self.spreads.append(fs.spread_ns)
            del self.spreads[:-SPREAD_WINDOW]
            self.last_set = fs
            self._report(time.monotonic())
        return self._enough()

    def _enough(self) -> bool:
        return self.frames is not None and self.n_sets >= self.frames

    def _report(self, now: float) -> None:
        """Callbacks and live figures after one stored set; sync statistics into the take every second."""
        self.recent.append(now)
        while self.recent and self.recent[0] < now - 1.0:
            self.recent.pop(0)
        if self.on_set is not None:
            self.on_set(self.n_sets)
        if now - self.last_stats > 1.0:
            self.writer.update_sync_stats(self.stored.stats(self.grouper.stats()))
            self.last_stats = now
        if self.progress is not None:
            r = self.recent
            self.progress(CaptureProgress(
                sets=self.n_sets,
                target_sets=self.frames,
                elapsed_s=now - self.t0,
                duration_s=self.duration_s,
                fps=float(len(r) - 1) / max(r[-1] - r[0], 1e-9) if len(r) > 1 else 0.0,
                drops=self.stored.missing_total(),
                queue_drops=sum(self.queue_drops.values()),
                disconnected=tuple(self.disconnected),
            ))


def _close_quietly(cid: str, driver: CameraDriver) -> None:
    try:
        driver.close()
    except Exception as exc:  # closing must never hide the real outcome
        log.warning("camera %s: error while closing: %s", cid, exc)


def live_sync_window(fps: float) -> int:
    """Frames of each camera a grouper watched live holds before trusting its clock offset
    (:class:`stage.sync.StreamGrouper`'s ``window``): one second of frames, at least 8, at most
    :func:`capture_take`'s 30 (see :class:`TakeRecorder`)."""
    return max(8, min(30, round(float(fps))))


class TakeRecorder(_Capture):
    """A take recorded from cameras that are already running (a stage session's).

    The cameras stay open and their grabbers belong to the caller, which puts
    ``("frame", camera_id, Frame)`` and ``("gone", camera_id, why)`` events on
    :attr:`queue` (``put_nowait``; a full queue is the caller's drop to count with
    :meth:`count_drop`). Grouping, storing, stall detection, sync statistics and the
    take's closing are :func:`capture_take`'s: the same take, the same figures.

    Parameters
    ----------
    rig : Rig
    out : path
        The take file to create (refused when it exists).
    granted : mapping of camera id -> Granted
        What each running camera was granted (every rig camera).
    frames, duration_s : optional
        Stop conditions (at least one, or set :attr:`stop`).
    compression, calibration, stall_timeout_s, queue_seconds, on_set :
        As in :func:`capture_take`.
    disconnected : mapping of camera id -> str, optional
        Cameras already gone when recording starts: missing from the first set on.

    Notes
    -----
    The grouper trusts the cameras' clock offsets after one second of frames (at least 8, at most
    :func:`capture_take`'s 30; :class:`stage.sync.StreamGrouper`'s ``window``) and holds the first
    sets until then. Someone watches a session's take as it is written (its figures, the board
    session's guidance, the live 3-D preview): at a board take's few frames a second, 30 frames
    would hold them back for several seconds. The offsets go on improving with every frame.
    """

    def __init__(self, rig: Rig, out: str | os.PathLike, *, granted: Mapping[str, Granted],
                 frames: int | None = None, duration_s: float | None = None, compression: str = "none",
                 calibration: Any = None, stall_timeout_s: float = 5.0, queue_seconds: float = 2.0,
                 on_set: Callable[[int], None] | None = None, disconnected: Mapping[str, str] | None = None) -> None:
        if not isinstance(rig, Rig):
            raise ValueError(f"rig must be a Rig, got {type(rig).__name__}")
        missing = [c.id for c in rig.cameras if c.id not in granted]
        if missing:
            raise ValueError(f"granted: no granted settings for cameras {missing}")
        _check_limits(frames, duration_s, stall_timeout_s, queue_seconds)
        out = Path(out)
        if out.exists():
            raise FileExistsError(f"{out}: take already exists")
        super().__init__(rig, out, {c.id: None for c in rig.cameras}, frames=frames, duration_s=duration_s,  # type: ignore[misc]
                         stop=threading.Event(), stall_timeout_s=stall_timeout_s, queue_seconds=queue_seconds,
                         progress=None, on_set=on_set, sync_window=live_sync_window(rig.fps))
        self.granted = dict(granted)
        self._compression, self._calibration = compression, calibration
        self._gone_at_start = dict(disconnected or {})
        self.state = "opened"

    def open_cameras(self) -> None:  # the session opened them
        self.state = "opened"

    def _start_grabbers(self) -> None:  # the session's grabbers feed self.queue
        self.threads = []

    def start_recording(self, *, compression: str, calibration: Any, overwrite: bool) -> None:
        super().start_recording(compression=compression, calibration=calibration, overwrite=overwrite)
        for cid, why in self._gone_at_start.items():
            self._store(self._camera_gone(cid, why))

    def close(self) -> SyncStats:
        """Close the take (never the cameras: they keep running for the session)."""
        self.stop.set()
        stats = self.stored.stats(self.grouper.stats())
        if self.writer is not None:
            self.writer.close(sync_stats=stats)
        self.state = "closed"
        return stats

    def record_take(self) -> CaptureResult:
        """Record until a stop condition (or :attr:`stop` is set); the take is closed in every case."""
        return self.run(compression=self._compression, calibration=self._calibration, overwrite=False)

    def count_drop(self, camera_id: str) -> None:
        """A frame the caller could not queue (the writer fell behind)."""
        self.queue_drops[camera_id] = self.queue_drops.get(camera_id, 0) + 1

    def snapshot(self) -> dict[str, Any]:
        """Live figures: sets stored, elapsed seconds, per camera sets missing and queue drops,
        disconnected cameras and the sync spread (ns) of the last stored sets."""
        missing = self.stored.missing()
        return {
            "sets": self.n_sets,
            "elapsed_s": time.monotonic() - self.t0 if self.state in ("recording", "draining") else None,
            "missing": missing,
            "queue_drops": dict(self.queue_drops),
            "disconnected": dict(self.disconnected),
            "spreads_ns": list(self.spreads),
            "state": self.state,
        }
