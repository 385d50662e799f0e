"""The processing grid: the subject's box over the whole take and the voxel the rig resolves there.

The box is :func:`pipeline.subject_box.find_subject_box` over every frame set's masks inside the
volume searched (the job's, the rig's capture volume, else the cameras' shared view); the voxel
edge is :data:`PIXELS_PER_VOXEL` times the median pixel footprint at the subject
(:func:`rig_resolution`), within :data:`MAX_VOXELS` and the carver's memory. The choice and why
go to ``OUT/grid.json`` and ``process.json``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from pipeline.process.params import ProcessError, ProcessParams

__all__ = ["MAX_VOXELS", "MIN_RESOLUTION", "PIXELS_PER_VOXEL", "blind_side_hint", "choose_grid", "rig_resolution",
           "search_volume"]

log = logging.getLogger("pipeline.process")

#: Default voxel edge in pixels at the subject (median footprint over the cameras).
PIXELS_PER_VOXEL = 2.0
#: Voxels in the processing grid at most (time: the carve and marching cubes grow with it).
MAX_VOXELS = 8_000_000
#: Voxels along the subject's longest side at least, whatever the cameras resolve.
MIN_RESOLUTION = 48


class _SetMasks:
    """The take's masks as a sequence of frame sets (:func:`pipeline.subject_box.find_subject_box`),
    each read when asked for: ``masks_of(k)`` gives the masks of set ``k`` and the cameras skipped."""

    def __init__(self, masks_of: Callable, n_sets: int) -> None:
        self._masks_of, self._n = masks_of, int(n_sets)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: int) -> list:
        return self._masks_of(int(k))[0]


def subject_grid(masks_of: Callable, calibration, n_sets: int, p: ProcessParams, volume_bounds: np.ndarray,
                  progress: Callable[[int, int], None] | None = None):
    """The subject's box over the whole take (:func:`pipeline.subject_box.find_subject_box`, every
    frame set carved coarse to fine inside ``volume_bounds``). ``masks_of(k)`` gives the masks of
    set ``k`` and the cameras skipped (:func:`pipeline.process.tasks.frame_masks`)."""
    from pipeline.subject_box import find_subject_box

    volume_bounds = np.asarray(volume_bounds, float).reshape(2, 3)
    return find_subject_box(_SetMasks(masks_of, n_sets), calibration, volume_bounds, tolerance=p.tolerance,
                            support_plane=p.support_plane, progress=progress)


def rig_resolution(calibration, box: np.ndarray, p: ProcessParams, centres: np.ndarray | None = None) -> tuple[int, dict]:
    """Voxels along the box's longest side, and why: ``--resolution`` when given, else from
    the pixel footprint at the subject (:data:`PIXELS_PER_VOXEL`) within the budgets. The
    footprint is the median over the frame sets of the median over the cameras that see the
    subject's centre there (``centres`` (S, 3), NaN where none; default the box's centre)."""
    from pipeline.hull import _memory_limit, hull_memory_bytes
    from pipeline.volume import grid_from_volume, pixel_footprint

    longest = float((box[1] - box[0]).max())
    if p.resolution is not None:
        return p.resolution, {"source": "resolution option", "resolution": p.resolution}
    pts = None if centres is None else np.asarray(centres, float).reshape(-1, 3)
    pts = (box[0] + box[1])[None] / 2 if pts is None or not np.isfinite(pts).all(axis=1).any() else pts[np.isfinite(pts).all(axis=1)]
    fp = pixel_footprint(calibration, pts)  # (C, S)
    seen = np.isfinite(fp)
    at = seen.any(axis=0)
    if not at.any():
        said = "no camera sees the centre of the subject's box; check the calibration or"
        raise ProcessError(f"{said} pass --resolution", job_message=f"{said} give parameters.resolution")
    footprint = float(np.median(np.nanmedian(fp[:, at], axis=0)))
    n_seeing = int(np.median(seen[:, at].sum(axis=0)))
    wanted = int(np.ceil(longest / (PIXELS_PER_VOXEL * footprint)))
    res, limit = max(wanted, MIN_RESOLUTION), "pixel footprint"
    if res == MIN_RESOLUTION and wanted < MIN_RESOLUTION:
        limit = f"at least {MIN_RESOLUTION} voxels along the subject"
    ext = box[1] - box[0]
    while res > MIN_RESOLUTION and (
        np.prod(np.ceil(ext / (longest / res))) > MAX_VOXELS
        or hull_memory_bytes(grid_from_volume(box, res), calibration) > _memory_limit()
    ):
        res, limit = int(res * 0.95), f"budget of {MAX_VOXELS:,} voxels and the carver's memory"
    why = {
        "source": "rig",
        "resolution": res,
        "pixel_footprint": footprint,
        "cameras_seeing_subject": n_seeing,
        "pixels_per_voxel": PIXELS_PER_VOXEL,
        "limited_by": limit,
    }
    return res, why



def search_volume(params: ProcessParams, rig: dict, calibration) -> tuple[np.ndarray, str]:
    """Where to look for the subject, ``(6,)`` ``[lo, hi]``: the job's volume, the rig's, else the
    cameras' shared view; and which it is (for the box's ``why``)."""
    from pipeline.volume import volume_from_cameras

    if params.volume is not None:
        return np.asarray(params.volume, float), "the volume option"
    if rig.get("volume"):
        c = np.asarray(rig["volume"]["center"], float)
        s = np.asarray(rig["volume"]["size"], float)
        return np.r_[c - s / 2, c + s / 2], "the rig's capture volume"
    return np.asarray(volume_from_cameras(calibration), float).reshape(-1), "the cameras' shared view"


def _box_choice(sb, volume: np.ndarray, source: str) -> dict:
    """The subject's box and why, for ``process.json`` and the report."""
    st = sb.stats
    why = (f"the pieces of the silhouettes' hull found by at least {sb.min_views} cameras (and by all but "
           f"{sb.view_slack} of those that find the best-found part) and explained by the "
           f"silhouettes of at least 2, in {st['with_subject']} of {st['frame_sets']} frame sets, carved coarse to "
           f"fine in {' / '.join(f'{v:.3g}' for v in sb.voxels)} cubes inside {source}, grown by {sb.margin:.3g}")
    return {**sb.to_dict(), "search_volume": np.asarray(volume, float).reshape(2, 3).tolist(), "searched_in": source,
            "why": why}



def blind_side_hint(calibration, grid) -> str:
    """A warning when every camera looks down on the subject (imported footage, no support plane); it names the
    support plane as ``stage process`` and a job both call it (``--support-plane``, ``parameters.support_plane``)."""
    from pipeline.volume import view_elevation

    centre = (grid.lo + grid.hi) / 2
    up, elev = view_elevation(calibration, centre)
    if elev < 5.0:
        return ""
    return (
        f"all {len(calibration)} cameras sit at least {elev:.1f} deg above the subject (seen from direction "
        f"{up[0]:.2f} {up[1]:.2f} {up[2]:.2f}): no silhouette can carve under its base, so the hull reaches about "
        f"{np.tan(np.radians(elev)):.2f} x the base's half-width below it. If the subject stands on a support, "
        f"give its plane, the support plane a b c D: {' '.join(f'{x:.3f}' for x in np.round(up, 3) + 0.0)} D (kept where "
        "a*x + b*y + c*z + D >= 0)"
    )


def choose_grid(masks_of: Callable, calibration, n_sets: int, p: ProcessParams, rig: dict,
                progress: Callable[[int, int], None] | None = None):
    """The grid of the surfaces fitted to the subject: its box over the take (``masks_of(k)``
    gives the masks of frame set ``k`` and the cameras skipped) and the rig's voxel there.

    Returns
    -------
    grid : pipeline.volume.Grid
    choice : dict
        How it was chosen (resolution and why, voxel, shape, the box and why), for ``grid.json``.
    hint : str
        A warning when every camera looks down on the subject and nothing bounds it below ("": none).
    """
    from pipeline.volume import grid_from_volume

    volume, source = search_volume(p, rig, calibration)
    sb = subject_grid(masks_of, calibration, n_sets, p, volume, progress=progress)
    res, why = rig_resolution(calibration, sb.bounds, p, sb.centres)
    grid = grid_from_volume(sb.bounds, res)
    choice = {**why, "voxel": grid.voxel, "shape": list(grid.shape), "box": _box_choice(sb, volume, source)}
    log.info("subject box %s: %s", " x ".join(f"{x:.4g}" for x in sb.bounds[1] - sb.bounds[0]), choice["box"]["why"])
    log.info("processing grid %s (%s)", grid, why["limited_by"] if "limited_by" in why else why["source"])
    hint = ""
    if p.support_plane is None and p.volume is None and not rig.get("volume"):
        hint = blind_side_hint(calibration, grid)
    return grid, choice, hint
