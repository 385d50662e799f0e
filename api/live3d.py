"""The live 3-D preview: a coarse visual hull of the latest frame set and its spine.

A worker thread takes the session's latest frame set a few times a second, keys each
camera's image (the control room's backdrop keyers), carves a hull on a ``resolution``^3
grid over the rig's volume (:class:`pipeline.hull.HullCarver`: its lookup tables are built
once, a carve is then a few milliseconds; one camera is allowed to disagree) and keeps its
surface voxels; when the subject is articulated (its surface has tips,
:func:`pipeline.spine.frame_skeleton`), the skeleton grown from the first tip as segments.
The page draws what :meth:`Live3D.latest` returns. Capture never waits for it: the worker
only reads the latest frames the grabbers already published, and numpy does the carving
outside the interpreter lock.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

__all__ = ["Live3D"]

log = logging.getLogger(__name__)


def _surface_voxels(occ: np.ndarray) -> np.ndarray:
    """(N, 3) int indices of occupied voxels with an empty 6-neighbour."""
    pad = np.pad(occ, 1)
    inner = pad[1:-1, 1:-1, 1:-1]
    full = (pad[:-2, 1:-1, 1:-1] & pad[2:, 1:-1, 1:-1] & pad[1:-1, :-2, 1:-1] & pad[1:-1, 2:, 1:-1]
            & pad[1:-1, 1:-1, :-2] & pad[1:-1, 1:-1, 2:])
    return np.argwhere(inner & ~full)


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
        return out

    def _set(self, **kw: Any) -> None:
        with self._lock:
            self._latest = {**kw, "updates": self.updates}

    def _loop(self) -> None:
        from pipeline.hull import HullCarver
        from pipeline.volume import grid_from_volume

        cal = self.room.calibration()
        if cal is None:
            self._set(state="unavailable", message="no calibration: start stage serve with --calibration CAL")
            return
        grid = grid_from_volume(self.room.session.rig.volume, self.resolution)
        carver = HullCarver(cal, grid)
        last = None
        while not self._stop.is_set():
            t0 = time.monotonic()
            fs = self.room.session.latest_set()
            if fs is not None and fs.index != last:
                last = fs.index
                try:
                    self._update(fs, cal, grid, carver)
                except Exception as exc:  # an empty or failed hull is shown as such, the worker goes on
                    self._set(state="empty", message=f"{type(exc).__name__}: {exc}", set=int(fs.index))
            self._stop.wait(max(0.0, self.period - (time.monotonic() - t0)))

    def _update(self, fs, cal, grid, carver) -> None:
        t0 = time.perf_counter()
        masks = []
        for name in cal.names:
            f = fs.frames.get(name)
            m = None if f is None else self.room.keyers.mask(name, f.image)
            cam = cal[name]
            masks.append(m if m is not None else np.ones((cam.height, cam.width), bool))
        occ = carver.carve(masks, tolerance=1).occupancy
        vox = _surface_voxels(occ)
        segments: list = []
        if self.spine:
            segments = _spine_segments(occ, grid)
        pts = grid.lo + (vox + 0.5) * grid.voxel
        self.updates += 1
        with self._lock:
            self._times.append(time.monotonic())
            del self._times[:-50]
        self._set(state="ok", set=int(fs.index), voxel=float(grid.voxel), occupied=int(occ.sum()),
                  points=np.round(pts, 1).tolist(), segments=segments, compute_ms=(time.perf_counter() - t0) * 1e3,
                  bounds=[list(map(float, b)) for b in self.room.session.rig.volume.bounds])


def _spine_segments(occ: np.ndarray, grid) -> list:
    """Segments ``[[x0, y0, z0], [x1, y1, z1]]`` of the skeleton grown from the surface's first tip."""
    from pipeline.spine import frame_skeleton
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
