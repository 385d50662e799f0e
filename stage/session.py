"""A stage session: the rig's cameras opened once and kept running, with live figures and takes.

:class:`StageSession` opens every camera of a rig, configures it and starts one grabber
thread per camera that pulls frames for as long as the session lives. Each frame

* becomes the camera's *latest frame* (what previews show),
* counts in the camera's live figures (delivered fps, device sequence gaps),
* goes to the live grouper (:class:`stage.sync.StreamGrouper`, on its own thread) whose
  frame sets give the sync spread of the last sets and the latest frame set, or
* while a take is recorded, to the :class:`stage.capture.TakeRecorder` instead, which groups
  and stores it exactly as :func:`stage.capture.capture_take` does (its sets are then the
  live ones): what is previewed is what is recorded.

A camera whose driver raises (unplugged) is marked disconnected with the driver's message;
the others go on, and a take being recorded marks it missing from then on (the take's
sync statistics hold the gap). Nothing here waits for a consumer: the grabbers only ever
``put_nowait`` and count what a full queue refused.

The disk figures: free bytes where takes are written, and minutes of recording left at the
rig's raw data rate (width x height x 3 bytes per camera and frame, a tenth of it for JPEG
storage). The USB figures are :mod:`stage.discovery`'s bandwidth model.
"""

from __future__ import annotations

import collections
import logging
import os
import queue
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from stage.capture import CaptureResult, TakeRecorder, live_sync_window
from stage.drivers.base import CameraDriver, CameraError, Granted
from stage.frame import Frame
from stage.rig import Rig
from stage.sync import FrameSet, StreamGrouper

__all__ = ["StageSession", "RecordingBusyError", "NoRecordingError", "CameraLive", "recording_rate_bytes"]

log = logging.getLogger(__name__)

#: seconds over which the delivered frame rate is measured
FPS_WINDOW_S = 2.0
#: JPEG-stored frames take about this fraction of raw ones (for the minutes-left estimate)
JPEG_FRACTION = 0.1


class RecordingBusyError(RuntimeError):
    """A take is being recorded already (one at a time per session)."""


class NoRecordingError(RuntimeError):
    """Stop was asked while nothing is recorded."""


@dataclass
class CameraLive:
    """One running camera: its state and counters (updated by its grabber thread)."""

    camera_id: str
    state: str = "starting"  # starting | running | disconnected | failed
    error: str | None = None
    granted: Granted | None = None
    delivered: int = 0
    sequence_gaps: int = 0
    last_index: int | None = None
    seq: int = 0  # bumps with every new latest frame
    latest: Frame | None = None
    times: collections.deque = field(default_factory=lambda: collections.deque(maxlen=4096))

    def fps(self, now: float) -> float:
        """Frames delivered per second over the last :data:`FPS_WINDOW_S` seconds."""
        t = [x for x in self.times if x >= now - FPS_WINDOW_S]
        if len(t) < 2:
            return 0.0
        return (len(t) - 1) / max(t[-1] - t[0], 1e-9)


#: the window (s) of a camera's recent dropped frames in :meth:`StageSession.figures`
RECENT_DROPS_S = 10.0


def recording_rate_bytes(rig: Rig) -> float:
    """Bytes per second a take of ``rig`` needs (raw BGR frames; JPEG-stored ones a tenth)."""
    total = 0.0
    for c in rig.cameras:
        per = c.width * c.height * 3 * float(c.fps or rig.fps)
        total += per * (JPEG_FRACTION if c.store == "jpeg" else 1.0)
    return total


class StageSession:
    """The rig's cameras, running for the life of the session.

    Parameters
    ----------
    rig : Rig
    takes_dir : path
        Where takes are written (its disk is the one whose free space is shown).
    drivers : mapping of camera id -> CameraDriver, optional
        Ready-made (not yet opened) drivers; default :func:`stage.drivers.open_driver`.
    stall_timeout_s : float
        A camera that delivers nothing for this long while recording is disconnected.
    bus_loads : list of stage.discovery.BusReport, optional
        The bandwidth check's reports of the rig's USB buses (shown per camera).
    clock : callable
        ``time.monotonic`` (a test hook).
    """

    def __init__(self, rig: Rig, takes_dir: str | os.PathLike, *, drivers: Mapping[str, CameraDriver] | None = None,
                 stall_timeout_s: float = 5.0, bus_loads: list | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not isinstance(rig, Rig):
            raise ValueError(f"rig must be a Rig, got {type(rig).__name__}")
        if stall_timeout_s <= 0:
            raise ValueError(f"stall_timeout_s must be positive, got {stall_timeout_s!r}")
        if drivers is not None:
            missing = [c.id for c in rig.cameras if c.id not in drivers]
            if missing:
                raise ValueError(f"drivers: no driver for cameras {missing}")
        self.rig = rig
        self.takes_dir = Path(takes_dir)
        self.ids = [c.id for c in rig.cameras]
        self._drivers = dict(drivers) if drivers is not None else None
        self.drivers: dict[str, CameraDriver] = {}
        self.stall_timeout_s = float(stall_timeout_s)
        self.bus_loads = list(bus_loads or [])
        self._clock = clock
        self.cameras = {c: CameraLive(c) for c in self.ids}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        period_ns = int(round(1e9 / rig.fps))
        self._period_ns = period_ns
        self._live_q: queue.Queue = queue.Queue(maxsize=max(64, 4 * len(self.ids)))
        # figures from the first second on, also at a board session's few frames a second
        self._grouper = StreamGrouper(self.ids, period_ns=period_ns, tolerance_ns=rig.tolerance_ns,
                                      timeout_ns=max(4 * period_ns, 500_000_000), window=live_sync_window(rig.fps))
        self._spreads: collections.deque = collections.deque(maxlen=30)
        self._recent_sets: collections.deque = collections.deque(maxlen=30)  # the last sets' frame times
        self._gaps: collections.deque = collections.deque(maxlen=4096)  # (clock, camera, frames lost) of recent gaps
        self._latest_set: FrameSet | None = None
        self._sets = 0
        self._recorder: TakeRecorder | None = None
        self._rec_thread: threading.Thread | None = None
        self._rec_take: str | None = None
        self._last: dict[str, Any] = {}
        self.opened = False
        self.closed = False

    # -- life ------------------------------------------------------------------------------------

    def open(self) -> "StageSession":
        """Open and configure every camera and start grabbing. A camera that fails to open is
        marked ``failed`` with the driver's message; :class:`CameraError` when none opens."""
        factory = None
        if self._drivers is None:
            from stage.drivers.registry import open_driver

            factory = open_driver
        for cfg in self.rig.cameras:
            live = self.cameras[cfg.id]
            try:
                drv = self._drivers[cfg.id] if factory is None else factory(cfg, self.rig)
                drv.open()
                live.granted = drv.configure()
                self.drivers[cfg.id] = drv
                live.state = "running"
            except Exception as exc:  # one camera failing must not take the stage down
                live.state, live.error = "failed", f"{type(exc).__name__}: {exc}" if not isinstance(exc, CameraError) else str(exc)
                log.warning("camera %s could not be opened: %s", cfg.id, live.error)
        if not self.drivers:
            raise CameraError("no camera of the rig could be opened: " +
                              "; ".join(f"{c}: {v.error}" for c, v in self.cameras.items()))
        for cid, drv in self.drivers.items():
            th = threading.Thread(target=self._grab_loop, args=(cid, drv), name=f"session-grab-{cid}", daemon=True)
            self._threads.append(th)
        self._threads.append(threading.Thread(target=self._group_loop, name="session-group", daemon=True))
        for th in self._threads:
            th.start()
        self.opened = True
        return self

    def close(self) -> None:
        """Stop a take being recorded (it is closed cleanly), stop grabbing, close the cameras."""
        if self.closed:
            return
        self.closed = True
        rec = self._recorder
        if rec is not None:
            rec.stop.set()
            if self._rec_thread is not None:
                self._rec_thread.join(30)
        self._stop.set()
        for th in self._threads:
            th.join(timeout=3.0)
        for cid, drv in self.drivers.items():
            try:
                drv.close()
            except Exception as exc:  # closing must never hide anything else
                log.warning("camera %s: error while closing: %s", cid, exc)

    def __enter__(self) -> "StageSession":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- threads ---------------------------------------------------------------------------------

    def _grab_loop(self, cid: str, drv: CameraDriver) -> None:
        live = self.cameras[cid]
        while not self._stop.is_set():
            try:
                frame = drv.grab()
            except Exception as exc:  # a driver that raises is gone (unplugged); a bug too, but said so
                why = str(exc) if isinstance(exc, CameraError) else f"{type(exc).__name__}: {exc}"
                self._camera_gone(cid, why)
                return
            if frame.camera_id != cid:
                from dataclasses import replace

                frame = replace(frame, camera_id=cid)
            now = self._clock()
            with self._lock:
                if live.last_index is not None and frame.index > live.last_index + 1:
                    live.sequence_gaps += frame.index - live.last_index - 1
                    self._gaps.append((now, cid, frame.index - live.last_index - 1))
                live.last_index = frame.index
                live.delivered += 1
                live.times.append(now)
                live.latest = frame
                live.seq += 1
                rec = self._recorder
            if rec is not None and not rec.stop.is_set():
                try:
                    rec.queue.put_nowait(("frame", cid, frame))
                except queue.Full:
                    rec.count_drop(cid)
                continue  # while recording, the take's sets are the live ones
            try:
                self._live_q.put_nowait(("frame", cid, frame))
            except queue.Full:
                pass  # the live figures skip a frame; the take does not

    def _camera_gone(self, cid: str, why: str) -> None:
        live = self.cameras[cid]
        with self._lock:
            live.state, live.error = "disconnected", why
            rec = self._recorder
        log.warning("camera %s disconnected: %s", cid, why)
        if rec is not None:
            try:
                rec.queue.put(("gone", cid, why), timeout=1.0)
            except queue.Full:  # the recorder's stall timeout marks it missing instead
                log.warning("camera %s: the take will notice the disconnect by its stall timeout", cid)
        try:
            self._live_q.put(("gone", cid, why), timeout=1.0)
        except queue.Full:
            pass

    def _group_loop(self) -> None:
        while not self._stop.is_set():
            try:
                kind, cid, payload = self._live_q.get(timeout=0.1)
            except queue.Empty:
                self._took(self._grouper.poll(time.monotonic_ns()))
                continue
            if kind == "frame":
                self._took(self._grouper.push(payload, now_ns=payload.host_timestamp_ns))
            else:
                self._took(self._grouper.close_camera(cid, now_ns=time.monotonic_ns()))

    def _took(self, sets: list) -> None:
        for fs in sets:
            with self._lock:
                self._spreads.append(fs.spread_ns)
                self._recent_sets.append(dict(fs.times_ns))
                self._latest_set = fs
                self._sets += 1

    # -- reading ---------------------------------------------------------------------------------

    def latest(self, camera_id: str) -> tuple[int, Frame | None]:
        """(sequence number, latest frame) of one camera; the number grows with every frame."""
        live = self.cameras.get(camera_id)
        if live is None:
            raise KeyError(camera_id)
        with self._lock:
            return live.seq, live.latest

    def latest_set(self) -> FrameSet | None:
        """The most recent frame set: the take's last stored one while recording, else the live
        grouper's (None before the first)."""
        with self._lock:
            rec = self._recorder
            live = self._latest_set
        last = None if rec is None else rec.last_set
        return last if last is not None else live

    def disk(self) -> dict[str, float | None]:
        """Free bytes on the takes' disk and minutes of recording left at the rig's data rate."""
        try:
            self.takes_dir.mkdir(parents=True, exist_ok=True)
            free = float(shutil.disk_usage(self.takes_dir).free)
        except OSError:
            return {"free_bytes": None, "minutes_left": None, "rate_mb_s": recording_rate_bytes(self.rig) / 1e6}
        rate = recording_rate_bytes(self.rig)
        return {"free_bytes": free, "minutes_left": free / rate / 60.0 if rate > 0 else None, "rate_mb_s": rate / 1e6}

    def _bus(self, cid: str) -> dict[str, Any]:
        from stage.discovery import camera_bandwidth_mbps

        cfg = next(c for c in self.rig.cameras if c.id == cid)
        g = self.cameras[cid].granted
        fmt = g.pixel_format if g is not None else "YUYV"
        fps = g.fps if g is not None and g.fps else float(cfg.fps or self.rig.fps)
        w, h = (g.width, g.height) if g is not None else (cfg.width, cfg.height)
        out: dict[str, Any] = {"stream_mbps": camera_bandwidth_mbps(w, h, fps, fmt), "bus": None,
                               "bus_need_mbps": None, "bus_budget_mbps": None, "oversubscribed": False}
        for rep in self.bus_loads:
            if any(c == cid for c, _ in rep.cameras):
                out.update(bus=rep.bus, bus_need_mbps=rep.need_mbps, bus_budget_mbps=rep.budget_mbps,
                           oversubscribed=rep.oversubscribed, warning=rep.warning())
        return out

    def figures(self) -> dict[str, Any]:
        """Everything the control room shows, as plain data (JSON-ready)."""
        now = self._clock()
        rec = self.recording()
        with self._lock:
            spreads = list(self._spreads)
            cams = []
            for cid in self.ids:
                live = self.cameras[cid]
                g = live.granted
                fps = round(live.fps(now), 2) if live.state == "running" else 0.0
                cams.append({
                    "id": cid, "state": live.state, "error": live.error, "fps": fps,
                    "delivered": live.delivered, "dropped": live.sequence_gaps,
                    **_levels(live.latest, g),
                    "width": None if g is None else g.width, "height": None if g is None else g.height,
                    "pixel_format": None if g is None else g.pixel_format,
                })
            sets = self._sets
            recent = list(self._recent_sets)
            while self._gaps and self._gaps[0][0] < now - RECENT_DROPS_S:
                self._gaps.popleft()
            recent_gaps = collections.Counter()
            for _, cid, n in self._gaps:
                recent_gaps[cid] += n
        offsets = sync_offsets(recent, cameras=self.ids)
        for c in cams:
            c["sync"] = {**offsets[c["id"]], "sets": len(recent)}
            c["dropped_recent"] = recent_gaps[c["id"]]
            c["dropped_recent_s"] = RECENT_DROPS_S
        snap = rec.get("live") or {}
        for c in cams:
            c.update(self._bus(c["id"]))
            if snap:
                c["take_missing"] = snap["missing"].get(c["id"], 0)
                c["take_queue_drops"] = snap["queue_drops"].get(c["id"], 0)
                c["take_disconnected"] = snap["disconnected"].get(c["id"])
        spread_src = snap.get("spreads_ns") if snap.get("spreads_ns") else spreads
        return {
            "rig": self.rig.name, "fps": self.rig.fps, "cameras": cams, "sets": sets,
            "sync_spread_ms": _spread_ms(spread_src), "tolerance_ms": self.rig.tolerance_ns / 1e6,
            "disk": self.disk(), "recording": rec,
        }

    # -- recording -------------------------------------------------------------------------------

    def start_recording(self, out: str | os.PathLike, *, take: str | None = None, frames: int | None = None,
                        duration_s: float | None = None, compression: str = "none", calibration: Any = None,
                        on_done: Callable[[CaptureResult | None, str | None], None] | None = None) -> dict[str, Any]:
        """Record a take from the running cameras into ``out`` until ``frames`` sets, ``duration_s``
        seconds or :meth:`stop_recording`.

        Raises
        ------
        RecordingBusyError
            A take is being recorded already.
        FileExistsError
            ``out`` exists.
        """
        if not self.opened or self.closed:
            raise RuntimeError("the session is not running")
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        with self._lock:
            if self._recorder is not None:
                raise RecordingBusyError(f"take {self._rec_take!r} is being recorded; stop it first")
            if out.exists():
                raise FileExistsError(f"take {take or out.stem!r} already exists")
            granted = {c: v.granted for c, v in self.cameras.items() if v.granted is not None}
            gone = {c: v.error or v.state for c, v in self.cameras.items() if v.state in ("failed", "disconnected")}
            for c in self.ids:  # a camera that never opened is recorded as missing at its rig size
                if c not in granted:
                    cfg = next(x for x in self.rig.cameras if x.id == c)
                    granted[c] = Granted(width=cfg.width, height=cfg.height, fps=float(cfg.fps or self.rig.fps))
            rec = TakeRecorder(self.rig, out, granted=granted, frames=frames, duration_s=duration_s,
                               compression=compression, calibration=calibration,
                               stall_timeout_s=self.stall_timeout_s, disconnected=gone)
            self._recorder, self._rec_take = rec, take or out.stem
            self._last = {"state": "recording", "take": self._rec_take, "started": time.time(), "result": None,
                          "error": None}
            self._rec_thread = threading.Thread(target=self._record, args=(rec, on_done), name="session-record",
                                                daemon=True)
            self._rec_thread.start()
            return dict(self._last)

    def _record(self, rec: TakeRecorder, on_done) -> None:
        result, err = None, None
        try:
            result = rec.record_take()
        except Exception as exc:  # a failed take is the state's error; the session goes on
            log.exception("recording %s failed", rec.out.name)
            err = f"{type(exc).__name__}: {exc}"
        with self._lock:
            self._recorder = None
            self._last = {**self._last, "state": "failed" if err else "done", "error": err,
                          "finished": time.time(), "result": None if result is None else _result_dict(result)}
        if on_done is not None:
            on_done(result, err)

    def stop_recording(self, *, wait: float | None = 30.0) -> dict[str, Any]:
        """Stop the take being recorded (it keeps what was written) and wait for it to close."""
        with self._lock:
            rec, th = self._recorder, self._rec_thread
        if rec is None:
            raise NoRecordingError("no take is being recorded")
        rec.stop.set()
        if th is not None and wait is not None:
            th.join(wait)
        return self.recording()

    def wait_recording(self, timeout: float | None = None) -> None:
        th = self._rec_thread
        if th is not None:
            th.join(timeout)

    @property
    def recording_active(self) -> bool:
        with self._lock:
            return self._recorder is not None

    def recording(self) -> dict[str, Any]:
        """The take being recorded (live figures under ``live``) or the last one."""
        with self._lock:
            rec, last = self._recorder, dict(self._last)
        if not last:
            return {"state": "idle"}
        if rec is not None:
            snap = rec.snapshot()
            last["live"] = snap
            last["frames_written"] = snap["sets"]
            last["elapsed_s"] = snap["elapsed_s"]
            last["drops"] = sum(snap["missing"].values()) + sum(snap["queue_drops"].values())
        elif last.get("result"):
            r = last["result"]
            last["frames_written"] = r["sets"]
            last["elapsed_s"] = r["duration_s"]
            last["drops"] = sum(r["drops"].values())
        return last


def _levels(frame: Frame | None, granted: Granted | None) -> dict[str, Any]:
    """Exposure (ms) and gain of a camera as its latest frame says (devices that report them per
    frame), else as the device granted them; None where the driver has neither."""
    exposure = None if frame is None else frame.exposure_ms
    gain = None if frame is None else frame.gain
    if granted is not None:
        exposure = granted.exposure if exposure is None else exposure
        gain = granted.extra.get("gain") if gain is None else gain
    return {"exposure_ms": exposure, "gain": gain, "gain_unit": None if granted is None else granted.extra.get("gain_unit")}


def sync_offsets(sets: list[Mapping[str, int]], *, cameras: list[str]) -> dict[str, dict[str, Any]]:
    """How late each camera's frames are against the others' in frame sets.

    Parameters
    ----------
    sets : list of dict of str -> int
        The present frames' mapped (host-clock) times of each set, ns (:attr:`stage.sync.FrameSet.times_ns`).
    cameras : list of str
        The cameras to report, also those in no set.

    Returns
    -------
    dict of str -> dict
        Per camera ``offset_ms``: the median over the sets with it and at least one other camera of its
        time minus the median time of the set's frames (positive: later than the others; None in no such
        set), and ``missing``: the sets without it.
    """
    if not isinstance(cameras, (list, tuple)) or not all(isinstance(c, str) for c in cameras):
        raise ValueError(f"cameras: a list of camera ids, got {cameras!r}")
    if not isinstance(sets, (list, tuple)) or not all(isinstance(t, Mapping) for t in sets):
        raise ValueError("sets: a list of {camera: time_ns} mappings")
    per: dict[str, list[float]] = {c: [] for c in cameras}
    for times in sets:
        if len(times) < 2:
            continue
        v = sorted(times.values())
        mid = (v[(len(v) - 1) // 2] + v[len(v) // 2]) / 2
        for c, t in times.items():
            if c in per:
                per[c].append(t - mid)
    out = {}
    for c in cameras:
        d = sorted(per[c])
        med = None if not d else (d[(len(d) - 1) // 2] + d[len(d) // 2]) / 2 / 1e6
        out[c] = {"offset_ms": med, "missing": sum(c not in t for t in sets)}
    return out


def _spread_ms(spreads: list) -> dict[str, float | None]:
    """Median and max sync spread (ms) of the last sets."""
    if not spreads:
        return {"median": None, "max": None, "n": 0}
    s = sorted(spreads)
    return {"median": s[len(s) // 2] / 1e6, "max": s[-1] / 1e6, "n": len(s)}


def _result_dict(r: CaptureResult) -> dict[str, Any]:
    st = r.stats
    return {
        "sets": int(r.sets), "frames": {k: int(v) for k, v in r.frames.items()}, "duration_s": float(r.duration_s),
        "fps": float(r.fps), "stopped": str(r.stopped), "disconnected": dict(r.disconnected),
        "drops": {k: int(v) for k, v in r.drops.items()},
        "queue_drops": {k: int(v) for k, v in r.queue_drops.items()},
        "sync": st.to_dict(),
    }


