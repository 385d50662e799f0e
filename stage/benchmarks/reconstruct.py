"""``stage bench reconstruct``: visual hull + surface frames per second, against plain carving.

Frames come from the simulated rig (``fake_cameras.take.simulate_take``, ground-truth masks,
so keying is excluded). For every grid resolution the benchmark builds the lookup tables
once (:class:`pipeline.hull.HullCarver`), then times per frame: coarse-to-fine carving,
surface preparation (crop, cavities, blur), marching cubes and cleanup (largest piece,
Taubin smoothing). In the same run it times the plain full-grid numpy projection carving
(:func:`pipeline.hull.carve_direct`: every voxel projected with ``Camera.project`` every
frame) and checks that both give the same occupancy. With ``--photo-refine`` it also times
the photo-consistent refinement of every surface (:func:`pipeline.photo_refine.refine_surface`)
and prints the surfaces' distance to the simulator's true surface before and after it.

With ``--accuracy`` it runs ``stage process`` at its defaults on the takes whose grid the tests
check on fewer frames or a coarser grid, and prints their figures instead of the timings: the
thin-tailed quadruped (:func:`fake_cameras.rigs.thin_tail_setup`, 24 frames; the limbs seen per
frame at the default grid and at voxels of 5.3 and 6.5 pixel footprints) and the Middlebury dino
(``../shared/data``, all 16 views, the plane it stands on; its surface box against the published
one, at the default grid and at 120 voxels).

Targets on a 2-core machine, 12 cameras at 640x480: >= 10 frames/s at 128^3 and >= 2 frames/s
at 256^3 (keying excluded).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

NAME = "reconstruct"
HELP = "visual hull + surface frames/s at 128^3 and 256^3 (time per step) vs plain numpy carving"

TARGETS = {128: 10.0, 256: 2.0}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="starfish", help="simulated subject (default starfish)")
    p.add_argument("--cameras", type=int, default=12, help="simulated cameras (default 12)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--frames", type=int, default=4, help="simulated frames, cycled while timing (default 4)")
    p.add_argument(
        "--resolutions", type=int, nargs="+", default=[128, 256], help="voxels along the longest axis (default 128 256)"
    )
    p.add_argument("--seconds", type=float, default=3.0, help="minimum timed seconds per resolution (default 3)")
    p.add_argument("--no-direct", action="store_true", help="skip the plain numpy carving baseline")
    p.add_argument("--accuracy", action="store_true",
                   help="instead of the timings: the thin-tail take (24 frames) and the Middlebury dino through "
                   "stage process at the default grid, the figures the tests check on smaller runs (about a minute)")
    p.add_argument("--photo-refine", action="store_true",
                   help="also time the photo-consistent refinement of each surface and print its distance to the "
                   "true surface before and after (voxels)")


def _ms(s: float) -> str:
    return f"{s * 1e3:8.1f} ms"


def _timed_frames(carver, grid, take, args: argparse.Namespace):
    """Carve and mesh the take's frames over and over for ``args.seconds`` (every frame at least once);
    -> seconds per step summed, frames timed, voxels tested one by one, the last mesh, and the
    distances to the true surface before and after the photo-consistent refinement (voxels)."""
    from pipeline.photo_refine import refine_surface
    from pipeline.surface import surface_from_occupancy

    cal, masks = take.calibration, take.masks
    steps = {"carve": 0.0, "prepare": 0.0, "marching_cubes": 0.0, "cleanup": 0.0}
    if args.photo_refine:
        steps["photo_refine"] = 0.0
    before: list = []
    after: list = []
    n = 0
    refined = 0
    faces = 0
    t_start = time.perf_counter()
    while True:
        m = masks[n % len(masks)]
        t = time.perf_counter()
        hull = carver.carve(m)
        steps["carve"] += time.perf_counter() - t
        tm: dict = {}
        mesh = surface_from_occupancy(hull.occupancy, grid, timings=tm)
        for k, v in tm.items():
            steps[k] += v
        if args.photo_refine:
            t = time.perf_counter()
            refined_v = refine_surface(mesh.vertices, mesh.faces, take.images[n % len(masks)], m, list(cal),
                                       voxel=grid.voxel)
            steps["photo_refine"] += time.perf_counter() - t
            if n < len(masks):  # the accuracy once per simulated frame
                pose = take.poses[n % len(masks)]
                before.append(np.abs(pose.sdf(np.asarray(mesh.vertices))) / grid.voxel)
                after.append(np.abs(pose.sdf(refined_v)) / grid.voxel)
        refined += hull.stats["refined"]
        faces += len(mesh.faces)
        n += 1
        if time.perf_counter() - t_start >= args.seconds and n >= len(masks):
            break
    return steps, n, refined, mesh, before, after


def _limbs_seen(results) -> list[int]:
    import json

    spine = json.loads((results / "spine.json").read_text())
    return [sum(v is not None for v in fr["tips"].values()) for fr in spine["frames"]]


def _thin_tail(tmp) -> None:
    """The thin-tail take at the default grid and at coarser voxels over the same box."""
    import json

    from fake_cameras.record import record_take
    from fake_cameras.rigs import thin_tail_setup
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take

    sim = simulate_take(frames=24, seed=0, **thin_tail_setup())
    take = record_take(sim, tmp / "tail.h5")
    process_take(take, tmp / "tail")
    g = json.loads((tmp / "tail" / "process.json").read_text())["grid"]
    seen = _limbs_seen(tmp / "tail")
    print(f"thin tail, 24 frames: pixel footprint {g['pixel_footprint']:.2f} mm, default voxel {g['voxel']:.2f} mm; "
          f"6 limbs in {seen.count(6)} of {len(seen)} frames")
    for px in (5.3, 6.5):
        res = int(np.ceil(max(g["box"]["size"]) / (px * g["pixel_footprint"])))
        process_take(take, tmp / f"tail{px}", steps=("key", "surface", "spine"), params={"resolution": res})
        seen = _limbs_seen(tmp / f"tail{px}")
        print(f"  voxels of {px} pixel footprints ({res} along the box): 6 limbs in {seen.count(6)} of {len(seen)} frames")


def _dino(tmp) -> None:
    """The Middlebury dino's surface box against the published one, default grid and 120 voxels."""
    from pipeline.process import process_take
    from pipeline.results import ResultsStore
    from stage.benchmarks._data import SHARED_DATA
    from stage.importer import import_take

    root = SHARED_DATA / "middlebury_dino_sparse_ring"
    if not root.is_dir():
        print(f"Middlebury dino: skipped, {root} not found")
        return
    take = import_take(root, root / "dinoSR_par.txt", tmp / "dino.h5", max_frames=1).path
    box = np.array([[-0.061897, -0.018874, -0.057845], [0.010897, 0.068227, 0.015495]])  # its README.txt
    for extra in ({}, {"resolution": 120}):
        params = {"key_mode": "luma", "support_plane": (0.0, 1.0, 0.0, -box[0, 1]), **extra}
        out = tmp / f"dino{len(extra)}"
        r = process_take(take, out, steps=("key", "surface"), params=params)
        rel = 100 * (np.ptp(ResultsStore(out).read_mesh(0).bounds, axis=0) / (box[1] - box[0]) - 1)
        print(f"Middlebury dino, {extra.get('resolution', 'default')} grid (voxel {r.report['grid']['voxel'] * 1000:.2f} mm): "
              f"surface box against the published one {', '.join(f'{v:+.1f} %' for v in rel)}")


def accuracy() -> int:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        _thin_tail(Path(tmp))
        _dino(Path(tmp))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.accuracy:
        return accuracy()
    from fake_cameras.take import simulate_take
    from pipeline.hull import HullCarver, carve_direct
    from pipeline.surface import surface_from_occupancy, surface_quality
    from pipeline.volume import grid_from_volume
    from stage.rig import Volume

    try:
        import fast_simplification  # noqa: F401

        decim = "fast-simplification installed"
    except ImportError:
        decim = "fast-simplification not installed (decimation falls back to coarser marching cubes; unused here)"

    print(
        f"simulated take: {args.subject}, {args.cameras} cameras at {args.width}x{args.height}, "
        f"{args.frames} frames (rendered once, cached)"
    )
    t0 = time.perf_counter()
    take = simulate_take(
        args.subject, n_cameras=args.cameras, frames=args.frames, size=(args.width, args.height), seed=0
    )
    print(f"  take ready in {time.perf_counter() - t0:.1f} s; masks are ground truth (keying excluded); {decim}")
    cal = take.calibration
    masks = take.masks
    bounds = Volume().bounds
    rows = []
    for res in args.resolutions:
        grid = grid_from_volume(bounds, res)
        print(f"\n{res}^3: {grid}")
        t0 = time.perf_counter()
        carver = HullCarver(cal, grid)
        build = time.perf_counter() - t0
        print(f"  lookup tables (once): {build:.2f} s, {carver.memory_bytes / 1024**3:.2f} GiB, levels {carver.levels}")
        surface_from_occupancy(carver.carve(masks[0]).occupancy, grid)  # warm up (imports, caches)
        steps, n, refined, mesh, before, after = _timed_frames(carver, grid, take, args)
        per = {k: v / n for k, v in steps.items()}
        total = sum(per.values())
        q = surface_quality(mesh)
        print(f"  frames timed: {n}; voxels tested one by one per frame: {refined // n} of {grid.n_voxels}")
        for k, v in per.items():
            print(f"    {k:15s}{_ms(v)}  {100 * v / total:5.1f} %")
        print(f"    {'total':15s}{_ms(total)}")
        fps_hull = 1.0 / per["carve"]
        fps_all = 1.0 / (total - per.get("photo_refine", 0.0))  # the target is the hull's and surface's
        target = TARGETS.get(res)
        verdict = ""
        if target is not None:
            verdict = f"  (target >= {target:g} frames/s: {'met' if fps_all >= target else 'NOT met'})"
        print(f"  hull only: {fps_hull:7.1f} frames/s; hull + surface: {fps_all:6.1f} frames/s{verdict}")
        if "photo_refine" in per:
            print(f"  with the photo-consistent refinement: {1.0 / total:6.2f} frames/s")
        print(f"  last mesh: {q.vertices} vertices, {q.faces} faces, watertight {q.watertight}, genus {q.genus}")
        if before:
            b, a = np.concatenate(before), np.concatenate(after)
            print(f"  distance of the surface's vertices to the true surface (voxels): hull mean {b.mean():.2f}, "
                  f"95th percentile {np.percentile(b, 95):.2f}; photo-refined mean {a.mean():.2f}, "
                  f"95th percentile {np.percentile(a, 95):.2f}")
        direct = None
        if not args.no_direct:
            t = time.perf_counter()
            ref = carve_direct(masks[0], cal, grid)
            direct = time.perf_counter() - t
            same = np.array_equal(ref, carver.carve(masks[0]).occupancy)
            print(
                f"  plain numpy projection carving (every voxel, every frame): {_ms(direct).strip()} per frame = "
                f"{1.0 / direct:.2f} frames/s; lookup tables coarse-to-fine are {direct / per['carve']:.0f}x faster; "
                f"identical occupancy: {'yes' if same else 'NO'}"
            )
        rows.append((res, build, per, fps_hull, fps_all, direct))
    print("\nsummary (frames/s):")
    print(f"  {'grid':>6s} {'tables s':>9s} {'hull':>8s} {'hull+surf':>10s} {'plain numpy':>12s}")
    for res, build, _per, fh, fa, direct in rows:
        d = f"{1.0 / direct:12.2f}" if direct else f"{'-':>12s}"
        print(f"  {res:>5d}^3 {build:9.2f} {fh:8.1f} {fa:10.1f} {d}")
    return 0
