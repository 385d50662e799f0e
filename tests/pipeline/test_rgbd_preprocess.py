"""Single RGB-D preprocessing (pipeline.rgbd_preprocess)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fake_cameras.rgbd import oak_camera, simulate_rgbd_take
from pipeline.rgbd_preprocess import (
    back_project,
    bilateral_depth,
    depth_normals,
    preprocess_depth,
    render_depth,
    rigid_icp,
    skin_mask,
    visible_vertices,
)
from pipeline.tracking import TrackingError, default_gate


def test_render_depth_of_a_sphere_matches_the_analytic_depth():
    cam = oak_camera(size=(160, 100), distance=600.0, target=(0, 0, 300))
    m = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    v = m.vertices + [0, 0, 300]
    z = render_depth(v, m.faces, cam)
    o, d = cam.pixel_grid_rays()
    c = np.array([0, 0, 300.0]) - o
    b = d @ c
    disc = b**2 - (c @ c - 80.0**2)
    t = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
    zt = t * (d @ cam.R[2])
    hit = np.isfinite(zt) & np.isfinite(z)
    z, zt = np.where(hit, z, 0), np.where(hit, zt, 0)
    inner = disc > 0.1 * 80.0**2  # away from the silhouette
    assert (np.isfinite(z) == np.isfinite(zt))[inner | ~np.isfinite(zt)].mean() > 0.99
    assert np.abs(z - zt)[hit & inner].max() < 0.3  # chord error of a 4x subdivided sphere
    vis = visible_vertices(v, m.faces, cam)
    assert 0.3 < vis.mean() < 0.44 and np.all(v[vis, 1] < 0)  # at most the cap seen from 600 mm (43 %), facing -y


def test_back_project_and_normals_of_a_plane():
    cam = oak_camera(size=(320, 200), distance=500.0, target=(0, 0, 300))
    depth = np.full((200, 320), 500, np.uint16)  # a wall facing the camera, ~2 mm per pixel
    P = back_project(depth, cam)
    np.testing.assert_allclose(P[..., 1], 0.0, atol=1e-9)
    n = depth_normals(P, cam)
    ok = np.isfinite(n).all(-1)
    assert ok[1:-1, 1:-1].all() and not ok[0].any()
    np.testing.assert_allclose(n[ok], np.broadcast_to([0, -1.0, 0], n[ok].shape), atol=1e-9)
    assert not np.isfinite(back_project(np.zeros((200, 320)), cam)).any()
    # the bilateral filter keeps the holes and does not smear the edge into them
    holed = depth.astype(np.float32)
    holed[:, :20] = 0
    out = bilateral_depth(holed)
    assert np.all(out[:, :20] == 0) and np.allclose(out[:, 20:], 500, atol=1e-3)


def test_skin_mask_removes_skin_keeps_object_and_backdrop():
    img = np.zeros((30, 90, 3), np.uint8)
    img[:, :30] = (120, 150, 210)  # light skin (BGR)
    img[:, 30:60] = (60, 110, 200)  # the simulator's brownish object? no: warm orange-brown
    img[:, 60:] = (50, 170, 50)  # green studio
    m = skin_mask(img)
    assert m[:, :30].mean() > 0.99
    assert m[:, 60:].mean() == 0
    blue = np.full((10, 10, 3), (200, 80, 30), np.uint8)
    assert not skin_mask(blue).any()
    with pytest.raises(ValueError, match="image"):
        skin_mask(np.zeros((4, 4)))


@pytest.fixture(scope="module")
def lamp():
    return simulate_rgbd_take("lamp", frames=2, bend=0.0)


def test_preprocess_crops_to_the_volume(lamp):
    cam = lamp.calibration[0]
    V = lamp.template_vertices
    lo, hi = V.min(0) - 30, V.max(0) + 30
    fr = preprocess_depth(lamp.depth[0], cam, bounds=(lo, hi))
    assert len(fr.points) > 1000
    assert np.all((fr.points >= lo) & (fr.points <= hi))
    sdf = lamp.object.pose(lamp.angles[0]).sdf(fr.points)
    assert np.abs(sdf).mean() < 0.5  # on the object (no floor, no wall), to the depth noise
    np.testing.assert_allclose(np.linalg.norm(fr.normals, axis=1), 1.0, atol=1e-9)
    with pytest.raises(ValueError, match="remove_skin"):
        preprocess_depth(lamp.depth[0], cam, remove_skin=True)


def test_rigid_icp_places_a_roughly_placed_template_and_refuses_a_far_one(lamp):
    cam = lamp.calibration[0]
    V, F = lamp.template_vertices, lamp.template_faces
    fr = preprocess_depth(lamp.depth[0], cam, bounds=(V.min(0) - 30, V.max(0) + 30))
    c = V.mean(0)
    a = np.radians(4.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rough = (V - c) @ Rz.T + c + [8.0, 5.0, -6.0]
    R, t, fit = rigid_icp(rough, F, fr.points, fr.normals, cam, gate=default_gate(V))
    assert np.linalg.norm(rough @ R.T + t - V, axis=1).mean() < 1.5 and fit > 0.9
    with pytest.raises(TrackingError, match="cannot place"):
        rigid_icp(V + [0, 0, 900.0], F, fr.points, fr.normals, cam, gate=default_gate(V))
