"""``stage bench rig``: seconds for motion segmentation, skeleton and fit (Tzionas & Gall 2016, section 4).

Subjects: the simulated quadruped posed along its kinematic tree
(:func:`fake_cameras.mesh_motion.mesh_sequence`) at two mesh resolutions (about
6k and 50k vertices) and two lengths (60 and 500 frames). Targets on a 2-core
machine: segmentation (1000 samples) under 10 s for 50k vertices x 500 frames;
fit under 20 ms a frame.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

NAME = "rig"
HELP = "seconds for segmentation, skeleton and per-frame fit on ~6k/50k vertices, 60/500 frames"

#: marching-cubes cell (mm) of the quadruped for about 6k and 50k vertices
VOXELS = {"6k": 7.0, "50k": 2.5}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sizes", default="6k,50k", help="mesh sizes to run (default 6k,50k)")
    p.add_argument("--frames", default="60,500", help="sequence lengths to segment (default 60,500)")
    p.add_argument("--fit-frames", type=int, default=20, help="frames timed for the fit (default 20)")
    p.add_argument("--samples", type=int, default=1000, help="sampled vertices (default 1000)")


def run(args: argparse.Namespace) -> int:
    from fake_cameras.mesh_motion import mesh_sequence
    from pipeline.articulated_fit import articulated_model, fit_sequence
    from pipeline.articulated_skeleton import articulated_skeleton
    from pipeline.motion_segmentation import motion_segmentation

    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    lengths = [int(x) for x in args.frames.split(",") if x.strip()]
    bad = [s for s in sizes if s not in VOXELS]
    if bad:
        raise ValueError(f"--sizes: unknown size {bad[0]!r} (choose from {', '.join(VOXELS)})")
    print(f"{'vertices':>9} {'frames':>7} {'segment s':>10} {'dt':>4} {'k':>4} {'segments':>9} {'skeleton s':>11} "
          f"{'fit ms/frame':>13}")
    for size in sizes:
        for T in lengths:
            ms = mesh_sequence("quadruped", frames=T, voxel=VOXELS[size], dtype=np.float32)
            V = ms.vertices
            t0 = time.perf_counter()
            seg = motion_segmentation(V, ms.faces, n_samples=args.samples, lambda_thr=0.98)
            t_seg = time.perf_counter() - t0
            t0 = time.perf_counter()
            sk = articulated_skeleton(np.asarray(V[0], dtype=np.float64), ms.faces, seg.labels, motion=V, reference=0)
            model = articulated_model(np.asarray(V[0], dtype=np.float64), ms.faces, sk)
            t_sk = time.perf_counter() - t0
            n_fit = min(int(args.fit_frames), T)
            t0 = time.perf_counter()
            fit_sequence(model, np.asarray(V[:n_fit], dtype=np.float64))
            t_fit = (time.perf_counter() - t0) / n_fit * 1e3
            print(f"{V.shape[1]:>9} {T:>7} {t_seg:>10.2f} {seg.interval:>4} {seg.k:>4} {seg.n_segments:>9} {t_sk:>11.2f} "
                  f"{t_fit:>13.1f}")
            del ms, V
    return 0
