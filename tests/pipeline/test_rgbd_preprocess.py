"""Single RGB-D preprocessing (pipeline.rgbd_preprocess)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fake_cameras.rgbd import oak_camera, simulate_rgbd_take
from pipeline.mesh_primitives import vertex_normals
from pipeline.rgbd_preprocess import (
    back_project,
    bilateral_depth,
    depth_edges,
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


def _slow_render(v, f, cam):
    """Triangle by triangle, pixel by pixel: the z-buffer of :func:`render_depth`'s definition."""
    w, h = cam.size
    uv, z = cam.project(v, return_depth=True)
    out = np.full((h, w), np.inf)
    for tri in f:
        if np.any(z[tri] <= 1e-6):
            continue
        (ax, ay), (bx, by), (cx, cy) = uv[tri]
        den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        if abs(den) <= 1e-12:
            continue
        for y in range(max(int(np.ceil(uv[tri, 1].min())), 0), min(int(np.floor(uv[tri, 1].max())), h - 1) + 1):
            for x in range(max(int(np.ceil(uv[tri, 0].min())), 0), min(int(np.floor(uv[tri, 0].max())), w - 1) + 1):
                l0 = ((by - cy) * (x - cx) + (cx - bx) * (y - cy)) / den
                l1 = ((cy - ay) * (x - cx) + (ax - cx) * (y - cy)) / den
                l2 = 1.0 - l0 - l1
                if min(l0, l1, l2) >= -1e-9:
                    out[y, x] = min(out[y, x], l0 * z[tri[0]] + l1 * z[tri[1]] + l2 * z[tri[2]])
    return out


def test_render_depth_and_visibility_match_a_slow_reference():
    """Sphere partly outside the image and partly behind the camera's near plane: the vectorised
    z-buffer equals the triangle-by-triangle loop to 1e-9 mm, and the visible vertices are the ones it implies."""
    cam = oak_camera(size=(64, 40), distance=600.0, target=(0, 0, 300))
    m = trimesh.creation.icosphere(subdivisions=2, radius=120.0)
    for shift in ([0, 0, 300.0], [150.0, 60.0, 300.0]):
        v = m.vertices + shift
        z = render_depth(v, m.faces, cam)
        ref = _slow_render(v, m.faces, cam)
        assert np.array_equal(np.isfinite(z), np.isfinite(ref)) and np.isfinite(z).any()
        np.testing.assert_allclose(z[np.isfinite(z)], ref[np.isfinite(ref)], rtol=0, atol=1e-9)
        uv, zv = cam.project(v, return_depth=True)
        col, row = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (col >= 0) & (col < 64) & (row >= 0) & (row < 40) & (zv > 0)
        expect = np.zeros(len(v), bool)
        expect[inside] = zv[inside] <= ref[row[inside], col[inside]] + 3.0
        expect &= np.einsum("ij,ij->i", vertex_normals(v, m.faces), v - cam.center) < 0
        assert np.array_equal(visible_vertices(v, m.faces, cam, tolerance=3.0), expect)


def _preprocess_whole_image(z, cam, lo, hi, max_points):
    """:func:`preprocess_depth`'s steps on the whole image: its reference."""
    valid = z > 0
    raw = back_project(np.where(valid, z, 0), cam)
    with np.errstate(invalid="ignore"):
        valid &= np.all((raw >= lo) & (raw <= hi), axis=-1)
    seen = valid.copy()
    zf = bilateral_depth(np.where(valid, z, 0))
    P = back_project(zf, cam)
    N = depth_normals(P, cam, max_jump=6.0)
    valid &= np.isfinite(N).all(-1) & np.isfinite(P).all(-1)
    rows, cols = np.nonzero(valid)
    if len(rows) > max_points:
        keep = np.linspace(0, len(rows) - 1, max_points).astype(np.int64)
        rows, cols = rows[keep], cols[keep]
    return (P[rows, cols], N[rows, cols], np.stack([cols, rows], 1), valid, depth_edges(np.where(seen, zf, 0.0), jump=12.0),
            np.where(valid, zf, 0.0))


def test_preprocess_on_the_window_around_the_data_equals_the_whole_image(lamp):
    """The filter, normals and edges are computed on the window around the kept pixels only: the same
    frame as the whole image's, also when the object touches the image's border or fills it."""
    cam = lamp.calibration[0]
    V = lamp.template_vertices
    z = lamp.depth[0]
    obj = np.where(_preprocess_whole_image(z, cam, V.min(0) - 30, V.max(0) + 30, 10**9)[3], z, 0)
    cols = np.flatnonzero(obj.any(0))
    at_border = np.zeros_like(obj)
    at_border[:, : obj.shape[1] - cols[0] - 2] = obj[:, cols[0] + 2:]  # the object cut by the left border
    everything = (np.full(3, -1e9), np.full(3, 1e9))
    for depth, (lo, hi), max_points in ((z, (V.min(0) - 30, V.max(0) + 30), 20000), (z, (V.min(0) - 30, V.mean(0)), 500),
                                        (at_border, everything, 20000), (z, everything, 20000)):
        fr = preprocess_depth(depth, cam, bounds=(lo, hi), max_points=max_points)
        ref = _preprocess_whole_image(depth, cam, lo, hi, max_points)
        for got, want in zip((fr.points, fr.normals, fr.pixels, fr.valid, fr.contour, fr.depth), ref):
            assert got.shape == want.shape and np.array_equal(got, want)
    with pytest.raises(ValueError, match="camera's shape"):
        preprocess_depth(z[:-1], cam)
    for bad in ((0.0, 1.0), (V.max(0), V.min(0)), ((0, 0, 0), (1, 1))):
        with pytest.raises(ValueError, match="bounds"):
            preprocess_depth(z, cam, bounds=bad)
    assert len(preprocess_depth(z, cam, bounds=(np.full(3, np.nan), np.full(3, np.nan))).points) == 0  # NaN: no data


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
