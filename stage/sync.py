"""Group frames of several free-running cameras into frame sets by timestamp.

Every camera stamps its frames on its own clock. Each frame also carries the
host's ``time.monotonic_ns()`` at reception. Transport latency ``host -
device - offset`` is one-sided and grows in bursts when the host is busy (and
stays high for seconds when a device buffer backs up), so the device -> host
offset is the *fastest delivery seen so far*, with a drift allowance: for frame
``j``, ``offset_j = min_{i <= j} (lat_i + rho * (dev_j - dev_i))``, ``lat = host -
device`` and ``rho = max_drift_ppm`` (default 200 ppm). A burst can raise the
estimate by at most ``rho`` times its duration (0.2 ms per second), never by the
burst's latency, and a device clock drifting against the host is followed (as
NTP's minimum-delay filter, with a bounded clock rate). The first ``window``
frames of a camera are buffered and mapped with the minimum over them. A
frame's *mapped time* is ``device + offset`` on the host clock.

Frame sets tile time in windows ``[T_k - tol, T_k + tol)``, spaced one frame
period apart. ``T_0`` is the centre of the first frames of all cameras; after
each set, ``T_{k+1} = T_k + period + gain * median(member times - T_k)``, a
phase-locked loop that keeps the windows centred on the cameras.

A camera's frames follow its *chain*: once a frame of it is placed in window
``k``, a frame ``n`` periods later on its device clock (rounded) belongs to window
``k + n``: consecutive frames go to consecutive sets, a gap of ``n`` periods skips
``n - 1`` sets, and one camera's frames are never swapped or doubled by a
latency burst or by jitter on a window edge. The chain is left (the frame is
placed by its mapped time instead) only when the mapped time is more than
``1.5 * tol`` from the chain's window (a free-running camera slowly slipping a
period). Unchained frames go to the window containing their mapped time.

A camera contributes to a set the one frame nearest ``T_k``; a camera with no
frame there is recorded as *missing* (never filled with a duplicate), and every
frame is used at most once. Frames that belong to no window (outside the
tolerance, a second frame of one camera in one window, or arriving after their
set was emitted on timeout) are counted as *unused*: a missing frame is better
than a wrong one.

The default tolerance is half a frame period, so the windows cover time
without gaps: a set's frames lie within ``tol`` of the set time, i.e. within
one period of each other (free-running webcams have arbitrary phases).

Two entry points for the same rule: :class:`StreamGrouper` (push frames as
they arrive, get sets as soon as they are decided or timed out; used by live
capture) and :func:`group_frames` (all frames at once, replayed through a
grouper in arrival order; used by tests and imports). They agree exactly when
no set times out.

This module is pure: no I/O, no clocks read (the caller passes ``now_ns``).
Brostow et al. 2004 ("Novel skeletal representation for articulated creatures") assume
synchronized views of one instant; this is what makes a frame set one instant.
"""

from __future__ import annotations

import heapq
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, Iterable, Mapping, NamedTuple, Sequence, TypeVar

import numpy as np

__all__ = [
    "Stamp",
    "FrameSet",
    "CameraSyncStats",
    "SyncStats",
    "SetStatsAccumulator",
    "StreamGrouper",
    "group_frames",
    "estimate_period_ns",
    "relock_warnings",
]

T = TypeVar("T")


class Stamp(NamedTuple):
    """Minimal frame-like record (the attributes :class:`~stage.frame.Frame` has)."""

    camera_id: str
    index: int
    timestamp_ns: int
    host_timestamp_ns: int


@dataclass(frozen=True)
class FrameSet(Generic[T]):
    """Frames of one instant, one (or none) per camera.

    Attributes
    ----------
    index : int
        Set number, 0, 1, 2 ... in time order.
    time_ns : int
        Window centre ``T_k`` on the host monotonic clock.
    frames : dict of str -> frame or None
        Every camera of the grouper; ``None`` = missing in this set.
    times_ns : dict of str -> int
        Mapped (host-clock) time of every present frame.
    relocked : tuple of str
        Cameras whose frame here left their chain: placed by its mapped time in
        another set than the camera's previous frame and device clock said (see
        :class:`CameraSyncStats`).
    """

    index: int
    time_ns: int
    frames: dict[str, T | None]
    times_ns: dict[str, int]
    relocked: tuple[str, ...] = ()

    @property
    def missing(self) -> list[str]:
        return [c for c, f in self.frames.items() if f is None]

    @property
    def complete(self) -> bool:
        return all(f is not None for f in self.frames.values())

    @property
    def spread_ns(self) -> int:
        """Max - min mapped time of the present frames (0 with fewer than two)."""
        if len(self.times_ns) < 2:
            return 0
        v = list(self.times_ns.values())
        return int(max(v) - min(v))


@dataclass
class CameraSyncStats:
    """Per-camera counters.

    ``missing``: sets without this camera; ``sequence_gaps``: frames the device
    itself reported as skipped (jumps in its sequence numbers); ``unused``:
    frames delivered but not placed in any set; ``offset_ns``: last estimated
    device -> host clock offset; ``relocks``: frames placed by their mapped time
    in another set than the camera's chain said (its clock offset corrected by a
    period or more, or a camera slipping a period against the rig's rate);
    ``first_relock_set`` / ``last_relock_set`` the indices of the first and last
    such sets (-1: none). The offset only ever decreases, so every set before the
    last re-lock may hold this camera's frame of another instant.
    """

    frames: int = 0
    missing: int = 0
    sequence_gaps: int = 0
    unused: int = 0
    offset_ns: int = 0
    relocks: int = 0
    first_relock_set: int = -1
    last_relock_set: int = -1

    @property
    def drops(self) -> int:
        """Frames lost for this camera in the take: sets where it is missing."""
        return self.missing


@dataclass
class SyncStats:
    """Synchronization statistics of a take.

    ``spread_median_ms`` / ``spread_max_ms``: inter-camera spread (max - min
    mapped time) over sets with at least two frames.
    """

    cameras: dict[str, CameraSyncStats]
    sets: int = 0
    sets_complete: int = 0
    spread_median_ms: float = 0.0
    spread_max_ms: float = 0.0
    period_ns: int = 0
    tolerance_ns: int = 0

    @property
    def sets_incomplete(self) -> int:
        return self.sets - self.sets_complete

    @property
    def drops(self) -> dict[str, int]:
        return {c: s.drops for c, s in self.cameras.items()}

    def to_dict(self) -> dict:
        return {
            "sets": self.sets,
            "sets_complete": self.sets_complete,
            "sets_incomplete": self.sets_incomplete,
            "spread_median_ms": self.spread_median_ms,
            "spread_max_ms": self.spread_max_ms,
            "period_ns": self.period_ns,
            "tolerance_ns": self.tolerance_ns,
            "cameras": {
                c: {
                    "frames": s.frames,
                    "missing": s.missing,
                    "sequence_gaps": s.sequence_gaps,
                    "unused": s.unused,
                    "offset_ns": s.offset_ns,
                    "relocks": s.relocks,
                    "first_relock_set": s.first_relock_set,
                    "last_relock_set": s.last_relock_set,
                }
                for c, s in self.cameras.items()
            },
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "SyncStats":
        cams = {c: CameraSyncStats(**{k: int(v) for k, v in d.items()}) for c, d in data.get("cameras", {}).items()}
        return cls(
            cameras=cams,
            sets=int(data.get("sets", 0)),
            sets_complete=int(data.get("sets_complete", 0)),
            spread_median_ms=float(data.get("spread_median_ms", 0.0)),
            spread_max_ms=float(data.get("spread_max_ms", 0.0)),
            period_ns=int(data.get("period_ns", 0)),
            tolerance_ns=int(data.get("tolerance_ns", 0)),
        )


def relock_warnings(sync: Mapping[str, Any]) -> list[str]:
    """One line per camera whose frames left their chain (``SyncStats.to_dict()``'s form, as a take stores it).

    Statistics without the counters (takes written before them) give none; an entry that is not
    statistics (hand-edited, damaged) is skipped, not an error: this only adds warnings to a summary.
    """
    cams = sync.get("cameras") if isinstance(sync, Mapping) else None
    out = []
    for c, cs in (cams.items() if isinstance(cams, Mapping) else ()):
        try:
            n, first = int(cs.get("relocks", 0)), int(cs.get("first_relock_set", -1))
            last = int(cs.get("last_relock_set", first))
        except (AttributeError, TypeError, ValueError):
            continue
        if n > 0:
            where = f"in set {first}" if n == 1 or last == first else f"first in set {first}, last in set {last}"
            out.append(f"{c}: its frames left their sync chain {n} time(s), {where}: its clock offset was "
                       f"corrected by a period or more (or it slipped a period against the rig's rate); the sets "
                       f"before set {last} may pair its frames with another instant")
    return out


class SetStatsAccumulator:
    """Sync statistics of a chosen subset of emitted sets (e.g. the ones a capture stored)."""

    def __init__(self, cameras: Sequence[str], *, period_ns: int, tolerance_ns: int) -> None:
        self._acc = _StatsAccumulator(list(cameras), period_ns, tolerance_ns)

    def add(self, fs: FrameSet) -> None:
        self._acc.add_set(fs)

    def missing_total(self) -> int:
        """Camera slots missing in the added sets."""
        return sum(s.missing for s in self._acc.cams.values())

    def missing(self) -> dict[str, int]:
        """Per camera: sets it is missing from (of the added sets)."""
        return {c: int(s.missing) for c, s in self._acc.cams.items()}

    def stats(self, stream: SyncStats | None = None) -> SyncStats:
        """Statistics of the added sets; per-camera frames, sequence gaps, unused
        frames and offsets are taken from ``stream`` (the grouper's) when given."""
        snap = self._acc.snapshot()
        if stream is not None:
            for c, s in snap.cameras.items():
                o = stream.cameras.get(c)
                if o is not None:
                    s.frames, s.sequence_gaps, s.unused, s.offset_ns = o.frames, o.sequence_gaps, o.unused, o.offset_ns
        return snap


class _StatsAccumulator:
    def __init__(self, cameras: Sequence[str], period_ns: int, tolerance_ns: int) -> None:
        self.cams = {c: CameraSyncStats() for c in cameras}
        self.sets = 0
        self.complete = 0
        self.spreads: list[int] = []
        self.period_ns = period_ns
        self.tolerance_ns = tolerance_ns

    def add_set(self, fs: FrameSet) -> None:
        self.sets += 1
        if fs.complete:
            self.complete += 1
        for c, f in fs.frames.items():
            if f is None:
                self.cams[c].missing += 1
        for c in fs.relocked:
            s = self.cams[c]
            s.relocks += 1
            s.first_relock_set = self.sets - 1 if s.first_relock_set < 0 else s.first_relock_set
            s.last_relock_set = self.sets - 1
        if len(fs.times_ns) >= 2:
            self.spreads.append(fs.spread_ns)

    def snapshot(self) -> SyncStats:
        sp = np.asarray(self.spreads, dtype=np.float64) / 1e6
        return SyncStats(
            cameras={c: CameraSyncStats(**vars(s)) for c, s in self.cams.items()},
            sets=self.sets,
            sets_complete=self.complete,
            spread_median_ms=float(np.median(sp)) if sp.size else 0.0,
            spread_max_ms=float(sp.max()) if sp.size else 0.0,
            period_ns=int(self.period_ns),
            tolerance_ns=int(self.tolerance_ns),
        )


def _check_common(cameras: Sequence[str], period_ns: int | None, tolerance_ns: int | None, window: int, gain: float,
                  clock: str, max_drift_ppm: float = 200.0) -> tuple[list[str], int | None, int | None]:
    cams = list(cameras)
    if not cams or not all(isinstance(c, str) and c for c in cams):
        raise ValueError("cameras must be a non-empty sequence of camera ids")
    if len(set(cams)) != len(cams):
        raise ValueError(f"cameras: duplicate camera ids in {cams}")
    if period_ns is not None and (not np.isfinite(period_ns) or period_ns <= 0):
        raise ValueError(f"period_ns must be positive, got {period_ns}")
    if tolerance_ns is not None and (not np.isfinite(tolerance_ns) or tolerance_ns <= 0):
        raise ValueError(f"tolerance_ns must be positive, got {tolerance_ns}")
    if int(window) < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    if not 0.0 <= gain <= 1.0:
        raise ValueError(f"gain must be in [0, 1], got {gain}")
    if clock not in ("per-camera", "shared", "device"):
        raise ValueError(f"clock must be 'per-camera', 'shared' or 'device', got {clock!r}")
    if not np.isfinite(max_drift_ppm) or not 0.0 <= max_drift_ppm <= 10_000.0:
        raise ValueError(f"max_drift_ppm must be in [0, 10000], got {max_drift_ppm}")
    return cams, (None if period_ns is None else int(period_ns)), (None if tolerance_ns is None else int(tolerance_ns))


def estimate_period_ns(device_ns: Iterable[np.ndarray]) -> int:
    """Frame period from device timestamps: median positive difference over all cameras.

    Parameters
    ----------
    device_ns : iterable of (N_c,) int ndarray
        Device timestamps of each camera, in capture order.
    """
    diffs = [np.diff(np.asarray(d, dtype=np.int64)) for d in device_ns]
    diffs = [d[d > 0] for d in diffs if d.size]
    if not diffs or not sum(d.size for d in diffs):
        raise ValueError("need at least two frames of one camera to estimate the frame period")
    return int(np.median(np.concatenate(diffs)))


_PPB = 10**9
_CHAIN_SLACK = 0.5  # a frame follows its camera's chain while within (1 + slack) * tol of the chain's set


def _offset_est(values: Sequence[int]) -> int:
    """Clock offset from ``host - device`` samples: their minimum.

    Transport latency is one-sided (a frame is never received before it was
    exposed) and grows in bursts when the host is busy, so the fastest delivery
    is the best estimate (as NTP's minimum-delay filter).
    """
    return int(min(values))


def _round_div(x: int, p: int) -> int:
    """``round(x / p)`` in integers (halves up), for any sign of ``x``."""
    return (2 * x + p) // (2 * p)


def _next_time(t: int, period: int, gain: float, residuals: list[int]) -> int:
    adj = gain * float(np.median(residuals)) if residuals else 0.0
    return int(t + period + round(adj))


# ---------------------------------------------------------------------------
# streaming


class _Cam:
    __slots__ = ("raw", "first_lat", "queue", "closed", "ready", "n", "last_seq", "first_host",
                 "d0", "best", "offset", "last_k", "last_d")

    def __init__(self) -> None:
        self.raw: list[tuple[int, int, Any]] = []  # (device, host, item) before the offset is known
        self.first_lat: list[int] = []  # host - device of the first `window` frames
        self.queue: deque[tuple[int, Any, int]] = deque()  # (mapped time, item, device time)
        self.closed = False
        self.ready = False
        self.n = 0
        self.last_seq: int | None = None
        self.first_host: int | None = None
        self.d0: int | None = None  # first device time (origin of the drift bound)
        self.best: int | None = None  # min over frames of (host - device) * 1e9 - rate_ppb * (device - d0)
        self.offset = 0  # last offset estimate (ns)
        self.last_k: int | None = None  # window index of the camera's last placed frame
        self.last_d = 0  # its device time


class StreamGrouper(Generic[T]):
    """Streaming frame-set grouper for live capture.

    Push frames in the order they arrive (per camera in capture order; cameras
    interleaved arbitrarily), then collect the sets that are decided::

        g = StreamGrouper(["a", "b"], period_ns=33_333_333)
        for frame in incoming:
            for fs in g.push(frame, now_ns=time.monotonic_ns()):
                store(fs)
        for fs in g.finish():
            store(fs)

    A set is emitted once every camera has delivered a frame past its window,
    is closed (:meth:`close_camera`), or ``timeout_ns`` has passed on the host
    clock since the window ended (then the late camera is recorded missing).

    Parameters
    ----------
    cameras : sequence of str
        Camera ids, in rig order.
    period_ns : int or None
        Nominal frame period; ``None`` estimates it from the first ``window``
        frames of each camera.
    tolerance_ns : int or None
        Half-width of a set's window; default half a period.
    window : int
        Frames of each camera buffered before its clock offset is trusted
        (the first offset is the minimum latency over them).
    gain : float
        Phase-locked-loop gain in [0, 1] for re-centring the windows.
    clock : {"per-camera", "shared", "device"}
        ``per-camera``: each device clock has its own offset (default);
        ``shared``: the devices share one clock (one offset, from all cameras);
        ``device``: device timestamps are already on the host clock.
    timeout_ns : int or None
        How long after a window ends to wait for a late camera; default
        ``4 * period``. Only :meth:`poll` / ``push(now_ns=...)`` use it.
    max_drift_ppm : float
        Bound on the rate of a device clock against the host clock: the
        offset estimate may rise at most this fast (see the module notes).
    """

    def __init__(
        self,
        cameras: Sequence[str],
        *,
        period_ns: int | None = None,
        tolerance_ns: int | None = None,
        window: int = 30,
        gain: float = 0.5,
        clock: str = "per-camera",
        timeout_ns: int | None = None,
        max_drift_ppm: float = 200.0,
    ) -> None:
        cams, period, tol = _check_common(cameras, period_ns, tolerance_ns, window, gain, clock, max_drift_ppm)
        if timeout_ns is not None and timeout_ns < 0:
            raise ValueError(f"timeout_ns must be >= 0, got {timeout_ns}")
        self.cameras = cams
        self._period = period
        self._tol = tol
        self._window = int(window)
        self._gain = float(gain)
        self._clock = clock
        self._timeout = timeout_ns
        self._rate = int(round(float(max_drift_ppm) * 1000.0))  # ppb
        self._cams = {c: _Cam() for c in cams}
        self._T: int | None = None
        self._k = 0  # window index of self._T (counts skipped empty windows too)
        self._next_index = 0
        self._acc: _StatsAccumulator | None = None
        self._shared_offset: int | None = None
        self._pending_gaps = {c: 0 for c in cams}
        self._pending_counts = {c: 0 for c in cams}
        self._pending_unused = {c: 0 for c in cams}

    # -- properties ---------------------------------------------------------
    @property
    def period_ns(self) -> int | None:
        return self._period

    @property
    def tolerance_ns(self) -> int | None:
        return self._tol

    def missing_total(self) -> int:
        """Camera slots missing in the sets emitted so far (cheap; for progress bars)."""
        return sum(s.missing for s in self._acc.cams.values()) if self._acc is not None else 0

    def stats(self) -> SyncStats:
        """Statistics of the sets emitted so far."""
        acc = self._acc or _StatsAccumulator(self.cameras, self._period or 0, self._tol or 0)
        snap = acc.snapshot()
        for c in self.cameras:
            s = snap.cameras[c]
            s.frames = self._pending_counts[c]
            s.sequence_gaps = self._pending_gaps[c]
            s.unused = self._pending_unused[c]
        return snap

    # -- input --------------------------------------------------------------
    def push(self, frame: Any, *, now_ns: int | None = None) -> list[FrameSet[T]]:
        """Add one frame (anything with ``camera_id``, ``index``, ``timestamp_ns``,
        ``host_timestamp_ns``); return the sets decided by it (maybe none)."""
        cid = getattr(frame, "camera_id", None)
        if cid not in self._cams:
            raise ValueError(f"frame.camera_id {cid!r} is not one of the grouper's cameras {self.cameras}")
        cam = self._cams[cid]
        if cam.closed:
            raise ValueError(f"camera {cid!r} was closed; it cannot deliver more frames")
        dev = int(frame.timestamp_ns)
        host = int(frame.host_timestamp_ns)
        seq = int(frame.index)
        if cam.last_seq is not None and seq > cam.last_seq + 1:
            self._pending_gaps[cid] += seq - cam.last_seq - 1
        cam.last_seq = seq if cam.last_seq is None else max(seq, cam.last_seq)
        self._pending_counts[cid] += 1
        if cam.first_host is None:
            cam.first_host = host
        cam.n += 1
        self._observe(cam, dev, host)
        if len(cam.first_lat) < self._window:
            cam.first_lat.append(host - dev)
        if self._clock == "device":
            cam.ready = True
            cam.queue.append((dev, frame, dev))
        elif cam.ready:
            cam.queue.append((dev + self._offset(cam, dev), frame, dev))
        else:
            cam.raw.append((dev, host, frame))
            if cam.n >= self._window:
                self._make_ready(cam)
        return self._emit(now_ns)

    def close_camera(self, camera_id: str, *, now_ns: int | None = None) -> list[FrameSet[T]]:
        """The camera delivers no more frames (disconnected or stopped)."""
        if camera_id not in self._cams:
            raise ValueError(f"camera_id {camera_id!r} is not one of the grouper's cameras {self.cameras}")
        cam = self._cams[camera_id]
        if not cam.closed:
            cam.closed = True
            if not cam.ready:
                self._make_ready(cam)
        return self._emit(now_ns)

    def poll(self, now_ns: int) -> list[FrameSet[T]]:
        """Emit sets whose wait for late cameras has timed out at host time ``now_ns``."""
        return self._emit(int(now_ns))

    def finish(self) -> list[FrameSet[T]]:
        """No more frames from anyone: emit every remaining set."""
        out: list[FrameSet[T]] = []
        for c in self.cameras:
            out += self.close_camera(c)
        return out

    # -- clock offsets ------------------------------------------------------
    def _observe(self, cam: _Cam, dev: int, host: int) -> None:
        """Fold one latency sample into the drift-bounded running minimum."""
        if self._clock == "device":
            return
        if cam.d0 is None:
            cam.d0 = dev
        v = (host - dev) * _PPB - self._rate * (dev - cam.d0)
        cam.best = v if cam.best is None else min(cam.best, v)

    def _per_camera_offset(self, cam: _Cam, dev: int) -> int:
        """``min_i (lat_i + rate * (dev - dev_i))`` over the camera's frames so far."""
        assert cam.best is not None and cam.d0 is not None
        return (cam.best + self._rate * (dev - cam.d0)) // _PPB

    def _offset(self, cam: _Cam, dev: int) -> int:
        if self._clock == "shared" and self._shared_offset is not None:
            off = self._shared_offset
        else:
            off = self._per_camera_offset(cam, dev)
        cam.offset = off
        return off

    def _make_ready(self, cam: _Cam) -> None:
        cam.ready = True
        if not cam.raw:
            return
        for dev, _host, item in cam.raw:
            cam.queue.append((dev + self._offset(cam, dev), item, dev))
        cam.raw = []

    # -- start --------------------------------------------------------------
    def _all_started(self, now_ns: int | None) -> bool:
        for cam in self._cams.values():
            if cam.ready or cam.closed:
                continue
            if now_ns is not None and self._timeout_for_start(cam, now_ns):
                self._make_ready(cam)
                continue
            return False
        return True

    def _timeout_for_start(self, cam: _Cam, now_ns: int) -> bool:
        first = min((c.first_host for c in self._cams.values() if c.first_host is not None), default=None)
        if first is None or self._period is None:
            return False
        limit = self._window * self._period + self._timeout_ns()
        return now_ns - first > limit

    def _timeout_ns(self) -> int:
        if self._timeout is not None:
            return self._timeout
        return 4 * (self._period or 33_333_333)

    def _start(self) -> bool:
        if self._clock == "shared" and self._shared_offset is None:
            # rebase everything on one common offset (over all cameras)
            lats = [v for cam in self._cams.values() for v in cam.first_lat]
            if lats:
                self._shared_offset = _offset_est(lats)
                for cam in self._cams.values():
                    cam.queue = deque((d + self._shared_offset, it, d) for _t, it, d in cam.queue)
                    cam.offset = self._shared_offset
        if self._period is None:
            devs = []
            for cam in self._cams.values():
                devs.append(np.array([t for t, _it, _d in cam.queue][: self._window], dtype=np.int64))
            try:
                self._period = estimate_period_ns(devs)
            except ValueError:
                return False
        if self._tol is None:
            self._tol = self._period // 2
        heads = [cam.queue[0][0] for cam in self._cams.values() if cam.queue]
        if not heads:
            return False
        self._T = _initial_time(heads, self._period)
        self._acc = _StatsAccumulator(self.cameras, self._period, self._tol)
        return True

    # -- assignment ---------------------------------------------------------
    def _target(self, cam: _Cam, mapped: int, dev: int, k: int, T: int) -> tuple[int, bool]:
        """Window index a queued frame belongs to, given window ``k`` centred at ``T``.

        Returns ``(j, usable)``. A camera's frames follow its *chain*: a frame
        ``n`` periods (device clock) after the camera's last placed frame goes
        ``n`` windows after it, so one camera's frames are never swapped, doubled
        or shifted by a latency burst or a jittery window boundary. The chain is
        left (re-locked on the mapped time) only when the mapped time is more
        than ``(1 + slack) * tol`` from the chain's window.
        """
        P, tol = self._period, self._tol
        assert P is not None and tol is not None
        if cam.last_k is not None:
            e = cam.last_k + _round_div(dev - cam.last_d, P)
            if e <= cam.last_k:  # within half a period of a placed frame: a duplicate
                return e, False
            if abs(mapped - T - (e - k) * P) <= tol + int(_CHAIN_SLACK * tol):
                return e, True
        j = k + _round_div(mapped - T, P)
        r = mapped - T - (j - k) * P
        return j, -tol <= r < tol

    def _emit(self, now_ns: int | None) -> list[FrameSet[T]]:
        """Every window that is decided now, in order, as frame sets."""
        out: list[FrameSet[T]] = []
        if self._T is None:
            if not self._all_started(now_ns) or not self._start():
                return out
        assert self._T is not None and self._tol is not None and self._period is not None
        while True:
            T, k = self._T, self._k
            heads = self._window_heads(k, T)
            if not heads:
                return out
            jmin = min(heads)
            if jmin > k:
                # skip empty windows (everyone dropped, or a pause)
                self._T = T + (jmin - k) * self._period
                self._k = jmin
                continue
            if not self._decided(k, T, now_ns):
                return out
            fs, times = self._take_window(k, T)
            out.append(fs)
            self._T = _next_time(T, self._period, self._gain, [t - T for t in times.values()])
            self._k = k + 1

    def _window_heads(self, k: int, T: int) -> list[int]:
        """Window of every camera's first usable frame; frames of emitted windows (or of none) are dropped."""
        heads: list[int] = []
        for c, cam in self._cams.items():
            while cam.queue:
                m, _it, d = cam.queue[0]
                j, ok = self._target(cam, m, d, k, T)
                if j < k or (j == k and not ok):
                    cam.queue.popleft()
                    self._pending_unused[c] += 1
                    continue
                heads.append(j)
                break
        return heads

    def _decided(self, k: int, T: int, now_ns: int | None) -> bool:
        """Every camera has delivered past window ``k`` (or is closed / timed out)."""
        hi = T + self._tol
        for cam in self._cams.values():
            if cam.closed and cam.ready:
                continue
            if cam.queue:
                m, _it, d = cam.queue[-1]
                if self._target(cam, m, d, k, T)[0] > k:
                    continue
            if now_ns is not None and now_ns >= hi + self._timeout_ns():
                continue
            return False
        return True

    def _take_window(self, k: int, T: int) -> tuple[FrameSet[Any], dict[str, int]]:
        """Pop window ``k``'s frames (the one nearest its time per camera) into a frame set."""
        frames: dict[str, Any] = {}
        times: dict[str, int] = {}
        relocked: list[str] = []
        for c, cam in self._cams.items():
            cand = []
            while cam.queue:
                m, it, d = cam.queue[0]
                j, ok = self._target(cam, m, d, k, T)
                if j != k or not ok:
                    break
                cand.append(cam.queue.popleft())
            frames[c] = None
            if cand:
                best = min(range(len(cand)), key=lambda i: (abs(cand[i][0] - T), i))
                frames[c] = cand[best][1]
                times[c] = cand[best][0]
                if self._off_chain(cam, cand[best][2], k):
                    relocked.append(c)
                cam.last_k, cam.last_d = k, cand[best][2]
                self._pending_unused[c] += len(cand) - 1
        fs = FrameSet(index=self._next_index, time_ns=int(T), frames=frames, times_ns=times, relocked=tuple(relocked))
        self._next_index += 1
        assert self._acc is not None
        self._acc.add_set(fs)
        for c, cam in self._cams.items():
            if cam.n:
                self._acc.cams[c].offset_ns = 0 if self._clock == "device" else int(cam.offset)
        return fs, times

    def _off_chain(self, cam: _Cam, dev: int, k: int) -> bool:
        """A frame placed in window ``k`` off its camera's chain (the chain would put it in another window)."""
        assert self._period is not None
        return cam.last_k is not None and cam.last_k + _round_div(dev - cam.last_d, self._period) != k


def _initial_time(heads: Sequence[int], period: int) -> int:
    """Centre of the first frames within one period of the earliest."""
    h = np.sort(np.asarray(heads, dtype=np.int64))
    first = h[h < h[0] + period]
    return int((int(first[0]) + int(first[-1])) // 2)


# ---------------------------------------------------------------------------
# batch


def group_frames(
    frames: Iterable[Any],
    cameras: Sequence[str] | None = None,
    *,
    period_ns: int | None = None,
    tolerance_ns: int | None = None,
    window: int = 30,
    gain: float = 0.5,
    clock: str = "per-camera",
    max_drift_ppm: float = 200.0,
) -> tuple[list[FrameSet], SyncStats]:
    """Group a whole recording into frame sets (same rule as :class:`StreamGrouper`).

    The frames are replayed through a :class:`StreamGrouper` in host-arrival
    order (each camera's frames in the given order) without timeouts, so the
    two agree exactly when no live set times out.

    Parameters
    ----------
    frames : iterable of frame-like
        Objects with ``camera_id``, ``index``, ``timestamp_ns``,
        ``host_timestamp_ns`` (e.g. :class:`~stage.frame.Frame` or
        :class:`Stamp`), per camera in capture order.
    cameras : sequence of str, optional
        Camera ids in rig order; default: in order of first appearance.
    period_ns, tolerance_ns, window, gain, clock, max_drift_ppm
        As in :class:`StreamGrouper`.

    Returns
    -------
    sets : list of FrameSet
    stats : SyncStats
    """
    items = list(frames)
    if cameras is None:
        seen: dict[str, None] = {}
        for f in items:
            seen.setdefault(getattr(f, "camera_id", None), None)
        cameras = [c for c in seen if c is not None]
        if not cameras:
            raise ValueError("frames is empty and no cameras were given")
    cams, period, tol = _check_common(cameras, period_ns, tolerance_ns, window, gain, clock, max_drift_ppm)
    per: dict[str, list[Any]] = {c: [] for c in cams}
    for f in items:
        cid = getattr(f, "camera_id", None)
        if cid not in per:
            raise ValueError(f"frame camera_id {cid!r} is not one of the cameras {cams}")
        per[cid].append(f)
    g: StreamGrouper = StreamGrouper(
        cams, period_ns=period, tolerance_ns=tol, window=window, gain=gain, clock=clock, max_drift_ppm=max_drift_ppm
    )
    sets: list[FrameSet] = []
    keyed = [[(int(f.host_timestamp_ns), ci, i, f) for i, f in enumerate(per[c])] for ci, c in enumerate(cams)]
    for _h, _ci, _i, f in heapq.merge(*keyed, key=lambda r: (r[0], r[1], r[2])):
        sets += g.push(f)
    sets += g.finish()
    return sets, g.stats()
