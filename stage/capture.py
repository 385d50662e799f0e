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

__all__ = ["CaptureProgress", "CaptureResult", "capture_take"]

log = logging.getLogger(__name__)


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
    if frames is not None and (not isinstance(frames, int) or frames < 1):
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"duration_s must be positive, got {duration_s!r}")
    if stall_timeout_s <= 0 or queue_seconds <= 0:
        raise ValueError("stall_timeout_s and queue_seconds must be positive")
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: take already exists (use --overwrite to replace it)")

    drv = _open_drivers(rig, drivers)
    ids = list(drv)
    granted: dict[str, Granted] = {}
    opened: list[str] = []
    try:
        for cid, d in drv.items():
            d.open()
            opened.append(cid)
            granted[cid] = d.configure()
    except BaseException:
        for cid in opened:
            _close_quietly(cid, drv[cid])
        raise
    for cfg in rig.cameras:
        g = granted[cfg.id]
        if (g.width, g.height) != (cfg.width, cfg.height):
            log.warning("camera %s: asked for %dx%d, the device granted %dx%d", cfg.id, cfg.width, cfg.height, g.width, g.height)
    specs = [
        CameraSpec(c.id, granted[c.id].width, granted[c.id].height, storage=c.store, depth=bool(granted[c.id].has_depth))
        for c in rig.cameras
    ]
    period_ns = int(round(1e9 / rig.fps))
    # a late camera is waited for half a second (GIL or disk stalls), then marked missing
    grouper: StreamGrouper = StreamGrouper(
        ids, period_ns=period_ns, tolerance_ns=rig.tolerance_ns, timeout_ns=max(4 * period_ns, 500_000_000)
    )
    stored = SetStatsAccumulator(ids, period_ns=period_ns, tolerance_ns=rig.tolerance_ns)
    stop_ev = stop or threading.Event()
    q: queue.Queue = queue.Queue(maxsize=max(8, int(len(ids) * rig.fps * queue_seconds)))
    qdrops = {c: 0 for c in ids}
    disconnected: dict[str, str] = {}
    last_seen: dict[str, float] = {}
    threads: list[_Grabber] = []
    stopped = "frames"
    writer = None
    n_sets = 0
    t0 = time.monotonic()
    try:
        writer = TakeWriter(
            out,
            specs,
            rig=rig.model_dump(mode="json"),
            calibration=calibration,
            compression=compression,
            fps=rig.fps,
            overwrite=overwrite,
            attrs={"granted": {c: vars(g) for c, g in granted.items()}},
            expected_sets=frames if frames is not None else int(duration_s * rig.fps),
        )
        threads = [_Grabber(c, drv[c], q, stop_ev, qdrops) for c in ids]
        t0 = time.monotonic()
        for th in threads:
            th.start()
        recent: list[float] = []
        last_stats = t0

        def store(sets: list) -> bool:
            nonlocal n_sets, last_stats
            for fs in sets:
                if frames is not None and n_sets >= frames:
                    return True
                writer.write_set({c: f for c, f in fs.frames.items()}, time_ns=fs.time_ns)
                stored.add(fs)
                n_sets += 1
                now = time.monotonic()
                recent.append(now)
                while recent and recent[0] < now - 1.0:
                    recent.pop(0)
                if on_set is not None:
                    on_set(n_sets)
                if now - last_stats > 1.0:
                    writer.update_sync_stats(stored.stats(grouper.stats()))
                    last_stats = now
                if progress is not None:
                    progress(
                        CaptureProgress(
                            sets=n_sets,
                            target_sets=frames,
                            elapsed_s=now - t0,
                            duration_s=duration_s,
                            fps=float(len(recent) - 1) / max(recent[-1] - recent[0], 1e-9) if len(recent) > 1 else 0.0,
                            drops=missing_so_far(),
                            queue_drops=sum(qdrops.values()),
                            disconnected=tuple(disconnected),
                        )
                    )
            return frames is not None and n_sets >= frames

        def missing_so_far() -> int:
            return stored.missing_total()

        def camera_gone(cid: str, why: str) -> list:
            if cid in disconnected:
                return []
            disconnected[cid] = why
            log.warning("camera %s disconnected mid-take (%s); it is marked missing from now on", cid, why)
            return grouper.close_camera(cid, now_ns=time.monotonic_ns())

        done = False
        while not done:
            if stop_ev.is_set():
                stopped = "stopped"
                break
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                stopped = "duration"
                break
            if len(disconnected) == len(ids):
                stopped = "all cameras disconnected"
                break
            try:
                kind, cid, payload = q.get(timeout=0.05)
            except queue.Empty:
                kind = None
            emitted: list = []
            if kind == "frame" and cid not in disconnected:
                # "now" for timeouts is the frame's own arrival time: a backlog in the
                # queue (slow disk) must not time out sets whose frames are still queued
                last_seen[cid] = payload.host_timestamp_ns / 1e9
                emitted += grouper.push(payload, now_ns=payload.host_timestamp_ns)
            elif kind == "gone":
                emitted += camera_gone(cid, payload)
            elif kind is None:  # queue empty: the wall clock is the truth
                now = time.monotonic()
                for c in ids:
                    if c not in disconnected and now - last_seen.get(c, t0) > stall_timeout_s:
                        emitted += camera_gone(c, f"no frame for {stall_timeout_s:g} s")
                emitted += grouper.poll(time.monotonic_ns())
            done = store(emitted)
        if not done and stopped != "stopped":
            # stop the grabbers, store what they delivered, then emit the sets still open
            stop_ev.set()
            for th in threads:
                th.join(timeout=2.0)
            while True:
                try:
                    kind, cid, payload = q.get_nowait()
                except queue.Empty:
                    break
                if kind == "frame" and cid not in disconnected:
                    if store(grouper.push(payload, now_ns=time.monotonic_ns())):
                        break
            store(grouper.finish())
    except KeyboardInterrupt:
        stopped = "interrupted"
        log.warning("capture interrupted; closing the take with %d frame sets", n_sets)
    finally:
        stop_ev.set()
        for th in threads:
            th.join(timeout=2.0)
        for cid in ids:
            _close_quietly(cid, drv[cid])
        stats = stored.stats(grouper.stats())
        if writer is not None:
            writer.close(sync_stats=stats)
    elapsed = time.monotonic() - t0
    counts = writer.frame_counts() if writer is not None else {}
    return CaptureResult(
        path=out,
        sets=n_sets,
        frames=counts,
        duration_s=elapsed,
        fps=n_sets / elapsed if elapsed > 0 else 0.0,
        stats=stats,
        stopped=stopped,
        disconnected=disconnected,
        queue_drops=dict(qdrops),
        granted=granted,
    )


def _close_quietly(cid: str, driver: CameraDriver) -> None:
    try:
        driver.close()
    except Exception as exc:  # closing must never hide the real outcome
        log.warning("camera %s: error while closing: %s", cid, exc)
