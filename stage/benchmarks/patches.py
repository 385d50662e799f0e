"""``stage bench patches``: the tracking's first stage (``stage track --armature-rounds 0``, before the default's armature
round) of the fast and slow simulated takes, and where its patches fall.

Every take is a directory of :mod:`stage.benchmarks.labels` (``sim.pkl`` and the processed ``results/``; a
missing one is simulated, recorded and processed there first, minutes). Its ``results/`` are copied without
``tracked/`` and ``rig/`` to a temporary directory and tracked there (:func:`pipeline.track.track_results`, in
one process); every template vertex is scored against the true surface point it started on
(:func:`fake_cameras.surface_motion.tracking_errors`, voxels). Printed per take: mean / 95th percentile over
all vertices and frames; the worst frame's mean / 95th percentile; the number of rigid patches; CPU seconds a
frame.

``--labels`` adds the tracking with the template's limb/body labels (``labels="spine"``, ``stage track
--labels``). ``--grid 0,0.25,...`` adds the tracking with the rigid patches the tracker cut before they
followed the surface: the cells of a grid of the patch size whose origin is the template's lowest corner moved
by that many cells along every axis (:func:`grid_patches`); how much the figures move with the offset is what
the patches of :func:`pipeline.tracking_patches.surface_patches` no longer depend on. ``--copies N`` tracks
every take also on N copies of its results whose surfaces are moved by 0.001 mm
(:func:`stage.benchmarks.moved_surfaces`) and prints, under the take's row, every figure's mean (least..most)
over the take and its copies (:func:`stage.benchmarks.spread_figures`): how far the figure moves when nothing
but round-off does.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from stage.benchmarks import COPY_SIGMA, check_copies, moved_surfaces, spread_figures
from stage.benchmarks.labels import take_dir, take_specs, takes_root

NAME = "patches"
HELP = "the tracking alone (--armature-rounds 0) of the fast and slow simulated takes, with its patches and with a grid's"

DEFAULT_TAKES = ",".join(f"{n}:{fps}:{s}:16" for n in ("biped", "quadruped", "starfish") for fps in (10, 30)
                         for s in (3, 4)) + ",starfish:30:3:30"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default=None, help="directory of the take directories, each simulated and processed "
                   "when missing (default: as stage bench labels)")
    p.add_argument("--takes", default=DEFAULT_TAKES,
                   help="NAME:FPS:SEED:FRAMES,... (8 cameras, 640x480); directory ROOT/NAME_FPS_sSEED_fFRAMES "
                   "(default: biped, quadruped, starfish at 10 and 30 fps, seeds 3 and 4, 16 frames; and the "
                   "30-frame starfish of seed 3, the multi-view test's take)")
    p.add_argument("--labels", action="store_true", help="also track with the template's limb/body labels (--labels)")
    p.add_argument("--grid", default="",
                   help="comma-separated offsets in cells (e.g. 0,0.25,0.5,0.75): also track with grid patches "
                   "whose origin is moved by that much")
    p.add_argument("--copies", type=int, default=0, metavar="N",
                   help="every tracking also on N copies of the take's results, every vertex of every surface moved by "
                   f"N(0, {1000 * COPY_SIGMA:g} um) (far below a voxel: what moves then is noise), and every figure's "
                   "mean (least..most) over the tracking and its copies printed under its row (default 0)")


def grid_patches(vertices, faces, size: float, offset: float = 0.0):
    """The grid patches: per connected component, one seed per ``size`` cell (the first vertex in it), the
    cells counted from the template's lowest corner moved by ``offset`` cells along every axis; every vertex
    with its component's nearest seed (the grid rule of a limb's patches,
    :func:`pipeline.tracking_patches.grid_seeds`). -> (patch per vertex, component per patch), as
    ``surface_patches``."""
    from pipeline.mesh_primitives import mesh_components
    from pipeline.tracking_patches import grid_seeds

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = len(v)
    comp = mesh_components(f, n)
    lo = v.min(0)
    per_component = []  # (its vertices, its seeds, every vertex's nearest among them)
    for c in np.unique(comp):
        mine = np.flatnonzero(comp == c)
        s_c, nearest = grid_seeds(v[mine], size, offset=offset, corner=lo)
        per_component.append((mine, mine[s_c], nearest))
    seeds = np.sort(np.concatenate([s_c for _, s_c, _ in per_component]))
    patch = np.empty(n, np.int64)
    for mine, s_c, nearest in per_component:
        patch[mine] = np.searchsorted(seeds, s_c)[nearest]
    return patch, comp[seeds]


@contextlib.contextmanager
def _patches(offset: float | None, counts: list):
    """The tracker's patches without labels cut by :func:`grid_patches` (``offset`` None: its own); every
    call's number of patches appended to ``counts``."""
    import pipeline.tracking as tracking

    own = tracking.surface_patches

    def patches(vertices, faces, size, *, labels=None):
        if offset is None or labels is not None:
            out = own(vertices, faces, size, labels=labels)
        else:
            out = grid_patches(vertices, faces, size, offset)
        counts.append(len(out[1]))
        return out

    tracking.surface_patches = patches
    try:
        yield
    finally:
        tracking.surface_patches = own


def track_row(d: Path, tmp: Path, *, labels=None, offset: float | None = None, copy: int = 0) -> dict:
    """Track a copy of take directory ``d``'s results (``copy`` k > 0: with its surfaces moved,
    :func:`stage.benchmarks.moved_surfaces` with seed k); -> errors and CPU seconds a frame."""
    import pickle

    from fake_cameras.surface_motion import tracking_errors
    from pipeline.track import track_results

    check_copies(copy, name="copy")
    res = tmp / "results"
    if copy:
        moved_surfaces(d / "results", res, seed=copy)
    else:
        shutil.rmtree(res, ignore_errors=True)
        shutil.copytree(d / "results", res, ignore=shutil.ignore_patterns("tracked", "rig"))
    with open(d / "sim.pkl", "rb") as fh:
        sim = pickle.load(fh)
    frames = int(d.name.rsplit("_f", 1)[1])
    counts = []
    with _patches(offset, counts):
        t0 = time.process_time()
        track_results(res, labels=labels)
        cpu = (time.process_time() - t0) / len(sim.times)
    err = tracking_errors(sim.creature, sim.times, res, frames=frames)[0]
    m, p95 = err.mean(1), np.percentile(err, 95, 1)
    return {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)), "worst": (float(m.max()), float(p95.max())),
            "patches": counts[0] if counts else 0, "cpu": cpu}


def grid_offsets(text: str) -> list[float]:
    """``--grid``'s offsets (finite numbers of cells), or a ValueError naming it."""
    try:
        offsets = [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        offsets = [math.nan]
    if not all(math.isfinite(o) for o in offsets):
        raise ValueError(f"--grid: comma-separated offsets in cells (e.g. 0,0.25,0.5,0.75), got {text!r}")
    return offsets


def run(args: argparse.Namespace) -> int:
    offsets, specs = grid_offsets(args.grid), take_specs(args.takes)
    copies = check_copies(getattr(args, "copies", 0), name="--copies")
    cases = [("default", None, None)] + ([("--labels", "spine", None)] if args.labels else []) \
        + [(f"grid moved {o:g} cell", None, o) for o in offsets]
    print("| take | tracking | mean / 95th percentile; worst frame | patches | CPU s a frame |")
    print("| --- | --- | --- | --- | --- |")
    means = {name: [] for name, _, _ in cases}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in specs:
            d = take_dir(takes_root(args.root), spec)
            for name, labels, offset in cases:
                r = track_row(d, Path(tmp), labels=labels, offset=offset)
                means[name].append(r["mean"])
                print(f"| {d.name} | {name} | {r['mean']:.3f} / {r['p95']:.3f}; {r['worst'][0]:.2f} / {r['worst'][1]:.2f} "
                      f"| {r['patches']} | {r['cpu']:.2f} |", flush=True)
                if copies:
                    moved = [track_row(d, Path(tmp), labels=labels, offset=offset, copy=k) for k in range(1, copies + 1)]
                    print(f"| {d.name} | {name} and {copies} copies moved by {1000 * COPY_SIGMA:g} um: mean (least..most) "
                          f"| {spread_figures([r, *moved])} | | |", flush=True)
    for name, vals in means.items():
        print(f"mean over the takes, {name}: {np.mean(vals):.3f}")
    return 0
