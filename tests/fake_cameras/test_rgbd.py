"""Simulated single RGB-D takes (fake_cameras.rgbd)."""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.rgbd import OBJECTS, make_object, simulate_rgbd_take, stereo_depth_noise, template_mesh
from pipeline.mesh_primitives import mesh_volume


@pytest.mark.parametrize("name, joints, at", [("pipe_half", 1, 0.5), ("pipe_3q", 1, 0.75), ("lamp", 3, None)])
def test_objects_and_per_vertex_ground_truth(name, joints, at):
    tk = simulate_rgbd_take(name, frames=3, bend=75.0)
    obj = tk.object
    assert len(obj.joints) == joints
    if at is not None:
        seg = np.linalg.norm(np.diff(obj.points, axis=0), axis=1)
        assert seg[0] / seg.sum() == pytest.approx(at)
    assert np.degrees(np.abs(tk.angles[-1])).min() > 45  # bent well past 45 degrees
    # every template vertex, moved with its capsule, lies on the posed surface
    for k in (0, 2):
        sdf = obj.pose(tk.angles[k]).sdf(tk.truth[k])
        # (vertices in the crease of a bent joint sink into the neighbouring capsule)
        assert np.median(np.abs(sdf)) < 0.3 and np.percentile(np.abs(sdf), 90) < 1.0
    np.testing.assert_allclose(tk.truth[0], tk.template_vertices, atol=1e-9)  # rest mesh = template
    assert tk.depth.dtype == np.uint16 and (tk.depth[0] > 0).any()
    assert mesh_volume(tk.template_vertices, tk.template_faces) > 0


def test_template_is_closed_and_outward():
    import trimesh

    v, f = template_mesh(make_object("pipe_half"), spacing=5.0)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.volume > 0
    assert m.volume == pytest.approx(np.pi * 15**2 * 300 + 4 / 3 * np.pi * 15**3, rel=0.03)


def test_invalid_input():
    with pytest.raises(ValueError, match="name"):
        simulate_rgbd_take("teapot")
    with pytest.raises(ValueError, match="frames"):
        simulate_rgbd_take("lamp", frames=1)
    with pytest.raises(ValueError, match="bend"):
        simulate_rgbd_take("lamp", bend=400)
    assert OBJECTS == ("pipe_half", "pipe_3q", "lamp")
    rng = np.random.default_rng(0)
    z = np.full((4, 5), 800.0)
    for bad in (-1.0, float("nan"), float("inf"), "2", None, True):
        with pytest.raises(ValueError, match="sigma"):
            stereo_depth_noise(z, sigma=bad, rng=rng)
    for bad in (z[0], z[None], np.where(z > 0, np.nan, z), -z, [["a"]], None):
        with pytest.raises(ValueError, match="z must be"):
            stereo_depth_noise(bad, sigma=2.0, rng=rng)
    with pytest.raises(ValueError, match="rng"):
        stereo_depth_noise(z, sigma=2.0, rng=3)
    out = stereo_depth_noise(np.zeros((4, 5)), sigma=0, rng=rng)  # nothing seen stays 0; sigma 0 is exact
    assert out.dtype == np.uint16 and not out.any()
    assert (stereo_depth_noise(z, sigma=0.0, rng=rng) == 800).all()


def test_surface_point_tracks_stay_on_the_creature():
    from fake_cameras.creatures import make_creature
    from fake_cameras.surface_motion import capsule_frames, surface_point_tracks

    c = make_creature("quadruped", seed=3)
    p0 = c.pose(0.0)
    lo, hi = p0.bounds()
    X = np.random.default_rng(0).uniform(lo, hi, (20000, 3))
    X = X[np.abs(p0.sdf(X)) < 3][:500]
    times = np.array([0.0, 0.3, 0.9])
    tr = surface_point_tracks(c, X, times)
    for k, t in enumerate(times):
        assert np.percentile(np.abs(c.pose(t).sdf(tr[k])), 95) < 1e-6  # rigidly carried, still on the surface
    assert np.linalg.norm(tr[2] - tr[0], axis=1).mean() > 5  # and they do move
    R, o = capsule_frames(c, 0.3)
    np.testing.assert_allclose(np.einsum("kij,kil->kjl", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert len(R) == c.pose(0.3).n_capsules
    with pytest.raises(ValueError, match="creature"):
        capsule_frames("starfish", 0.0)
