"""Write a simulated take straight into a take file (no real-time capture).

``stage capture`` with ``driver = "fake"`` cameras exercises the real capture path
(threads, clocks, synchronization); tests and benchmarks that only need a take on
disk use :func:`record_take`, which stores every rendered frame as one complete
frame set with ideal timestamps, the clean background plate per camera
(``cameras/<cam>/plate``, used by the keyer) and the ground truth beside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fake_cameras.take import SimulatedTake, write_ground_truth

__all__ = ["record_take", "take_scene_frames"]


def record_take(
    take: SimulatedTake,
    path: str | Path,
    *,
    calibration=None,
    compression: str = "none",
    with_calibration: bool = True,
    overwrite: bool = True,
) -> Path:
    """Store a :class:`~fake_cameras.take.SimulatedTake` as a take file.

    Parameters
    ----------
    take : SimulatedTake
    path : path
        The ``.h5`` file to create; the ground truth goes to ``<stem>.gt.npz`` beside it.
    calibration : Calibration, optional
        Stored in the take (default: the simulator's true cameras).
    compression : {"none", "lz4", "gzip"}
    with_calibration : bool
        Store a calibration at all (False: a take that still needs ``stage calibrate``).
    overwrite : bool

    Returns
    -------
    Path
        The take file.
    """
    from fake_cameras.rigs import simulated_rig_dict
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter

    if not isinstance(take, SimulatedTake):
        raise ValueError(f"take must be a SimulatedTake, got {type(take).__name__}")
    path = Path(path)
    w, h = take.size
    names = take.calibration.names
    cal = (calibration or take.calibration) if with_calibration else None
    # the rig's [simulation] says what a fake camera films live; a mesh sequence is no live
    # subject, so its rig names the empty studio (the take's images hold the mesh)
    subject = "empty" if take.mesh_vertices is not None else take.subject
    rig = simulated_rig_dict(
        take.n_cameras, subject=subject, frames=take.n_frames, fps=take.fps, size=(w, h),
        depth=take.depth is not None, clock_offsets_ms=0.0, jitter_ms=0.0, name="simulated", volume=take.volume,
    )
    period = int(round(1e9 / take.fps))
    specs = [CameraSpec(n, w, h, depth=take.depth is not None) for n in names]
    plates = {f"cameras/{n}/plate": take.plate[c] for c, n in enumerate(names)}  # shot with the take
    with TakeWriter(path, specs, rig=rig, calibration=cal, compression=compression, fps=take.fps, overwrite=overwrite,
                    arrays=plates) as wr:
        for f in range(take.n_frames):
            t = f * period
            frames = {
                n: Frame(
                    take.images[f, c], n, f, t, t,
                    depth=None if take.depth is None else take.depth[f, c],
                )
                for c, n in enumerate(names)
            }
            wr.write_set(frames, time_ns=t)
    write_ground_truth(take, path)
    return path


def take_scene_frames(path: str | Path, n_scene_frames: int) -> np.ndarray:
    """Scene frame shown in each frame set of a take filmed by simulated cameras.

    A simulated camera's frame with sequence number ``q`` shows scene frame
    ``q mod F`` (:mod:`fake_cameras.device`: every camera starts at scene frame 0),
    so the stored sequence numbers say it exactly, also when frames were dropped.

    Parameters
    ----------
    path : path
        The take.
    n_scene_frames : int
        ``F``, the frames the simulated rig renders.

    Returns
    -------
    (S,) int ndarray
        Scene frame of each set (``SimulatedTake.select`` gives its ground truth in take order).
    """
    from stage.store import TakeReader

    if int(n_scene_frames) < 1:
        raise ValueError(f"n_scene_frames must be >= 1, got {n_scene_frames!r}")
    with TakeReader(path) as r:
        table = r.set_table()
        seq = [r.timestamps(c)["sequence"] for c in r.cameras]
    out = np.full(table.shape[0], -1, dtype=np.int64)
    for k, row in enumerate(table):
        ci = int(np.flatnonzero(row >= 0)[0])
        out[k] = int(seq[ci][row[ci]]) % int(n_scene_frames)
    return out
