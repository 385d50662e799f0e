"""The live 3-D preview: a coarse visual hull of the latest frame set and its spine.

A worker *process* (so that capture never waits for it, not even for the interpreter lock)
receives the session's latest frame set a few times a second, keys each camera's image
(:mod:`stage.keying`, the rig's backdrop; the model is estimated once per camera), carves a
hull on a ``resolution``^3 grid over the rig's volume (:class:`pipeline.hull.HullCarver`: its
lookup tables are built once, a carve is then a few milliseconds; one camera is allowed to
disagree) and returns its surface voxels and the sides of the volume it reaches (:func:`volume_edges`);
when the subject is articulated (its surface has tips, :func:`pipeline.frame_skeleton.frame_skeleton`),
also the skeleton grown from the first tip as segments. A thread of the server sends a set only when
the worker is free (the newest one; sets in between are skipped) and keeps the last answer, which the page draws
(:meth:`Live3D.latest`).
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
import time
from typing import Any

import numpy as np

__all__ = ["Live3D", "volume_edges"]

log = logging.getLogger(__name__)


def _surface_voxels(occ: np.ndarray) -> np.ndarray:
    """(N, 3) int indices of occupied voxels with an empty 6-neighbour."""
    pad = np.pad(occ, 1)
    inner = pad[1:-1, 1:-1, 1:-1]
    full = (pad[:-2, 1:-1, 1:-1] & pad[2:, 1:-1, 1:-1] & pad[1:-1, :-2, 1:-1] & pad[1:-1, 2:, 1:-1]
            & pad[1:-1, 1:-1, :-2] & pad[1:-1, 1:-1, 2:])
    return np.argwhere(inner & ~full)


#: the sides of the capture volume, as :func:`volume_edges` names them (axis, end)
_SIDES = (("x min", 0, 0), ("x max", 0, -1), ("y min", 1, 0), ("y max", 1, -1), ("z max", 2, -1))


def volume_edges(occupancy: np.ndarray) -> list[str]:
    """The sides of the capture volume a hull reaches: where the subject may go on outside it.

    Parameters
    ----------
    occupancy : (X, Y, Z) bool ndarray
        The hull on a grid over the volume (x, y, z axes; z up).

    Returns
    -------
    list of str
        Of ``"x min"``, ``"x max"``, ``"y min"``, ``"y max"``, ``"z max"``: the sides with an occupied voxel
        in the grid's outer layer. The floor (``z min``) is never named: a subject stands on it.
    """
    occ = np.asarray(occupancy)
    if occ.ndim != 3 or occ.dtype != bool or min(occ.shape, default=0) < 1:
        raise ValueError(f"occupancy must be a non-empty (X, Y, Z) bool array, got {occ.dtype} {occ.shape}")
    return [name for name, axis, end in _SIDES if occ.take(end, axis=axis).any()]


class _Worker:
    """What the worker process holds: the grid's carver and each camera's backdrop model."""

    def __init__(self, calibration: dict, bounds, resolution: int, backdrop: tuple[str, str], spine: bool) -> None:
        from calib.calibration import Calibration
        from pipeline.hull import HullCarver
        from pipeline.volume import grid_from_volume

        self.cal = Calibration.from_dict(calibration)
        self.grid = grid_from_volume(np.asarray(bounds, dtype=np.float64), resolution)
        self.carver = HullCarver(self.cal, self.grid)
        self.backdrop, self.spine = backdrop, spine
        self.params: dict[str, Any] = {}

    def mask(self, name: str, image: np.ndarray | None) -> np.ndarray:
        from stage.keying import KeyingError, KeyParams, estimate_model, key_one

        cam = self.cal[name]
        everything = np.ones((cam.height, cam.width), bool)  # a camera without a mask carves nothing
        if image is None or image.shape[:2] != (cam.height, cam.width):
            return everything
        p = self.params.get(name)
        try:
            if p is None:
                p = self.params[name] = estimate_model(image[None], params=KeyParams(mode=self.backdrop[0],
                                                                                     backdrop_color=self.backdrop[1]))
            return key_one(image, p)[0]
        except (KeyingError, ValueError):
            return everything

    def update(self, index: int, images: dict) -> dict[str, Any]:
        t0 = time.perf_counter()
        masks = [self.mask(n, images.get(n)) for n in self.cal.names]
        occ = self.carver.carve(masks, tolerance=1).occupancy
        vox = _surface_voxels(occ)
        segments = _spine_segments(occ, self.grid) if self.spine and vox.size else []
        pts = self.grid.lo + (vox + 0.5) * self.grid.voxel
        return {"state": "ok", "set": int(index), "voxel": float(self.grid.voxel), "occupied": int(occ.sum()),
                "edges": volume_edges(occ),
                "points": np.round(pts, 1).tolist(), "segments": segments,
                "compute_ms": (time.perf_counter() - t0) * 1e3}


def _worker_main(conn, calibration: dict, bounds, resolution: int, backdrop: tuple[str, str], spine: bool) -> None:
    """The worker process: (index, {camera: image}) in, the preview's dict out; None ends it."""
    # a camera missing from a set carves nothing: the hull's "mask is all foreground" notes are expected
    logging.getLogger("pipeline.hull").setLevel(logging.ERROR)
    try:
        w = _Worker(calibration, bounds, resolution, backdrop, spine)
    except Exception as exc:  # said once, in the answer the page shows
        conn.send({"state": "unavailable", "message": f"{type(exc).__name__}: {exc}"})
        return
    conn.send({"state": "ready"})
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        try:
            conn.send(w.update(*msg))
        except Exception as exc:  # an empty or failed hull is shown as such; the worker goes on
            conn.send({"state": "empty", "set": int(msg[0]), "message": f"{type(exc).__name__}: {exc}"})


class Live3D:
    """The worker behind the live 3-D preview.

    Parameters
    ----------
    room : ControlRoom
    resolution : int
        Voxels along the volume's longest axis.
    rate_hz : float
        Updates a second it aims at.
    spine : bool
        Also grow the skeleton of the hull's surface.
    """

    def __init__(self, room, *, resolution: int = 64, rate_hz: float = 4.0, spine: bool = True) -> None:
        if resolution < 8 or resolution > 256:
            raise ValueError(f"resolution must be in [8, 256], got {resolution!r}")
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        self.room, self.resolution, self.period, self.spine = room, int(resolution), 1.0 / rate_hz, bool(spine)
        self._lock = threading.Lock()
        self._latest: dict[str, Any] = {"state": "starting", "updates": 0}
        self._times: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="live-3d", daemon=True)
        self.updates = 0
        self.compute_ms: list[float] = []  # of the last updates
        self.process = None

    def start(self) -> "Live3D":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def latest(self) -> dict[str, Any]:
        with self._lock:
            out = dict(self._latest)
            t = [x for x in self._times if x > time.monotonic() - 5.0]
        out["updates_per_s"] = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
        # how old what the view shows is: from its frame set's time (host clock) to now
        st = out.get("set_time_ns")
        out["age_s"] = None if st is None else max(0.0, (time.monotonic_ns() - int(st)) / 1e9)
        return out

    def _set(self, **kw: Any) -> None:
        with self._lock:
            self._latest = {**kw, "updates": self.updates}

    def _loop(self) -> None:
        """A worker on the room's calibration; started again on the newest one whenever the session
        makes or is given another (a board session's calibration job), until stopped."""
        while not self._stop.is_set():
            cal = self.room.calibration()
            if cal is None:
                self._set(state="unavailable", message="no calibration: run a board session and calibrate, or "
                          "start stage serve with --calibration CAL")
                self._stop.wait(1.0)
                continue
            version = self.room.calibration_version
            self._run_worker(cal, version)
            while self.room.calibration_version == version and not self._stop.wait(1.0):
                self.room.calibration()  # the worker ended on its own (said in the state): wait for another

    def _run_worker(self, cal, version: int) -> None:
        rig = self.room.session.rig
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_worker_main, name="live-3d", daemon=True,
                           args=(child, cal.to_dict(), rig.volume.bounds, self.resolution,
                                 (rig.backdrop.key_mode, rig.backdrop.color), self.spine))
        proc.start()
        self.process = proc
        try:
            self._serve(parent, proc, rig, version, [c for c in self.room.session.ids if c not in cal.names])
        finally:
            try:
                parent.send(None)
            except (OSError, ValueError):
                pass
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
            parent.close()

    def _answer(self, parent, proc) -> dict | None:
        while not self._stop.is_set():
            if parent.poll(0.1):
                return parent.recv()
            if not proc.is_alive():
                self._set(state="unavailable", message=f"the 3-D worker exited ({proc.exitcode})")
                return None
        return None

    def _serve(self, parent, proc, rig, version: int, uncalibrated: list[str]) -> None:
        """Sets to the worker and its answers to the page; ``uncalibrated``: the rig's cameras the calibration
        lacks (the hull is carved without them, and the page says so)."""
        ready = self._answer(parent, proc)
        if ready is None or ready.get("state") != "ready":
            if ready is not None:
                self._set(**ready, calibration=self.room.calibration_source)
            return
        bounds = [list(map(float, b)) for b in rig.volume.bounds]
        last = None
        while not self._stop.is_set():
            t0 = time.monotonic()
            self.room.calibration()  # a calibration the session made since: the worker starts again on it
            if self.room.calibration_version != version:
                return
            fs = self.room.session.latest_set()
            if fs is not None and fs.index != last:
                last = fs.index
                parent.send((fs.index, {n: f.image for n, f in fs.frames.items() if f is not None}))
                out = self._answer(parent, proc)
                if out is None:
                    return
                if out.get("state") == "ok":
                    self.compute_ms.append(float(out["compute_ms"]))
                    del self.compute_ms[:-100]
                    self.updates += 1
                    with self._lock:
                        self._times.append(time.monotonic())
                        del self._times[:-50]
                self._set(**out, bounds=bounds, calibration=self.room.calibration_source, uncalibrated=uncalibrated,
                          set_time_ns=int(fs.time_ns))
            self._stop.wait(max(0.0, self.period - (time.monotonic() - t0)))


def _spine_segments(occ: np.ndarray, grid) -> list:
    """Segments ``[[x0, y0, z0], [x1, y1, z1]]`` of the skeleton grown from the surface's first tip."""
    from pipeline.frame_skeleton import frame_skeleton
    from pipeline.surface import EmptySurfaceError, surface_from_occupancy

    try:
        mesh = surface_from_occupancy(occ, grid, taubin_iterations=2, face_budget=4000)
    except (EmptySurfaceError, ValueError):
        return []
    fsk = frame_skeleton(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    if not fsk.skeletons:
        return []
    sk = fsk.skeletons[0]
    nodes = np.asarray(sk.nodes)
    return [[np.round(nodes[i], 1).tolist(), np.round(nodes[p], 1).tolist()]
            for i, p in enumerate(np.asarray(sk.parent)) if p >= 0]
