"""``stage demo --rgbd``: the single RGB-D camera path end to end on the simulated pipe.

1. render a take of one OAK-like RGB-D camera filming a pipe bent at 1/2 of its length,
   with its rest mesh as the template and per-vertex ground truth (``fake_cameras.rgbd``);
2. track the template through it (``stage track TAKE.h5 --template MESH``);
3. the armature of the tracked template (``stage armature``);
4. print the tracking accuracy against the ground truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def run_rgbd(args: argparse.Namespace) -> int:
    from fake_cameras.rgbd import record_rgbd_take, simulate_rgbd_take, template_path
    from pipeline.mesh_primitives import mesh_volume
    from pipeline.meshio import load_mesh
    from pipeline.track_rgbd import track_rgbd_take
    from stage.cli._progress import StepBars

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frames = int(args.frames)
    print(f"1/3 rendering {frames} frames of the simulated RGB-D pipe (joint at 1/2, bent 75 degrees)")
    tk = simulate_rgbd_take("pipe_half", frames=frames, spacing=4.0)
    take = record_rgbd_take(tk, out / "pipe_half.h5")
    print(f"2/3 tracking the {len(tk.template_vertices)}-vertex template: stage track {take} --template {template_path(take)}")
    quiet = bool(getattr(args, "quiet", False)) or args.no_progress
    with StepBars(disable=quiet) as bars:
        track_rgbd_take(take, template_path(take), out / "results", progress=bars)
    err, vol = [], []
    for k in range(frames):
        v, f = load_mesh(out / "results" / "tracked" / f"{k:06d}.ply", largest=False)
        err.append(np.linalg.norm(v - tk.truth[k], axis=1).mean())
        vol.append(mesh_volume(v, f) / mesh_volume(tk.template_vertices, tk.template_faces))
    from pipeline.armature import counted
    from pipeline.armature_files import armature_results

    arm = armature_results(out / "results")
    n = int(arm.skeleton.articulation.sum())
    print(f"3/3 stage armature: {counted(n, 'articulation')} (the pipe has 1) -> {out / 'results' / 'rig'}")
    print(f"accuracy: mean vertex error {np.mean(err):.2f} mm = {100 * np.mean(err) / tk.size:.2f} % of the pipe's "
          f"{tk.size:.0f} mm over the take (last frame {100 * err[-1] / tk.size:.2f} %); volume {min(vol):.3f}..{max(vol):.3f} "
          "of the template's")
    return 0
