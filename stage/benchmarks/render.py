"""``stage bench render``: seconds of the simulator's mesh renderer (:mod:`fake_cameras.mesh_render`).

Two subjects from ``../shared/data``: the Tzionas & Gall pipe (12 714 triangles, its first frame)
seen by the OAK-like camera at the sensor's pose (640x400, :func:`fake_cameras.rgbd.oak_sensor_camera`),
and the Sumner & Popovic horse (16 843 triangles, its first frame, stood in the capture volume)
in a dome of simulated cameras (640x480). Printed: the Embree scene's build, one camera's whole
frame (rays, shading, noise) and one frame in every dome camera; the best of ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

NAME = "render"
HELP = "seconds of the simulator's mesh renderer: the real pipe in one camera, the horse in a dome"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", type=int, default=8, help="dome cameras for the horse (default 8)")
    p.add_argument("--repeat", type=int, default=5, help="runs of each figure; the best is printed (default 5)")


def _best(f, n: int) -> float:
    times = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return min(times)


def run(args: argparse.Namespace) -> int:
    import trimesh

    from fake_cameras.dome import make_dome
    from fake_cameras.mesh_render import MeshScene, render_mesh_views
    from fake_cameras.mesh_take import stand_in_volume
    from fake_cameras.rgbd import oak_sensor_camera
    from stage.benchmarks._data import SHARED_DATA

    if args.cameras < 1 or args.repeat < 1:
        raise ValueError(f"--cameras and --repeat must be >= 1, got {args.cameras}, {args.repeat}")
    pipe, horse = SHARED_DATA / "tzionas_pipe" / "pipe.npz", SHARED_DATA / "horse_gallop" / "0001.obj"
    for path in (pipe, horse):
        if not path.is_file():
            raise ValueError(f"{path} is not there (the shared data next to the checkout); nothing to render")
    rng = np.random.default_rng(0)
    d = np.load(pipe)
    cam, world_from_sensor = oak_sensor_camera()
    V = d["vertices"][0] @ world_from_sensor[:3, :3].T + world_from_sensor[:3, 3]
    F = np.asarray(d["faces"])
    scene = _best(lambda: MeshScene(V, F), args.repeat)
    frame = _best(lambda: render_mesh_views([cam], V, F, rng=rng), args.repeat)
    print(f"pipe, {len(F)} triangles: Embree scene {1e3 * scene:.0f} ms; one 640x400 camera, whole frame "
          f"{1e3 * frame:.0f} ms")
    mesh = trimesh.load(horse, process=False)
    HV, _ = stand_in_volume(np.asarray(mesh.vertices)[None])
    dome = make_dome(args.cameras)
    views = _best(lambda: render_mesh_views(dome, HV[0], np.asarray(mesh.faces), rng=rng), args.repeat)
    print(f"horse, {len(mesh.faces)} triangles, {args.cameras} dome cameras 640x480: {views:.2f} s a frame")
    return 0
