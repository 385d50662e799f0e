"""``stage bench labels``: the limb/body labels of a tracked template against the simulator's, on processed takes.

Every take is a directory holding the simulation (``sim.pkl``, the pickled
:func:`fake_cameras.take.simulate_take` result) and its processed ``results/``; a missing one is simulated,
recorded and processed there first (minutes). The template is what :func:`pipeline.track.track_results`
tracks: the surface of the spine's reference frame (its largest component). The simulator's label of a
vertex is the limb of the capsule nearest to it at that frame (-1: the body). Printed per take, for the
spine's bone heat weights (:func:`pipeline.armature_limbs.vertex_limbs`) and for
:func:`pipeline.template_labels.template_labels` from the template's shape alone and with every frame's surface
(``surfaces=``, the results' ``meshes/``): the fraction of vertices whose label is right (each label
mapped to the true limb most of its vertices lie on, the body to the body), the body's recall and precision,
and CPU seconds.
"""

from __future__ import annotations

import argparse
import math
import pickle
import time
from pathlib import Path

import numpy as np

NAME = "labels"
HELP = "the template's limb/body labels against the simulator's on processed simulated takes"

DEFAULT_TAKES = ",".join(f"{n}:{fps}:{s}:16" for n in ("biped", "quadruped", "starfish") for fps in (10, 30)
                         for s in (3, 4)) + "," + ",".join(f"{n}:30:{s}:30" for n in ("biped", "quadruped", "starfish")
                                                             for s in (3, 5))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", default=None, help="directory of the take directories, each simulated and processed "
                   "when missing (default: the simulated takes' cache, $CAPTURE_STAGE_CACHE/takes or "
                   "~/.cache/capture-stage/takes)")
    p.add_argument("--takes", default=DEFAULT_TAKES,
                   help="NAME:FPS:SEED:FRAMES,... (8 cameras, 640x480); directory ROOT/NAME_FPS_sSEED_fFRAMES "
                   "(default: biped, quadruped, starfish at 10 and 30 fps, seeds 3 and 4, 16 frames; and 30 frames "
                   "at 30 fps, seeds 3 and 5)")


def label_scores(pred, true) -> tuple[float, float, float]:
    """(fraction right, body recall, body precision): every limb label mapped to the true limb most of its
    vertices lie on (a label on the body alone is wrong everywhere), -1 the body."""
    pred, true = np.asarray(pred), np.asarray(true)
    mapped = np.full(len(pred), -1)
    for k in np.unique(pred[pred >= 0]):
        on = true[pred == k]
        on = on[on >= 0]
        mapped[pred == k] = np.bincount(on).argmax() if len(on) else -2
    pb, tb = pred < 0, true < 0
    both = float((pb & tb).sum())
    return float((mapped == true).mean()), both / max(int(tb.sum()), 1), both / max(int(pb.sum()), 1)


def takes_root(root: str | None) -> Path:
    """``--root``, or the processed takes' cache beside the simulated takes' (``fake_cameras.take.cache_dir``)."""
    from fake_cameras.take import cache_dir

    return Path(root) if root else cache_dir().parent / "takes"


def take_specs(takes: str) -> list[str]:
    """``--takes``' entries, every one checked before any take is simulated or tracked (a ValueError naming it)."""
    specs = [t for t in str(takes).split(",") if t.strip()]
    for spec in specs:
        _parse_take(spec)
    if not specs:
        raise ValueError(f"--takes: give at least one NAME:FPS:SEED:FRAMES, got {takes!r}")
    return specs


def _parse_take(spec: str) -> tuple[str, float, int, int]:
    try:
        name, fps, seed, frames = spec.split(":")
        out = name, float(fps), int(seed), int(frames)
    except ValueError:
        raise ValueError(f"--takes: every take is NAME:FPS:SEED:FRAMES (e.g. biped:10:3:16), got {spec!r}") from None
    if not name or not (math.isfinite(out[1]) and out[1] > 0) or out[3] < 2:
        raise ValueError(f"--takes: every take is NAME:FPS:SEED:FRAMES with a positive FPS and at least 2 frames, "
                         f"got {spec!r}")
    return out


def take_dir(root: Path, spec: str) -> Path:
    """The take directory of ``NAME:FPS:SEED:FRAMES`` under ``root``, simulated and processed if missing."""
    name, fps, seed, frames = _parse_take(spec)
    d = root / f"{name}_{fps:g}_s{seed}_f{frames}"
    if (d / "results" / "spine.json").is_file() and (d / "sim.pkl").is_file():
        return d
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.process import process_take

    d.mkdir(parents=True, exist_ok=True)
    sim = simulate_take(name, n_cameras=8, frames=int(frames), size=(640, 480), seed=int(seed), fps=float(fps))
    with open(d / "sim.pkl", "wb") as fh:
        pickle.dump(sim, fh)
    process_take(record_take(sim, d / "take.h5"), d / "results", executor=None)
    return d


def take_labels(d: Path) -> dict:
    """Template, the simulator's labels, the heat weights' and template_labels' of one take directory."""
    from pipeline.armature_limbs import vertex_limbs
    from pipeline.armature_spine import reference_frame, rigged_model
    from pipeline.meshio import load_mesh
    from pipeline.spine_format import read_spine
    from pipeline.template_labels import template_labels
    from pipeline.track_frames import surface_meshes

    root = d / "results"
    frames, by_frame = surface_meshes(root, "meshes")
    spine = read_spine(root / "spine.json")
    ref = reference_frame(spine)
    V, F = load_mesh(by_frame[frames[ref]], largest=True)
    with open(d / "sim.pkl", "rb") as fh:
        sim = pickle.load(fh)
    pose = sim.creature.pose(float(sim.times[frames[ref]]))
    true = pose.limb[pose.capsule_sdf(V).argmin(1)]
    t0 = time.process_time()
    vl = vertex_limbs(rigged_model(spine, V, F, reference=ref))
    heat_s = time.process_time() - t0
    t0 = time.process_time()
    ours = template_labels(spine, V, F, reference=ref)
    ours_s = time.process_time() - t0
    surfaces = [load_mesh(by_frame[f], largest=False)[0] for f in frames]
    t0 = time.process_time()
    moving = template_labels(spine, V, F, reference=ref, surfaces=surfaces)
    moving_s = time.process_time() - t0
    return {"vertices": len(V), "true": true, "heat": vl.limb, "heat_s": heat_s, "labels": ours, "labels_s": ours_s,
            "motion": moving, "motion_s": moving_s}


def run(args: argparse.Namespace) -> int:
    root, specs = takes_root(args.root), take_specs(args.takes)
    print("| take | vertices | heat weights: right / body recall / body precision | template_labels | "
          "template_labels(surfaces=) | CPU s (heat, labels, surfaces=) |")
    print("| --- | --- | --- | --- | --- | --- |")
    rows = []
    for spec in specs:
        d = take_dir(root, spec)
        r = take_labels(d)
        scores = [label_scores(r[key], r["true"]) for key in ("heat", "labels", "motion")]
        rows.append(sum(scores, ()))
        print(f"| {d.name} | {r['vertices']} | " + " | ".join(f"{a:.3f} / {b:.3f} / {c:.3f}" for a, b, c in scores)
              + f" | {r['heat_s']:.2f}, {r['labels_s']:.2f}, {r['motion_s']:.2f} |", flush=True)
    if rows:
        m = np.mean(rows, axis=0)
        print("| mean | | " + " | ".join(f"{m[i]:.3f} / {m[i + 1]:.3f} / {m[i + 2]:.3f}" for i in (0, 3, 6)) + " | |")
    return 0
