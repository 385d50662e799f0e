"""``stage bench track``: seconds per frame of template tracking (15 rounds), 6k and 25k vertices.

Multi-view: the template is the simulated pipe's surface (marching cubes), the data each
frame's surface of the bending pipe, every frame after the second started from the
constant-velocity prediction, as in ``pipeline.track``. Single RGB-D: the simulated OAK-like
take of the pipe recorded to a file and tracked by :func:`pipeline.track_rgbd.track_rgbd_take`
itself; the figure is its frames' own times (``tracked/track.json``: the take reads,
preprocessing, z-buffer visibility, colour tracks, the rounds with the previous-shape prior and
the ``tracked/`` file; not the rigid ICP placement, once per take), and the take reads of those
frames, timed apart, are printed beside it. Also times the solver backends (one numeric
refactorisation + solve of the 15 per frame), and the prediction and one round's solve with the
previous-shape prior on the multi-view loop's last frames, and the armature mode's CPU seconds a frame
at 6k vertices (:func:`armature_seconds`). With ``--accuracy`` the simulated
multi-view takes are also tracked on their true surfaces
(:func:`fake_cameras.surface_motion.true_surface`), the tracker's error apart from the surfaces',
and on their surfaces carved across time (:mod:`pipeline.carve`, two rounds); ``--copies N`` tracks every
fast and slow take also on N copies whose surfaces are moved by 0.001 mm and prints every row's figures as
mean (least..most) under it (:func:`fast_accuracy`); ``--take-starts 0,0.3125,...`` simulates them also starting
that many seconds into the creature's motion. :func:`skeleton_oracle` tracks a fast take with the
simulator's own skeleton as the armature.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import time

import numpy as np

from stage.benchmarks import (
    COPY_SIGMA,
    check_copies,
    check_starts,
    moved_surfaces,
    seeds_option,
    spread_figures,
    starts_option,
)
from stage.benchmarks._data import SHARED_DATA

NAME = "track"
# degrees a frame on average (up to 31 frames; the simulator's bend is at most 150): the pipe bends at one rate
# whatever --frames is, since the work of a frame grows with its motion
BEND_PER_FRAME = 5.0
HELP = ("seconds per frame of template tracking for 6k / 25k-vertex templates (multi-view and single RGB-D), "
        "and of the armature mode at 6k")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=5,
                   help=f"frames timed per case (default 5; the pipe bends {BEND_PER_FRAME:g} degrees a frame on average)")
    p.add_argument("--accuracy", action="store_true",
                   help="also track the simulated RGB-D pipe 1/2, pipe 3/4 and lamp (30 frames, bent 75 degrees), "
                   "the real tracked pipe of Tzionas & Gall rendered at its sensor's pose (60 frames, when "
                   "../shared/data is there) and the simulated multi-view starfish and quadruped (30 frames, also on their "
                   "true surfaces, with and without --shape-memory, and on their surfaces carved across time, --carve; and "
                   "fast takes at 10 fps, limbs 3+ voxels a frame, also tracked with a rig as the articulated prior), "
                   "and print the vertex errors against the truth, "
                   "the volume and what `stage armature` finds (several minutes)")
    p.add_argument("--take-seeds", default="3",
                   help="with --accuracy: the simulator's seeds of the fast and slow takes (default 3; e.g. 3,4)")
    p.add_argument("--take-starts", default="0", metavar="S1,S2,...",
                   help="with --accuracy: the fast and slow takes of every seed also simulated starting at each of these "
                   "seconds into the creature's motion (default 0; e.g. 0,0.3125,0.625); a row's name shows its "
                   "start when it is not 0 (e.g. 'biped s3 t0.3125')")
    p.add_argument("--copies", type=int, default=0, metavar="N",
                   help="with --accuracy: every fast and slow take also tracked on N copies of its results, every vertex "
                   f"of every surface moved by N(0, {1000 * COPY_SIGMA:g} um) (far below a voxel: what moves then is "
                   "noise), and every row's figures printed as mean (least..most) over the take and its copies under "
                   "it (default 0)")


def multiview_accuracy(frames: int = 30) -> None:
    """Simulated starfish and quadruped (8 cameras, 640x480): `stage process`, then tracking; every
    template vertex against the true surface point it started on (fake_cameras.surface_motion)."""
    import concurrent.futures as cf
    import json
    import multiprocessing
    import tempfile
    from pathlib import Path

    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.meshio import load_mesh
    from pipeline.process import process_take

    with tempfile.TemporaryDirectory() as tmp:
        for name in ("starfish", "quadruped"):
            sim = simulate_take(name, n_cameras=8, frames=frames, size=(640, 480), seed=3)
            take = record_take(sim, Path(tmp) / f"{name}.h5")
            res = Path(tmp) / f"{name}_results"
            process_take(take, res, executor=None)
            t0 = time.perf_counter()
            process_take(take, res, steps=("track",), executor=None)
            dt = (time.perf_counter() - t0) / frames
            in_order = {k: load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(frames)}
            shutil.rmtree(res / "tracked")
            t0 = time.perf_counter()
            # the halves before and after the reference frame at once (a second process), as `stage track --workers 2`
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver")) as ex:
                process_take(take, res, steps=("track",), executor=ex)
            dt2 = (time.perf_counter() - t0) / frames
            same = all(np.array_equal(load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)[0], v)
                       for k, v in in_order.items())
            rep, (means, p95s, vols, pooled) = _multiview_scores(sim, res, frames)
            ref = int(rep["reference_frame"])
            voxel = float(json.loads((res / "grid.json").read_text())["voxel"])
            print(f"{name:9s} {rep['vertices']} vertices (template = frame {ref}), voxel {voxel:.2f} mm: vertex error mean "
                  f"{np.mean(means):.2f} voxels over the take (worst frame {max(means):.2f}), 95th percentile "
                  f"{np.mean(p95s):.2f} (worst {max(p95s):.2f}); volume {min(vols):.3f}..{max(vols):.3f}; {dt:.2f} s/frame in order, "
                  f"{dt2:.2f} s/frame with the two halves at once ({'the same' if same else 'NOT the same'} vertices); "
                  f"over all vertices and frames (as tests/pipeline/test_tracking_multiview.py scores) {pooled[0]:.3f} / "
                  f"{pooled[1]:.3f}")
            from fake_cameras.surface_motion import invented_motion

            inv = invented_motion(sim.creature, sim.times, res, frames=frames)
            print(f"  invented motion (where the body is rigid): {np.mean(inv):.2f} voxels on average (worst frame {max(inv):.2f})")
            _tracker_apart_from_surfaces(sim, res, frames)
            _carved_rounds(sim, res, frames)


#: The fast takes: the simulated creatures filmed at 10 frames a second (8 cameras, 640x480): their
#: limbs move 3 voxels a frame and more (the quadruped's legs 2.5 on average, up to 4.6 on a frame,
#: feet up to 8.9; the surface points' 95th percentile 4.4 voxels a frame; the biped's forearms 3.8..4.1
#: on average, up to 8.8); and the quadruped, the starfish and the biped at 30 frames a second, the slow
#: takes the armature mode must do no worse on.
FAST_TAKES = (("quadruped", 10.0, 16), ("starfish", 10.0, 16), ("biped", 10.0, 16), ("quadruped", 30.0, 16),
              ("starfish", 30.0, 16), ("biped", 30.0, 16))


def fast_accuracy(*, seeds=(3,), copies: int = 0, starts=(0.0,)) -> None:
    """Fast takes (and slow ones): the tracking alone (``stage track --armature-rounds 0``), then tracked again
    with an armature as the articulated prior (:func:`pipeline.track_armature.track_with_armature`): one round
    (``stage track``'s default, CPU seconds of both stages), the armature built from the
    tracking (``stage track --armature-rounds auto``), the take's spine as the first round's armature and then
    one or ``auto`` rounds built from the tracking (``spine=True``, ``--spine-armature``), one round of it with
    the colour tracks pulling its pose (``colour=True``), and the armature of the true motion, with
    and without its true poses among the starts (what the tracking gives with the right segments,
    and with the right starts too), and the same take tracked with the template's limb/body labels
    (:func:`_labels_rows`); the worst frame's mean and 95th percentile, the invented motion
    (:func:`fake_cameras.surface_motion.invented_motion`) and CPU seconds a frame; every take once for each of the
    simulator's ``seeds``. With ``copies`` (an integer >= 0) every take's rows are also tracked on that many copies
    of its processed results whose surfaces are moved by 0.001 mm
    (:func:`stage.benchmarks.moved_surfaces`, seeds 1..``copies``), and under every row its figures over
    the take and the copies, each mean (least..most) (:func:`stage.benchmarks.spread_figures`): the
    row's run-to-run spread. With ``starts`` every take of every seed is simulated starting at each of those
    seconds into the creature's motion (:func:`fake_cameras.take.simulate_take`'s ``start``).

    Parameters
    ----------
    seeds : sequence of int
        The simulator's seeds (>= 0, none twice): every take once for each, in their order.
    copies : int
        Moved copies of every take's processed results (an integer >= 0).
    starts : sequence of float
        Seconds into the creature's motion the takes start at (finite, >= 0, none twice): every take of every
        seed once for each, the starts of a seed in their order; a row's name shows its start when it is not 0
        (``"biped s3 t0.3125"``). The default, 0 alone, is the takes as they were before starts.

    Raises
    ------
    ValueError
        Naming ``seeds``, ``copies`` or ``starts`` when out of range, before any take is simulated.
    """
    import tempfile
    from pathlib import Path

    if isinstance(seeds, str) or not all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) for x in seeds):
        raise ValueError(f"seeds must be a sequence of integers, got {seeds!r}")
    seeds = seeds_option(",".join(map(str, seeds)), "seeds")
    copies = check_copies(copies)
    starts = check_starts(starts)
    with tempfile.TemporaryDirectory() as tmp:
        for seed, start, (creature, fps, frames) in itertools.product(seeds, starts, FAST_TAKES):
            _fast_take(creature, fps, frames, seed=seed, root=Path(tmp), copies=copies, start=start)


def _start_tag(start: float) -> str:
    """How a take's name shows its start (seconds): nothing at 0, else e.g. ``" t0.3125"``."""
    return f" t{start:.15g}" if start else ""


def _fast_take(creature: str, fps: float, frames: int, *, seed: int, root, copies: int = 0, start: float = 0.0) -> None:
    """:func:`fast_accuracy`'s rows of one take, simulated (``start`` seconds into the motion), recorded and
    processed in ``root``; with ``copies``, every row followed by its figures over the take and that many copies
    moved by 0.001 mm."""
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take

    sim = simulate_take(creature, n_cameras=8, frames=frames, size=(640, 480), seed=seed, fps=fps, start=start)
    stem = f"{creature}_{fps:g}_s{seed}{_start_tag(start).replace(' ', '_')}"
    take = record_take(sim, root / f"{stem}.h5")
    res = root / f"{stem}_results"
    process_take(take, res, executor=None)
    moved = [moved_surfaces(res, res.with_name(f"{res.name}_copy{k}"), seed=k) for k in range(1, copies + 1)]
    rows = [] if copies else None  # printed as they come without copies
    name = f"{creature} s{seed}{_start_tag(start)}"
    _take_rows(name, fps, sim, res, frames, rows=rows)
    if not copies:
        return
    per_copy = []
    for copy in moved:
        per_copy.append([])
        _take_rows(name, fps, sim, copy, frames, rows=per_copy[-1])
    for i, row in enumerate(rows):
        print(row["line"])
        print(f"    the take and {copies} copies moved by {1000 * COPY_SIGMA:g} um, mean (least..most): "
              f"{spread_figures([row, *(c[i] for c in per_copy)])}", flush=True)


def _take_rows(name: str, fps: float, sim, res, frames: int, *, rows=None) -> None:
    """The rows of :func:`_fast_take` tracked from the surfaces of the processed results ``res``; printed, or
    appended to ``rows`` (:func:`_fast_row`)."""
    from fake_cameras.surface_motion import surface_point_tracks
    from pipeline.armature import build_armature
    from pipeline.meshio import load_mesh
    from pipeline.track import track_results
    from pipeline.track_armature import track_with_armature

    t0 = time.process_time()
    track_results(res)
    cpu = (time.process_time() - t0) / frames
    _fast_row(f"{name} at {fps:g} fps, --armature-rounds 0 (the tracking alone)", sim, res, frames, cpu, rows=rows)
    base = res.with_name(res.name + "_default")
    shutil.copytree(res, base)
    t0 = time.process_time()
    track_with_armature(res, rounds=1)  # ``stage track``'s default: one round; CPU seconds of both stages
    _fast_row(f"{name}, default (--armature-rounds 1)", sim, res, frames, cpu + (time.process_time() - t0) / frames,
              rows=rows)
    _restore(res, base / "tracked")
    t0 = time.process_time()
    rep = track_with_armature(res, rounds="auto")
    kept = rep["rig_prior"]["kept_round"]
    _fast_row(f"{name}, --armature-rounds auto (kept round {kept} of {len(rep['rig_prior']['rounds'])}; segments "
              f"{rep['rig_prior']['rounds'][kept - 1]['segments']})", sim, res, frames,
              (time.process_time() - t0) / frames, rows=rows)
    for rounds in (1, "auto"):  # the spine's armature first (``--spine-armature``), then built from the tracking
        _restore(res, base / "tracked")
        t0 = time.process_time()
        rep = track_with_armature(res, rounds=rounds, spine=True)
        _fast_row(f"{name}, --armature-rounds {rounds} --spine-armature (kept round {rep['rig_prior']['kept_round']} "
                  f"of {len(rep['rig_prior']['rounds'])})", sim, res, frames, (time.process_time() - t0) / frames, rows=rows)
    _restore(res, base / "tracked")
    t0 = time.process_time()
    rep = track_with_armature(res, rounds=1, colour=True)
    _fast_row(f"{name}, --armature-rounds 1 with the colour tracks (from the tracking alone; colour tracks "
              f"{'on' if rep['rig_prior']['colour_tracks'] else 'OFF'})", sim, res, frames,
              (time.process_time() - t0) / frames, rows=rows)
    ref = int(json.loads((res / "tracked" / "track.json").read_text())["reference_frame"])
    V0, F0 = load_mesh(base / "tracked" / f"{ref:06d}.ply", largest=False)
    truth = surface_point_tracks(sim.creature, V0, [sim.times[ref], *sim.times])[1:]
    rig = build_armature(truth, F0, reference=ref)
    for poses, label in ((dict(enumerate(rig.fit.poses)), "with its poses"), (None, "without its poses")):
        _restore(res, base / "tracked")
        t0 = time.process_time()
        track_with_armature(res, rig.model, poses=poses)
        _fast_row(f"{name}, the armature of the true motion {label}", sim, res, frames,
                  (time.process_time() - t0) / frames, rows=rows)
    _labels_rows(name, sim, res, frames, rows=rows)


def _labels_rows(name: str, sim, res, frames: int, *, rows=None) -> None:
    """Rows of :func:`fast_accuracy` with the template's limb/body labels (``stage track --labels``): the
    tracking alone, then with the colour tracks and one colour round of the armature mode (``--labels
    --colour --armature-rounds 1``), and the same with the round's armature from the labels (``--armature-parts
    limbs``); each tracks ``res`` again from its surfaces. ``rows``: as :func:`_fast_row`."""
    from pipeline.track import track_results
    from pipeline.track_armature import track_with_armature

    t0 = time.process_time()
    track_results(res, labels="spine")
    _fast_row(f"{name}, --labels", sim, res, frames, (time.process_time() - t0) / frames, rows=rows)
    t0 = time.process_time()
    track_results(res, labels="spine", colour=True)
    track_with_armature(res, rounds=1, colour=True, labels="spine")
    _fast_row(f"{name}, --labels --colour --armature-rounds 1", sim, res, frames, (time.process_time() - t0) / frames, rows=rows)
    t0 = time.process_time()
    track_results(res, labels="spine", colour=True)
    track_with_armature(res, rounds=1, colour=True, labels="spine", parts="limbs")
    _fast_row(f"{name}, --labels --colour --armature-rounds 1 --armature-parts limbs", sim, res, frames,
              (time.process_time() - t0) / frames, rows=rows)


def simulator_armature(creature, time_s: float, vertices, faces):
    """The simulator's own skeleton as an armature of a template (the oracle of the armature mode).

    Parts: the creature's body (every body capsule) and every limb capsule that carries template vertices
    (each vertex on the capsule nearest to it at ``time_s``); every limb part hangs from the part before it on
    its limb (from the body for the first), its joint at the start of its capsule chain; every vertex moves
    rigidly with its part (one influence).
    """
    from pipeline.armature_fit import ArticulatedModel
    from pipeline.armature_skeleton import ArticulatedSkeleton

    V = np.asarray(vertices, dtype=np.float64)
    pose = creature.pose(float(time_s))
    cap = pose.capsule_sdf(V).argmin(axis=1)
    limb = pose.limb
    caps = [c for c in np.unique(cap) if limb[c] >= 0]
    part_of_cap = {c: 0 for c in np.flatnonzero(limb < 0)}
    parent, rest = [-1], [V[limb[cap] < 0].mean(0)]
    for c in caps:  # capsules in limb order: the one before on the limb with vertices is the parent
        before = [d for d in caps if d < c and limb[d] == limb[c]]
        parent.append(part_of_cap[before[-1]] if before else 0)
        first = (before[-1] + 1) if before else int(np.flatnonzero(limb == limb[c])[0])
        rest.append(pose.p0[first])
        part_of_cap[c] = len(parent) - 1
    P = len(parent)
    tips = [V[np.isin(cap, [c for c, q in part_of_cap.items() if q == p])].mean(0) for p in range(P)]
    joints = np.array(rest + tips)  # a joint per part, then a tip per part: every part drives one bone
    parents = np.array([-1] + [parent[p] for p in range(1, P)] + list(range(P)))
    part = np.r_[np.arange(P), np.arange(P)]
    bones = np.array([(parents[j], j) for j in range(1, 2 * P)])
    names = tuple(["root"] + [f"joint{p}" for p in range(1, P)] + [f"aux{p}" for p in range(P)])
    sk = ArticulatedSkeleton(names=names, parents=parents, rest=joints, articulation=np.r_[False, np.ones(P - 1, bool),
                             np.zeros(P, bool)], segment_pairs=(None,) * (2 * P), part=part,
                             part_joint=np.arange(P), part_parent=np.array(parent), bones=bones,
                             placement=(None,) * (2 * P))
    vpart = np.array([part_of_cap[c] for c in cap])
    return ArticulatedModel(V, np.asarray(faces, dtype=np.int64), sk, (P - 1 + vpart)[:, None], np.ones((len(V), 1)))


def skeleton_oracle(name: str = "biped", fps: float = 10.0, frames: int = 16) -> None:
    """A take of :data:`FAST_TAKES` tracked with the defaults, then one round of the armature mode with the
    simulator's own skeleton as the armature (:func:`simulator_armature`), without and with its poses fitted
    to the true tracks among the starts, and with the armature built from the tracking
    (``--armature-rounds 1``): what the mode gives with a right armature, apart from building it."""
    import tempfile
    from pathlib import Path

    from fake_cameras.record import record_take
    from fake_cameras.surface_motion import surface_point_tracks
    from fake_cameras.take import simulate_take
    from pipeline.armature_fit import fit_sequence
    from pipeline.meshio import load_mesh
    from pipeline.process import process_take
    from pipeline.track import track_results
    from pipeline.track_armature import track_with_armature

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_take(name, n_cameras=8, frames=frames, size=(640, 480), seed=3, fps=fps)
        res = Path(tmp) / "results"
        process_take(record_take(sim, Path(tmp) / "take.h5"), res, executor=None)
        t0 = time.process_time()
        track_results(res)
        _fast_row(f"{name} at {fps:g} fps, default", sim, res, frames, (time.process_time() - t0) / frames)
        base = Path(tmp) / "default"
        shutil.copytree(res / "tracked", base)
        ref = int(json.loads((base / "track.json").read_text())["reference_frame"])
        V0, F0 = load_mesh(base / f"{ref:06d}.ply", largest=False)
        model = simulator_armature(sim.creature, sim.times[ref], V0, F0)
        truth = surface_point_tracks(sim.creature, V0, [sim.times[ref], *sim.times[:frames]])[1:]
        poses = dict(enumerate(fit_sequence(model, truth).poses))
        for label, kw in (("the simulator's skeleton", dict(model=model)),
                          ("the simulator's skeleton with its true poses", dict(model=model, poses=poses)),
                          ("--armature-rounds 1", {})):
            _restore(res, base)
            t0 = time.process_time()
            track_with_armature(res, **kw)
            _fast_row(f"{name}, {label}", sim, res, frames, (time.process_time() - t0) / frames)


#: Voxels along the subject of the take :func:`armature_seconds` times: its template has about 6,000
#: vertices (6,018), the size the armature mode's cost is budgeted at (1 CPU s a frame).
ARMATURE_RESOLUTION = 67


def armature_seconds(frames: int = 16) -> None:
    """Seconds a frame of the armature mode at 6k vertices: the fast quadruped of :data:`FAST_TAKES`
    (10 fps, 8 cameras, 640x480), processed on a grid of :data:`ARMATURE_RESOLUTION` voxels along the
    subject, tracked with the defaults (``stage track``), then tracked again with its armature, one
    round (``stage track --armature-rounds 1``), without and with the colour tracks (``--colour``): the
    CPU time of :func:`pipeline.track_armature.track_with_armature` (building the armature, the spine's
    starts, every frame's colour tracks, articulated ICP and template fit; one BLAS thread) over the
    frames, this process's and the second process's together (and the first's alone: on two free cores the
    wall time comes near it), and its wall time in order in one process and with one half of the frames in a
    second process (``stage track --workers 2``, the default), each from the same tracking alone
    (``--armature-rounds 0``)."""
    import tempfile
    from pathlib import Path

    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take
    from pipeline.track import track_results
    from pipeline.track_armature import track_with_armature
    from stage.workers import process_pool

    with tempfile.TemporaryDirectory() as tmp, process_pool(1) as pool:
        sim = simulate_take("quadruped", n_cameras=8, frames=frames, size=(640, 480), seed=3, fps=10.0)
        take = record_take(sim, Path(tmp) / "quadruped.h5")
        res = Path(tmp) / "results"
        process_take(take, res, params={"resolution": ARMATURE_RESOLUTION}, executor=None)
        t0 = time.process_time()
        rep = track_results(res)
        default = (time.process_time() - t0) / frames
        base = Path(tmp) / "default"
        shutil.copytree(res / "tracked", base)
        pool.submit(int, 0).result()  # the second process started, as after `stage track`'s own tracking
        figures = {}
        for colour in (False, True):
            for ex in (None, pool):
                _restore(res, base)
                t0, w0 = time.process_time(), time.perf_counter()
                out = track_with_armature(res, rounds=1, colour=colour, executor=ex)
                here = time.process_time() - t0
                cpu = here + out["rig_prior"].get("worker_cpu_seconds", 0.0)
                figures[colour, ex is not None] = (cpu / frames, here / frames, (time.perf_counter() - w0) / frames)
    for colour, label in ((False, "--armature-rounds 1"), (True, "--armature-rounds 1 --colour")):
        (cpu, _, wall), (cpu2, here, wall2) = figures[colour, False], figures[colour, True]
        print(f"{rep['vertices']:6d} vertices  armature mode (fast quadruped, 10 fps, {frames} frames), {label}: "
              f"{cpu:.2f} CPU s per frame a round ({wall:.2f} s wall) in one process; with a second process "
              f"{cpu2:.2f} CPU s, {here:.2f} of them in the first ({wall2:.2f} s wall); the tracking before it "
              f"(--armature-rounds 0) {default:.2f} CPU s")


def _restore(res, tracked) -> None:
    """The tracking in ``tracked`` (a copy of a ``tracked/`` folder) put back as ``res``'s own, for the next run."""
    shutil.rmtree(res / "tracked")
    shutil.copytree(tracked, res / "tracked")


def _fast_row(label: str, sim, res, frames: int, cpu: float, *, rows=None) -> None:
    """A row of :func:`fast_accuracy`: the tracking in ``res`` scored; printed, or appended to ``rows`` (its
    ``line`` and the figures ``mean``, ``p95`` and ``worst``, as :func:`stage.benchmarks.patches.track_row`'s)."""
    from fake_cameras.surface_motion import invented_motion

    _, (means, p95s, vols, pooled) = _multiview_scores(sim, res, frames)
    inv = invented_motion(sim.creature, sim.times, res, frames=frames)
    line = (f"  {label}: {pooled[0]:.3f} / {pooled[1]:.3f} voxels (mean / 95th percentile over all vertices and frames), "
            f"worst frame {max(means):.2f} / {max(p95s):.2f}; volume {min(vols):.3f}..{max(vols):.3f}; invented motion "
            f"{np.mean(inv):.2f} voxels (worst frame {max(inv):.2f}); {cpu:.2f} CPU s/frame")
    if rows is None:
        print(line, flush=True)
    else:
        rows.append({"line": line, "mean": pooled[0], "p95": pooled[1], "worst": (max(means), max(p95s))})


def _carved_rounds(sim, res, frames: int, rounds: int = 2) -> None:
    """The take tracked as ``stage track --carve 2 --shape-memory --colour`` tracks it: with shape
    memory and colour tracks on the surfaces of ``stage process``, then twice carved across time
    with the tracked motion (:func:`pipeline.carve.carve_results`) and tracked on the carved
    surfaces; each round's figures and seconds."""

    from pipeline.carve import carve_results
    from pipeline.track import track_results

    carved = res.with_name(res.name + "_carved")
    shutil.copytree(res, carved, ignore=shutil.ignore_patterns("rig", "tracked"))
    t0 = time.perf_counter()
    track_results(carved, shape_memory=True, colour=True)
    _, (_, _, vols, pooled) = _multiview_scores(sim, carved, frames)
    print(f"  --shape-memory --colour, round 0 of --carve: {pooled[0]:.3f} / {pooled[1]:.3f} voxels; volume "
          f"{min(vols):.3f}..{max(vols):.3f}; {(time.perf_counter() - t0) / frames:.2f} s/frame in order")
    for r in range(1, rounds + 1):
        t0 = time.perf_counter()
        carve_results(carved)
        t1 = time.perf_counter()
        track_results(carved, surfaces="carved", shape_memory=True, colour=True)
        t2 = time.perf_counter()
        _, (_, _, vols, pooled) = _multiview_scores(sim, carved, frames)
        print(f"  carved across time, round {r} of --carve {rounds} --shape-memory --colour: {pooled[0]:.3f} / {pooled[1]:.3f} "
              f"voxels; volume {min(vols):.3f}..{max(vols):.3f}; carving {(t1 - t0) / frames:.2f} s/frame, tracking "
              f"{(t2 - t1) / frames:.2f} s/frame in order")


def _multiview_scores(sim, res, frames: int):
    """Every tracked vertex of ``res`` against the true surface point it started on (voxels) ->
    (track.json, (per-frame means, per-frame 95th percentiles, volume ratios, (mean, 95th
    percentile) over all vertices and frames)); scored as the multi-view tracking test scores."""
    from fake_cameras.surface_motion import tracking_errors

    err, vols, rep = tracking_errors(sim.creature, sim.times, res, frames=frames)
    return rep, (err.mean(axis=1).tolist(), np.percentile(err, 95, axis=1).tolist(), vols.tolist(),
                 (float(err.mean()), float(np.percentile(err, 95))))


def _tracker_apart_from_surfaces(sim, res, frames: int) -> None:
    """The same take tracked on its true surfaces (:func:`fake_cameras.surface_motion.true_surface`
    on the take's grid, in place of the hull's): what is left is the tracker's own error. Default,
    ``shape_memory`` and ``shape_memory`` with the colour tracks."""
    import json

    from fake_cameras.surface_motion import true_surface
    from pipeline.results import atomic_write_bytes, ply_bytes
    from pipeline.track import track_results
    from pipeline.volume import Grid

    exact = res.with_name(res.name + "_true_surfaces")
    shutil.copytree(res, exact, ignore=shutil.ignore_patterns("tracked", "rig"))
    grid = Grid.from_dict(json.loads((exact / "grid.json").read_text()))
    for k in range(frames):
        m = true_surface(sim.creature, sim.times[k], grid)
        atomic_write_bytes(exact / "meshes" / f"frame_{k:06d}.ply", ply_bytes(m.vertices, m.faces))
    for label, kw in (("default", {}), ("--shape-memory", {"shape_memory": True}),
                      ("--shape-memory --colour", {"shape_memory": True, "colour": True})):
        shutil.rmtree(exact / "tracked", ignore_errors=True)
        track_results(exact, **kw)
        _, (_, _, vols, pooled) = _multiview_scores(sim, exact, frames)
        print(f"  on the true surfaces, {label}: {pooled[0]:.3f} / {pooled[1]:.3f} voxels (mean / 95th percentile over "
              f"all vertices and frames); volume {min(vols):.3f}..{max(vols):.3f}")


def accuracy(frames: int = 30) -> None:
    """Mean vertex error against the simulator's per-vertex truth, volume ratio, rig articulations."""
    import tempfile
    from pathlib import Path

    from fake_cameras.rgbd import OBJECTS, record_rgbd_take, simulate_rgbd_take, template_path
    from pipeline.armature import counted
    from pipeline.armature_files import armature_results
    from pipeline.mesh_primitives import mesh_volume
    from pipeline.meshio import load_mesh
    from pipeline.track_rgbd import track_rgbd_take

    expected = {"pipe_half": 1, "pipe_3q": 1, "lamp": 3}
    with tempfile.TemporaryDirectory() as tmp:
        for name in OBJECTS:
            tk = simulate_rgbd_take(name, frames=frames, spacing=4.0 if name != "lamp" else None)
            take = record_rgbd_take(tk, Path(tmp) / f"{name}.h5")
            out = Path(tmp) / name
            t0 = time.perf_counter()
            track_rgbd_take(take, template_path(take), out)
            dt = (time.perf_counter() - t0) / frames
            V0, F0 = tk.template_vertices, tk.template_faces
            err, vol = [], []
            for k in range(frames):
                v, _ = load_mesh(out / "tracked" / f"{k:06d}.ply", largest=False)
                err.append(np.linalg.norm(v - tk.truth[k], axis=1).mean())
                vol.append(mesh_volume(v, F0) / mesh_volume(V0, F0))
            line = (f"{name:9s} {len(V0)} vertices: mean vertex error {100 * np.mean(err) / tk.size:.2f} % of {tk.size:.0f} mm "
                    f"over the take (last frame {100 * err[-1] / tk.size:.2f} %), volume {min(vol):.3f}..{max(vol):.3f} "
                    f"of the template's, {dt:.2f} s/frame")
            rig = armature_results(out)
            n = int(rig.skeleton.articulation.sum())
            print(f"{line}; stage armature: {counted(n, 'articulation')} (true {expected[name]})")


def real_pipe_accuracy() -> None:
    """The real tracked pipe of Tzionas & Gall (2016, section 5), ``../shared/data/tzionas_pipe``,
    rendered by the OAK-like camera at the original sensor's pose
    (:func:`fake_cameras.rgbd.simulate_sensor_rgbd_take`) and tracked like the simulated objects;
    every vertex against its given position, the volume, what `stage armature` finds. Skipped (one
    line) when the data are absent."""
    path = SHARED_DATA / "tzionas_pipe" / "pipe.npz"
    if not path.is_file():
        print(f"real pipe (Tzionas): skipped, {path} not found")
        return

    import tempfile
    from pathlib import Path

    from fake_cameras.rgbd import record_rgbd_take, simulate_sensor_rgbd_take, template_path
    from pipeline.armature import counted
    from pipeline.armature_files import armature_results
    from pipeline.mesh_primitives import mesh_volume
    from pipeline.meshio import load_mesh
    from pipeline.track_rgbd import track_rgbd_take
    d = np.load(path)
    J = d["joints"].astype(np.float64)
    length = float(np.linalg.norm(np.diff(J[0], axis=0), axis=1).sum())
    tk = simulate_sensor_rgbd_take(d["vertices"], d["faces"], joint_positions=J[:, 1:2],
                                   vertex_segment=d["bone_of_vertex"], length=length, name="tzionas_pipe")
    F0 = tk.template_faces
    v0 = mesh_volume(tk.template_vertices, F0)
    with tempfile.TemporaryDirectory() as tmp:
        take = record_rgbd_take(tk, Path(tmp) / "pipe.h5")
        out = Path(tmp) / "out"
        t0 = time.perf_counter()
        track_rgbd_take(take, template_path(take), out)
        dt = (time.perf_counter() - t0) / tk.n_frames
        err, vol, true_vol = [], [], []
        for k in range(tk.n_frames):
            v, _ = load_mesh(out / "tracked" / f"{k:06d}.ply", largest=False)
            err.append(np.linalg.norm(v - tk.truth[k], axis=1).mean())
            vol.append(mesh_volume(v, F0) / v0)
            true_vol.append(mesh_volume(tk.truth[k], F0) / v0)
        vol, true_vol = np.array(vol), np.array(true_vol)
        line = (f"real pipe (Tzionas) {len(tk.template_vertices)} vertices, {tk.n_frames} frames: mean vertex error "
                f"{100 * np.mean(err) / length:.2f} % of {length:.0f} mm (worst frame {100 * max(err) / length:.2f} %), "
                f"volume {vol.min():.3f}..{vol.max():.3f} of the template's (the given surface's own "
                f"{true_vol.min():.3f}..{true_vol.max():.3f}; tracked / given {np.min(vol / true_vol):.3f}.."
                f"{np.max(vol / true_vol):.3f}), {dt:.2f} s/frame")
        rig = armature_results(out)
        sk = rig.skeleton
        n = int(sk.articulation.sum())
        found = rig.fit.joints[:, sk.articulation]
        near = np.linalg.norm(found - tk.joint_positions[:, :1], axis=2)  # (F, n) from the true joint
        where = f", nearest {np.median(near, axis=0).min():.1f} mm from the true joint (median over frames)" if n else ""
        print(f"{line}; stage armature: {counted(n, 'articulation')} (true 1){where}")


def _spacing_for(obj, target):
    from fake_cameras.rgbd import template_mesh

    s = 4.0
    for _ in range(4):
        v, _ = template_mesh(obj, spacing=s)
        s *= np.sqrt(len(v) / target)
    return s


def _rgbd_seconds(take, out, *, colour: bool) -> tuple[float, float]:
    """Seconds a frame of :func:`pipeline.track_rgbd.track_rgbd_take` on a recorded take, and of them
    the take reads.

    The frames' own times in ``tracked/track.json`` (the real frame loop: reading the frame's
    depth and colour, preprocessing, z-buffer visibility, colour tracks, the rounds and writing
    its ``tracked/`` file; not the once-per-take rigid ICP placement), averaged; the take reads
    of the same frames (depth, and colour with ``colour``) are timed separately after the run, so
    the tracking alone is the first figure less the second.
    """
    from fake_cameras.rgbd import template_path
    from pipeline.track_rgbd import track_rgbd_take
    from stage.store import TakeReader

    rep = track_rgbd_take(take, template_path(take), out, colour=colour)
    frames = [int(k) for k in rep["frames"]]
    if not frames:
        raise RuntimeError(f"{take}: no frame was tracked (skipped: {rep['skipped']})")
    per_frame = float(np.mean([f["seconds"] for f in rep["frames"].values()]))
    with TakeReader(take) as rd:
        t0 = time.perf_counter()
        for k in frames:
            rd.depth(rep["camera"], k)
            if colour:
                rd.frame(rep["camera"], k)
        reads = (time.perf_counter() - t0) / len(frames)
    return per_frame, reads


def _timings(F: int) -> None:
    """Seconds a frame of the solver, the multi-view and single RGB-D tracking and the prediction, at 6k and 25k
    vertices (``F`` frames timed)."""
    import tempfile
    from pathlib import Path

    from fake_cameras.rgbd import make_object, record_rgbd_take, simulate_rgbd_take, template_mesh
    from pipeline.cholesky import CholeskySystem
    from pipeline.mesh_primitives import vertex_normals
    from pipeline.tracking import TemplateTracker
    from pipeline.tracking_patches import predict_motion

    obj = make_object("pipe_half")
    for target in (6000, 25000):
        s = _spacing_for(obj, target)
        V, T = template_mesh(obj, spacing=s)
        tr = TemplateTracker(V, T)
        for be in ("qdldl", "splu"):
            try:
                cs = CholeskySystem(tr.LtL, backend=be)
            except ImportError:
                continue
            d = np.full(len(V), tr.gamma)
            t0 = time.perf_counter()
            for _ in range(5):
                cs.factor(d)
                cs.solve(np.ones((len(V), 3)))
            t1 = time.perf_counter()
            for _ in range(5):
                cs.solve(np.ones((len(V), 3)))
            solve_ms = (time.perf_counter() - t1) / 5 * 1000
            total = (t1 - t0) / 5 * 1000
            print(f"{len(V):6d} vertices  solver {be:6s}: {total:7.1f} ms per refactor + solve (solve alone {solve_ms:.1f} ms)")
        tk = simulate_rgbd_take("pipe_half", frames=F, spacing=s, bend=min(BEND_PER_FRAME * (F - 1), 150.0))
        # multi-view: each frame's true surface as data; every frame started from the prediction
        prev, before, seen = V.copy(), None, None
        t0 = time.perf_counter()
        for k in range(F):
            init = None if before is None else tr.predict(prev, before, constrained=seen)
            fit = tr.fit(tk.truth[k], vertex_normals(tk.truth[k], T), previous=prev, init=init)
            before, prev, seen = prev, fit.vertices, fit.constrained
        mv = (time.perf_counter() - t0) / F
        print(f"{len(V):6d} vertices  multi-view : {mv:6.3f} s per frame ({tr.system.backend}, {tr.rounds} rounds)")
        with tempfile.TemporaryDirectory() as tmp:
            take = record_rgbd_take(tk, Path(tmp) / "pipe.h5")
            rg, rd = _rgbd_seconds(take, Path(tmp) / "out", colour=False)
            rgc, rdc = _rgbd_seconds(take, Path(tmp) / "out_colour", colour=True)
        print(f"{len(V):6d} vertices  single RGB-D: {rgc:6.3f} s per frame with colour tracks (the default), "
              f"{rg:.3f} without (pipeline.track_rgbd.track_rgbd_take's frame loop; of which reading the take "
              f"{1000 * rdc:.1f} and {1000 * rd:.1f} ms)")
        tr = TemplateTracker(V, T, prior="previous")
        tr.predict(prev, before, constrained=seen)  # its matrices, once per take
        t0 = time.perf_counter()
        for _ in range(5):
            tr.predict(prev, before, constrained=seen)
        t1 = time.perf_counter()
        for _ in range(5):
            predict_motion(prev, before, T, tr.patches, constrained=seen)  # the matrices built in the call
        t2 = time.perf_counter()
        for _ in range(5):
            tr._solve_round(prev, np.arange(len(V)), prev, vertex_normals(prev, T), tr.LtL @ prev, prev, True, prev=before)
        print(f"{len(V):6d} vertices  of which: prediction {1000 * (t1 - t0) / 5:.1f} ms a frame "
              f"({1000 * (t2 - t1) / 5:.1f} building its matrices in the call), "
              f"one round's solve with the previous-shape prior {1000 * (time.perf_counter() - t2) / 5:.1f} ms")


def run(args: argparse.Namespace) -> int:
    seeds = seeds_option(getattr(args, "take_seeds", "3"))
    copies = check_copies(getattr(args, "copies", 0), name="--copies")
    starts = starts_option(getattr(args, "take_starts", "0"))
    if copies and not args.accuracy:
        raise ValueError("--copies needs --accuracy (it copies the fast and slow takes that --accuracy tracks)")
    if starts != [0.0] and not args.accuracy:
        raise ValueError("--take-starts needs --accuracy (it starts the fast and slow takes that --accuracy tracks)")
    _timings(max(2, int(args.frames)))
    armature_seconds()
    if args.accuracy:
        accuracy()
        real_pipe_accuracy()
        multiview_accuracy()
        fast_accuracy(seeds=seeds, copies=copies, starts=starts)
    print("reused per take: Laplacian, L^T L and its pattern, the LDL^T ordering and elimination tree (qdldl), "
          "the patches and the summing matrices of the per-round sums (vertex normals, patch centroids and Kabsch), "
          "the prediction's averaging matrix, "
          "each camera's pixel rays and their depths; per frame: KD-tree of the data, the first round's numeric factor "
          "(CG preconditioner of the later rounds), the prediction; per round: KD-tree of the vertices, pairs, patch "
          "motions (and, single RGB-D, the previous frame's shape placed patch by patch, the z-buffer)")
    return 0
