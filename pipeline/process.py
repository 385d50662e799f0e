"""Process a take: keying -> visual hull and surface per frame -> spines -> ``spine.json``.

This is the worker pipeline's driver: a list of named steps (:data:`STEPS`, extended
with :func:`register_step`) run in order on one :class:`RunContext`. Per-frame work (surfaces, per-frame skeletons)
fans out over a :class:`concurrent.futures.Executor` (a local process pool by
default, a Dask ``Client.get_executor()`` on a cluster); the correspondence of tips
over time is the reduce step. Workers open the take by path themselves, so a Dask
cluster needs a shared filesystem.

Every per-frame result is persisted in the output directory as soon as it is
finished (meshes as PLY, skeletons as binary ``.npz``, written atomically by a
background thread of the task while it computes the next frame), and a second call
on the same output directory resumes from the unfinished frames: an interrupted
job re-run gives the same ``spine.json`` as an uninterrupted one.

Frames are read once: a keying task reads its camera's frames, and the masks it
returns (bit-packed) stay in this process and travel with the surface tasks of the
same run, which then never open the take (a resumed run, or a take whose masks
exceed :data:`_KEEP_MASKS_BYTES`, reads them from the take).

Output directory layout::

    OUT/process.json              parameters and the take it came from
    OUT/meshes/frame_000000.ply   one surface per frame set (missing: empty frame)
    OUT/frames/frame_000000.json  per-frame surface quality (or why it is empty)
    OUT/skeletons/frame_000000.npz   per-frame tips and skeletons (numpy arrays, for resuming)
    OUT/spine.json                the take's spine (capture-stage/spine@1)
    OUT/consistency.json          per camera and frame set, the IoU of its mask and the projected surface
    OUT/report.json               summary: steps, timings, per-frame quality, tip counts, how K was chosen
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from calib.fileio import atomic_write, json_default
from stage.store.space import check_free_space, raise_disk_full

__all__ = [
    "STEPS", "DEFAULT_STEPS", "ProcessError", "ProcessParams", "ProcessResult", "RunContext", "Step", "TrackParams",
    "process_take",
    "register_step",
]

log = logging.getLogger("pipeline.process")

#: Default voxel edge in pixels at the subject (median footprint over the cameras).
PIXELS_PER_VOXEL = 2.0
#: Voxels in the processing grid at most (time: the carve and marching cubes grow with it).
MAX_VOXELS = 8_000_000
#: Voxels along the subject's longest side at least, whatever the cameras resolve.
MIN_RESOLUTION = 48
#: Masks stored per update of the take's derived data (bytes, unpacked).
_STORE_BATCH_BYTES = 512 << 20
#: Keyed masks kept in memory (bit-packed) for the surface tasks, at most (else they read the take).
_KEEP_MASKS_BYTES = 1 << 30



class ProcessError(ValueError):
    """A take that cannot be processed; the message says why and what to do."""


class TrackParams(BaseModel):
    """Options of the ``track`` step, as ``stage track RESULTS_DIR`` takes them (docs/tracking.md).

    Parameters
    ----------
    carve : int
        Rounds of surfaces carved across time with the tracked motion, each tracked again
        (``--carve``; 0: the surfaces of ``stage process``).
    carve_margin : float or None
        Pixels every silhouette grows by in the carving (``--carve-margin``; default per camera
        from its calibration, :func:`pipeline.carve.carve_results`).
    shape_memory : bool
        Keep the previous frame's shape in the rigid prior (``--shape-memory``).
    colour : bool
        Feature tracks from every camera's colour images (``--colour``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    carve: Annotated[int, Field(ge=0, le=5)] = 0
    carve_margin: Annotated[float, Field(ge=0, le=10)] | None = None
    shape_memory: bool = False
    colour: bool = False


class ProcessParams(BaseModel):
    """Options of :func:`process_take` (defaults scale with the subject and the rig).

    Attributes
    ----------
    key_mode : {"chroma", "luma", "plate"} or None
        Keying mode; default: the rig's backdrop, else chosen from the footage (a backdrop
        colour covering a large share of the views: chroma with layers; none: a plate from
        the take; :func:`stage.keying.take.choose_key_mode`). The choice and why are in
        ``process.json`` (``key``).
    key_layers : tuple of {"volume", "graphcut"} or None
        Keying layers (docs/keying.md): ``volume``, pixels whose rays miss the volume
        searched for the subject are background; ``graphcut``, the ``refine`` step cuts
        every camera's silhouettes with colour models seeded by a first hull. Default: the
        rig's, else the footage's choice.
    rekey : bool
        Key again even when the take already holds masks.
    resolution : int or None
        Voxels along the longest side of the subject's bounding box (the box is
        found by a coarse carve of the whole capture volume). Default: from the rig,
        a voxel of :data:`PIXELS_PER_VOXEL` times the median pixel footprint at the
        subject over the cameras that see it (so a limb 4 pixels wide in most views is
        2 voxels across), within :data:`MAX_VOXELS` and the memory the carver may use.
    volume : (6,) floats or None
        ``[xmin, ymin, zmin, xmax, ymax, zmax]`` to search for the subject; default the
        rig's capture volume, else derived from the cameras.
    tolerance : int
        Cameras allowed to disagree before a voxel is carved.
    silhouette_margin : int
        Pixels every silhouette grows by before carving (a conservative hull): with
        calibration and masks each a fraction of a pixel off, the intersection of many
        exact silhouettes shaves thin parts that every camera only just sees.
    support_plane : (4,) floats or None
        ``(a, b, c, d)`` of the plane the subject stands on (kept where
        ``a x + b y + c z + d >= 0``, world units). Cameras that all look down on the
        subject cannot carve the cone under its base; the plane removes it. Our own
        rigs need none (their capture volume starts at the floor); give it for imported
        footage, e.g. a turntable or pedestal at a known height.
    smooth_iterations : int
        Taubin smoothing iterations of the surface.
    face_budget : int or None
        Decimate surfaces to at most this many faces before skeletons (their cost grows
        with the faces; the tips and limbs do not need more). ``None``: never.
    chunk : int
        Frames per task sent to the executor.
    depth : {"auto", "off"}
        ``auto``: when every camera of the take delivers depth (RGB-D), fuse the depth
        frames into a truncated signed distance volume intersected with the visual hull
        and take its zero level set; ``off``: the visual hull alone.
    photo_refine : bool
        Move every hull surface's vertices along their normals to where the cameras'
        colours agree (:func:`pipeline.photo_refine.refine_surface`): the hull's excess in
        concavities that two cameras see is carved. Surfaces from fused depth are not refined.
    spine : dict
        Options of :class:`pipeline.spine.SpineParams`.
    track : TrackParams
        Options of the ``track`` step. They change the tracking alone: a run with other ones
        tracks again (``tracked/track.json`` says what changed) and keeps every other result.
    skip_damaged : bool
        A take with damaged frames (a chunk failing its checksum, :func:`stage.store.verify.verify_take`)
        is processed without the frame sets that hold them: no damaged frame is read, those sets
        get no surface (``frames/`` records them as ``damaged``) and ``process.json``, the report and
        the log list them. Off: such a take stops before any work, naming the damage. Damage outside
        the frames (metadata, the set table) always stops.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    key_mode: Literal["chroma", "luma", "plate"] | None = None
    key_layers: tuple[Literal["volume", "graphcut"], ...] | None = None
    rekey: bool = False
    resolution: Annotated[int, Field(ge=16, le=512)] | None = None
    volume: tuple[float, float, float, float, float, float] | None = None
    tolerance: Annotated[int, Field(ge=0)] = 0
    silhouette_margin: Annotated[int, Field(ge=0, le=10)] = 1
    support_plane: tuple[float, float, float, float] | None = None
    smooth_iterations: Annotated[int, Field(ge=0, le=200)] = 10
    face_budget: Annotated[int, Field(ge=100)] | None = 16000
    chunk: Annotated[int, Field(ge=1)] = 4
    depth: Literal["auto", "off"] = "auto"
    photo_refine: bool = False
    spine: dict = Field(default_factory=dict)
    track: TrackParams = Field(default_factory=TrackParams)
    skip_damaged: bool = False

    @field_validator("volume")
    @classmethod
    def _check_volume(cls, v: tuple[float, float, float, float, float, float] | None):
        if v is None:
            return v
        from pipeline.volume import check_bounds

        lo_hi = check_bounds(np.reshape(np.asarray(v, float), (2, 3)), "volume")  # before any step runs
        return tuple(float(x) for x in lo_hi.reshape(-1))

    @field_validator("support_plane")
    @classmethod
    def _unit_plane(cls, v: tuple[float, float, float, float] | None) -> tuple[float, float, float, float] | None:
        if v is None:
            return v
        from pipeline.volume import check_plane

        a, b, c, d = check_plane(v).tolist()  # ValueError (a zero normal) becomes a ValidationError
        return (a, b, c, d)


@dataclass
class ProcessResult:
    out: Path
    steps: tuple[str, ...]
    frames: int
    empty_frames: list[int] = field(default_factory=list)
    spine_path: Path | None = None
    report: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- files and caches


def _frame_name(k: int) -> str:
    return f"frame_{k:06d}"


def _calibration_key(calib_dict: dict, grid_dict: dict) -> str:
    blob = json.dumps([calib_dict, grid_dict], sort_keys=True).encode()
    return hashlib.sha1(blob).hexdigest()


_CARVERS: dict[str, object] = {}
_FUSERS: dict[str, object] = {}


def _fuser(calib_dict: dict, grid_dict: dict):
    """One :class:`pipeline.tsdf.TSDFFusion` per (calibration, grid) and worker process."""
    from calib.calibration import Calibration
    from pipeline.tsdf import TSDFFusion
    from pipeline.volume import Grid

    key = _calibration_key(calib_dict, grid_dict)
    if key not in _FUSERS:
        _FUSERS.clear()
        cal = Calibration.from_dict(calib_dict)
        scale = {"mm": 1.0, "m": 1e-3, "cm": 0.1}.get(cal.units, 1.0)  # depth images are uint16 mm
        _FUSERS[key] = TSDFFusion(cal, Grid.from_dict(grid_dict), depth_scale=scale)
    return _FUSERS[key]


def _frame_depths(reader, cameras: Sequence[str], k: int) -> np.ndarray:
    """(C, H, W) uint16 depth of frame set ``k``; 0 (no measurement) for a missing camera."""
    rows = reader.set_rows(k)
    out = []
    for cam in cameras:
        w, h = reader.image_size(cam)
        d = reader.depth(cam, rows[cam]) if rows[cam] >= 0 else None
        out.append(np.zeros((h, w), np.uint16) if d is None else d)
    return np.stack(out)


def _carver(calib_dict: dict, grid_dict: dict):
    """One :class:`pipeline.hull.HullCarver` per (calibration, grid) and worker process."""
    from calib.calibration import Calibration
    from pipeline.hull import HullCarver
    from pipeline.volume import Grid

    key = _calibration_key(calib_dict, grid_dict)
    if key not in _CARVERS:
        _CARVERS.clear()  # one grid at a time keeps worker memory bounded
        _CARVERS[key] = HullCarver(Calibration.from_dict(calib_dict), Grid.from_dict(grid_dict))
    return _CARVERS[key]


def _mask_validity(reader, cameras: Sequence[str]) -> dict[str, np.ndarray | None]:
    """Per camera, the keyer's per-row validity flags (None when the take has none)."""
    return {
        cam: reader.read_array(f"cameras/{cam}", "mask_valid")[0].astype(bool)
        if reader.has_array(f"cameras/{cam}", "mask_valid")
        else None
        for cam in cameras
    }


def _frame_masks(reader, cameras: Sequence[str], k: int, validity: dict) -> tuple[list, list[str]]:
    """Masks of frame set ``k``, one (H, W) bool array per camera; ``None`` for a camera
    missing in the set or whose mask the keyer marked invalid (it neither carves nor counts
    as a view). ``validity`` is :func:`_mask_validity` of the same reader."""
    rows = reader.set_rows(k)
    masks = []
    skipped = []
    for cam in cameras:
        r = rows[cam]
        valid = validity[cam]
        ok = r >= 0 and (valid is None or r >= valid.shape[0] or valid[r])
        m = reader.mask(cam, r) if ok else None
        if m is None:
            skipped.append(cam)
        masks.append(m)
    return masks, skipped


# ----------------------------------------------------------------------------- per-frame tasks


def key_task(take: str, cameras: Sequence[str], base: dict, workers: int, volume=None,
             skip: dict[str, list[int]] | None = None) -> list[dict]:
    """Key some cameras of the take (in a worker), the take opened once; their masks come
    back bit-packed for the parent to store (one writer per take file). ``skip``: per camera,
    damaged rows never read (their masks empty and invalid)."""
    import cv2

    from stage.keying.params import KeyParams
    from stage.keying.take import key_camera
    from stage.store import TakeReader

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # parallelism comes from the workers (threads or processes), not OpenCV's pool
    out = []
    try:
        with TakeReader(take) as reader:
            for camera in cameras:
                key = key_camera(reader, camera, base=KeyParams(**base), workers=workers, volume=volume,
                                 skip=(skip or {}).get(camera, ()))
                if key is None:
                    out.append({"camera": camera, "key": None})
                    continue
                shape = key.masks.shape
                key.masks = np.packbits(key.masks, axis=-1)
                out.append({"camera": camera, "key": key, "shape": shape})
    finally:
        cv2.setNumThreads(threads)
    return out


def _camera_groups(cameras: Sequence[str], executor) -> list[list[str]]:
    """Cameras per key task: two tasks per worker (each opens the take once; the last ones
    still key while this process stores the others' masks); one camera a task in this process
    (progress and cancellation are seen between tasks)."""
    if executor is None:
        return [[c] for c in cameras]
    n = min(len(cameras), 2 * _pool_size(executor))
    return [list(cameras[i::n]) for i in range(n)]


def _skeleton_record(k: int, mesh, params, *, bodies: int | None = None) -> dict:
    """Per-frame tips and skeletons (Brostow et al. 2004, 4.1) of one frame's surface
    (``None``: an empty frame): ``{"index", "status", "skeleton"}`` (a :class:`FrameSkeleton`,
    ``None`` unless ``ok``) or ``reason``. The mesh is taken as
    :func:`pipeline.meshio.load_mesh` reads it back (its largest connected part); with
    ``bodies == 1`` (the surface's quality counted its pieces) it is that part already."""
    from pipeline.geodesic import largest_component
    from pipeline.spine import frame_skeleton

    if mesh is None:
        return {"index": int(k), "status": "empty", "skeleton": None}
    v, f = np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int64)
    if bodies != 1:
        v2, f2, _ = largest_component(v, f, warn=False)
        if len(f2) != len(f):
            v, f = v2, f2
    try:
        return {"index": int(k), "status": "ok", "skeleton": frame_skeleton(v, f, params=params)}
    except ValueError as exc:
        log.warning("frame set %d: no skeleton: %s", k, exc)
        return {"index": int(k), "status": "failed", "reason": str(exc), "skeleton": None}


_TIP_FIELDS = ("seed", "nodes", "parent", "cost", "frame", "count", "level", "tip_nodes")
_ALT_FIELDS = ("tip", "point", "vertex", "limb_points", "rings", "alt_rings")  # pipeline.spine.Alternate
# format of a ``skeletons/`` record; 2: with the alternates. A record of another format (or none:
# written before alternates existed, which reads as "no alternates") is recomputed on a resume.
_SKELETON_FORMAT = 2


def _skeleton_bytes(rec: dict) -> bytes:
    """A ``skeletons/`` record as an uncompressed ``.npz`` (binary arrays: exact, and a
    fraction of the time JSON takes for the ~10^4 floats of a frame's skeletons)."""
    import io

    arrays: dict[str, np.ndarray] = {"format": np.int64(_SKELETON_FORMAT), "index": np.int64(rec["index"]),
                                     "status": np.str_(rec["status"]), "reason": np.str_(rec.get("reason", ""))}
    sk = rec.get("skeleton")
    if sk is not None:
        arrays.update(tips=sk.tips, tip_vertices=sk.tip_vertices, size=np.float64(sk.size), n_faces=np.int64(sk.n_faces),
                      limb_points=sk.limb_points, n_skeletons=np.int64(len(sk.skeletons)))
        for i, tip in enumerate(sk.skeletons):
            arrays.update({f"skeleton{i}.{name}": np.asarray(getattr(tip, name)) for name in _TIP_FIELDS})
        arrays["n_alternates"] = np.int64(len(sk.alternates))
        for j, alt in enumerate(sk.alternates):
            arrays.update({f"alternate{j}.{name}": np.asarray(getattr(alt, name)) for name in _ALT_FIELDS})
            arrays.update({f"alternate{j}.skeleton.{name}": np.asarray(getattr(alt.skeleton, name)) for name in _TIP_FIELDS})
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _load_skeleton(path: Path) -> dict:
    """A record written by :func:`_skeleton_bytes`."""
    from pipeline.spine import FrameSkeleton

    with np.load(path, allow_pickle=False) as z:
        rec = {"index": int(z["index"]), "status": str(z["status"]), "skeleton": None}
        if str(z["reason"]):
            rec["reason"] = str(z["reason"])
        if "tips" in z:
            d = {name: z[name] for name in ("tips", "tip_vertices", "size", "n_faces", "limb_points")}
            d["skeletons"] = [{name: z[f"skeleton{i}.{name}"] for name in _TIP_FIELDS} for i in range(int(z["n_skeletons"]))]
            n_alt = int(z["n_alternates"]) if "n_alternates" in z else 0  # an older record (see _stale_skeletons)
            d["alternates"] = [{**{name: z[f"alternate{j}.{name}"] for name in _ALT_FIELDS},
                                "skeleton": {name: z[f"alternate{j}.skeleton.{name}"] for name in _TIP_FIELDS}}
                               for j in range(n_alt)]
            rec["skeleton"] = FrameSkeleton.from_dict(d)
    return rec


def _stale_skeletons(out: Path, n: int) -> list[int]:
    """Remove the ``skeletons/`` records of the first ``n`` frame sets written in another format
    than :data:`_SKELETON_FORMAT` (or unreadable), so the skeleton step recomputes them; their
    frame indices. Reads only each archive's directory and one scalar."""
    import zipfile

    stale = []
    for k in range(n):
        path = out / "skeletons" / f"{_frame_name(k)}.npz"
        if not path.exists():
            continue
        try:
            with np.load(path, allow_pickle=False) as z:
                current = "format" in z and int(z["format"]) == _SKELETON_FORMAT
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):  # EOFError: an empty or cut file
            current = False
        if not current:
            path.unlink()
            stale.append(k)
    if stale:
        log.info("%d skeleton records of an older format are recomputed", len(stale))
    return stale


class _Writer:
    """Files of a task written in order by one background thread: the disk's waits (fsync)
    overlap the next frame's computation; :meth:`close` waits and re-raises a failed write."""

    def __init__(self) -> None:
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="results-writer")
        self._pending: list[cf.Future] = []

    def write(self, path: Path, data: bytes | str) -> None:
        self._pending.append(self._pool.submit(atomic_write, path, data))

    def close(self) -> None:
        try:
            for fut in self._pending:
                fut.result()
        finally:
            self._pool.shutdown(wait=True)


def _unpack_masks(packed: list, widths: Sequence[int]) -> list:
    """The masks of one frame set shipped with a task: bit-packed rows -> (H, W) bool (or None)."""
    return [None if p is None else np.unpackbits(p, axis=-1, count=w).view(bool) for p, w in zip(packed, widths)]


def _surface_of(carver, masks, p: ProcessParams, depth=None, images=None):
    """The frame set's surface and its source: the hull's, or with ``depth`` (a fuser and the
    set's depth images) the depth fused inside the hull; with ``images`` (the set's colour
    images, None for a missing camera) the hull's surface refined where the colours agree."""
    from pipeline.surface import surface_from_occupancy

    hull = _carve(carver, masks, p)
    if depth is not None:
        fuser, depth_images = depth
        fused = fuser.fuse(depth_images, hull=hull.occupancy)
        return fused.surface(taubin_iterations=p.smooth_iterations, face_budget=p.face_budget), "depth+hull"
    mesh = surface_from_occupancy(hull.occupancy, carver.grid, taubin_iterations=p.smooth_iterations,
                                  face_budget=p.face_budget)
    if images is None:
        return mesh, "hull"
    return _photo_refined(mesh, carver, masks, images), "hull+photo"


def _photo_refined(mesh, carver, masks, images):
    """The hull's surface refined by :func:`pipeline.photo_refine.refine_surface` over the
    cameras with both a mask and an image in this set (unchanged with fewer than two)."""
    from pipeline.photo_refine import refine_surface

    use = [i for i, (m, im) in enumerate(zip(masks, images)) if m is not None and im is not None]
    if len(use) < 2:
        return mesh
    cams = list(carver.calibration)
    mesh.vertices = refine_surface(mesh.vertices, mesh.faces, [images[i] for i in use], [masks[i] for i in use],
                                   [cams[i] for i in use], voxel=carver.grid.voxel)
    return mesh


def _frame_images(reader, cameras: Sequence[str], k: int) -> list:
    """Colour images of frame set ``k``, one (H, W, 3) uint8 BGR per camera (None: missing)."""
    rows = reader.set_rows(k)
    return [reader.frame(cam, rows[cam]) if rows[cam] >= 0 else None for cam in cameras]


def surface_task(
    take: str,
    frames: Sequence[int],
    calib_dict: dict,
    grid_dict: dict,
    params: dict,
    out: str,
    spine_params: dict | None = None,
    masks: dict | None = None,
    use_depth: bool | None = None,
) -> list[dict]:
    """Visual hull + surface of some frame sets; writes ``meshes/`` and ``frames/`` (and,
    with ``spine_params``, the frames' skeletons to ``skeletons/`` from the mesh in memory).

    ``masks`` (optional): the sets' masks as keyed in this run, ``{"widths": [W per camera],
    "sets": {k: [bit-packed (H, W/8) rows or None per camera]}}``; without it they are read
    from the take. ``use_depth``: fuse depth (default: when ``params.depth`` is ``auto`` and
    every camera has depth); with masks given, no depth and no ``params.photo_refine``, the
    take is not opened at all.
    Top level (picklable) so it runs in a process pool or on a Dask worker.
    """
    from contextlib import nullcontext

    from pipeline.hull import EmptyHullError
    from pipeline.results import ResultsStore, ply_bytes
    from pipeline.spine import SpineParams
    from pipeline.surface import EmptySurfaceError, surface_quality
    from stage.store import TakeReader

    p = ProcessParams(**params)
    sp = SpineParams(**spine_params) if spine_params is not None else None
    out_dir = Path(out)
    store = ResultsStore(out_dir)
    carver = _carver(calib_dict, grid_dict)
    cameras = [c["name"] for c in calib_dict["cameras"]]
    results = []
    writer = _Writer()
    try:
        needs_take = masks is None or use_depth is not False or p.photo_refine
        with TakeReader(take) if needs_take else nullcontext() as reader:
            if use_depth is None:
                use_depth = _uses_depth(p, all_depth=_all_depth(reader, cameras))
            validity = _mask_validity(reader, cameras) if masks is None else None
            for k in frames:
                t0 = time.perf_counter()
                if masks is None:
                    ms, skipped = _frame_masks(reader, cameras, k, validity)
                else:
                    ms = _unpack_masks(masks["sets"][k], masks["widths"])
                    skipped = [c for c, m in zip(cameras, ms) if m is None]
                info: dict = {"index": int(k), "skipped_cameras": skipped}
                mesh = quality = None
                try:
                    if len(skipped) == len(cameras):
                        raise EmptyHullError("no camera has a valid mask in this frame set")
                    depth = (_fuser(calib_dict, grid_dict), _frame_depths(reader, cameras, k)) if use_depth else None
                    images = _frame_images(reader, cameras, k) if p.photo_refine and not use_depth else None
                    mesh, info["source"] = _surface_of(carver, ms, p, depth, images)
                    quality = surface_quality(mesh).to_dict()
                    info["consistency"] = _consistency(mesh, ms, carver.calibration, p.silhouette_margin)
                    writer.write(store.mesh_path(k), ply_bytes(mesh.vertices, mesh.faces))
                    info.update(status="ok", quality=quality)
                except (EmptyHullError, EmptySurfaceError) as exc:
                    mesh = None
                    info.update(status="empty", reason=str(exc))
                    log.warning("frame set %d: %s", k, exc)
                info["seconds"] = time.perf_counter() - t0
                res = dict(info)
                if sp is not None:
                    rec = _skeleton_record(k, None if mesh is None else (mesh.vertices, mesh.faces), sp,
                                           bodies=None if quality is None else quality["bodies"])
                    writer.write(out_dir / "skeletons" / f"{_frame_name(k)}.npz", _skeleton_bytes(rec))
                    res["skeleton"] = rec["skeleton"]  # travels back: the spine step need not read it again
                # written last: a frame with its record has its mesh (and skeletons) on disk
                writer.write(out_dir / "frames" / f"{_frame_name(k)}.json", json.dumps(info))
                results.append(res)
    finally:
        writer.close()
    return results


def _consistency(mesh, masks: list, calibration, margin: int) -> dict[str, float | None]:
    """Per camera, the IoU of its mask (grown by the carving's margin) and the projection of the
    frame's surface (None: no mask)."""
    from pipeline.consistency import silhouette_consistency

    iou = silhouette_consistency(mesh.vertices, mesh.faces, masks, calibration, margin=margin)
    return {cam.name: (round(float(x), 4) if np.isfinite(x) else None) for cam, x in zip(calibration, iou)}


def _all_depth(reader, cameras: Sequence[str]) -> bool:
    """Every camera of the take delivers depth."""
    return all(reader.camera_info(c).get("has_depth") for c in cameras)


def _uses_depth(p: ProcessParams, *, all_depth: bool) -> bool:
    """Depth is fused when the job allows it and every camera of the take delivers depth."""
    return p.depth == "auto" and all_depth


def skeleton_task(out: str, frames: Sequence[int], spine_params: dict) -> list[dict]:
    """Per-frame tips and skeletons of some frames' stored meshes -> ``skeletons/``."""
    from pipeline.meshio import load_mesh
    from pipeline.results import ResultsStore
    from pipeline.spine import SpineParams

    params = SpineParams(**spine_params)
    out_dir = Path(out)
    store = ResultsStore(out_dir)
    done = []
    for k in frames:
        mesh_path = store.mesh_path(k)
        rec = _skeleton_record(k, load_mesh(mesh_path, largest=False) if mesh_path.exists() else None, params)
        atomic_write(out_dir / "skeletons" / f"{_frame_name(k)}.npz", _skeleton_bytes(rec))
        done.append({"index": int(k), "status": rec["status"], "skeleton": rec["skeleton"]})
    return done


def warm_task() -> int:
    """Import what the per-frame tasks need (run once per worker while the parent reads the take)."""
    import pipeline.hull
    import pipeline.spine
    import pipeline.surface  # noqa: F401
    import stage.keying.take  # noqa: F401

    return os.getpid()


# ----------------------------------------------------------------------------- driver


def _chunks(items: Sequence[int], n: int) -> list[list[int]]:
    return [list(items[i : i + n]) for i in range(0, len(items), n)]


def _carve(carver, masks, p: ProcessParams):
    """One frame's hull with the job's carving options (the subject grid and the surfaces alike)."""
    return carver.carve(masks, tolerance=p.tolerance, support_plane=p.support_plane, margin=p.silhouette_margin)


class _SetMasks:
    """The take's masks as a sequence of frame sets (:func:`pipeline.subject_box.find_subject_box`),
    each read when asked for: ``masks_of(k)`` gives the masks of set ``k`` and the cameras skipped."""

    def __init__(self, masks_of: Callable, n_sets: int) -> None:
        self._masks_of, self._n = masks_of, int(n_sets)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: int) -> list:
        return self._masks_of(int(k))[0]


def _subject_grid(masks_of: Callable, calibration, n_sets: int, p: ProcessParams, volume_bounds: np.ndarray,
                  progress: Callable[[int, int], None] | None = None):
    """The subject's box over the whole take (:func:`pipeline.subject_box.find_subject_box`, every
    frame set carved coarse to fine inside ``volume_bounds``). ``masks_of(k)`` gives the masks of
    set ``k`` and the cameras skipped (:func:`_frame_masks`)."""
    from pipeline.subject_box import find_subject_box

    volume_bounds = np.asarray(volume_bounds, float).reshape(2, 3)
    return find_subject_box(_SetMasks(masks_of, n_sets), calibration, volume_bounds, tolerance=p.tolerance,
                            support_plane=p.support_plane, progress=progress)


def _rig_resolution(calibration, box: np.ndarray, p: ProcessParams, centres: np.ndarray | None = None) -> tuple[int, dict]:
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
        raise ProcessError("no camera sees the centre of the subject's box; check the calibration or pass --resolution")
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


# ----------------------------------------------------------------------------- steps


@dataclass
class RunContext:
    """What the steps of one :func:`process_take` call share: the take's facts, the job's
    options, the runner's hooks, and what earlier steps left for later ones."""

    take: Path
    out: Path
    params: ProcessParams
    executor: cf.Executor | None
    progress: Callable[[str, int, int], None] | None
    cancel: threading.Event | None
    calibration: object
    cameras: list[str]
    n_sets: int
    fps: float
    rig: dict
    need_key: bool
    all_depth: bool = False  # every camera records depth
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    spine_path: Path | None = None
    tip_counts: list[int | None] = field(default_factory=list)
    grid_choice: dict = field(default_factory=dict)
    steps: tuple[str, ...] = ()
    skeletons: dict[int, object] = field(default_factory=dict)  # frame -> FrameSkeleton (None: none), as computed
    keyed: dict | None = field(default_factory=dict)  # camera -> (bit-packed masks, width, valid) keyed in this run
    set_table: np.ndarray | None = None  # (S, C) frame row of every camera in every set
    limb_count: dict = field(default_factory=dict)  # the spine's K and the rule that chose it
    key_choice: dict = field(default_factory=dict)  # the keying mode and layers of this run, and why
    consistency: dict = field(default_factory=dict)  # per camera median silhouette IoU, and those below the threshold
    step: str = ""  # the step running
    damaged: dict = field(default_factory=dict)  # skip_damaged: {"sets", "frames" per camera, "summary"} of the damage skipped
    reported: dict[str, tuple[int, int]] = field(default_factory=dict)  # progress name -> latest (done, total)
    planned: dict[str, list[str]] = field(default_factory=dict)  # step -> progress names announced for it
    cpu: dict[str, float] = field(default_factory=dict)  # step -> CPU seconds (this process and the workers)
    worker_cpu: dict[str, float] = field(default_factory=dict)  # step -> CPU seconds of its tasks on the executor
    part_cpu: dict[str, float] = field(default_factory=dict)  # step -> CPU seconds of its parts counted on their own

    @contextmanager
    def part(self, name: str):
        """Count a part of the running step on its own (e.g. the surface step's grid choice): its
        wall and CPU seconds are added to ``timings[name]`` and ``cpu[name]`` (a part run several
        times counts every run), not to the step's."""
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            cpu = time.process_time() - c0
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
            self.cpu[name] = self.cpu.get(name, 0.0) + cpu
            self.part_cpu[self.step] = self.part_cpu.get(self.step, 0.0) + cpu

    @property
    def skipped_sets(self) -> frozenset[int]:
        """Frame sets holding a damaged frame, skipped by this run (``skip_damaged``)."""
        return frozenset(self.damaged.get("sets", ()))

    def report_progress(self, step: str, done: int, total: int) -> None:
        self.reported[step] = (int(done), int(total))
        if self.progress:
            self.progress(step, done, total)

    def announce(self, step: str, items: Sequence[tuple[str, int]]) -> None:
        """Report the progress entries ``(name, total)`` a step will report as 0 done before it
        runs, so the run's summed total counts every step it will run (a job never reads n/n while
        steps are still to come); :meth:`complete` closes those the step did not report."""
        for name, total in items:
            self.planned.setdefault(step, []).append(name)
            if name not in self.reported:
                self.report_progress(name, 0, total)

    def complete(self, step: str) -> None:
        """The announced entries of a finished step at done == total (a resumed step reports none)."""
        for name in self.planned.get(step, ()):
            done, total = self.reported.get(name, (0, 0))
            if done < total:
                self.report_progress(name, total, total)

    def run_frames(self, step: str, task: Callable[..., list[dict]], done_dir: str, *, suffix: str = ".json",
                   chunk_args: Callable[[list[int]], dict] | None = None) -> None:
        """Run a per-frame ``task`` on every frame set without a result in ``OUT/done_dir``
        (the one runner all per-frame steps share: chunks, executor, progress, cancel);
        ``chunk_args(frames)`` adds keywords per chunk (e.g. its masks)."""
        todo = [k for k in range(self.n_sets) if not (self.out / done_dir / f"{_frame_name(k)}{suffix}").exists()]
        done = self.n_sets - len(todo)
        self.report_progress(step, done, self.n_sets)
        chunks = _chunks(todo, self.params.chunk)
        tasks = [partial(task, ch, **(chunk_args(ch) if chunk_args else {})) for ch in chunks]
        for finished in _map_tasks(self, tasks):
            done += len(finished)
            for rec in finished:
                if "skeleton" in rec:
                    self.skeletons[rec["index"]] = rec.pop("skeleton")
            self.report_progress(step, done, self.n_sets)


@dataclass(frozen=True)
class Step:
    """One named step of :func:`process_take`: ``run(ctx)`` does the work and persists it."""

    name: str
    run: Callable[[RunContext], None]
    doc: str = ""
    totals: Callable[[RunContext], list[tuple[str, int]]] | None = None  # its progress entries and their totals


_REGISTRY: dict[str, Step] = {}


def register_step(name: str, run: Callable[[RunContext], None], *, doc: str = "", after: str | None = None,
                  totals: Callable[[RunContext], list[tuple[str, int]]] | None = None) -> None:
    """Add a step to the pipeline (after ``after``, default at the end); updates :data:`STEPS`.
    ``totals(ctx)``: the progress entries ``(name, total)`` the step reports, announced before
    the run's first step (:meth:`RunContext.announce`)."""
    global STEPS
    if not name or not name.isidentifier():
        raise ValueError(f"name must be an identifier, got {name!r}")
    if after is not None and after not in _REGISTRY:
        raise ValueError(f"after: no step {after!r} (steps: {list(_REGISTRY)})")
    items = [(n, s) for n, s in _REGISTRY.items() if n != name]
    pos = len(items) if after is None else [n for n, _ in items].index(after) + 1
    items.insert(pos, (name, Step(name=name, run=run, doc=doc, totals=totals)))
    _REGISTRY.clear()
    _REGISTRY.update(items)
    STEPS = tuple(_REGISTRY)


def _step_key(ctx: RunContext) -> None:
    """Key every camera of the take (unless it holds masks and ``rekey`` is off): tasks of a
    few cameras on the executor (frames read once, in the worker), masks stored here."""
    total = ctx.n_sets * len(ctx.cameras)
    if not ctx.need_key:
        ctx.report_progress("key", total, total)
        return
    from stage.keying.take import resolve_key_choice, store_camera_keys, take_key_params

    t0 = time.perf_counter()
    skip = ctx.damaged.get("frames") or None
    choice = resolve_key_choice(ctx.take, ctx.rig, key_mode=ctx.params.key_mode, layers=ctx.params.key_layers, skip=skip)
    ctx.key_choice = choice
    _add_to_record(ctx, key=choice)
    if "graphcut" in choice["layers"] and "refine" in ctx.steps:
        ctx.announce("refine", [("refine", total)])
    base = take_key_params(ctx.rig, key_mode=choice["mode"]).to_dict()
    volume = _volume_bounds(ctx).tolist() if "volume" in choice["layers"] else None
    done = 0
    ctx.report_progress("key", 0, total)
    # OpenCV's thread pool does not survive fork(): forked workers key nothing, this process does
    where = ctx if not _forking_pool(ctx.executor) else replace(ctx, executor=None)
    threads = 1 if where.executor else 2
    # masks unpacked as each camera arrives; those done are stored once a worker falls idle
    # (the last cameras still keying: a core is free then), the rest at the end: few updates of
    # the derived data (each copies it), at most ~512 MB of masks a batch
    groups = _camera_groups(ctx.cameras, where.executor)
    pending = len(groups)
    overlap_at = max(1, _pool_size(where.executor) - 1) if where.executor is not None else 0
    batch: list = []
    for results in _map_tasks(where, [partial(key_task, str(ctx.take), g, base, threads, volume, skip) for g in groups]):
        pending -= 1
        for res in results:
            if res["key"] is None:
                continue
            key = res["key"]
            _keep_masks(ctx, key, res["shape"][-1])
            key.masks = np.unpackbits(key.masks, axis=-1, count=res["shape"][-1]).view(bool)
            done += len(key.valid)
            if batch and sum(k.masks.nbytes for k in batch) + key.masks.nbytes > _STORE_BATCH_BYTES:
                store_camera_keys(ctx.take, batch)
                batch = []
            batch.append(key)
        if batch and 0 < pending <= overlap_at:
            store_camera_keys(ctx.take, batch)
            batch = []
        ctx.report_progress("key", min(done, total), total)
    if batch:
        store_camera_keys(ctx.take, batch)
    ctx.timings["key"] = time.perf_counter() - t0


def _step_refine(ctx: RunContext) -> None:
    """The keying's ``graphcut`` layer: every camera's masks keyed in this run cut again with colour
    models seeded by a first hull (:func:`pipeline.silhouette_refine.refine_take`), stored in place."""
    layers = ctx.key_choice.get("layers", []) if ctx.key_choice else []
    if "graphcut" not in layers or not ctx.need_key:
        return
    from pipeline.silhouette_refine import refine_take

    t0 = time.perf_counter()
    total = ctx.n_sets * len(ctx.cameras)
    done = [0]

    def tick(n: int) -> None:
        done[0] += n
        ctx.report_progress("refine", min(done[0], total), total)

    info = refine_take(ctx.take, volume=_volume_bounds(ctx), progress=tick, skip_sets=ctx.skipped_sets)
    ctx.keyed = None  # the masks in memory are the keyer's: the surface tasks read the refined ones
    _add_to_record(ctx, refine={"method": "graphcut", "masks": info["frames"], "first_hull_grid": info["grid"]})
    ctx.timings["refine"] = time.perf_counter() - t0


def _keep_masks(ctx: RunContext, key, width: int) -> None:
    """Keep a camera's bit-packed masks for the surface step (within :data:`_KEEP_MASKS_BYTES`)."""
    if ctx.keyed is None:
        return
    ctx.keyed[key.camera] = (key.masks, int(width), np.asarray(key.valid, bool))
    if sum(m.nbytes for m, _, _ in ctx.keyed.values()) > _KEEP_MASKS_BYTES:
        ctx.keyed = None  # a long take: the surface tasks read the masks from it


def _kept_masks(ctx: RunContext) -> Callable[[list[int]], dict] | None:
    """Per chunk of frame sets, its masks as keyed in this run (``surface_task(masks=)``), or
    None when they are not all in memory (a resumed run, a long take)."""
    if not ctx.keyed or set(ctx.keyed) != set(ctx.cameras) or ctx.set_table is None:
        return None
    kept = [ctx.keyed[c] for c in ctx.cameras]
    widths = [w for _, w, _ in kept]
    skipped = ctx.skipped_sets

    def packed(k: int) -> list:
        if k in skipped:
            return [None] * len(kept)
        out = []
        for (m, _, valid), r in zip(kept, ctx.set_table[k]):
            ok = 0 <= r < len(m) and (r >= len(valid) or valid[r])  # as _frame_masks
            out.append(m[r] if ok else None)
        return out

    return lambda frames: {"masks": {"widths": widths, "sets": {k: packed(k) for k in frames}}}


def _pool_size(executor) -> int:
    """Tasks an executor runs at once (a process pool's workers; 2 when it does not say)."""
    return int(getattr(executor, "_max_workers", 0) or 2)


def _forking_pool(executor) -> bool:
    """A local process pool whose workers are forked from this process."""
    ctx = getattr(executor, "_mp_context", None)
    return isinstance(executor, cf.ProcessPoolExecutor) and (ctx is None or ctx.get_start_method(allow_none=False) == "fork")


def _with_cpu(task: Callable[[], object]) -> tuple[object, float, int]:
    """A task's result, the CPU seconds its process spent on it and that process's id (run in the worker)."""
    t = time.process_time()
    out = task()
    return out, time.process_time() - t, os.getpid()


def _map_tasks(ctx: RunContext, tasks: list[Callable[[], object]]):
    """Results of ``tasks`` as they finish (on the executor, or here one by one); stops
    between tasks when cancelled. The CPU seconds of workers in other processes add to the
    running step's (a thread pool's are already this process's)."""

    def check_cancel() -> None:
        if ctx.cancel is not None and ctx.cancel.is_set():
            raise InterruptedError("cancelled")

    if ctx.executor is None:
        for task in tasks:
            check_cancel()
            yield task()
        return
    futures = [ctx.executor.submit(_with_cpu, task) for task in tasks]
    try:
        for fut in cf.as_completed(futures):
            check_cancel()
            out, cpu, pid = fut.result()
            if pid != os.getpid():
                ctx.worker_cpu[ctx.step] = ctx.worker_cpu.get(ctx.step, 0.0) + cpu
            yield out
    finally:
        for fut in futures:
            fut.cancel()


def _volume_bounds(ctx: RunContext) -> np.ndarray:
    """Where to look for the subject: the job's volume, the rig's, else the cameras'."""
    return _search_volume(ctx)[0]


def _search_volume(ctx: RunContext) -> tuple[np.ndarray, str]:
    """:func:`_volume_bounds` and which it is (for the box's ``why``)."""
    from pipeline.volume import volume_from_cameras

    if ctx.params.volume is not None:
        return np.asarray(ctx.params.volume, float), "the volume option"
    if ctx.rig.get("volume"):
        c = np.asarray(ctx.rig["volume"]["center"], float)
        s = np.asarray(ctx.rig["volume"]["size"], float)
        return np.r_[c - s / 2, c + s / 2], "the rig's capture volume"
    return np.asarray(volume_from_cameras(ctx.calibration), float).reshape(-1), "the cameras' shared view"


def _box_choice(sb, volume: np.ndarray, source: str) -> dict:
    """The subject's box and why, for ``process.json`` and the report."""
    st = sb.stats
    why = (f"the pieces of the silhouettes' hull found by at least {sb.min_views} cameras (and by all but "
           f"{sb.view_slack} of those that find the best-found part) and explained by the "
           f"silhouettes of at least 2, in {st['with_subject']} of {st['frame_sets']} frame sets, carved coarse to "
           f"fine in {' / '.join(f'{v:.3g}' for v in sb.voxels)} cubes inside {source}, grown by {sb.margin:.3g}")
    return {**sb.to_dict(), "search_volume": np.asarray(volume, float).reshape(2, 3).tolist(), "searched_in": source,
            "why": why}


def _processing_grid(ctx: RunContext):
    """The grid of the surfaces: ``OUT/grid.json`` when an earlier run chose it, else fitted
    to the subject now (and written there)."""
    from pipeline.volume import Grid, grid_from_volume
    from stage.store import TakeReader

    grid_path = ctx.out / "grid.json"
    with TakeReader(ctx.take) as reader:
        missing = sorted(set(ctx.cameras) - set(reader.masks_present()))
        if missing:
            raise ProcessError(f"{ctx.take}: cameras {missing} have no masks; run the key step")
        if grid_path.exists():
            grid = Grid.from_dict(json.loads(grid_path.read_text()))
            ctx.grid_choice = json.loads(grid_path.read_text()).get("choice", {})
            return grid
        kept = _kept_masks(ctx)
        if kept is not None:  # the masks keyed in this run, in memory
            widths = [w for _, w, _ in (ctx.keyed[c] for c in ctx.cameras)]

            def masks_of(k: int):
                ms = _unpack_masks(kept([k])["masks"]["sets"][k], widths)
                return ms, [c for c, m in zip(ctx.cameras, ms) if m is None]
        else:
            validity = _mask_validity(reader, ctx.cameras)
            masks_of = partial(_frame_masks, reader, ctx.cameras, validity=validity)
        if ctx.skipped_sets:
            masks_of = _without_sets(masks_of, ctx.skipped_sets, ctx.cameras)
        volume, source = _search_volume(ctx)
        sb = _subject_grid(masks_of, ctx.calibration, ctx.n_sets, ctx.params, volume,
                           progress=lambda d, t: ctx.report_progress("box", d, t))
    p = ctx.params
    res, why = _rig_resolution(ctx.calibration, sb.bounds, p, sb.centres)
    grid = grid_from_volume(sb.bounds, res)
    ctx.grid_choice = {**why, "voxel": grid.voxel, "shape": list(grid.shape), "box": _box_choice(sb, volume, source)}
    log.info("subject box %s: %s", " x ".join(f"{x:.4g}" for x in sb.bounds[1] - sb.bounds[0]), ctx.grid_choice["box"]["why"])
    log.info("processing grid %s (%s)", grid, why["limited_by"] if "limited_by" in why else why["source"])
    if p.support_plane is None and p.volume is None and not ctx.rig.get("volume"):
        hint = _blind_side_hint(ctx.calibration, grid)
        if hint:
            log.warning("%s", hint)
            ctx.warnings.append(hint)
    atomic_write(grid_path, json.dumps({**grid.to_dict(), "choice": ctx.grid_choice}))
    return grid


def _without_sets(masks_of: Callable, skipped: frozenset[int], cameras: Sequence[str]) -> Callable:
    """``masks_of`` with no mask in the ``skipped`` frame sets (every camera skipped)."""

    def masks(k: int):
        return ([None] * len(cameras), list(cameras)) if k in skipped else masks_of(k)

    return masks


def _record_skipped(ctx: RunContext) -> None:
    """``frames/`` records of the skipped frame sets (``status: damaged``), their results removed:
    the surface and skeleton tasks pass them by, the report lists them."""
    from pipeline.results import ResultsStore

    store = ResultsStore(ctx.out)
    for k in sorted(ctx.skipped_sets):
        store.mesh_path(k).unlink(missing_ok=True)
        (ctx.out / "skeletons" / f"{_frame_name(k)}.npz").unlink(missing_ok=True)
        cams = [c for c, r in zip(ctx.cameras, ctx.set_table[k]) if r in ctx.damaged["frames"].get(c, ())]
        info = {"index": int(k), "status": "damaged", "skipped_cameras": list(ctx.cameras),
                "reason": f"damaged frames of camera {', '.join(cams)} in the take: the set was skipped (--skip-damaged)"}
        atomic_write(ctx.out / "frames" / f"{_frame_name(k)}.json", json.dumps(info))


def _step_surface(ctx: RunContext) -> None:
    """Visual hull (and depth fusion) and a surface per frame set -> ``meshes/``, ``frames/``."""
    _record_skipped(ctx)
    with ctx.part("grid"):
        grid = _processing_grid(ctx)
        _add_to_record(ctx, grid=ctx.grid_choice)
    t0 = time.perf_counter()
    task = partial(
        surface_task,
        str(ctx.take.resolve()),
        calib_dict=ctx.calibration.to_dict(),
        grid_dict=grid.to_dict(),
        params=ctx.params.model_dump(),
        out=str(ctx.out.resolve()),
        # skeletons straight from the surfaces in memory when the spine step follows
        spine_params=ctx.params.spine if "spine" in ctx.steps else None,
        use_depth=_uses_depth(ctx.params, all_depth=ctx.all_depth),
    )
    ctx.run_frames("surface", task, "frames", chunk_args=_kept_masks(ctx))
    _write_consistency(ctx)
    ctx.timings["surface"] = time.perf_counter() - t0


def _write_consistency(ctx: RunContext) -> None:
    """``OUT/consistency.json`` from the frames' records: per camera and frame set the IoU of the
    camera's mask and the projection of the surface (:mod:`pipeline.consistency`), each camera's
    median; a camera whose median is below :data:`pipeline.consistency.CONSISTENCY_WARN` is named
    in a warning."""
    from pipeline.consistency import CONSISTENCY_WARN

    iou = np.full((len(ctx.cameras), ctx.n_sets), np.nan)
    for k in range(ctx.n_sets):
        f = ctx.out / "frames" / f"{_frame_name(k)}.json"
        per_cam = json.loads(f.read_text()).get("consistency") if f.exists() else None
        for i, cam in enumerate(ctx.cameras):
            v = (per_cam or {}).get(cam)
            iou[i, k] = np.nan if v is None else v
    seen = np.isfinite(iou).any(axis=1)
    median = {cam: (float(np.nanmedian(iou[i])) if seen[i] else None) for i, cam in enumerate(ctx.cameras)}
    low = [cam for cam, m in median.items() if m is not None and m < CONSISTENCY_WARN]
    doc = {"cameras": ctx.cameras, "threshold": CONSISTENCY_WARN, "median": median, "low": low,
           "iou": [[None if not np.isfinite(x) else float(x) for x in row] for row in iou]}
    atomic_write(ctx.out / "consistency.json", json.dumps(doc))
    ctx.consistency = {"median": median, "low": low, "threshold": CONSISTENCY_WARN}
    for cam in low:
        msg = (f"camera {cam}: median silhouette consistency {median[cam]:.2f} (IoU of its masks and the projected "
               f"hull) is below {CONSISTENCY_WARN}: check its keying and calibration (report: worst frames)")
        log.warning("%s", msg)
        ctx.warnings.append(msg)


def _step_spine(ctx: RunContext) -> None:
    """Per-frame skeletons -> ``skeletons/``, then their tips corresponded over time -> ``spine.json``."""
    from pipeline.spine import FrameSkeleton, SpineParams, build_spine, write_spine

    n = ctx.n_sets
    if any(not (ctx.out / "frames" / f"{_frame_name(k)}.json").exists() for k in range(n)):
        raise ProcessError(f"{ctx.out}: surfaces are missing for some frames; run the surface step")
    t0 = time.perf_counter()
    for k in _stale_skeletons(ctx.out, n):
        ctx.skeletons.pop(k, None)
    ctx.run_frames("skeleton", partial(skeleton_task, str(ctx.out.resolve()), spine_params=ctx.params.spine), "skeletons",
                   suffix=".npz")
    skeletons: list[FrameSkeleton] = []
    for k in range(n):
        sk = ctx.skeletons[k] if k in ctx.skeletons else _load_skeleton(ctx.out / "skeletons" / f"{_frame_name(k)}.npz")["skeleton"]
        sk = FrameSkeleton.empty() if sk is None else sk
        skeletons.append(sk)
        ctx.tip_counts[k] = sk.n_tips
    ctx.report_progress("spine", 0, 1)
    spine = build_spine(skeletons, fps=float(ctx.fps), units=ctx.calibration.units, params=SpineParams(**ctx.params.spine))
    ctx.spine_path = write_spine(ctx.out / "spine.json", spine)
    # how K was chosen (the mode of the tip counts, or a borderline count decided): in the report
    ctx.limb_count = {"K": int(spine.meta.get("K", len(spine.limb_ids))), "rule": spine.meta.get("count_rule", "mode")}
    ctx.report_progress("spine", 1, 1)
    ctx.timings["spine"] = time.perf_counter() - t0


def _step_track(ctx: RunContext) -> None:
    """The first surface tracked through the take -> ``tracked/`` (:func:`pipeline.carve.track_with_carving`
    with ``ProcessParams.track``)."""
    from pipeline.carve import track_with_carving

    t0, opt = time.perf_counter(), ctx.params.track
    rep = track_with_carving(ctx.out, opt.carve, margin=opt.carve_margin, progress=ctx.report_progress, executor=ctx.executor,
                             colour=opt.colour, shape_memory=opt.shape_memory)
    if rep.get("started_over"):  # frames of other settings, and the rig on them, removed: the job report says so
        ctx.warnings.append(rep["started_over"])
    ctx.worker_cpu["track"] = ctx.worker_cpu.get("track", 0.0) + rep.get("worker_cpu_seconds", 0.0)
    ctx.timings["track"] = time.perf_counter() - t0


STEPS: tuple[str, ...] = ()
def _surface_totals(ctx: RunContext) -> list[tuple[str, int]]:
    box = [] if (ctx.out / "grid.json").exists() else [("box", ctx.n_sets)]  # the grid is chosen once
    return [*box, ("surface", ctx.n_sets)]


register_step("key", _step_key, doc="keying masks into the take", totals=lambda ctx: [("key", ctx.n_sets * len(ctx.cameras))])
register_step("refine", _step_refine, doc="graph-cut refinement of the masks (the keying's graphcut layer)")  # announced by key
register_step("surface", _step_surface, doc="visual hull and surface per frame set", totals=_surface_totals)
register_step("spine", _step_spine, doc="per-frame skeletons and the take's spine",
              totals=lambda ctx: [("skeleton", ctx.n_sets), ("spine", 1)])


def _step_rig(ctx: RunContext) -> None:
    """Articulated rig from the tracked template (``tracked/``) -> ``rig/``. Without a tracked
    template the track step runs first (``ProcessParams.track``; a warning in the job report says so)."""
    from pipeline.armature import NoTrackingError, armature_results, tracked_meshes

    t0 = time.perf_counter()
    try:
        tracked_meshes(ctx.out)
    except NoTrackingError:
        if "track" not in ctx.steps:
            msg = "rig: the take had no tracked template: the track step ran first (with the job's track parameters)"
            ctx.warnings.append(msg)
            log.warning("%s", msg)
            if not any((ctx.out / "meshes").glob("frame_*.ply")):
                raise ProcessError("rig: the take has no surfaces to track yet (meshes/frame_NNNNNN.ply): "
                                   "run the surface step first") from None
            _step_track(ctx)
        t0 = time.perf_counter()
    try:
        armature_results(ctx.out, units=ctx.calibration.units, fps=float(ctx.fps),
                         progress=lambda s, d, t: ctx.report_progress(f"rig {s}", d, t))
    except NoTrackingError as exc:
        raise ProcessError(f"rig: {exc}") from None
    ctx.timings["rig"] = time.perf_counter() - t0


def _track_totals(ctx: RunContext) -> list[tuple[str, int]]:
    """The tracking, then per round of carving the carve and the tracking again (:func:`pipeline.carve.track_with_carving`)."""
    rounds = [(f"{what} round {r}", ctx.n_sets) for r in range(1, ctx.params.track.carve + 1) for what in ("carve", "track")]
    return [("track", ctx.n_sets), *rounds]


register_step("rig", _step_rig, doc="articulated rig from the tracked template (Tzionas & Gall 2016)", after="spine",
              totals=lambda ctx: [("rig segmentation", 1), ("rig skeleton", 1), ("rig fit", ctx.n_sets),
                                  ("rig write", ctx.n_sets)])
register_step("track", _step_track, doc="template tracking of the surfaces (only when asked for)", after="spine",
              totals=_track_totals)
# what runs when no steps are given: tracking and the rig on it are asked for (``stage track``,
# ``stage rig`` or a job's steps); a plain run does not warn about a rig it was not asked for
DEFAULT_STEPS: tuple[str, ...] = tuple(s for s in STEPS if s not in ("track", "rig"))


# ----------------------------------------------------------------------------- driver


def _check_params(params: ProcessParams | dict | None) -> ProcessParams:
    if params is None:
        params = ProcessParams()
    elif isinstance(params, dict):
        try:
            params = ProcessParams(**params)
        except ValidationError as exc:
            raise ValueError(f"params: {exc}") from None
    elif not isinstance(params, ProcessParams):
        raise ValueError(f"params must be ProcessParams or a dict, got {type(params).__name__}")
    try:
        from pipeline.spine import SpineParams

        SpineParams(**params.spine)
    except ValidationError as exc:
        raise ValueError(f"params.spine: {exc}") from None
    return params


def _check_frames(take: Path, *, skip: bool) -> dict:
    """Every chunk of the frames this run will read, checked before any work: a damaged take
    stops here naming its damaged cameras, frames and frame sets (``stage verify`` lists them);
    with ``skip``, damage confined to frames is returned instead: ``{"sets", "frames", "summary"}``
    (empty when there is none)."""
    from stage.store.verify import verify_take

    damage = verify_take(take)
    if damage.ok:
        return {}
    if not skip or not damage.skippable:
        hint = "" if skip else "; --skip-damaged processes the other frame sets"
        raise ProcessError(f"{damage.summary()}; nothing was processed (`stage verify {take}` lists the damage){hint}")
    msg = f"{damage.summary()}: these frame sets are skipped (no surface, no skeleton)"
    log.warning("%s", msg)
    return {"sets": list(damage.sets), "frames": {c: list(v) for c, v in damage.frames.items()}, "summary": msg}


def _open_context(take: Path, out: Path, params: ProcessParams, **hooks) -> RunContext:
    """Read what every step needs from the take once (and check it can be processed)."""
    from stage.store import TakeReader

    with TakeReader(take) as reader:
        if not reader.has_calibration:
            raise ProcessError(f"{take}: the take has no calibration; run `stage calibrate` first")
        calibration = reader.calibration
        cameras = list(reader.cameras)
        missing_cal = [c for c in cameras if c not in calibration.names]
        if missing_cal:
            raise ProcessError(f"{take}: cameras {missing_cal} are not in the take's calibration")
        n_sets = reader.n_sets
        fps = reader.fps or reader.measured_fps() or 30.0
        rig = reader.rig or {}
        if params.support_plane is None and rig.get("support_plane") is not None:
            # the rig's (or the import's) support plane, unless the job gives its own
            params = ProcessParams(**{**params.model_dump(), "support_plane": tuple(rig["support_plane"])})
        need_key = params.rekey or len(reader.masks_present()) < len(cameras)
        all_depth = _all_depth(reader, cameras)
        table = reader.set_table()
        set_table = table[:, [list(reader.cameras).index(c) for c in cameras]]
    if n_sets == 0:
        raise ProcessError(f"{take}: the take holds no frame sets")
    # skipping needs the damage's frame sets on a resumed run too (its surfaces read the take)
    damaged = _check_frames(take, skip=params.skip_damaged) if need_key or params.photo_refine or params.skip_damaged else {}
    calibration = type(calibration)(tuple(calibration[c] for c in cameras), units=calibration.units, meta=calibration.meta)
    ctx = RunContext(
        take=take, out=out, params=params, calibration=calibration, cameras=cameras, n_sets=n_sets,
        fps=float(fps), rig=rig, need_key=need_key, all_depth=all_depth, tip_counts=[None] * n_sets, set_table=set_table, **hooks,
    )
    if damaged:
        ctx.damaged = damaged
        ctx.warnings.append(damaged["summary"])
    return ctx


def _start_record(ctx: RunContext) -> None:
    """Write ``process.json``; results of other parameters or another take are removed first."""
    record = {"take": str(ctx.take.resolve()), "params": ctx.params.model_dump(), "frames": ctx.n_sets, "cameras": ctx.cameras}
    if ctx.damaged:
        record["damaged"] = ctx.damaged
    prev = ctx.out / "process.json"
    if prev.exists():
        old = json.loads(prev.read_text())
        if _compared(old.get("params")) != _compared(record["params"]) or old.get("take") != record["take"]:
            _start_over(ctx)
    atomic_write(prev, json.dumps(record, indent=2))


def _compared(params) -> object:
    """The parameters a start-over compares: all but the ``track`` step's (the tracking compares its own)."""
    return {k: v for k, v in params.items() if k != "track"} if isinstance(params, dict) else params


def _start_over(ctx: RunContext) -> None:
    """Remove the results of other parameters or another take and all that was made from them
    (report, spine exports, tracking, rig), in one warning (also in the job report)."""
    from pipeline.armature import counted
    from pipeline.track import remove_tracking

    for sub in ("meshes", "frames", "skeletons"):  # the results themselves: what "starting over" says
        for f in (ctx.out / sub).glob("frame_*"):
            f.unlink()
    exported = sorted((ctx.out / "export").glob("frame_*"))  # meshes converted (ResultsStore.export)
    for f in exported:
        f.unlink()
    (ctx.out / "spine.json").unlink(missing_ok=True)
    (ctx.out / "grid.json").unlink(missing_ok=True)  # the grid follows the parameters too
    # made from the frames and the spine: the report (`stage report`, the API's page) and the
    # exports (`stage export`, the API's first request), then the tracking and the rig on it
    made = [ctx.out / n for n in _MADE_FROM_FRAMES if (ctx.out / n).is_file()]
    for f in made:
        f.unlink()
    said = [f.name for f in made if f.name not in ("report.json", "consistency.json")]  # written again by this run
    if exported:
        said.append(f"{counted(len(exported), 'exported mesh file')} ({ctx.out / 'export'})")
    note = f"; removed {', '.join(said)}" if said else ""
    msg = f"{ctx.out} holds results of other parameters or another take; starting over{note}{remove_tracking(ctx.out)}"
    log.warning("%s", msg)
    ctx.warnings.append(msg)


#: Files of a results directory made from its frames and spine, removed when it starts over.
_MADE_FROM_FRAMES = ("report.json", "report.html", "spine_rig.glb", "spine.glb", "consistency.json")


def _add_to_record(ctx: RunContext, **items) -> None:
    """Add what a step decided (e.g. the grid and why) to ``process.json``."""
    path = ctx.out / "process.json"
    atomic_write(path, json.dumps({**json.loads(path.read_text()), **items}, indent=2, default=json_default))


def _write_report(ctx: RunContext, steps: tuple[str, ...], t_start: float) -> ProcessResult:
    frame_infos: dict[int, dict] = {}
    for k in range(ctx.n_sets):
        f = ctx.out / "frames" / f"{_frame_name(k)}.json"
        if f.exists():
            frame_infos[k] = json.loads(f.read_text())
    empty = sorted(k for k, i in frame_infos.items() if i.get("status") not in ("ok", "damaged"))
    if not ctx.consistency and (ctx.out / "consistency.json").is_file():  # made by an earlier run's surface step
        doc = json.loads((ctx.out / "consistency.json").read_text())
        ctx.consistency = {k: doc.get(k) for k in ("median", "low", "threshold")}
    report = {
        "take": str(ctx.take.resolve()),
        "frames": ctx.n_sets,
        "cameras": ctx.cameras,
        "steps": list(steps),
        "seconds": ctx.timings,
        "cpu_seconds": ctx.cpu,
        "total_seconds": time.perf_counter() - t_start,
        "empty_frames": empty,
        "damaged_sets": sorted(ctx.skipped_sets),
        "tip_counts": ctx.tip_counts,
        "per_frame": [frame_infos.get(k) for k in range(ctx.n_sets)],
        "warnings": ctx.warnings,
        "grid": ctx.grid_choice,
        "limb_count": ctx.limb_count,
        "consistency": ctx.consistency,
    }
    atomic_write(ctx.out / "report.json", json.dumps(report, indent=1, default=json_default))
    return ProcessResult(
        out=ctx.out, steps=steps, frames=ctx.n_sets, empty_frames=empty, spine_path=ctx.spine_path, report=report
    )


def process_take(
    take: str | os.PathLike,
    out: str | os.PathLike,
    *,
    steps: Sequence[str] | None = None,
    params: ProcessParams | dict | None = None,
    executor: cf.Executor | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> ProcessResult:
    """Run keying, reconstruction and spines on a take; resumable.

    Parameters
    ----------
    take : path
        The take (.h5) with a calibration.
    out : path
        Results directory (beside the take, never inside it).
    steps : sequence of str, optional
        Steps to run (names in :data:`STEPS`, default :data:`DEFAULT_STEPS`), run in pipeline order (a later
        step needs the earlier ones' results, which may come from an earlier run).
    params : ProcessParams or dict, optional
    executor : concurrent.futures.Executor, optional
        Where per-frame work runs; ``None`` runs it in this process.
    progress : callable, optional
        ``progress(step, done, total)`` after every finished chunk of frames.
    cancel : threading.Event, optional
        Set it to stop between chunks (``InterruptedError``); finished frames stay.

    Returns
    -------
    ProcessResult
    """
    take, out = Path(take), Path(out)
    steps = DEFAULT_STEPS if steps is None else tuple(steps)
    bad = [s for s in steps if s not in _REGISTRY]
    if bad or not steps:
        raise ValueError(f"steps must be a non-empty subset of {STEPS}, got {steps}")
    if "key" in steps:
        steps = (*steps, "refine")  # keying's graphcut layer (a no-op without it)
    steps = tuple(s for s in STEPS if s in steps)
    params = _check_params(params)
    if not take.is_file():
        raise FileNotFoundError(f"{take}: take not found")
    if out.resolve() == take.resolve() or out.suffix in (".h5", ".hdf5"):
        raise ValueError(f"out must be a directory beside the take, got {out}")
    created = not out.exists()
    t_start = time.perf_counter()
    if executor is not None:
        for _ in range(2):
            executor.submit(warm_task)  # workers import while this process reads the take
    try:
        ctx = _open_context(take, out, params, executor=executor, progress=progress, cancel=cancel)
        ctx.steps = steps
        need = _space_needed(ctx, steps)
        with raise_disk_full(out, "the processing results", need,
                             detail="the take is unchanged; free space and run again"):
            check_free_space(out, need, f"processing {ctx.n_sets} frame sets of {take.name}")
            out.mkdir(parents=True, exist_ok=True)
            _start_record(ctx)
            for name in steps:  # the run's total counts every step it will run
                if _REGISTRY[name].totals is not None:
                    ctx.announce(name, _REGISTRY[name].totals(ctx))
            for name in steps:
                _run_step(ctx, name)
            return _write_report(ctx, steps, t_start)
    except Exception:
        if created and out.is_dir():  # a failed run leaves no results folder it made itself
            shutil.rmtree(out, ignore_errors=True)
        raise


def _run_step(ctx: RunContext, name: str) -> None:
    """Run one step; its CPU seconds (this process's and its tasks' in other processes) go to
    ``ctx.cpu``, less those of its parts counted on their own (:meth:`RunContext.part`)."""
    ctx.step = name
    t = time.process_time()
    _REGISTRY[name].run(ctx)
    ctx.complete(name)
    own = time.process_time() - t - ctx.part_cpu.get(name, 0.0)
    ctx.cpu[name] = own + ctx.worker_cpu.get(name, 0.0)


def _space_needed(ctx: RunContext, steps: Sequence[str]) -> int:
    """About how many bytes processing writes: compressed masks (if keying), meshes and records per frame."""
    from stage.store import TakeReader

    need = 1 << 20
    if "key" in steps and ctx.need_key:
        with TakeReader(ctx.take) as r:
            pixels = sum(r.n_frames(c) * int.__mul__(*r.image_size(c)) for c in ctx.cameras)
            old = r.derived_path.stat().st_size if r.derived_path.exists() else 0
        need += pixels // 16 + old  # the derived file is rebuilt beside the old one
    if "surface" in steps or "spine" in steps:
        res = ctx.params.resolution or round(MAX_VOXELS ** (1 / 3))  # chosen later from the rig: at most this
        need += ctx.n_sets * (64 * res**2 + (16 << 10))
    return need


def _blind_side_hint(calibration, grid) -> str:
    """A warning when every camera looks down on the subject (imported footage, no support plane)."""
    from pipeline.volume import view_elevation

    centre = (grid.lo + grid.hi) / 2
    up, elev = view_elevation(calibration, centre)
    if elev < 5.0:
        return ""
    return (
        f"all {len(calibration)} cameras sit at least {elev:.1f} deg above the subject (seen from direction "
        f"{up[0]:.2f} {up[1]:.2f} {up[2]:.2f}): no silhouette can carve under its base, so the hull reaches about "
        f"{np.tan(np.radians(elev)):.2f} x the base's half-width below it. If the subject stands on a support, "
        f"pass its plane: --support-plane {up[0]:.3f} {up[1]:.3f} {up[2]:.3f} D (kept where a*x + b*y + c*z + D >= 0)"
    )
