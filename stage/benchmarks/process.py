"""``stage bench process``: ``stage process`` end to end against the speed of its parts.

A simulated take (the demo's by default: the starfish, 12 cameras at 640x480, 30 frame
sets, raw frames) is recorded once; then, in the same run:

1. the disk-read floor: every frame of the take read (and decoded) once;
2. each step's own benchmark on the same data in this process (one core, no files):
   keying (``key_frames`` on the frames in memory, 1 and 2 threads, as ``stage bench key``),
   hull + surface on the grid the process chose (as ``stage bench reconstruct``), the silhouette
   consistency of each surface,
   per-frame skeletons on those surfaces (as ``stage bench spines``) and the reduce step
   (correspondence and one graph, ``build_spine``);
3. ``process_take`` with the default settings on a fresh copy of the take (no masks) with
   1 and 2 worker processes and on a Dask ``LocalCluster`` of 2 single-threaded workers.

The table gives seconds per step inside ``stage process`` beside the step's own figure at
the same parallelism, measured right before the run (the step's own code on its data in
memory, split over as many processes started together as the run has workers), their ratio
(the overhead), the one-time costs (worker start-up: forkserver processes importing the
pipeline; the grid choice: the subject's box, every set carved coarse to fine, printed with its
seconds a set) and sets/s end to end (start-up
included). ``--profile`` adds a
cProfile of the in-process run (the heaviest functions by own time).

Target on a 2-core machine: >= 8 sets/s end to end for the demo's take, no step more than
1.5x slower than its own benchmark.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from stage.cli._args import parse_size

NAME = "process"
HELP = "stage process end to end (1, 2 workers, Dask) vs each step's own benchmark and the disk-read floor"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="starfish", help="simulated subject (default starfish, as the demo)")
    p.add_argument("--cameras", type=int, default=12, help="simulated cameras (default 12)")
    p.add_argument("--frames", type=int, default=30, help="frame sets (default 30)")
    p.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker processes to try (default 1 2)")
    p.add_argument("--no-dask", action="store_true", help="skip the Dask LocalCluster run")
    p.add_argument("--repeat", type=int, default=1, help="rounds of every measurement (default 1); medians at the end")
    p.add_argument("--profile", action="store_true", help="also profile an in-process run (cProfile, top 20)")
    p.add_argument("--keep", type=Path, default=None, metavar="DIR", help="keep the take and results in DIR")


def _disk_floor(take: Path) -> float:
    from stage.store import TakeReader

    t = time.perf_counter()
    with TakeReader(take) as r:
        for cam in r.cameras:
            for i in range(r.n_frames(cam)):
                r.frame(cam, i)
    return time.perf_counter() - t


def _own_key(images: np.ndarray, plates: np.ndarray, rig: dict) -> dict[int, tuple[float, float]]:
    """Images/s of the keyer on frames in memory (model estimation included) and its CPU
    seconds, with 1 and 2 threads."""
    import cv2

    from stage.keying.keyer import estimate_model, key_frames
    from stage.keying.take import take_key_params

    base = take_key_params(rig)
    F, C = images.shape[:2]
    out = {}
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        for workers in (1, 2):
            t, cpu = time.perf_counter(), time.process_time()
            for c in range(C):
                frames = images[:, c]
                sample = frames[np.unique(np.linspace(0, F - 1, min(F, 16)).round().astype(int))]
                params = estimate_model(sample, params=base, plate=plates[c])
                key_frames(frames, params=params, plate=plates[c], workers=workers)
            out[workers] = (F * C / (time.perf_counter() - t), time.process_time() - cpu)
    finally:
        cv2.setNumThreads(threads)
    return out


def _own_reconstruct(take: Path, out: Path) -> dict:
    """Per set: hull + surface on the process's grid and masks, then skeletons; and the reduce step."""
    from pipeline.consistency import silhouette_consistency
    from pipeline.frame_skeleton import SpineParams, frame_skeleton
    from pipeline.surface import surface_from_occupancy

    p, grid, carver, masks = _surface_inputs(take, out, None)
    t_carve = t_surf = t_cons = t_skel = 0.0
    skeletons = []
    cpu = time.process_time()
    for m in masks:
        t = time.perf_counter()
        hull = carver.carve(m, tolerance=p.tolerance, support_plane=p.support_plane, margin=p.silhouette_margin)
        t_carve += time.perf_counter() - t
        t = time.perf_counter()
        mesh = surface_from_occupancy(hull.occupancy, grid, taubin_iterations=p.smooth_iterations, face_budget=p.face_budget)
        t_surf += time.perf_counter() - t
        t = time.perf_counter()
        silhouette_consistency(mesh.vertices, mesh.faces, m, carver.calibration, margin=p.silhouette_margin)
        t_cons += time.perf_counter() - t
        t = time.perf_counter()
        skeletons.append(frame_skeleton(mesh.vertices, mesh.faces, params=SpineParams(**p.spine)))
        t_skel += time.perf_counter() - t
    n = len(masks)
    return {"carve": t_carve / n, "surface": t_surf / n, "consistency": t_cons / n, "skeleton": t_skel / n, "grid": grid,
            "cpu": time.process_time() - cpu,
            "reduce": lambda: _own_reduce(skeletons, SpineParams(**p.spine))}


def _own_reduce(skeletons, params) -> tuple[float, float]:
    """Wall and CPU seconds of the reduce step alone: correspondence and one graph (``build_spine``)."""
    from pipeline.spine import build_spine

    t, cpu = time.perf_counter(), time.process_time()
    build_spine(skeletons, fps=30.0, params=params)
    return time.perf_counter() - t, time.process_time() - cpu


def _own_worker(what: str, take: str, out: str, part: list, barrier, queue) -> None:
    """One process of an own benchmark at several processes: load the data of its part (the
    clock not running), wait for the others, then run the part of the step (as
    :func:`_own_key` / :func:`_own_reconstruct` do) and report its monotonic start and end."""
    try:
        run = _load_key_part(take, part) if what == "key" else _load_surface_part(take, Path(out), part)
        barrier.wait(timeout=300)
        t0, cpu = time.monotonic(), time.process_time()
        run()
        queue.put((t0, time.monotonic(), time.process_time() - cpu, None))
    except BaseException as exc:  # reported to the parent, which raises it
        barrier.abort()
        queue.put((0.0, 0.0, 0.0, f"{type(exc).__name__}: {exc}"))


def _load_key_part(take: str, cameras: list[str]):
    import cv2

    from stage.keying.keyer import estimate_model, key_frames
    from stage.keying.take import take_key_params
    from stage.store import TakeReader

    cv2.setNumThreads(1)  # as a pool worker keys
    with TakeReader(take) as r:
        base = take_key_params(r.rig)
        data = []
        for cam in cameras:
            plate = r.read_array(f"cameras/{cam}", "plate")[0] if r.has_array(f"cameras/{cam}", "plate") else None
            data.append((r.frames(cam, 0, r.n_frames(cam)), plate))

    def run():
        for frames, plate in data:
            F = len(frames)
            sample = frames[np.unique(np.linspace(0, F - 1, min(F, 16)).round().astype(int))]
            params = estimate_model(sample, params=base, plate=plate)
            key_frames(frames, params=params, plate=plate, workers=1)

    return run


def _surface_inputs(take, out: Path, sets: list[int] | None):
    """The process's parameters and grid, a carver on them, and the stored masks of ``sets``
    (every set when None): what the surface step starts from."""
    import json

    from calib.calibration import Calibration
    from pipeline.hull import HullCarver
    from pipeline.process import ProcessParams
    from pipeline.volume import Grid
    from stage.store import TakeReader

    p = ProcessParams(**json.loads((out / "process.json").read_text())["params"])
    grid = Grid.from_dict(json.loads((out / "grid.json").read_text()))
    with TakeReader(take) as r:
        cams = list(r.cameras)
        cal = r.calibration
        cal = Calibration(tuple(cal[c] for c in cams), units=cal.units, meta=cal.meta)
        table = r.set_table()
        ks = range(len(table)) if sets is None else sets
        masks = [[r.mask(c, int(table[k, i])) for i, c in enumerate(cams)] for k in ks]
    return p, grid, HullCarver(cal, grid), masks


def _load_surface_part(take: str, out: Path, sets: list[int]):
    from pipeline.consistency import silhouette_consistency
    from pipeline.frame_skeleton import SpineParams, frame_skeleton
    from pipeline.surface import surface_from_occupancy

    p, grid, carver, masks = _surface_inputs(take, out, sets)
    sp = SpineParams(**p.spine)

    def run():
        for m in masks:
            hull = carver.carve(m, tolerance=p.tolerance, support_plane=p.support_plane, margin=p.silhouette_margin)
            mesh = surface_from_occupancy(hull.occupancy, grid, taubin_iterations=p.smooth_iterations,
                                          face_budget=p.face_budget)
            silhouette_consistency(mesh.vertices, mesh.faces, m, carver.calibration, margin=p.silhouette_margin)
            frame_skeleton(mesh.vertices, mesh.faces, params=sp)

    return run


def _own_parallel(what: str, take: Path, out: Path, parts: list[list], timeout: float = 600.0) -> tuple[float, float]:
    """Wall and CPU seconds of one step's own benchmark split over ``len(parts)`` forkserver
    processes that start together (each with its data in memory): the own figure at that
    parallelism, measured, not extrapolated from one process."""
    import multiprocessing

    ctx = multiprocessing.get_context("forkserver")
    parts = [p for p in parts if p]
    barrier, queue = ctx.Barrier(len(parts)), ctx.Queue()
    procs = [ctx.Process(target=_own_worker, args=(what, str(take), str(out), part, barrier, queue)) for part in parts]
    for pr in procs:
        pr.start()
    try:
        got = [queue.get(timeout=timeout) for _ in procs]
    finally:
        for pr in procs:
            pr.join(timeout=30)
    errors = [g[3] for g in got if g[3]]
    if errors:
        raise RuntimeError(f"own benchmark of {what} failed in a worker: {errors[0]}")
    return max(g[1] for g in got) - min(g[0] for g in got), sum(g[2] for g in got)


def _own_at(take: Path, out: Path, cameras: list[str], n_sets: int, workers: int) -> dict[str, tuple[float, float]]:
    """Wall and CPU seconds of keying and of hull + surface + skeletons at ``workers`` processes (cameras
    dealt round-robin, frame sets in contiguous runs: as the pool gets them)."""
    cams = [cameras[i::workers] for i in range(workers)]
    sets = [list(a) for a in np.array_split(np.arange(n_sets), workers)]
    return {"key": _own_parallel("key", take, out, cams), "surface": _own_parallel("surface", take, out, sets)}


def _executors(args):
    import concurrent.futures as cf
    import multiprocessing

    ctx = multiprocessing.get_context("forkserver")  # as `stage process`
    for w in args.workers:
        if w < 1:
            raise ValueError("--workers must be >= 1")
        yield f"{w} worker{'s' if w > 1 else ''}", w, lambda w=w: (cf.ProcessPoolExecutor(max_workers=w, mp_context=ctx), None)
    if not args.no_dask:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            print("(Dask is not installed: the LocalCluster run is skipped; pip install 'dask[distributed]')")
            return

        def dask():
            import logging

            import dask

            from api.executors import DASK_WORKER_ENV

            with dask.config.set(DASK_WORKER_ENV):  # as the API's LocalCluster
                cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                       host="127.0.0.1", silence_logs=logging.ERROR)
            client = Client(cluster)
            return client.get_executor(pure=False), (client, cluster)

        yield "Dask LocalCluster (2 workers)", 2, dask


def _copy_take(src: Path, dst: Path) -> Path:
    """A copy of the take and its derived data (the plates; never keyed)."""
    from stage.store import derived_path

    derived_path(dst).unlink(missing_ok=True)  # masks of an earlier round
    shutil.copy(src, dst)
    if derived_path(src).exists():
        shutil.copy(derived_path(src), derived_path(dst))
    return dst


def _run(take_src: Path, work: Path, i: int, make) -> tuple[float, dict]:
    from pipeline.process import process_take

    take = _copy_take(take_src, work / f"take-{i}.h5")
    out = work / f"out-{i}"
    shutil.rmtree(out, ignore_errors=True)
    from pipeline.process import warm_task

    t = time.perf_counter()
    ex, closers = make()
    try:
        for f in [ex.submit(warm_task) for _ in range(4)]:
            f.result()
        startup = time.perf_counter() - t
        res = process_take(take, out, executor=ex)
        wall = time.perf_counter() - t  # the pool's or cluster's shutdown aside
    finally:
        if closers is None:
            ex.shutdown()
        else:
            for c in closers:
                c.close()
    return wall, {**res.report, "startup": startup}


_NAMES = {"key": "key", "grid": "grid choice", "surface": "surface + skeletons", "spine": "spine (reduce)"}


def _measure(src: Path, work: Path, args, sim, rig: dict, prof) -> list[tuple]:
    """One round: the in-process run and its own figures, then per executor its own figures at
    its parallelism and its run. Returns ``(label, workers, wall, report, own)`` per run."""
    from pipeline.process import process_take, warm_task
    from stage.store import TakeReader

    n_sets, n_img = sim.n_frames, sim.n_frames * sim.n_cameras
    shutil.rmtree(work / "out-0", ignore_errors=True)
    take0 = _copy_take(src, work / "take-0.h5")
    t = time.perf_counter()
    warm_task()  # the imports a worker makes at start-up, here too
    startup0 = time.perf_counter() - t
    if prof is not None:
        prof.enable()
    t = time.perf_counter()
    rep0 = process_take(take0, work / "out-0", executor=None).report
    wall0 = time.perf_counter() - t + startup0
    if prof is not None:
        prof.disable()
    own_key = _own_key(sim.images, sim.plate, rig)
    own = _own_reconstruct(take0, work / "out-0")
    g = rep0.get("grid", {})
    print(f"grid: {own['grid']} ({g.get('source', '?')}; voxel {g.get('voxel', float('nan')):.2f}, "
          f"pixel at the subject {g.get('pixel_footprint', float('nan')):.2f})")
    box = g.get("box") or {}
    if box:
        sec, cpu = rep0["seconds"].get("grid", float("nan")), rep0.get("cpu_seconds", {}).get("grid", float("nan"))
        n = max(1, box["frame_sets"])
        print(f"subject box: {' x '.join(f'{x:.4g}' for x in box['size'])} from {box['frame_sets']} sets in {sec:.2f} s, "
              f"{cpu:.2f} s CPU ({1e3 * sec / n:.1f} ms a set, {1e3 * cpu / n:.1f} ms CPU; "
              f"cubes {', '.join(f'{v:.3g}' for v in box['level_voxels'])})")
    per_set = own["carve"] + own["surface"] + own["consistency"] + own["skeleton"]
    print(f"own benchmarks (this process, files aside): keying {own_key[1][0]:.0f} images/s (1 thread), "
          f"{own_key[2][0]:.0f} (2 threads); hull {1e3 * own['carve']:.1f} ms + surface {1e3 * own['surface']:.1f} ms "
          f"+ consistency {1e3 * own['consistency']:.1f} ms + skeletons {1e3 * own['skeleton']:.1f} ms per set "
          f"= {1 / per_set:.1f} sets/s")
    # each run's own figures are measured at its parallelism right before it (processes
    # started together, data in memory): a fair ratio on a machine whose load moves
    own0 = {"key": (n_img / own_key[2][0], own_key[2][1]), "surface": (n_sets * per_set, own["cpu"]), "spine": own["reduce"]()}
    runs = [("in process (keying 2 threads)", 0, wall0, {**rep0, "startup": startup0}, own0)]
    with TakeReader(take0) as r:
        cameras = list(r.cameras)
    for i, (label, w, make) in enumerate(_executors(args), start=1):
        own_w = {**_own_at(take0, work / "out-0", cameras, n_sets, w), "spine": own["reduce"]()}
        wall, rep = _run(src, work, i, make)
        runs.append((label, w, wall, rep, own_w))
    return runs


def _print_round(runs: list[tuple], n_sets: int) -> None:
    print("own benchmarks at the runs' parallelism (measured; ideal = the 1-process figure / workers):")
    one = next((o for _, w, _, _, o in runs if w == 1), None)
    for label, w, _, _, o in runs[1:]:
        k, sf = o["key"][0], o["surface"][0]
        ideal = "" if one is None else (f"  (ideal key {one['key'][0] / w:.2f}, surface {one['surface'][0] / w:.2f}; "
                                        f"scaling {one['key'][0] / k:.2f}x, {one['surface'][0] / sf:.2f}x)")
        print(f"  {label:<30} key {k:.2f} s, hull + surface + skeletons {sf:.2f} s{ideal}")
    print()
    print("wall seconds, and CPU seconds of this process and the workers (CPU does not count other jobs' time slices)")
    print(f"{'run':<30} {'step':<22} {'inside s':>9} {'own s':>8} {'ratio':>6} {'cpu in':>8} {'own':>7} {'ratio':>6}")
    for label, _w, wall, rep, own_s in runs:
        sec, cpu = rep["seconds"], rep.get("cpu_seconds", {})
        print(f"{label:<30} {'start-up':<22} {rep['startup']:9.2f}")
        for step in ["key", "grid", "surface", "spine"] + [k for k in sec if k not in _NAMES]:
            if step in sec:
                ratio = ""
                if step in own_s:
                    (ow, oc), c = own_s[step], cpu.get(step, float("nan"))
                    ratio = f"{ow:8.2f} {sec[step] / ow:6.2f} {c:8.2f} {oc:7.2f} {c / oc:6.2f}"
                print(f"{label:<30} {_NAMES.get(step, step):<22} {sec[step]:9.2f} {ratio}")
        other = wall - sum(sec.values()) - rep["startup"]
        print(f"{label:<30} {'other':<22} {other:9.2f}")
        print(f"{label:<30} {'END TO END':<22} {wall:9.2f} {'':>8} {'':>6}  {n_sets / wall:5.1f} sets/s"
              f" ({n_sets / (wall - rep['startup']):.1f} after start-up)")


def _print_summary(rounds: list[list[tuple]], n_sets: int) -> None:
    """Median over the rounds of every ratio and of sets/s."""
    print(f"\nmedian of {len(rounds)} rounds:")
    for j, (label, *_rest) in enumerate(rounds[0]):
        steps = [s for s in ("key", "surface", "spine") if all(s in r[j][3]["seconds"] for r in rounds)]
        wall = {s: float(np.median([r[j][3]["seconds"][s] / r[j][4][s][0] for r in rounds])) for s in steps}
        cpu = {s: float(np.median([r[j][3]["cpu_seconds"][s] / r[j][4][s][1] for r in rounds])) for s in steps}
        rate = float(np.median([n_sets / r[j][2] for r in rounds]))
        print(f"  {label:<30} wall ratio " + ", ".join(f"{_NAMES[k]} {v:.2f}" for k, v in wall.items())
              + "; CPU ratio " + ", ".join(f"{v:.2f}" for v in cpu.values()) + f"; {rate:.1f} sets/s")


def run(args: argparse.Namespace) -> int:
    import os

    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from stage.store import TakeReader

    size = parse_size(args.size)
    if args.frames < 2 or args.cameras < 4:
        raise ValueError("--frames must be >= 2 and --cameras >= 4")
    if args.repeat < 1:
        raise ValueError("--repeat must be >= 1")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-process-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        print(f"load average at the start: {os.getloadavg()[0]:.1f} (2 cores: figures above ~1 are shared with others)")
        print(f"simulated take: {args.subject}, {args.cameras} cameras at {size[0]}x{size[1]}, {args.frames} frame sets")
        sim = simulate_take(args.subject, n_cameras=args.cameras, frames=args.frames, size=size, seed=0)
        src = record_take(sim, work / "source.h5")
        n_sets = sim.n_frames
        with TakeReader(src) as r:
            rig = r.rig
        floor = _disk_floor(src)
        print(f"disk-read floor: every frame read once in {floor:.2f} s ({n_sets / floor:.0f} sets/s)")
        prof = None
        if args.profile:
            import cProfile

            prof = cProfile.Profile()
        rounds = []
        for i in range(args.repeat):
            print(f"\n== round {i + 1} of {args.repeat} (load average {os.getloadavg()[0]:.1f})")
            rounds.append(_measure(src, work, args, sim, rig, prof if i == 0 else None))
            _print_round(rounds[-1], n_sets)
        print(f"load average at the end: {os.getloadavg()[0]:.1f}")
        if len(rounds) > 1:
            _print_summary(rounds, n_sets)
        best = max(n_sets / wall for rnd in rounds for _, _, wall, _, _ in rnd)
        print(f"\nbest end to end: {best:.1f} sets/s (target >= 8 on 2 cores); disk-read floor {n_sets / floor:.0f} sets/s")
        if prof is not None:
            import pstats

            print("\nprofile of the in-process run (own time):")
            pstats.Stats(prof).sort_stats("tottime").print_stats(20)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0
