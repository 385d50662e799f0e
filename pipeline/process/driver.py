"""Run the steps over a take: check the take and the job, start over or resume, write the report."""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from calib.fileio import atomic_write, json_default
from pipeline.process.context import Made, RunContext, TakeFacts
from pipeline.process.grid import MAX_VOXELS
from pipeline.process.params import ProcessError, ProcessParams, ProcessResult, check_params
from pipeline.process.records import frame_name
from pipeline.process.steps import DEFAULT_STEPS, STEPS, _job_warnings
from pipeline.process.tasks import every_camera_has_depth, warm_task
from pipeline.run.settings import changed_settings, read_settings
from stage.store.space import check_free_space, raise_disk_full

__all__ = ["process_take"]

log = logging.getLogger("pipeline.process")


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
        said = f"{damage.summary()}; nothing was processed"
        raise ProcessError(f"{said} (`stage verify {take}` lists the damage)"
                           + ("" if skip else "; --skip-damaged processes the other frame sets"),
                           job_message=said + ("" if skip else "; parameters.skip_damaged = true processes the other "
                                               "frame sets"))
    msg = f"{damage.summary()}: these frame sets are skipped (no surface, no skeleton)"
    log.warning("%s", msg)
    return {"sets": list(damage.sets), "frames": {c: list(v) for c, v in damage.frames.items()}, "summary": msg}


def _open_context(take: Path, out: Path, params: ProcessParams, **hooks) -> RunContext:
    """Read what every step needs from the take once (and check it can be processed)."""
    from stage.store import TakeReader

    with TakeReader(take) as reader:
        if not reader.has_calibration:
            raise ProcessError(f"{take}: the take has no calibration; run `stage calibrate` first",
                               job_message=f"{take}: the take has no calibration; a job processes a take recorded or "
                               "imported with its calibration")
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
        all_depth = every_camera_has_depth(reader, cameras)
        table = reader.set_table()
        set_table = table[:, [list(reader.cameras).index(c) for c in cameras]]
    if n_sets == 0:
        raise ProcessError(f"{take}: the take holds no frame sets")
    # skipping needs the damage's frame sets on a resumed run too (its surfaces read the take)
    damaged = _check_frames(take, skip=params.skip_damaged) if need_key or params.photo_refine or params.skip_damaged else {}
    calibration = type(calibration)(tuple(calibration[c] for c in cameras), units=calibration.units, meta=calibration.meta)
    facts = TakeFacts(path=take, calibration=calibration, cameras=cameras, n_sets=n_sets, fps=float(fps), rig=rig,
                      all_depth=all_depth, set_table=set_table)
    ctx = RunContext(out=out, params=params, need_key=need_key, take=facts, made=Made(tip_counts=[None] * n_sets),
                     **hooks)
    if damaged:
        ctx.damaged = damaged
        ctx.keep_warning(damaged["summary"])
    return ctx


def _start_record(ctx: RunContext) -> None:
    """Write ``process.json``; results of other parameters or another take are removed first."""
    record = {"take": str(ctx.take.path.resolve()), "params": ctx.params.model_dump(), "frames": ctx.take.n_sets,
              "cameras": ctx.take.cameras}
    if ctx.damaged:
        record["damaged"] = ctx.damaged
    prev = ctx.out / "process.json"
    if prev.exists():  # an unreadable one says nothing of its results: they are made again
        old = read_settings(prev)
        now = {"take": record["take"], "params": _compared(record["params"])}
        if old is None or changed_settings(old, now, was=lambda o, k, _: _compared(o.get(k)) if k == "params" else o.get(k)):
            _start_over(ctx)
    atomic_write(prev, json.dumps(record, indent=2))


def _compared(params) -> object:
    """The parameters a start-over compares: all but the ``track`` and ``rig`` steps' (the tracking compares its
    own; the rig is built again every run)."""
    return {k: v for k, v in params.items() if k not in ("track", "rig")} if isinstance(params, dict) else params


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
    ctx.warn(msg)


#: Files of a results directory made from its frames and spine, removed when it starts over.
_MADE_FROM_FRAMES = ("report.json", "report.html", "spine_rig.glb", "spine.glb", "consistency.json")


def _write_report(ctx: RunContext, steps: tuple[str, ...], t_start: float) -> ProcessResult:
    frame_infos: dict[int, dict] = {}
    for k in range(ctx.take.n_sets):
        f = ctx.out / "frames" / f"{frame_name(k)}.json"
        if f.exists():
            frame_infos[k] = json.loads(f.read_text())
    empty = sorted(k for k, i in frame_infos.items() if i.get("status") not in ("ok", "damaged"))
    if not ctx.made.consistency and (ctx.out / "consistency.json").is_file():  # made by an earlier run's surface step
        doc = json.loads((ctx.out / "consistency.json").read_text())
        ctx.made.consistency = {k: doc.get(k) for k in ("median", "low", "threshold")}
    report = {
        "take": str(ctx.take.path.resolve()),
        "frames": ctx.take.n_sets,
        "cameras": ctx.take.cameras,
        "steps": list(steps),
        "seconds": ctx.clock.wall,
        "cpu_seconds": ctx.clock.cpu,
        "total_seconds": time.perf_counter() - t_start,
        "empty_frames": empty,
        "damaged_sets": sorted(ctx.skipped_sets),
        "tip_counts": ctx.made.tip_counts,
        "per_frame": [frame_infos.get(k) for k in range(ctx.take.n_sets)],
        "warnings": ctx.warnings,
        "grid": ctx.made.grid_choice,
        "limb_count": ctx.made.limb_count,
        "consistency": ctx.made.consistency,
    }
    if "rig" in steps:  # the job's armature: its segments and joints (the results' listing shows the same)
        from pipeline.armature_files import armature_summary

        report["rig"] = armature_summary(ctx.out / "rig" / "rig.json")
    atomic_write(ctx.out / "report.json", json.dumps(report, indent=1, default=json_default))
    return ProcessResult(
        out=ctx.out, steps=steps, frames=ctx.take.n_sets, empty_frames=empty, spine_path=ctx.made.spine_path, report=report
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
    warn: Callable[[str], None] | None = None,
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
        ``progress(name, done, total)`` after every finished chunk of frames, ``name`` a progress entry (a step's
        part: ``box`` of ``surface``...); one that takes ``of_step`` is told the step the entry belongs to too
        (the one that announced it: :meth:`pipeline.run.Run.step_of`).
    cancel : threading.Event, optional
        Set it to stop between chunks (``InterruptedError``); finished frames stay, in a folder this run made too
        (a run that fails otherwise removes a folder it made), and a later run resumes from them.
    warn : callable, optional
        ``warn(message)`` as each of the run's warnings is said (those of ``report.json``, in its words): a caller
        keeps those said before a step fails or the run is cancelled, which no report holds (a job's record does).

    Returns
    -------
    ProcessResult
    """
    take, out = Path(take), Path(out)
    steps = DEFAULT_STEPS if steps is None else tuple(steps)
    bad = [s for s in steps if s not in STEPS]
    if bad or not steps:
        raise ValueError(f"steps must be a non-empty subset of {tuple(STEPS)}, got {steps}")
    if "key" in steps:
        steps = (*steps, "refine")  # keying's graphcut layer (a no-op without it)
    steps = tuple(s for s in STEPS if s in steps)
    params = check_params(params)
    if warn is not None and not callable(warn):
        raise ValueError(f"warn must be a callable taking a message, or None, got {type(warn).__name__}")
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
        ctx = _open_context(take, out, params, executor=executor, progress=progress, cancel=cancel, on_warning=warn)
        ctx.steps = steps
        need = _space_needed(ctx, steps)
        with raise_disk_full(out, "the processing results", need,
                             detail="the take is unchanged; free space and run again"):
            check_free_space(out, need, f"processing {ctx.take.n_sets} frame sets of {take.name}")
            out.mkdir(parents=True, exist_ok=True)
            _start_record(ctx)
            for name in steps:  # the run's total counts every step it will run
                if STEPS.step(name).totals is not None:
                    ctx.announce(name, STEPS.step(name).totals(ctx))
            for name in steps:
                with _job_warnings(ctx, name):  # what the step's functions warn of is the run's warnings too
                    ctx.run_step(name, STEPS.step(name).run)
            return _write_report(ctx, steps, t_start)
    except Exception as exc:
        # a failed run leaves no results folder it made itself; a cancelled one keeps its finished frames
        if created and out.is_dir() and not isinstance(exc, InterruptedError):
            shutil.rmtree(out, ignore_errors=True)
        raise


def _space_needed(ctx: RunContext, steps: Sequence[str]) -> int:
    """About how many bytes processing writes: compressed masks (if keying), meshes and records per frame."""
    from stage.store import TakeReader

    need = 1 << 20
    if "key" in steps and ctx.need_key:
        with TakeReader(ctx.take.path) as r:
            pixels = sum(r.n_frames(c) * int.__mul__(*r.image_size(c)) for c in ctx.take.cameras)
            old = r.derived_path.stat().st_size if r.derived_path.exists() else 0
        need += pixels // 16 + old  # the derived file is rebuilt beside the old one
    if "surface" in steps or "spine" in steps:
        res = ctx.params.resolution or round(MAX_VOXELS ** (1 / 3))  # chosen later from the rig: at most this
        need += ctx.take.n_sets * (64 * res**2 + (16 << 10))
    return need

