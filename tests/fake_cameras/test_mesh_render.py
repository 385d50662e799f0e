"""Ray-cast mesh rendering (fake_cameras.mesh_render) and RGB-D takes of mesh sequences (fake_cameras.rgbd)."""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.creatures import make_creature
from fake_cameras.dome import make_dome
from fake_cameras.mesh_render import MeshScene, render_mesh, render_mesh_views
from fake_cameras.render import Backdrop, render_view
from fake_cameras.rgbd import (
    load_rgbd_ground_truth,
    make_object,
    oak_camera,
    oak_sensor_camera,
    record_rgbd_take,
    simulate_mesh_rgbd_take,
    simulate_sensor_rgbd_take,
    template_mesh,
)


def _pose_mesh(pose, h=2.0):
    """Marching cubes of a capsule pose's exact signed distance (the slow reference's surface)."""
    from skimage.measure import marching_cubes

    lo, hi = pose.bounds()
    lo, hi = lo - 2 * h, hi + 2 * h
    axes = [np.arange(lo[i], hi[i] + h, h) for i in range(3)]
    v, f, _, _ = marching_cubes(pose.grid_sdf(axes), 0.0, spacing=(h, h, h))
    return v + lo, f.astype(np.int64)


def test_mesh_of_the_capsules_renders_as_the_capsules_in_every_distorted_dome_camera():
    """The analytic capsule renderer is the reference: a 2 mm marching-cubes mesh of the same pose."""
    pose = make_creature("starfish", seed=0).pose(0.0)
    V, F = _pose_mesh(pose)
    cal = make_dome(6, size=(320, 240), seed=1)
    assert any(np.abs(c.dist).max() > 0 for c in cal.cameras)  # lens distortion is rendered
    bd = Backdrop(painted=False)  # both: the texture of the world position
    views = render_mesh_views(cal, V, F, backdrop=bd, rng=np.random.default_rng(0), depth=True, noise_sigma=0)
    assert len(views) == len(cal.cameras)
    for cam, mv in zip(cal.cameras, views):
        ref = render_view(cam, pose, backdrop=bd, rng=np.random.default_rng(0), depth=True, noise_sigma=0)
        assert mv.mask.sum() > 500
        # measured: 0..0.4 % of the silhouette's pixels differ (the mesh's chords at the outline)
        assert (mv.mask ^ ref.mask).sum() <= 0.03 * ref.mask.sum()
        both = mv.mask & ref.mask
        dz = np.abs(mv.depth[both].astype(float) - ref.depth[both])
        assert np.median(dz) <= 0.5 and np.percentile(dz, 99) <= 2.0  # measured: median 0, 99th 1 mm
        di = np.abs(mv.image[both].astype(float) - ref.image[both])
        assert di.mean() <= 2.0  # measured: 0.4..0.6 grey levels (interpolated vertex normals against the exact ones)
        assert (mv.label[mv.mask] == -1).all() and (mv.label[~mv.mask] == -2).all()


def test_painted_texture_moves_with_the_surface():
    """Mesh and camera moved together: with rest-point texture the object's pixels are the same."""
    obj = make_object("pipe_half")
    V, F = template_mesh(obj, spacing=4.0)
    cam = oak_camera(target=obj.points.mean(0))
    d = np.array([40.0, 0.0, 0.0])
    moved = cam.replace(t=cam.t - cam.R @ d)  # the camera's centre moved by d
    bd = Backdrop(wall_radius=4000.0, wall_height=4000.0, texture=0.15, texture_scale=0.5, shadow_strength=0.0)
    kw = dict(backdrop=bd, noise_sigma=0)
    a = render_mesh(cam, V, F, texture_points=V, **kw)
    b = render_mesh(moved, V + d, F, texture_points=V, **kw)
    c = render_mesh(moved, V + d, F, **kw)  # texture of the world position: it stays behind
    assert np.array_equal(a.mask, b.mask)
    import cv2

    inner = cv2.erode(a.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)  # blur mixes the edge
    diff_b = np.abs(a.image[inner].astype(int) - b.image[inner]).max()
    diff_c = np.abs(a.image[inner].astype(int) - c.image[inner]).mean()
    assert diff_b <= 1  # the same up to rounding (measured: 0)
    assert diff_c > 2 * max(diff_b, 1)  # measured: 3.9 grey levels on average


def test_scene_hits_match_a_slow_reference():
    """Embree's first hits against a per-ray loop over every triangle (Moller-Trumbore)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    sc = MeshScene(m.vertices + [0, 0, 500.0], m.faces)
    rng = np.random.default_rng(0)
    dirs = rng.normal([0, 0, 1], 0.08, (200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, face, bary = sc.cast(np.zeros(3), dirs)
    tri = sc.vertices[sc.faces]
    for i, dvec in enumerate(dirs):
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        p = np.cross(dvec, e2)
        det = np.einsum("ij,ij->i", e1, p)
        s = -tri[:, 0]
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        v = (q @ dvec) / det
        tt = np.einsum("ij,ij->i", e2, q) / det
        ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > 0)
        if not ok.any():
            assert face[i] == -1 and np.isinf(t[i])
            continue
        j = np.flatnonzero(ok)[np.argmin(tt[ok])]
        assert t[i] == pytest.approx(tt[j], abs=1e-6)
        np.testing.assert_allclose(bary[i], [1 - u[j] - v[j], u[j], v[j]], atol=1e-4)  # Embree's float32


def test_sensor_frame_take_sees_the_sequence_where_the_sensor_did(tmp_path):
    obj = make_object("pipe_half", base=(0.0, 0.0, 0.0))
    V, F = template_mesh(obj, spacing=5.0)
    V = V[:, [2, 0, 1]]  # its axis along the sensor's x (an even permutation: still outward)
    seq = np.stack([V + [0, 40.0, 600.0], V + [10.0, 40.0, 600.0]])  # in front of the sensor, below its axis
    tk = simulate_sensor_rgbd_take(seq, F, joint_positions=np.zeros((2, 1, 3)) + [0, 40.0, 600.0], length=330.0)
    cam = tk.calibration[0]
    np.testing.assert_allclose(cam.world_to_camera(tk.truth[1]), seq[1], atol=1e-9)
    np.testing.assert_allclose(cam.world_to_camera(tk.joint_positions[0]), [[0, 40.0, 600.0]], atol=1e-9)
    near = tk.depth[0][(tk.depth[0] > 0) & (tk.depth[0] < 1000)]
    assert near.size > 1000 and 570 <= near.min() and near.max() <= 620  # the pipe's near side, 15 mm radius
    path = record_rgbd_take(tk, tmp_path / "seq.h5")
    gt = load_rgbd_ground_truth(path)
    assert gt["length"] == 330.0 and gt["truth"].shape == (2, len(V), 3)
    np.testing.assert_allclose(gt["template_vertices"], tk.truth[0])


def test_invalid_input():
    obj = make_object("pipe_half")
    V, F = template_mesh(obj, spacing=6.0)
    cam = oak_camera(target=obj.points.mean(0))
    with pytest.raises(ValueError, match="cameras"):
        render_mesh_views([], V, F)
    with pytest.raises(ValueError, match="camera"):
        render_mesh("oak", V, F)
    with pytest.raises(ValueError, match="vertices"):
        render_mesh(cam, V[:, :2], F)
    with pytest.raises(ValueError, match="faces"):
        render_mesh(cam, V, F + len(V))
    with pytest.raises(ValueError, match="texture_points"):
        render_mesh(cam, V, F, texture_points=V[:-1])
    with pytest.raises(ValueError, match="face_label"):
        render_mesh(cam, V, F, face_label=np.zeros(3, int))
    with pytest.raises(ValueError, match="backdrop"):
        render_mesh(cam, V, F, backdrop="green")
    with pytest.raises(ValueError, match="noise_sigma"):
        render_mesh(cam, V, F, noise_sigma=-1)
    with pytest.raises(ValueError, match="vertices"):
        simulate_mesh_rgbd_take(V[None], F, cam)  # one frame
    with pytest.raises(ValueError, match="camera"):
        simulate_mesh_rgbd_take(np.stack([V, V]), F, "oak")
    with pytest.raises(ValueError, match="joint_positions"):
        simulate_mesh_rgbd_take(np.stack([V, V]), F, cam, joint_positions=np.zeros((3, 1, 3)))
    with pytest.raises(ValueError, match="in view"):
        simulate_mesh_rgbd_take(np.stack([V, V]) + [0, -2000.0, 0], F, cam)  # behind the camera
    for bad in ("x", [1.0, 2.0], 0.0, -3.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="length must be a positive number"):
            simulate_mesh_rgbd_take(np.stack([V, V]), F, cam, length=bad)
    with pytest.raises(ValueError, match="height"):
        oak_sensor_camera(height=-5.0)
    with pytest.raises(ValueError, match="vertices"):
        simulate_sensor_rgbd_take(V, F)  # one frame, not a sequence
