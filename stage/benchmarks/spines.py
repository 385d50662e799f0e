"""``stage bench spines``: per-frame skeleton time vs mesh size, and correspondence time for a long take.

Meshes: the simulated quadruped (marching cubes of its signed distance at
three resolutions, about 10k / 50k / 200k faces) and, when ``../shared/data``
is present, the Sumner & Popovic horse (17k faces, and 4x / 16x subdivided).
Correspondence: a 495-frame take (the paper's camel length) synthesised by
cycling the simulated frames back and forth with small perturbations.
skeletor (wavefront and mesh-contraction) runs side by side when installed
(``pip install skeletor``; benchmark-only extra).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from stage.benchmarks._data import SHARED_DATA

NAME = "spines"
HELP = "seconds per frame of the spine pipeline on 10k/50k/200k-face meshes and correspondence time for 495 frames"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=495, help="take length for the correspondence timing (default 495)")
    p.add_argument("--repeat", type=int, default=2, help="timed runs per mesh, best kept (default 2)")
    p.add_argument("--no-skeletor", action="store_true", help="skip skeletor even when installed")


def _mesh_pose(pose, voxel):
    from skimage.measure import marching_cubes

    lo, hi = pose.bounds()
    lo, hi = lo - 2 * voxel, hi + 2 * voxel
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    g = [lo[i] + voxel * np.arange(n[i]) for i in range(3)]
    P = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    v, f, _, _ = marching_cubes(pose.sdf(P).reshape(n), 0.0, spacing=(voxel,) * 3)
    return v + lo, f


def _timed(fn, repeat):
    best, out = np.inf, None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def _tip_error(found, truth, size):
    if len(found) == 0 or truth is None:
        return float("nan")
    d = np.linalg.norm(np.asarray(found)[:, None] - truth[None], axis=2)
    return float(d.min(axis=0).mean() / size)


def _skeletor_rows(v, f, truth, size):
    try:
        import skeletor as sk
        import trimesh
    except ImportError:
        return None
    rows = []
    mesh = trimesh.Trimesh(v, f, process=False)
    for method in ("wavefront", "contraction"):
        t = time.perf_counter()
        try:
            if method == "wavefront":
                s = sk.skeletonize.by_wavefront(mesh, waves=1, step_size=1, progress=False)
            else:
                cont = sk.pre.contract(mesh, epsilon=1e-7, iter_lim=10, progress=False)
                s = sk.skeletonize.by_vertex_clusters(cont, sampling_dist=size / 50, progress=False)
        except Exception as exc:  # noqa: BLE001 - third-party extra, report and go on
            rows.append((method, float("nan"), 0, float("nan"), f"failed: {exc}"))
            continue
        dt = time.perf_counter() - t
        deg = np.bincount(np.asarray(s.edges).ravel(), minlength=len(s.vertices))
        leaves = np.asarray(s.vertices)[deg == 1]
        rows.append((method, dt, len(leaves), _tip_error(leaves, truth, size), ""))
    return rows


def run(args: argparse.Namespace) -> int:
    from fake_cameras.creatures import make_creature
    from pipeline.correspond import correspond_tips
    from pipeline.frame_skeleton import frame_skeleton
    from pipeline.spine import build_spine

    creature = make_creature("quadruped")
    pose = creature.pose(0.0)
    lo, hi = pose.bounds()
    size = float(np.linalg.norm(hi - lo))
    truth = pose.tip_array()
    cases = []
    for label, voxel in (("~10k", size / 85), ("~50k", size / 190), ("~200k", size / 380)):
        v, f = _mesh_pose(pose, voxel)
        cases.append((f"quadruped {label}", v, f, truth, size))
    import trimesh

    from pipeline.meshio import load_mesh

    p = SHARED_DATA / "horse_gallop" / "0001.obj"
    if p.is_file():
        v, f = load_mesh(p)
        hs = float(np.sqrt(trimesh.Trimesh(v, f, process=False).area))
        cases.append(("horse 17k", v, f, None, hs))
        v4, f4 = trimesh.remesh.subdivide(v, f)
        cases.append(("horse x4", v4, f4, None, hs))
        v16, f16 = trimesh.remesh.subdivide(v4, f4)
        cases.append(("horse x16", v16, f16, None, hs))
    else:
        print(f"(horse meshes not found at {p}: skipped)")

    skeletor_ok = not args.no_skeletor
    if skeletor_ok:
        try:
            import skeletor  # noqa: F401
        except ImportError:
            skeletor_ok = False
            print("skeletor is not installed (benchmark-only extra: pip install skeletor): its columns are skipped")

    print(f"{'mesh':<16} {'faces':>8} {'s/frame':>8} {'tips':>5} {'tip err/size':>13}")
    for name, v, f, tr, sz in cases:
        dt, fs = _timed(lambda v=v, f=f: frame_skeleton(v, f), args.repeat)
        err = _tip_error(fs.tips, tr, sz)
        print(f"{name:<16} {len(f):>8} {dt:>8.3f} {fs.n_tips:>5} {err:>13.4f}")
        if skeletor_ok:
            for method, sdt, n, serr, note in _skeletor_rows(v, f, tr, sz) or []:
                print(f"  skeletor {method:<11} {sdt:>8.3f} {n:>5} {serr:>13.4f} {note}")

    # correspondence on a long take
    T = int(args.frames)
    base_frames = []
    for i in range(24):
        v, f = _mesh_pose(creature.pose(i / 30.0), size / 56)
        base_frames.append(frame_skeleton(v, f))
    cycle = base_frames + base_frames[::-1][1:-1]
    rng = np.random.default_rng(0)
    from dataclasses import replace

    frames = []
    for t in range(T):
        fr = cycle[t % len(cycle)]
        jit = rng.normal(scale=0.002 * size, size=fr.tips.shape)
        frames.append(replace(fr, tips=fr.tips + jit, limb_points=fr.limb_points + jit[:, None]))
    dt_c, corr = _timed(
        lambda: correspond_tips([f.tips for f in frames], features=[f.limb_points for f in frames]), 1
    )
    dt_b, spine = _timed(lambda: build_spine(frames, fps=30.0), 1)
    print(f"correspondence, {T} frames: {dt_c:.2f} s (K = {corr.K}, references {corr.references})")
    print(f"whole reduce step (correspondence + imposed graph + resampling), {T} frames: {dt_b:.2f} s")
    return 0
