"""The steps of :func:`pipeline.process.process_take`, in order (:data:`STEPS`).

key -> refine -> surface -> spine, then (asked for) track -> rig. A step is a function of the
run's :class:`~pipeline.process.context.RunContext`: it fans its per-frame tasks
(:mod:`pipeline.process.tasks`) out over the executor, persists its results in the results
directory, and leaves what later steps need on the context. A plug-in adds a step with
:func:`register_step`.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from calib.fileio import atomic_write
from pipeline.process.context import RunContext
from pipeline.process.grid import choose_grid, search_volume
from pipeline.process.params import ProcessError
from pipeline.process.records import (
    frame_name,
    frame_said,
    load_skeleton,
    skeleton_path,
    skeleton_said,
    stale_skeletons,
)
from pipeline.process.tasks import (
    frame_masks,
    key_task,
    mask_validity,
    skeleton_task,
    surface_task,
    unpack_masks,
    uses_depth,
)
from pipeline.run import StepList, forking_pool, frame_warnings, once_per_run, pool_size, submitted_by

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = ["DEFAULT_STEPS", "STEPS", "check_job_steps", "register_step"]

log = logging.getLogger("pipeline.process")

#: Masks stored per update of the take's derived data (bytes, unpacked).
_STORE_BATCH_BYTES = 512 << 20
#: Keyed masks kept in memory (bit-packed) for the surface tasks, at most (else they read the take).
_KEEP_MASKS_BYTES = 1 << 30

#: The steps' names in the order they run (one object: :func:`register_step` adds to it in place).
STEPS = StepList()


def register_step(name: str, run: Callable[[RunContext], None], *, doc: str = "", after: str | None = None,
                  totals: Callable[[RunContext], list[tuple[str, int]]] | None = None) -> None:
    """Add a step to the pipeline (after ``after``, default at the end); :data:`STEPS` has it at once.
    ``totals(ctx)``: the progress entries ``(name, total)`` the step reports, announced before
    the run's first step (:meth:`pipeline.run.Run.announce`)."""
    STEPS.register(name, run, doc=doc, after=after, totals=totals)


def _step_key(ctx: RunContext) -> None:
    """Key every camera of the take (unless it holds masks and ``rekey`` is off): tasks of a
    few cameras on the executor (frames read once, in the worker), masks stored here."""
    total = ctx.take.n_sets * len(ctx.take.cameras)
    if not ctx.need_key:
        ctx.report_progress("key", total, total)
        return
    from stage.keying.take import resolve_key_choice, store_camera_keys, take_key_params

    skip = ctx.damaged.get("frames") or None
    choice = resolve_key_choice(ctx.take.path, ctx.take.rig, key_mode=ctx.params.key_mode, layers=ctx.params.key_layers, skip=skip)
    ctx.made.key_choice = choice
    ctx.add_to_record(key=choice)
    if "graphcut" in choice["layers"] and "refine" in ctx.steps:
        ctx.announce("refine", [("refine", total)])
    base = take_key_params(ctx.take.rig, key_mode=choice["mode"]).to_dict()
    volume = _volume_bounds(ctx).tolist() if "volume" in choice["layers"] else None
    done = 0
    ctx.report_progress("key", 0, total)
    # OpenCV's thread pool does not survive fork(): forked workers key nothing, this process does
    where = ctx if not forking_pool(ctx.executor) else replace(ctx, executor=None)
    threads = 1 if where.executor else 2
    # masks unpacked as each camera arrives; those done are stored once a worker falls idle
    # (the last cameras still keying: a core is free then), the rest at the end: few updates of
    # the derived data (each copies it), at most ~512 MB of masks a batch
    groups = _camera_groups(ctx.take.cameras, where.executor)
    pending = len(groups)
    overlap_at = max(1, pool_size(where.executor) - 1) if where.executor is not None else 0
    batch: list = []
    for results in where.map_tasks([partial(key_task, str(ctx.take.path), g, base, threads, volume, skip) for g in groups]):
        pending -= 1
        for res in results:
            if res["key"] is None:
                continue
            key = res["key"]
            _keep_masks(ctx, key, res["shape"][-1])
            key.masks = np.unpackbits(key.masks, axis=-1, count=res["shape"][-1]).view(bool)
            done += len(key.valid)
            if batch and sum(k.masks.nbytes for k in batch) + key.masks.nbytes > _STORE_BATCH_BYTES:
                store_camera_keys(ctx.take.path, batch)
                batch = []
            batch.append(key)
        if batch and 0 < pending <= overlap_at:
            store_camera_keys(ctx.take.path, batch)
            batch = []
        ctx.report_progress("key", min(done, total), total)
    if batch:
        store_camera_keys(ctx.take.path, batch)


def _step_refine(ctx: RunContext) -> None:
    """The keying's ``graphcut`` layer: every camera's masks keyed in this run cut again with colour
    models seeded by a first hull (:func:`pipeline.silhouette_refine.refine_take`), stored in place."""
    layers = ctx.made.key_choice.get("layers", []) if ctx.made.key_choice else []
    if "graphcut" not in layers or not ctx.need_key:
        return
    from pipeline.silhouette_refine import refine_take

    total = ctx.take.n_sets * len(ctx.take.cameras)
    done = [0]

    def tick(n: int) -> None:
        done[0] += n
        ctx.report_progress("refine", min(done[0], total), total)

    info = refine_take(ctx.take.path, volume=_volume_bounds(ctx), progress=tick, skip_sets=ctx.skipped_sets)
    ctx.made.keyed = None  # the masks in memory are the keyer's: the surface tasks read the refined ones
    ctx.add_to_record(refine={"method": "graphcut", "masks": info["frames"], "first_hull_grid": info["grid"]})


def _keep_masks(ctx: RunContext, key, width: int) -> None:
    """Keep a camera's bit-packed masks for the surface step (within :data:`_KEEP_MASKS_BYTES`)."""
    if ctx.made.keyed is None:
        return
    ctx.made.keyed[key.camera] = (key.masks, int(width), np.asarray(key.valid, bool))
    if sum(m.nbytes for m, _, _ in ctx.made.keyed.values()) > _KEEP_MASKS_BYTES:
        ctx.made.keyed = None  # a long take: the surface tasks read the masks from it


def _kept_masks(ctx: RunContext) -> Callable[[list[int]], dict] | None:
    """Per chunk of frame sets, its masks as keyed in this run (``surface_task(masks=)``), or
    None when they are not all in memory (a resumed run, a long take)."""
    if not ctx.made.keyed or set(ctx.made.keyed) != set(ctx.take.cameras) or ctx.take.set_table is None:
        return None
    kept = [ctx.made.keyed[c] for c in ctx.take.cameras]
    widths = [w for _, w, _ in kept]
    skipped = ctx.skipped_sets

    def packed(k: int) -> list:
        if k in skipped:
            return [None] * len(kept)
        out = []
        for (m, _, valid), r in zip(kept, ctx.take.set_table[k]):
            ok = 0 <= r < len(m) and (r >= len(valid) or valid[r])  # as frame_masks
            out.append(m[r] if ok else None)
        return out

    return lambda frames: {"masks": {"widths": widths, "sets": {k: packed(k) for k in frames}}}



def _camera_groups(cameras: Sequence[str], executor) -> list[list[str]]:
    """Cameras per key task: two tasks per worker (each opens the take once; the last ones
    still key while this process stores the others' masks); one camera a task in this process
    (progress and cancellation are seen between tasks)."""
    if executor is None:
        return [[c] for c in cameras]
    n = min(len(cameras), 2 * pool_size(executor))
    return [list(cameras[i::n]) for i in range(n)]



def _volume_bounds(ctx: RunContext) -> np.ndarray:
    """Where to look for the subject: the job's volume, the rig's, else the cameras'."""
    return search_volume(ctx.params, ctx.take.rig, ctx.take.calibration)[0]


def _processing_grid(ctx: RunContext):
    """The grid of the surfaces: ``OUT/grid.json`` when an earlier run chose it, else fitted
    to the subject now (and written there)."""
    from pipeline.hull import EmptyHullError
    from pipeline.volume import Grid
    from stage.store import TakeReader

    grid_path = ctx.out / "grid.json"
    with TakeReader(ctx.take.path) as reader:
        missing = sorted(set(ctx.take.cameras) - set(reader.masks_present()))
        if missing:
            raise ProcessError(f"{ctx.take.path}: cameras {missing} have no masks; run the key step")
        if grid_path.exists():
            grid = Grid.from_dict(json.loads(grid_path.read_text()))
            ctx.made.grid_choice = json.loads(grid_path.read_text()).get("choice", {})
            return grid
        kept = _kept_masks(ctx)
        if kept is not None:  # the masks keyed in this run, in memory
            widths = [w for _, w, _ in (ctx.made.keyed[c] for c in ctx.take.cameras)]

            def masks_of(k: int):
                ms = unpack_masks(kept([k])["masks"]["sets"][k], widths)
                return ms, [c for c, m in zip(ctx.take.cameras, ms) if m is None]
        else:
            validity = mask_validity(reader, ctx.take.cameras)
            masks_of = partial(frame_masks, reader, ctx.take.cameras, validity=validity)
        if ctx.skipped_sets:
            masks_of = _without_sets(masks_of, ctx.skipped_sets, ctx.take.cameras)
        try:
            grid, ctx.made.grid_choice, hint = choose_grid(masks_of, ctx.take.calibration, ctx.take.n_sets, ctx.params,
                                                      ctx.take.rig, progress=lambda d, t: ctx.report_progress("box", d, t))
        except EmptyHullError as exc:  # said with where to look at the masks (a job's take id is its file's stem)
            take = ctx.take.path.stem
            raise ProcessError(f"{exc} (check the masks: `stage key --preview`)",
                               job_message=f"{exc} (check the masks: /ui/takes/{take} shows each camera's, e.g. "
                               f"/takes/{take}/frames/0/{ctx.take.cameras[0]}/mask.png)") from None
    if hint:
        ctx.warn(hint)
    atomic_write(grid_path, json.dumps({**grid.to_dict(), "choice": ctx.made.grid_choice}))
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
        skeleton_path(ctx.out, k).unlink(missing_ok=True)
        cams = [c for c, r in zip(ctx.take.cameras, ctx.take.set_table[k]) if r in ctx.damaged["frames"].get(c, ())]
        info = {"index": int(k), "status": "damaged", "skipped_cameras": list(ctx.take.cameras),
                "reason": f"damaged frames of camera {', '.join(cams)} in the take: the set was skipped, as asked"}
        atomic_write(ctx.out / "frames" / f"{frame_name(k)}.json", json.dumps(info))


def _step_surface(ctx: RunContext) -> None:
    """Visual hull (and depth fusion) and a surface per frame set -> ``meshes/``, ``frames/``."""
    _record_skipped(ctx)
    with ctx.part("grid"):
        grid = _processing_grid(ctx)
        ctx.add_to_record(grid=ctx.made.grid_choice)
    task = partial(
        surface_task,
        str(ctx.take.path.resolve()),
        calib_dict=ctx.take.calibration.to_dict(),
        grid_dict=grid.to_dict(),
        params=ctx.params.model_dump(),
        out=str(ctx.out.resolve()),
        # skeletons straight from the surfaces in memory when the spine step follows
        spine_params=ctx.params.spine if "spine" in ctx.steps else None,
        use_depth=uses_depth(ctx.params, all_depth=ctx.take.all_depth),
        bridge_gaps=_bridge_gaps(ctx),
    )
    ctx.run_frames("surface", task, "frames", chunk_args=_kept_masks(ctx), said_before=partial(frame_said, ctx.out))
    _write_consistency(ctx)


def _bridge_gaps(ctx: RunContext) -> float:
    """The surface step's bridging of one camera's miss (:func:`pipeline.silhouette_refine.subject_hull`):
    when every camera's masks were keyed against a plate, the gaps the keyer's closing could not
    decide by colour (the plate explains them within its noise, ``close_relative``) are bridged where
    the other cameras see the subject; off for a backdrop's keyer (its colour is chosen unlike the
    subject's) and for masks made elsewhere. Recorded in ``process.json`` (``bridge_gaps``)."""
    from stage.store import TakeReader

    with TakeReader(ctx.take.path) as r:
        keys = [(r.mask_params(c) or {}).get("key") or {} for c in ctx.take.cameras]
    plate = all(k.get("mode") == "plate" for k in keys)
    value = float(min(k.get("close_relative") or 0.0 for k in keys)) if plate and keys else 0.0
    why = ("every camera's masks keyed against a plate: the gaps of its closing (close_relative) that the plate "
           "explains are bridged where the other cameras see the subject" if value > 0 else
           "the masks were not all keyed against a plate with a closing (a backdrop's keyer or masks made elsewhere)")
    ctx.add_to_record(bridge_gaps={"relative": value, "why": why})
    return value


def _write_consistency(ctx: RunContext) -> None:
    """``OUT/consistency.json`` from the frames' records: per camera and frame set the IoU of the
    camera's mask and the projection of the surface (:mod:`pipeline.consistency`), each camera's
    median; a camera whose median is below :data:`pipeline.consistency.CONSISTENCY_WARN` is named
    in a warning, and so is one whose keyed silhouettes held more than
    :data:`pipeline.silhouette_refine.DROPPED_WARN` of pixels the subject does not explain (median
    over the frame sets; dropped before carving, :func:`pipeline.silhouette_refine.subject_hull`)."""
    from pipeline.consistency import CONSISTENCY_WARN
    from pipeline.silhouette_refine import DROPPED_WARN

    iou = np.full((len(ctx.take.cameras), ctx.take.n_sets), np.nan)
    dropped = np.full((len(ctx.take.cameras), ctx.take.n_sets), np.nan)
    for k in range(ctx.take.n_sets):
        f = ctx.out / "frames" / f"{frame_name(k)}.json"
        rec = json.loads(f.read_text()) if f.exists() else {}
        per_cam, per_drop = rec.get("consistency") or {}, rec.get("dropped") or {}
        for i, cam in enumerate(ctx.take.cameras):
            v, d = per_cam.get(cam), per_drop.get(cam)
            iou[i, k] = np.nan if v is None else v
            dropped[i, k] = np.nan if d is None else d
    seen = np.isfinite(iou).any(axis=1)
    median = {cam: (float(np.nanmedian(iou[i])) if seen[i] else None) for i, cam in enumerate(ctx.take.cameras)}
    # the frame sets where the capture volume's walls cut the subject are said once, by their own warning: a camera
    # is judged on the others (its medians there would blame its keying and calibration for the walls)
    walled = _name_poor_sets(ctx, iou)
    within = np.ones(iou.shape[1], bool)
    within[sorted(walled)] = False
    judged = np.isfinite(iou[:, within]).any(axis=1)
    median_within = {cam: (float(np.nanmedian(iou[i, within])) if judged[i] else None)
                     for i, cam in enumerate(ctx.take.cameras)}
    low = [cam for cam, m in median_within.items() if m is not None and m < CONSISTENCY_WARN]
    has_drop = np.isfinite(dropped).any(axis=1)
    drop = {cam: (float(np.nanmedian(dropped[i])) if has_drop[i] else None) for i, cam in enumerate(ctx.take.cameras)}
    dropping = [cam for cam, m in drop.items() if m is not None and m > DROPPED_WARN]
    doc = {"cameras": ctx.take.cameras, "threshold": CONSISTENCY_WARN, "median": median, "low": low,
           "walled_sets": sorted(walled), "median_within_volume": median_within,
           "iou": [[None if not np.isfinite(x) else float(x) for x in row] for row in iou],
           "dropped": drop, "dropping": dropping, "dropped_threshold": DROPPED_WARN}
    atomic_write(ctx.out / "consistency.json", json.dumps(doc))
    ctx.made.consistency = {"median": median, "low": low, "threshold": CONSISTENCY_WARN, "dropped": drop,
                       "dropping": dropping}
    for cam in low:
        msg = (f"camera {cam}: median silhouette consistency {median_within[cam]:.2f} (IoU of its masks and the projected "
               f"hull) is below {CONSISTENCY_WARN}: check its keying and calibration (report: worst frames)")
        ctx.warn(msg)
    for cam in dropping:
        msg = (f"camera {cam}: {100 * drop[cam]:.0f} % of its silhouette (median over the frame sets) is no part of "
               f"the subject the other cameras see and was dropped before carving (silhouette consistency): check "
               f"its keying (a wall, a shadow, a second person)")
        ctx.warn(msg)
    if low:  # (when every camera is explained, none cut much from the hull)
        _name_missing(ctx, np.where(within, iou, np.nan), doc)


def _name_poor_sets(ctx: RunContext, iou: np.ndarray) -> set[int]:
    """A warning naming the frame sets whose surface explains little of the silhouettes
    (:func:`pipeline.consistency.poor_sets`; the per-camera medians over a take can hide a few), and the capture
    volume's walls their surfaces reach (:func:`pipeline.consistency.walls_reached`): a subject that goes beyond
    the volume is cut off there without another word. Returns the frame sets the walls explain."""
    from pipeline.consistency import CONSISTENCY_WARN, poor_sets, walls_reached
    from pipeline.meshio import load_mesh
    from stage.messages import frames_named

    sets, median = poor_sets(iou)
    grid_path = ctx.out / "grid.json"
    if not sets or not grid_path.exists():
        return set()
    g = json.loads(grid_path.read_text())
    box = (g.get("choice") or {}).get("box") or {}
    lo = np.asarray(g["lo"], float)
    grid_bounds = np.stack([lo, lo + np.asarray(g["shape"], float) * float(g["voxel"])])
    bounds = np.full((ctx.take.n_sets, 2, 3), np.nan)
    for k in range(ctx.take.n_sets):
        path = ctx.out / "meshes" / f"{frame_name(k)}.ply"
        if path.exists():
            v, _ = load_mesh(path, largest=False)
            if len(v):
                bounds[k] = v.min(axis=0), v.max(axis=0)
    walls = walls_reached(bounds, [box["lo"], box["hi"]] if box else grid_bounds,
                          box.get("search_volume", grid_bounds), sets=sets, tol=1.5 * float(g["voxel"]))
    m = median[sets]
    def named(ks):
        return f"frame set{'s' if len(ks) > 1 else ''} {frames_named(ks)}"

    head = (f"{named(sets)}: the surface explains little of the silhouettes (median IoU over the "
            f"cameras {m.min():.2f}..{m.max():.2f}, below {CONSISTENCY_WARN})")
    if not walls:
        ctx.warn(f"{head}: check the keying and calibration of those frame sets (report: worst frames)")
        return set()
    where = ", ".join(f"{wall} ({named(ks)})" for wall, ks in walls.items())
    msg = (f"{head} and reaches the capture volume's wall at {where}: the subject goes beyond the volume there and "
           "is cut off; give a volume that holds it")
    ctx.warn(f"{msg} (--volume XMIN YMIN ZMIN XMAX YMAX ZMAX, or the rig file's [volume])",
             job_message=f"{msg} (the volume parameter, or the rig file's [volume])")
    return {k for ks in walls.values() for k in ks}


#: Frame sets (those of lowest median consistency) a hull is carved without each camera in.
MISSING_SETS = 3


def _name_missing(ctx: RunContext, iou: np.ndarray, doc: dict) -> None:
    """The cameras whose silhouettes miss part of the subject (:func:`pipeline.consistency.leave_one_out_gain`
    on the :data:`MISSING_SETS` frame sets of lowest median consistency, the surface step's
    silhouettes): ``missing`` (median gain per camera) and ``misses`` in ``consistency.json``, a
    warning naming each camera above :data:`pipeline.consistency.MISSING_WARN`. Run when some
    camera's median consistency is low: a camera that cuts a part of the subject the others see
    lowers their consistency."""
    from pipeline.consistency import MISSING_WARN, leave_one_out_gain
    from pipeline.hull import EmptyHullError, HullCarver
    from pipeline.silhouette_refine import subject_hull
    from pipeline.volume import Grid
    from stage.store import TakeReader

    finite = np.isfinite(iou)
    has = finite.any(axis=0)  # sets with no consistency at all (skipped, empty) have no median
    med = np.full(has.shape, np.nan)
    if has.any():
        med[has] = np.nanmedian(np.where(finite, iou, np.nan)[:, has], axis=0)
    sets = [int(k) for k in np.argsort(np.where(np.isfinite(med), med, np.inf))[:MISSING_SETS] if np.isfinite(med[k])]
    grid_path = ctx.out / "grid.json"
    if len(ctx.take.cameras) < 3 or not sets or not grid_path.exists():
        return
    p = ctx.params
    carver = HullCarver(ctx.take.calibration, Grid.from_dict(json.loads(grid_path.read_text())))
    gains = []
    with TakeReader(ctx.take.path) as reader:
        validity = mask_validity(reader, ctx.take.cameras)
        for k in sets:
            with frame_warnings(k):  # (what the surface's tasks said of these frame sets already: kept at DEBUG)
                ms, _ = frame_masks(reader, ctx.take.cameras, k, validity)
                try:
                    used = subject_hull(ms, carver, tolerance=p.tolerance, support_plane=p.support_plane,
                                        margin=p.silhouette_margin).masks
                except EmptyHullError:
                    continue
                gains.append(leave_one_out_gain(used, carver, tolerance=p.tolerance, support_plane=p.support_plane,
                                                margin=p.silhouette_margin))
    if not gains:
        return
    g = np.array(gains)
    has = np.isfinite(g).any(axis=0)
    with np.errstate(all="ignore"):
        gain = {cam: (float(np.nanmedian(g[:, i])) if has[i] else None) for i, cam in enumerate(ctx.take.cameras)}
    misses = [cam for cam, v in gain.items() if v is not None and v > MISSING_WARN]
    doc.update(missing=gain, misses=misses, missing_sets=sets, missing_threshold=MISSING_WARN)
    atomic_write(ctx.out / "consistency.json", json.dumps(doc))
    ctx.made.consistency.update(missing=gain, misses=misses)
    for cam in misses:
        msg = (f"camera {cam}: the hull carved without it explains the other cameras' silhouettes better (their "
               f"silhouette consistency {gain[cam]:+.2f}, median over frame sets {sets}): its silhouettes miss part of "
               f"the subject; check its keying and calibration")
        ctx.warn(msg)


def _step_spine(ctx: RunContext) -> None:
    """Per-frame skeletons -> ``skeletons/``, then their tips corresponded over time -> ``spine.json``."""
    from pipeline.frame_skeleton import FrameSkeleton, SpineParams
    from pipeline.spine import build_spine
    from pipeline.spine_format import write_spine

    n = ctx.take.n_sets
    if any(not (ctx.out / "frames" / f"{frame_name(k)}.json").exists() for k in range(n)):
        raise ProcessError(f"{ctx.out}: surfaces are missing for some frames; run the surface step")
    for k in stale_skeletons(ctx.out, n):
        ctx.made.skeletons.pop(k, None)
    ctx.run_frames("skeleton", partial(skeleton_task, str(ctx.out.resolve()), spine_params=ctx.params.spine), "skeletons",
                   suffix=".npz", said_before=partial(skeleton_said, ctx.out))
    skeletons: list[FrameSkeleton] = []
    for k in range(n):
        sk = ctx.made.skeletons[k] if k in ctx.made.skeletons else load_skeleton(skeleton_path(ctx.out, k))["skeleton"]
        sk = FrameSkeleton.empty() if sk is None else sk
        skeletons.append(sk)
        ctx.made.tip_counts[k] = sk.n_tips
    ctx.report_progress("spine", 0, 1)
    spine = build_spine(skeletons, fps=float(ctx.take.fps), units=ctx.take.calibration.units, params=SpineParams(**ctx.params.spine))
    ctx.made.spine_path = write_spine(ctx.out / "spine.json", spine)
    # how K was chosen (the mode of the tip counts, or a borderline count decided): in the report
    ctx.made.limb_count = {"K": int(spine.meta.get("K", len(spine.limb_ids))), "rule": spine.meta.get("count_rule", "mode")}
    ctx.report_progress("spine", 1, 1)


class _StepWarnings(logging.Handler):
    """The ``pipeline`` and ``stage`` loggers' warnings said in this thread, kept in ``ctx.warnings``
    (:func:`_job_warnings`)."""

    def __init__(self, ctx: RunContext, step: str) -> None:
        super().__init__(logging.WARNING)
        self.ctx, self.step, self.thread = ctx, step, threading.get_ident()

    def emit(self, record: logging.LogRecord) -> None:
        if submitted_by(record.thread) != self.thread or record.name == log.name or record.name.startswith(f"{log.name}."):
            return  # another job's thread (or its task's); the processing's own (ctx.warn keeps those itself)
        msg = f"{self.step}: {getattr(record, 'job_message', None) or record.getMessage()}"
        if msg not in self.ctx.warnings:  # (a round's armature says what the round before said)
            self.ctx.keep_warning(msg)


@contextlib.contextmanager
def _job_warnings(ctx: RunContext, step: str) -> Iterator[None]:
    """While the step runs, every warning the ``pipeline`` and ``stage`` loggers say in this thread is also one of
    the job's ``warnings`` (and ``report.json``'s), as ``"{step}: ..."``, once: what the tracking and the armature
    only logged (the spine unusable for the spine armature, ``armature_parts`` 'limbs' falling back to the motion's
    parts, the frames of other settings tracked again...), what the keying says of a camera (a plate from the take
    that is unreliable, a camera without frames), reaches an API user, who sees no log. Every step runs in one
    (:func:`pipeline.process.process_take`); a step run by another (the rig's tracking) says its own name. What a
    per-frame task warns of while it works on a frame set is not said here one frame at a time: the step says it
    once per kind, with the frame sets (:func:`pipeline.run.frame_warnings`,
    :meth:`~pipeline.process.context.RunContext.run_frames`).

    The warnings are caught as they are said rather than derived from the reports the functions return
    (``track.json``): one mechanism for every message, with its reason, and a warning added to these functions
    later reaches the job without a change here; a report says what was used, not always why nor every fallback
    (the first of ``carve`` rounds' trackings' start-over is in no returned report). A message that names a
    command line option or a function's keyword says it in the job's parameters in the record's ``job_message``
    (``log.warning(..., extra={"job_message": ...})``, as :class:`~pipeline.process.params.ProcessError`'s
    ``job_message``), which is kept instead. Only this thread's records (a server runs several jobs at once) and
    those of the tasks it submits: a task in a worker process (the carve's and the tracking's half aside, a Dask
    worker's) has its warnings said again in this thread when its result is taken (:func:`pipeline.run.submit_aside`,
    :meth:`pipeline.run.Run.map_tasks`), a task in a thread pool's thread is this thread's
    (:func:`pipeline.run.submitted_by`)."""
    active = _STEP_WARNINGS.get()
    if active is not None and active.ctx is ctx:  # a step within a step (the rig's tracking): said as the inner one
        was, active.step = active.step, step
        try:
            yield
        finally:
            active.step = was
        return
    keep = _StepWarnings(ctx, step)
    token = _STEP_WARNINGS.set(keep)
    loggers = [logging.getLogger(name) for name in ("pipeline", "stage")]
    for logger in loggers:
        logger.addHandler(keep)
    try:
        yield
    finally:
        for logger in loggers:
            logger.removeHandler(keep)
        _STEP_WARNINGS.reset(token)


#: the handler of the step running in this thread (:func:`_job_warnings`)
_STEP_WARNINGS: contextvars.ContextVar[_StepWarnings | None] = contextvars.ContextVar("step_warnings", default=None)


def _need_surfaces(ctx: RunContext, step: str) -> None:
    """The surfaces the track step follows (``meshes/frame_NNNNNN.ply``), or a ProcessError in the words of the
    steps (a job's, and process_take's with these steps), which name no command."""
    if not any((ctx.out / "meshes").glob("frame_*.ply")):
        raise ProcessError(f"{step}: the take has no surfaces to track yet (meshes/frame_NNNNNN.ply): "
                           "run the surface step first")


def _step_track(ctx: RunContext) -> None:
    """The first surface tracked through the take -> ``tracked/`` (:func:`pipeline.carve.track_with_carving`
    with ``ProcessParams.track``; with the template's limb/body labels too when the job's rig takes its parts from
    them, ``rig.parts="limbs"``: :attr:`~pipeline.process.ProcessParams.track_labels`), then tracked again with an
    armature as the articulated prior for ``track.armature_rounds`` (:func:`pipeline.track_armature.track_with_armature`),
    as ``stage track`` does. What
    these functions warn of (frames of other settings tracked again, a fallback of the armature rounds...) is in the
    job report too (:func:`_job_warnings`)."""
    from pipeline.carve import track_with_carving

    _need_surfaces(ctx, "track")
    if "rig" in ctx.steps:  # a rest frame past the surfaces is said before the tracking, which could not help
        _check_rig_reference(ctx, len(list((ctx.out / "meshes").glob("frame_*.ply"))))
    opt = ctx.params.track
    labels = ctx.params.track_labels  # (track.labels, or the rig's parts from the labels)
    # (one run: what the first tracking, each carve round and each armature round say of the surfaces, once)
    with _job_warnings(ctx, "track"), once_per_run():  # (the start-over of frames of other settings, a fallback...)
        rep = track_with_carving(ctx.out, opt.carve, margin=opt.carve_margin, progress=ctx.report_progress,
                                 executor=ctx.executor, colour=opt.colour, shape_memory=opt.shape_memory,
                                 labels="spine" if labels else None)
        ctx.clock.add_worker_cpu("track", rep.get("worker_cpu_seconds", 0.0))
        if opt.armature_rounds:
            from pipeline.track_armature import track_with_armature

            rep = track_with_armature(ctx.out, rounds=opt.armature_rounds, colour=opt.colour, spine=opt.spine_armature,
                                      progress=ctx.report_progress, executor=ctx.executor,
                                      labels="spine" if labels else None, parts=opt.armature_parts)
            ctx.clock.add_worker_cpu("track", rep["rig_prior"].get("worker_cpu_seconds", 0.0))


def _surface_totals(ctx: RunContext) -> list[tuple[str, int]]:
    box = [] if (ctx.out / "grid.json").exists() else [("box", ctx.take.n_sets)]  # the grid is chosen once
    return [*box, ("surface", ctx.take.n_sets)]


register_step("key", _step_key, doc="keying masks into the take",
              totals=lambda ctx: [("key", ctx.take.n_sets * len(ctx.take.cameras))])
register_step("refine", _step_refine, doc="graph-cut refinement of the masks (the keying's graphcut layer)")  # announced by key
register_step("surface", _step_surface, doc="visual hull and surface per frame set", totals=_surface_totals)
register_step("spine", _step_spine, doc="per-frame skeletons and the take's spine",
              totals=lambda ctx: [("skeleton", ctx.take.n_sets), ("spine", 1)])


def _step_rig(ctx: RunContext) -> None:
    """Articulated rig from the tracked template (``tracked/``) -> ``rig/`` (``ProcessParams.rig``). Without a
    tracked template the track step runs first (:func:`_step_track`; a warning in the job report says so); what
    the armature's building warns of (parts from the limbs that fall back to the motion segmentation, and why:
    a template tracked without its labels...) is in the job report too (:func:`_job_warnings`), and so is an
    armature of one segment (nothing bends)."""
    from pipeline.armature_files import NoTrackingError, armature_results, tracked_meshes

    limbs = ctx.params.rig.parts == "limbs"
    if ctx.take.n_sets < 2:  # before any tracking, which could not help
        raise ProcessError("rig: the take has one frame set: an armature is found from how the subject moves; it needs "
                           "2 frame sets or more")
    try:
        tracked_meshes(ctx.out)
    except NoTrackingError:
        if "track" not in ctx.steps:
            msg = "rig: the take had no tracked template: the track step ran first (with the job's track parameters" + \
                  (" and the template's labels, for rig parts 'limbs')" if limbs else ")")
            ctx.keep_warning(msg)
            log.warning("%s", msg)
            _need_surfaces(ctx, "rig")
            with ctx.part("track"):  # its seconds are the tracking's, not the rig's
                _step_track(ctx)
    opt = ctx.params.rig
    try:
        _check_rig_reference(ctx, len(tracked_meshes(ctx.out)))
        with _job_warnings(ctx, "rig"):  # (parts 'limbs' falling back to the motion segmentation, and why...)
            rig = armature_results(ctx.out, units=ctx.take.calibration.units, fps=float(ctx.take.fps),
                                   progress=lambda s, d, t: ctx.report_progress(f"rig {s}", d, t), parts=opt.parts,
                                   lambda_thr=opt.lambda_thr, n_samples=opt.samples, reference=opt.reference)
    except NoTrackingError as exc:
        raise ProcessError(f"rig: {exc}") from None
    if rig.segmentation.n_segments == 1:  # as stage armature says it: the report's one segment is no failure
        ctx.warn("rig: nothing bends in this take: one segment, the armature moves rigidly")


def _check_rig_reference(ctx: RunContext, frames: int) -> None:
    """``rig.reference`` within the ``frames`` the armature is built from (the surfaces before the tracking, the
    tracked frames after it), as ``stage armature --reference`` is (:func:`pipeline.armature.check_armature_options`)."""
    from pipeline.armature import check_armature_options

    try:
        check_armature_options(reference=ctx.params.rig.reference, frames=frames, names={"reference": "rig.reference"})
    except ValueError as exc:
        raise ProcessError(f"rig: {exc}") from None


def _track_totals(ctx: RunContext) -> list[tuple[str, int]]:
    """The tracking, then per round of carving the carve and the tracking again (:func:`pipeline.carve.track_with_carving`),
    then every armature round that may run (:func:`pipeline.track_armature.track_with_armature`; those that do
    not, the rounds stop when one does not help, are closed when the step ends)."""
    from pipeline.track_armature import AUTO_RIG_ROUNDS

    opt = ctx.params.track
    rounds = [(f"{what} round {r}", ctx.take.n_sets) for r in range(1, opt.carve + 1) for what in ("carve", "track")]
    most = 0 if not opt.armature_rounds else (AUTO_RIG_ROUNDS if opt.armature_rounds == "auto" else opt.armature_rounds)
    most += bool(most and opt.spine_armature)  # the spine's round comes first
    rig = [(f"track with the rig round {r}", ctx.take.n_sets) for r in range(1, most + 1)]
    return [("track", ctx.take.n_sets), *rounds, *rig]


register_step("rig", _step_rig, doc="articulated rig from the tracked template (Tzionas & Gall 2016)", after="spine",
              totals=lambda ctx: [("rig segmentation", 1), ("rig skeleton", 1), ("rig fit", ctx.take.n_sets),
                                  ("rig write", ctx.take.n_sets)])
register_step("track", _step_track, doc="template tracking of the surfaces (only when asked for)", after="spine",
              totals=_track_totals)
# what runs when no steps are given: tracking and the rig on it are asked for (``stage track``,
# ``stage rig`` or a job's steps); a plain run does not warn about a rig it was not asked for
DEFAULT_STEPS: tuple[str, ...] = tuple(s for s in STEPS if s not in ("track", "rig"))


def check_job_steps(steps) -> None:
    """The steps of a job of the API, whose results folder starts empty: a step that works on the surfaces
    (``spine``, ``track``, ``rig``) needs the ``surface`` step in the same job, or it could only fail.

    Parameters
    ----------
    steps : list or tuple of str
        Names in :data:`STEPS`.

    Raises
    ------
    ValueError
        Naming ``steps``, what needs the surfaces and the steps to give instead.
    """
    if not isinstance(steps, (list, tuple)) or not all(isinstance(s, str) for s in steps):
        raise ValueError(f"steps must be a sequence of step names, got {steps!r}")
    given = set(steps)
    need = [s for s in STEPS if s in given and s in ("spine", "track", "rig")]
    if need and "surface" not in given:
        example = [s for s in STEPS if s in given or (s in DEFAULT_STEPS and s != "refine")]  # all the job gave
        raise ValueError(f"steps: {', '.join(need)} {'works' if len(need) == 1 else 'work'} on the surfaces the job "
                         f"makes itself (a job's results start empty): add the surface step, e.g. steps {example}")
