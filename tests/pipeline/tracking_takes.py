"""Small simulated takes the tracking and carving tests share."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from pipeline.results import atomic_write_bytes, ply_bytes


def turning_sphere_results(root, *, frames=6, degrees=2.0, size=(320, 240), calib_meta=None):
    """A textured sphere (radius 150 mm) turning about an oblique axis through its centre, filmed by
    6 dome cameras, with its keyed (true) masks; the results directory holds the same surface every
    frame, so the turn is invisible to the surfaces. ``calib_meta``: the take's calibration's ``meta``
    (default the simulator's: exact cameras). -> (results directory, true vertices per frame)."""
    from calib import Calibration
    from fake_cameras.creatures import Pose, _rot
    from fake_cameras.dome import make_dome
    from fake_cameras.render import Backdrop, render_view
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter
    from stage.store.derived import write_masks

    calib = make_dome(6, size=size, seed=1)
    if calib_meta is not None:
        calib = Calibration(calib.cameras, calib.units, meta=calib_meta)
    c, r = np.array([0.0, 0.0, 300.0]), 150.0
    turns = [_rot((0.3, 0.2, 1.0), np.deg2rad(degrees) * k) for k in range(frames)]
    # texture painted on the body, without shading: what the images see is the turn alone
    bd = Backdrop(texture=0.3, texture_scale=0.5, key_intensity=0.0, fill_intensity=0.0, ambient=1.0)
    rng = np.random.default_rng(0)
    views = [[render_view(cam, Pose(p0=c[None], p1=c[None], r0=[r], r1=[r], limb=[-1],
                                    rest=np.concatenate([R, (c - R @ c)[:, None]], axis=1)[None]), backdrop=bd, rng=rng)
              for cam in calib] for R in turns]
    take = root / "take.h5"
    with TakeWriter(take, [CameraSpec(n, *size) for n in calib.names], calibration=calib, fps=30.0) as wr:
        for k in range(frames):
            t = int(k * 1e9 / 30)
            wr.write_set({n: Frame(views[k][i].image, n, k, t, t) for i, n in enumerate(calib.names)}, time_ns=t)
    for i, n in enumerate(calib.names):
        write_masks(take, n, np.stack([v[i].mask for v in views]))
    res = root / "results"
    m = trimesh.creation.icosphere(subdivisions=3, radius=r)
    for k in range(frames):
        atomic_write_bytes(res / "meshes" / f"frame_{k:06d}.ply", ply_bytes(m.vertices + c, m.faces))
    (res / "process.json").write_text(json.dumps({"take": str(take.resolve())}))
    return res, [m.vertices @ R.T + c for R in turns]


def pose_surface(pose, voxel: float):
    """Marching cubes of a simulated creature pose's exact distance at ``voxel`` mm, outward normals: (V, F)."""
    from skimage.measure import marching_cubes

    lo, hi = pose.bounds()
    lo, hi = lo - 2 * voxel, hi + 2 * voxel
    sdf = pose.grid_sdf([np.arange(lo[i], hi[i] + voxel, voxel) for i in range(3)])
    V, F, _, _ = marching_cubes(sdf, 0.0, spacing=(voxel,) * 3)
    return V + lo, F[:, ::-1].copy()


def still_spine(pose, frames: int):
    """A spine of ``frames`` equal frames: one junction at the centre of the pose's body capsules, limb ``k``'s axis
    from there through the pose's limb ``k`` (its capsules' axis)."""
    from pipeline.spine_format import Spine

    body = pose.limb < 0
    centre = ((pose.p0[body] + pose.p1[body]) / 2).mean(0)
    axes = {f"limb{k}": np.repeat(np.vstack([centre, pose.axes[m]])[None], frames, 0) for k, m in enumerate(pose.names)}
    return Spine(units="mm", fps=30.0, frame_indices=np.arange(frames), limb_ids=list(axes), junction_ids=["j0"],
                 parents={"j0": None, **{lid: "j0" for lid in axes}},
                 tips=np.repeat(np.array([[pose.axes[m][-1] for m in pose.names]]), frames, 0),
                 junctions=np.repeat(centre[None, None], frames, 0), axes=axes)


def creature_spine_results(root, name: str = "quadruped", *, frames: int = 3, voxel: float = 20.0,
                           step=(4.0, 0.0, 0.0)):
    """A simulated creature's surface (marching cubes of its exact distance) moving by ``step`` a frame, written
    as a results directory's ``meshes/`` with a ``spine.json`` of one junction at the body's centre whose limb axes
    run through the creature's limb axes. -> (vertices, faces) of frame 0."""
    from dataclasses import replace

    from fake_cameras.creatures import make_creature
    from pipeline.spine_format import write_spine

    pose = make_creature(name).pose(0.3)
    V, F = pose_surface(pose, voxel)
    spine = still_spine(pose, 1)
    moved = [k * np.asarray(step, float) for k in range(frames)]
    for k in range(frames):
        atomic_write_bytes(root / "meshes" / f"frame_{k:06d}.ply", ply_bytes(V + moved[k], F))
    write_spine(root / "spine.json", replace(
        spine, frame_indices=np.arange(frames), tips=np.concatenate([spine.tips + d for d in moved]),
        junctions=np.concatenate([spine.junctions + d for d in moved]),
        axes={lid: np.concatenate([a + d for d in moved]) for lid, a in spine.axes.items()}))
    return V, F
