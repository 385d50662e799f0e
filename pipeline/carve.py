"""``stage track --carve``: every frame's surface carved across time with the tracked motion -> ``carved/``.

A results directory's tracked template (``tracked/NNNNNN.ply``) says how every surface point
moves; :func:`pipeline.temporal_hull.carve_across_time` then carves each frame's hull with the
silhouettes of the frames around it, and the surfaces written to ``carved/frame_NNNNNN.ply``
are what ``track_results(surfaces="carved")`` tracks again (docs/tracking.md, "Surfaces
carved across time"). ``carved/carve.json`` holds the settings, the digest of the
``tracked/track.json`` whose motion carved them and per-frame figures; a killed run resumes,
keeping the frames of the same settings and motion.
"""

from __future__ import annotations

import contextlib
import json
import logging
from concurrent.futures import BrokenExecutor
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.results import atomic_write_bytes, ply_bytes
from pipeline.run.context import frame_warnings, frames_said, once_per_run, submit_aside
from pipeline.run.settings import changed_settings, file_digest, read_settings

__all__ = ["carve_results", "carve_frames_task", "carved_path", "remove_carved", "track_with_carving", "CarveError",
           "CARVED_DIR"]

log = logging.getLogger(__name__)


class CarveError(ValueError):
    """A carving that cannot run (no take, masks or calibration, an unreadable record), from
    :func:`track_with_carving`."""


#: The folder of a results directory that holds the carved surfaces.
CARVED_DIR = "carved"


def carved_path(out_dir, frame: int) -> Path:
    """``OUT/carved/frame_NNNNNN.ply``."""
    return Path(out_dir) / CARVED_DIR / f"frame_{int(frame):06d}.ply"


def _take_path(root: Path, process: dict) -> Path:
    """The take a results directory came from (``process.json``, read), or a ValueError saying why not."""
    take = process.get("take") if isinstance(process, dict) else None
    if not isinstance(take, str):
        raise ValueError(f"{root / 'process.json'} names no take; carving needs its masks")
    if not Path(take).is_file():
        raise ValueError(f"{root}: the take {take} is not there; carving needs its masks and calibration")
    return Path(take)


def _tracked(root: Path) -> dict:
    """Frame -> tracked template vertices of every frame ``tracked/track.json`` lists."""
    from pipeline.meshio import load_mesh

    report = root / "tracked" / "track.json"
    try:
        frames = json.loads(report.read_text())["frames"]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{report}: unreadable ({exc}); run `stage track` first") from None
    out: dict = {}
    for k in sorted(int(f) for f in frames):
        path = root / "tracked" / f"{k:06d}.ply"
        try:
            out[k] = load_mesh(path, largest=False)[0]
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: unreadable ({exc}); run `stage track` again") from None
        first = out[min(out)]
        if out[k].shape != first.shape:
            raise ValueError(f"{path}: {len(out[k])} vertices, not the template's {len(first)}; run `stage track` again")
    if len(out) < 2:
        raise ValueError(f"{report}: {len(out)} tracked frame(s); carving across time needs two or more")
    return out


def _images_of(rd, cameras: list):
    """``images(k)``: every camera's signed distance image of frame set ``k`` (None where it has no
    mask, or its mask cannot be read: one warning per camera, and that view carves nothing)."""
    from pipeline.temporal_hull import signed_distance_image
    from stage.store import TakeError

    warned: set = set()

    def mask(c, rows, k):
        try:
            r = rows.get(c, -1)
            return rd.mask(c, r) if r >= 0 else None
        except (IndexError, TakeError, OSError) as exc:  # truncated masks, read error
            if c not in warned:
                warned.add(c)
                log.warning("carving: camera %s, frame set %d has no readable mask (%s); "
                            "its views that cannot be read carve nothing", c, k, exc)
            return None

    def images(k):
        rows = rd.set_rows(k)
        masks = [mask(c, rows, k) for c in cameras]
        return [None if m is None else signed_distance_image(np.asarray(m, bool)) for m in masks]

    return images


def _read_json(path: Path, what: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable ({exc}); {what}") from None


def carve_results(results_dir, *, window: int = 15, neighbours: int = 100, band: float = 3.0, ignore: int = 1,
                  margin: float | None = None, progress=None, executor=None) -> dict:
    """Carve every tracked frame's surface across time into ``carved/frame_NNNNNN.ply``.

    Parameters
    ----------
    results_dir : path
        A ``stage process`` results directory after ``stage track`` (``grid.json``,
        ``process.json`` naming the take, whose masks and calibration are read, ``tracked/``).
    window : int, optional
        Each frame is carved by the ``2 * window`` tracked frames nearest it (as many before as
        after it, more on one side at the take's ends, so that every frame gets as many views:
        a frame carved by fewer is looser, and the tracked volume would change with it). The
        work grows with the take's length times the window, not with its square.
    neighbours, band, ignore
        See :func:`pipeline.temporal_hull.carve_across_time`.
    margin : float, optional
        Pixels by which every camera's silhouettes are grown. Default, per camera: twice the
        reprojection error its calibration records of itself
        (:meth:`calib.calibration.Calibration.reprojection_error_px`: held-out RMS where
        ``stage calibrate`` measured it, 0 for a simulator's true cameras), at most the
        ``silhouette_margin`` that ``stage process`` carved the take's hulls with
        (``process.json``); that margin for a camera the calibration says nothing of. Across
        time a point meets some 30 times more silhouettes than one frame's hull: what a
        camera's calibration is off by would shave thin parts all the more, and the
        calibration's own residual says by how much.
    progress : callable(step, done, total), optional
    executor : concurrent.futures.Executor, optional
        Carves the second half of the frames to carve (a process pool:
        :func:`carve_frames_task` is its task) while this process carves the first; the
        surfaces are the same either way (every frame is carved on its own).

    Returns
    -------
    dict
        The report written to ``carved/carve.json`` (``worker_cpu_seconds``: the CPU seconds of the
        frames carved in another process). What a frame's carving warns of (its carved surface left
        out...) is in its figures (``warnings``) and said once per kind for the frames carved now, with
        the frame sets (:func:`pipeline.run.frame_warnings`).

    Raises
    ------
    ValueError
        No tracking, no take, masks or calibration to carve with.
    """
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window must be an integer >= 1 (frames), got {window!r}")
    root = Path(results_dir)
    tracks = _tracked(root)
    from pipeline.volume import Grid

    process = _read_json(root / "process.json", "carving needs the take it names")
    take, params = _take_path(root, process), process.get("params", {})
    grid = Grid.from_dict(_read_json(root / "grid.json", "carving needs the grid of `stage process`"))
    margin = _default_margins(take, float(params.get("silhouette_margin", 0))) if margin is None else float(margin)
    report = {"tracked_sha256": file_digest(root / "tracked" / "track.json"), "window": int(window),
              "neighbours": int(neighbours), "band": float(band), "ignore": int(ignore), "margin_px": margin,
              "taubin_iterations": int(params.get("smooth_iterations", 10)), "frames": {}}
    settings = {k: report[k] for k in ("window", "neighbours", "band", "ignore", "margin_px", "taubin_iterations")}
    kept = _start_over_if_changed(root, report)
    frames = list(tracks)
    todo = [k for k in frames if not (str(k) in kept and carved_path(root, k).is_file())]
    report["frames"] = {str(k): kept[str(k)] for k in frames if k not in todo}
    done = [len(report["frames"])]

    def record(k, figures):
        report["frames"][str(k)] = figures
        _write_report(root, report)
        done[0] += 1
        if progress is not None:
            progress("carve", done[0], len(frames))

    here, there = (todo[: (len(todo) + 1) // 2], todo[(len(todo) + 1) // 2:]) if executor is not None else (todo, [])
    job = {"root": str(root), "take": str(take), "grid": grid.to_dict(), "frames": there, "settings": settings}
    aside = submit_aside(executor if there else None, partial(carve_frames_task, job),
                         unavailable="carving: the worker process is not available ({exc}); carving its frames here",
                         logger=log)
    if aside is None:
        here, there = todo, []
    _carve_frames(root, take, grid, here, tracks, settings, record)
    if aside is not None:
        try:
            figures = aside.result()
        except BrokenExecutor as exc:  # the worker died: its frames are carved here
            log.warning("carving: the worker process failed (%s); carving its frames here", exc)
            figures = _carve_frames(root, take, grid, [k for k in there if not carved_path(root, k).is_file()], tracks,
                                    settings)
        for k in there:
            if str(k) in figures:
                record(k, figures[str(k)])
    report["frames"] = {str(k): report["frames"][str(k)] for k in frames if str(k) in report["frames"]}
    said = {k: [(m, None) for m in report["frames"][str(k)].get("warnings", ())] for k in todo
            if str(k) in report["frames"]}
    for msg, _ in frames_said("carving", said):  # what the frames carved now warned of, once per kind
        log.warning("%s", msg)
    # a thread's CPU seconds are already this process's; None: no worker carved
    report["worker_cpu_seconds"] = round(aside.cpu_seconds, 3) if aside is not None and aside.cpu_seconds is not None \
        else 0.0
    _write_report(root, report)
    return report


#: Silhouettes grow by this many times a camera's recorded reprojection error (RMS, pixels): the
#: error of most points' projections, not only of a typical one.
MARGIN_PER_RMS = 2.0


def _default_margins(take: Path, hull_margin: float) -> dict:
    """Camera -> pixels its silhouettes grow by (see :func:`carve_results`, ``margin``)."""
    from stage.store import TakeError, TakeReader

    try:
        with TakeReader(take) as rd:
            calib = rd.calibration
    except (OSError, TakeError) as exc:
        raise ValueError(f"{take}: unreadable ({exc}); carving needs its masks and calibration") from None
    if calib is None:
        raise ValueError(f"{take}: no calibration; carving needs the cameras")
    known = calib.reprojection_error_px()
    return {n: min(hull_margin, MARGIN_PER_RMS * known[n]) if n in known else hull_margin for n in calib.names}


@once_per_run()  # (what every round's tracking says of the surfaces: once)
def track_with_carving(results_dir, rounds: int, *, margin: float | None = None, progress=None, executor=None,
                       **track_options) -> dict:
    """Track the surfaces of ``stage process``, then ``rounds`` times carve them across time with
    the tracked motion and track the carved surfaces (``stage track --carve ROUNDS``, the
    ``track`` step with ``ProcessParams.track.carve``).

    Parameters
    ----------
    results_dir : path
        A ``stage process`` results directory.
    rounds : int
        Carvings (0: the tracking of ``meshes/`` alone).
    margin, progress, executor
        See :func:`carve_results`; ``progress`` and ``executor`` serve the trackings too (the steps
        of round ``r`` are reported as ``"carve round r"`` and ``"track round r"``).
    **track_options
        Keywords of :func:`pipeline.track.track_results` (``colour``, ``shape_memory``...), the
        same for every round.

    Returns
    -------
    dict
        The last tracking's report (``tracked/track.json``), its ``worker_cpu_seconds`` the CPU
        seconds of every tracking's and carving's task in other processes.

    Raises
    ------
    CarveError
        A carving cannot run (:func:`carve_results`' ValueError).
    """
    from pipeline.track import track_results

    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 0:
        raise ValueError(f"rounds must be an integer >= 0, got {rounds!r}")
    rep = track_results(results_dir, progress=progress, executor=executor, **track_options)
    worker_cpu = rep.get("worker_cpu_seconds", 0.0)
    for r in range(1, int(rounds) + 1):
        named = _in_round(progress, r)
        try:
            carved = carve_results(results_dir, margin=margin, progress=named, executor=executor)
        except ValueError as exc:
            raise CarveError(str(exc)) from None
        rep = track_results(results_dir, surfaces="carved", progress=named, executor=executor, **track_options)
        worker_cpu += carved.get("worker_cpu_seconds", 0.0) + rep.get("worker_cpu_seconds", 0.0)
    return {**rep, "worker_cpu_seconds": round(worker_cpu, 3)}


def _in_round(progress, r: int):
    """``progress`` with the steps of round ``r`` named ``"carve round r"``, ``"track round r"``
    (each round's progress counts on its own, never back from the last round's total)."""
    if progress is None:
        return None
    return lambda step, done, total: progress(f"{step} round {r}", done, total)


def carve_frames_task(job: dict) -> dict:
    """Some frames of a results directory carved in a worker process (see :func:`carve_results`);
    -> their per-frame figures by frame (``carve.json`` is written by the caller)."""
    from pipeline.volume import Grid

    root = Path(job["root"])
    return _carve_frames(root, Path(job["take"]), Grid.from_dict(job["grid"]), list(job["frames"]), _tracked(root),
                         job["settings"])


def _carve_frames(root: Path, take: Path, grid, todo: list, tracks: dict, settings: dict, record=None) -> dict:
    """Carve the frames ``todo`` into ``carved/``; ``record(frame, figures)`` after each; -> figures by frame."""
    from pipeline.mesh_primitives import mesh_volume
    from pipeline.surface import EmptySurfaceError, surface_from_field
    from pipeline.temporal_hull import carve_across_time

    out: dict = {}
    if not todo:
        return out
    frames, window = list(tracks), settings["window"]
    from stage.store import TakeReader

    with TakeReader(take) as rd:
        cameras, images_of = _cameras(rd)
        m = settings["margin_px"]
        margin = [float(m.get(c.name, 0.0)) for c in cameras] if isinstance(m, dict) else float(m)
        cache: dict = {}
        for k in todo:
            near = sorted(sorted(frames, key=lambda s: (abs(s - k), s))[:2 * window + 1])
            for s in [s for s in cache if s not in near]:
                del cache[s]  # only the window's images are held
            for s in near:
                if s not in cache:
                    cache[s] = images_of(s)
            with frame_warnings(k) as said:  # said once per kind by carve_results, with the frame sets
                field = carve_across_time(grid, k, {s: tracks[s] for s in near}, cache, cameras,
                                          band=settings["band"], neighbours=settings["neighbours"],
                                          ignore=settings["ignore"], margin=margin)
                try:
                    mesh = surface_from_field(field, grid, level=0.0, inside="above",
                                              taubin_iterations=settings["taubin_iterations"])
                except EmptySurfaceError as exc:
                    log.warning("%s; the carved surface is left out", exc)
                    out[str(k)] = {"vertices": 0}
                else:
                    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
                    atomic_write_bytes(carved_path(root, k), ply_bytes(V, F))
                    out[str(k)] = {"vertices": int(len(V)), "volume_mm3": float(mesh_volume(V, F))}
            if said:
                out[str(k)]["warnings"] = list(dict.fromkeys(m for m, _ in said))
            if record is not None:
                record(k, out[str(k)])
    return out


def _cameras(rd):
    """(calibrated cameras with masks, ``images(k)`` of theirs) of an open take, or a ValueError."""
    calib = rd.calibration
    if calib is None:
        raise ValueError(f"{rd.path}: no calibration; carving needs the cameras")
    keyed = set(rd.masks_present())
    names = [c for c in calib.names if c in keyed and c in rd.cameras]
    if not names:
        raise ValueError(f"{rd.path}: no camera has both a calibration and masks; run the key step")
    return [calib[calib.names.index(c)] for c in names], _images_of(rd, names)


def _write_report(root: Path, report: dict) -> None:
    atomic_write_bytes(root / CARVED_DIR / "carve.json", json.dumps(report, indent=1).encode())


def _start_over_if_changed(root: Path, report: dict) -> dict:
    """Per-frame figures of an earlier run with the same settings and motion (kept), else ``{}``
    and the old carved frames removed first."""
    old = read_settings(root / CARVED_DIR / "carve.json")
    if old is not None and not changed_settings(old, report, results={"frames"}):
        return old.get("frames", {}) if isinstance(old.get("frames"), dict) else {}
    _remove_frames(root)
    return {}


def _remove_frames(root: Path) -> int:
    """Remove ``carved/frame_NNNNNN.ply``; -> how many there were."""
    files = list((root / CARVED_DIR).glob("frame_*.ply"))
    for f in files:
        f.unlink(missing_ok=True)
    return len(files)


def remove_carved(out_dir) -> str:
    """Remove the surfaces carved with the tracked motion (``carved/``: ``frame_NNNNNN.ply`` and
    ``carve.json``; the folder too when that leaves it empty), as a tracking start-over does
    (:func:`pipeline.track.remove_tracking`); -> what its warning says of it (``""``: nothing there)."""
    carved = Path(out_dir) / CARVED_DIR
    files = _remove_frames(Path(out_dir))
    if (carved / "carve.json").is_file():
        (carved / "carve.json").unlink()
        files += 1
    with contextlib.suppress(OSError):  # not there, or not empty: kept
        carved.rmdir()
    return f"; removed the surfaces carved with that motion ({carved})" if files else ""
