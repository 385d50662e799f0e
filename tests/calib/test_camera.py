"""The camera model against OpenCV and exact formulas."""

import cv2
import numpy as np
import pytest

from calib.camera import (
    Camera,
    cached_pixel_grid_rays,
    cached_pixel_ray_depths,
    distort_normalized,
    matrix_to_rodrigues,
    pixel_rays,
    project_points,
    rodrigues_to_matrix,
    rotation_angle_deg,
    undistort_normalized,
)


def _camera(seed=0, dist=(-0.08, 0.03, 0.001, -0.0015, -0.01)):
    rng = np.random.default_rng(seed)
    R = rodrigues_to_matrix(rng.normal(size=3) * 0.4)
    t = np.array([20.0, -35.0, 1500.0])
    K = np.array([[820.0, 0.0, 322.5], [0.0, 815.0, 241.0], [0.0, 0.0, 1.0]])
    return Camera("c0", K, np.array(dist), R, t, (640, 480))


def _points_in_view(cam, n=500, seed=1):
    rng = np.random.default_rng(seed)
    pix = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(n, 2))
    z = rng.uniform(800.0, 2200.0, size=n)
    return cam.unproject(pix, z), pix, z


def test_project_matches_cv2_projectPoints():
    cam = _camera()
    pts, _, _ = _points_in_view(cam)
    ours = cam.project(pts)
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cam.rvec, cam.t, cam.K, cam.dist)
    # tolerance: float64 round-off only
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-8)


def test_unproject_roundtrip_and_rays():
    cam = _camera(3)
    pts, pix, z = _points_in_view(cam, seed=4)
    # unproject then project returns the pixel (Newton undistortion converges to ~1e-10 px)
    np.testing.assert_allclose(cam.project(pts), pix, atol=1e-7)
    np.testing.assert_allclose(cam.world_to_camera(pts)[:, 2], z, rtol=1e-12)
    origin, dirs = cam.rays(pix)
    np.testing.assert_allclose(origin, cam.center, atol=1e-9)
    # every point lies on its ray
    v = pts - origin
    cross = np.cross(v, dirs)
    assert np.max(np.linalg.norm(cross, axis=1)) < 1e-6
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)


def test_undistort_matches_cv2_undistortPoints():
    cam = _camera(5)
    rng = np.random.default_rng(0)
    pix = rng.uniform([0, 0], [639, 479], size=(300, 2))
    ref = cv2.undistortPoints(
        pix.reshape(-1, 1, 2), cam.K, cam.dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ).reshape(-1, 2)
    yd = (pix[:, 1] - cam.K[1, 2]) / cam.K[1, 1]
    xd = (pix[:, 0] - cam.K[0, 2]) / cam.K[0, 0]
    ours = undistort_normalized(np.stack([xd, yd], 1), cam.dist)
    np.testing.assert_allclose(ours, ref, atol=1e-7)
    # and distortion is its exact inverse
    np.testing.assert_allclose(distort_normalized(ours, cam.dist), np.stack([xd, yd], 1), atol=1e-12)


def test_no_distortion_is_pinhole_formula():
    cam = _camera(dist=(0, 0, 0, 0, 0))
    pts, _, _ = _points_in_view(cam, n=50)
    pc = pts @ cam.R.T + cam.t
    expected = (pc @ cam.K.T)[:, :2] / pc[:, 2:3]
    np.testing.assert_allclose(cam.project(pts), expected, atol=1e-9)
    np.testing.assert_allclose(cam.P @ np.c_[pts, np.ones(len(pts))].T, (pc @ cam.K.T).T, atol=1e-6)


def test_rodrigues_matches_cv2():
    rng = np.random.default_rng(2)
    for _ in range(20):
        r = rng.normal(size=3)
        ref, _ = cv2.Rodrigues(r)
        np.testing.assert_allclose(rodrigues_to_matrix(r), ref, atol=1e-12)
        np.testing.assert_allclose(rodrigues_to_matrix(matrix_to_rodrigues(ref)), ref, atol=1e-12)


def test_dict_roundtrip_and_depth():
    cam = _camera(7)
    again = Camera.from_dict(cam.to_dict())
    assert again == cam
    pts = np.array([[0.0, 0.0, 0.0], cam.center + cam.R[2] * -10.0])
    _, depth = cam.project(pts, return_depth=True)
    assert depth[0] > 0 and depth[1] < 0  # second point is behind the camera
    assert cam.in_image(np.array([[0, 0], [639.4, 479.4], [-1, 3], [640, 10]])).tolist() == [True, True, False, False]


def test_cached_grid_rays_equal_the_computed_ones():
    cam = _camera(dist=(-0.08, 0.03, 0.001, -0.0015, -0.01)).replace(size=(64, 48))
    o, d = cam.pixel_grid_rays()
    co, cd = cached_pixel_grid_rays(cam)
    np.testing.assert_array_equal(co, o)  # exact: the same computation
    np.testing.assert_array_equal(cd, d)
    again = cached_pixel_grid_rays(cam.replace())  # an equal camera hits the cache
    assert again[1] is cd
    with pytest.raises(ValueError, match="read-only"):
        cd[0, 0, 0] = 1.0
    other = cached_pixel_grid_rays(cam.replace(t=cam.t + 1.0))
    assert other[1] is not cd


def test_cached_ray_depths_are_the_rays_camera_frame_z_in_the_same_cache(monkeypatch):
    import calib.camera as camera_module

    cam = _camera(dist=(-0.08, 0.03, 0.001, -0.0015, -0.01)).replace(size=(64, 48))
    dz = cached_pixel_ray_depths(cam)
    o, d = cam.pixel_grid_rays()
    # independent check: a depth image back-projected as the docstring says lands at camera-frame
    # Z = the depth (world_to_camera, R X + t) on its own pixel (project, with the distortion).
    # Measured: 7.8e-16 relative in Z, 2.3e-13 px.
    depth = np.random.default_rng(4).uniform(300.0, 4000.0, size=dz.shape)
    P = (o + d * (depth / dz)[..., None]).reshape(-1, 3)
    np.testing.assert_allclose(cam.world_to_camera(P)[:, 2], depth.ravel(), rtol=1e-12)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    np.testing.assert_allclose(cam.project(P), np.stack([u.ravel(), v.ravel()], axis=1), rtol=0, atol=1e-9)
    assert dz.shape == (cam.height, cam.width) and (dz > 0).all() and (dz <= 1).all()  # unit rays, in front
    assert cached_pixel_ray_depths(cam.replace()) is dz  # an equal camera hits the cache
    with pytest.raises(ValueError, match="read-only"):
        dz[0, 0] = 1.0
    # one cache: the rays' entry holds the depths, and both go when the entry is evicted
    assert camera_module._RAY_CACHE[cam][2] is dz
    monkeypatch.setattr(camera_module, "_RAY_CACHE_SIZE", 1)
    cached_pixel_grid_rays(cam.replace(t=cam.t + 2.5))  # a camera not asked for before
    assert cam not in camera_module._RAY_CACHE and cached_pixel_ray_depths(cam) is not dz
    with pytest.raises(ValueError, match="camera"):
        cached_pixel_ray_depths(cam.to_dict())


def test_rotation_angle_is_the_rotation_vector_norm():
    """Against the exact angle |rvec| (to 1e-9 deg), batched and single, over (0, 180) degrees."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    theta = np.concatenate([rng.uniform(0, np.pi, 197), [1e-9, 1e-5, np.pi - 1e-6]])
    Rs = np.stack([rodrigues_to_matrix(a * t) for a, t in zip(axes, theta)])
    np.testing.assert_allclose(rotation_angle_deg(Rs), np.degrees(theta), atol=1e-9)
    assert isinstance(rotation_angle_deg(Rs[0]), float)
    assert rotation_angle_deg(Rs.reshape(20, 10, 3, 3)).shape == (20, 10)
    # the product of a rotation and its transpose is the identity to 1e-16: its angle is ~0, which
    # arccos of the trace reads as ~1e-6 degrees
    assert rotation_angle_deg(Rs[5] @ Rs[5].T) < 1e-12


def test_invalid_input():
    cam = _camera()
    with pytest.raises(ValueError, match="R must"):
        rotation_angle_deg(np.eye(2))
    with pytest.raises(ValueError, match="points"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="pixels"):
        cam.rays(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="K"):
        Camera("a", np.eye(2), np.zeros(5), np.eye(3), np.zeros(3), (10, 10))
    with pytest.raises(ValueError, match="R"):
        Camera("a", cam.K, np.zeros(5), np.diag([1.0, 1.0, -1.0]), np.zeros(3), (10, 10))
    with pytest.raises(ValueError, match="size"):
        Camera("a", cam.K, np.zeros(5), np.eye(3), np.zeros(3), (0, 10))
    with pytest.raises(ValueError, match="dist"):
        project_points(np.zeros((1, 3)), K=cam.K, dist=np.zeros(3), R=np.eye(3), t=np.ones(3))
    with pytest.raises(ValueError, match="depth"):
        cam.unproject(np.zeros((3, 2)), np.ones(2))
    with pytest.raises(ValueError, match="missing the key"):
        Camera.from_dict({"name": "x"})
    with pytest.raises(ValueError, match="pixels"):
        pixel_rays(np.zeros(5), K=cam.K, dist=cam.dist, R=cam.R, t=cam.t)
    with pytest.raises(ValueError, match="camera"):
        cached_pixel_grid_rays(cam.to_dict())
