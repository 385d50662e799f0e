"""The per-frame tasks of :func:`pipeline.process.process_take`, run on the executor's workers.

Top-level functions with plain arguments (picklable), so they run in a process pool or on a Dask
worker: a worker opens the take by path itself (a Dask cluster needs a shared filesystem), keeps one
carver (and depth fuser) per calibration and grid, and writes its frames' results itself
(:class:`pipeline.run.BackgroundWriter`: the disk's waits overlap the next frame).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calib.fileio import atomic_write
from pipeline.process.params import ProcessParams
from pipeline.process.records import frame_name, said_fields, skeleton_bytes, skeleton_path, skeleton_record
from pipeline.run import BackgroundWriter, frame_warnings

__all__ = ["carve_hull", "every_camera_has_depth", "frame_masks", "key_task", "mask_validity", "skeleton_task", "surface_task",
           "unpack_masks", "uses_depth", "warm_task"]

log = logging.getLogger("pipeline.process")


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


def mask_validity(reader, cameras: Sequence[str]) -> dict[str, np.ndarray | None]:
    """Per camera, the keyer's per-row validity flags (None when the take has none)."""
    return {
        cam: reader.read_array(f"cameras/{cam}", "mask_valid")[0].astype(bool)
        if reader.has_array(f"cameras/{cam}", "mask_valid")
        else None
        for cam in cameras
    }


def frame_masks(reader, cameras: Sequence[str], k: int, validity: dict) -> tuple[list, list[str]]:
    """Masks of frame set ``k``, one (H, W) bool array per camera; ``None`` for a camera
    missing in the set or whose mask the keyer marked invalid (it neither carves nor counts
    as a view). ``validity`` is :func:`mask_validity` of the same reader."""
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



def carve_hull(carver, masks, p: ProcessParams):
    """One frame's hull with the job's carving options (the subject grid and the surfaces alike)."""
    return carver.carve(masks, tolerance=p.tolerance, support_plane=p.support_plane, margin=p.silhouette_margin)


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



def unpack_masks(packed: list, widths: Sequence[int]) -> list:
    """The masks of one frame set shipped with a task: bit-packed rows -> (H, W) bool (or None)."""
    return [None if p is None else np.unpackbits(p, axis=-1, count=w).view(bool) for p, w in zip(packed, widths)]


def _subject_hull(carver, masks, p: ProcessParams, bridge_gaps: float = 0.0):
    """The frame set's hull without phantom pieces, and the silhouettes without the parts the
    subject does not explain (:func:`pipeline.silhouette_refine.subject_hull`), carved as the job says;
    ``bridge_gaps``: one camera's miss bridged inside its silhouette's gaps (plate-keyed masks)."""
    from pipeline.silhouette_refine import subject_hull

    return subject_hull(masks, carver, tolerance=p.tolerance, support_plane=p.support_plane, margin=p.silhouette_margin,
                        bridge_gaps=bridge_gaps)


def _surface_of(carver, masks, p: ProcessParams, depth=None, images=None, hull=None):
    """The frame set's surface and its source: the hull's (``hull``: the occupancy, else
    carved now), or with ``depth`` (a fuser and the set's depth images) the depth fused
    inside the hull; with ``images`` (the set's colour images, None for a missing camera)
    the hull's surface refined where the colours agree."""
    from pipeline.surface import surface_from_occupancy

    occupancy = carve_hull(carver, masks, p).occupancy if hull is None else hull
    if depth is not None:
        fuser, depth_images = depth
        fused = fuser.fuse(depth_images, hull=occupancy)
        return fused.surface(taubin_iterations=p.smooth_iterations, face_budget=p.face_budget), "depth+hull"
    mesh = surface_from_occupancy(occupancy, carver.grid, taubin_iterations=p.smooth_iterations,
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
    bridge_gaps: float = 0.0,
) -> list[dict]:
    """Visual hull + surface of some frame sets; writes ``meshes/`` and ``frames/`` (and,
    with ``spine_params``, the frames' skeletons to ``skeletons/`` from the mesh in memory).

    ``masks`` (optional): the sets' masks as keyed in this run, ``{"widths": [W per camera],
    "sets": {k: [bit-packed (H, W/8) rows or None per camera]}}``; without it they are read
    from the take. ``use_depth``: fuse depth (default: when ``params.depth`` is ``auto`` and
    every camera has depth); with masks given, no depth and no ``params.photo_refine``, the
    take is not opened at all. ``bridge_gaps``: :func:`pipeline.silhouette_refine.subject_hull`'s
    (0: off; the driver turns it on for plate-keyed masks). What a frame set warns of (a camera's mask all
    foreground, an empty frame...) is kept in its record (``warnings``) and its result (``said``) rather than said
    at once (:func:`pipeline.run.frame_warnings`): the step says each kind once, with the frame sets.
    Top level (picklable) so it runs in a process pool or on a Dask worker.
    """
    from contextlib import nullcontext

    from pipeline.frame_skeleton import SpineParams
    from pipeline.hull import EmptyHullError
    from pipeline.results import ResultsStore, ply_bytes
    from pipeline.surface import EmptySurfaceError, surface_quality
    from stage.store import TakeReader

    p = ProcessParams(**params)
    sp = SpineParams(**spine_params) if spine_params is not None else None
    out_dir = Path(out)
    store = ResultsStore(out_dir)
    carver = _carver(calib_dict, grid_dict)
    cameras = [c["name"] for c in calib_dict["cameras"]]
    results = []
    writer = BackgroundWriter()
    try:
        needs_take = masks is None or use_depth is not False or p.photo_refine
        with TakeReader(take) if needs_take else nullcontext() as reader:
            if use_depth is None:
                use_depth = uses_depth(p, all_depth=every_camera_has_depth(reader, cameras))
            validity = mask_validity(reader, cameras) if masks is None else None
            for k in frames:
                with frame_warnings(k) as said:  # said once per kind by the step, with the frame sets
                    t0 = time.perf_counter()
                    if masks is None:
                        ms, skipped = frame_masks(reader, cameras, k, validity)
                    else:
                        ms = unpack_masks(masks["sets"][k], masks["widths"])
                        skipped = [c for c, m in zip(cameras, ms) if m is None]
                    info: dict = {"index": int(k), "skipped_cameras": skipped}
                    mesh = quality = None
                    try:
                        if len(skipped) == len(cameras):
                            raise EmptyHullError("no camera has a valid mask in this frame set")
                        depth = (_fuser(calib_dict, grid_dict), _frame_depths(reader, cameras, k)) if use_depth else None
                        images = _frame_images(reader, cameras, k) if p.photo_refine and not use_depth else None
                        sh = _subject_hull(carver, ms, p, bridge_gaps)
                        ms = sh.masks  # the hull's silhouettes: the consistency compares with them
                        info["dropped"] = {c: (None if not np.isfinite(x) else round(float(x), 4))
                                           for c, x in zip(cameras, sh.dropped)}
                        info["bridged"] = sh.bridged
                        mesh, info["source"] = _surface_of(carver, ms, p, depth, images, hull=sh.occupancy)
                        quality = surface_quality(mesh).to_dict()
                        info["consistency"] = _consistency(mesh, ms, carver.calibration, p.silhouette_margin)
                        writer.write(store.mesh_path(k), ply_bytes(mesh.vertices, mesh.faces))
                        info.update(status="ok", quality=quality)
                    except (EmptyHullError, EmptySurfaceError) as exc:
                        mesh = None
                        info.update(status="empty", reason=str(exc))
                        log.warning("%s", exc)
                    info["seconds"] = time.perf_counter() - t0
                    rec = None if sp is None else skeleton_record(
                        k, None if mesh is None else (mesh.vertices, mesh.faces), sp,
                        bodies=None if quality is None else quality["bodies"])
                # the frame's record keeps them (the report's per_frame; a later run says them again); the step says
                # them once
                info.update(said_fields(said))
                res = {**info, "said": said}
                if rec is not None:
                    writer.write(skeleton_path(out_dir, k), skeleton_bytes(rec))
                    res["skeleton"] = rec["skeleton"]  # travels back: the spine step need not read it again
                # written last: a frame with its record has its mesh (and skeletons) on disk
                writer.write(out_dir / "frames" / f"{frame_name(k)}.json", json.dumps(info))
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


def every_camera_has_depth(reader, cameras: Sequence[str]) -> bool:
    """Every camera of the take delivers depth."""
    return all(reader.camera_info(c).get("has_depth") for c in cameras)


def uses_depth(p: ProcessParams, *, all_depth: bool) -> bool:
    """Depth is fused when the job allows it and every camera of the take delivers depth."""
    return p.depth == "auto" and all_depth


def skeleton_task(out: str, frames: Sequence[int], spine_params: dict) -> list[dict]:
    """Per-frame tips and skeletons of some frames' stored meshes -> ``skeletons/``; each frame's result says what
    the frame warned of (``said``, :func:`pipeline.run.frame_warnings`)."""
    from pipeline.frame_skeleton import SpineParams
    from pipeline.meshio import load_mesh
    from pipeline.results import ResultsStore

    params = SpineParams(**spine_params)
    out_dir = Path(out)
    store = ResultsStore(out_dir)
    done = []
    for k in frames:
        with frame_warnings(k) as said:  # said once per kind by the step, with the frame sets
            mesh_path = store.mesh_path(k)
            rec = skeleton_record(k, load_mesh(mesh_path, largest=False) if mesh_path.exists() else None, params)
        atomic_write(skeleton_path(out_dir, k), skeleton_bytes({**rec, "said": said}))  # (said again by a later run)
        done.append({"index": int(k), "status": rec["status"], "skeleton": rec["skeleton"], "said": said})
    return done


def warm_task() -> int:
    """Import what the per-frame tasks need (run once per worker while the parent reads the take)."""
    import pipeline.hull
    import pipeline.spine
    import pipeline.surface  # noqa: F401
    import stage.keying.take  # noqa: F401

    return os.getpid()

