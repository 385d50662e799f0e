"""Shape from silhouette across time (:mod:`pipeline.temporal_hull`).

The subject is an L of two capsules turning about the vertical axis, filmed by three cameras of
the analytic rig (:mod:`tests.pipeline.simrig`: silhouettes ray-marched from the signed distance
function); its motion is known exactly, so the tracks are the true motion of points on its
surface. Compared: the signed distance images with a brute-force distance to every background
pixel, the local rigid motions with a per-vertex Kabsch loop, and the carved surface with the
true one.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.surface import surface_from_field
from pipeline.temporal_hull import carve_across_time, local_motions, signed_distance_image, silhouette_distance
from pipeline.volume import Grid
from tests.pipeline.simrig import _capsule_sdf, dome, render

CENTRE = np.array([0.0, 0.0, 300.0])


def _turn(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ell_sdf(angle: float):
    """The L turned by ``angle`` about the vertical axis through CENTRE."""
    R = _turn(angle)
    caps = [(np.array([-120.0, 0, 0]), np.array([120.0, 0, 0]), 45.0),
            (np.array([120.0, 0, 0]), np.array([120.0, 110, 60]), 30.0)]

    def sdf(points):
        p = (np.asarray(points, float).reshape(-1, 3) - CENTRE) @ R  # into the L's own frame
        return np.min([_capsule_sdf(p, a, b, r) for a, b, r in caps], axis=0)

    return sdf


@pytest.fixture(scope="module")
def turning_ell():
    cams = dome(3, size=(160, 120), target=tuple(CENTRE), distortion=False, seed=1)
    angles = np.deg2rad(np.arange(0, 120, 15))  # 8 frames, 15 degrees apart
    images = {}
    for k, a in enumerate(angles):
        masks, _ = render(cams, _ell_sdf(a))
        images[k] = [signed_distance_image(m) for m in masks]
    grid = Grid(lo=CENTRE - 230, shape=(46, 46, 46), voxel=10.0)
    # template: points on the true surface at frame 0, carried by the true motion
    rng = np.random.default_rng(0)
    x = rng.uniform(-230, 230, size=(200000, 3)) + CENTRE
    sdf0 = _ell_sdf(0.0)
    x = x[np.abs(sdf0(x)) < 2.0][:4000]
    tracks = {k: (x - CENTRE) @ _turn(a).T + CENTRE for k, a in enumerate(angles)}
    return dict(cams=list(cams), images=images, grid=grid, tracks=tracks, angles=angles)


def test_signed_distance_image_matches_brute_force():
    yy, xx = np.mgrid[0:40, 0:50]
    mask = (xx - 22.3) ** 2 + (yy - 19.6) ** 2 < 11.0 ** 2
    mask[5:9, 40:46] = True
    sd = signed_distance_image(mask)
    fg, bg = np.argwhere(mask), np.argwhere(~mask)
    for (r, c) in [(19, 22), (10, 22), (30, 30), (7, 43), (2, 2), (39, 49), (20, 34)]:
        other = bg if mask[r, c] else fg
        d = np.sqrt(((other - [r, c]) ** 2).sum(axis=1)).min()  # distance to the nearest pixel of the other side
        assert sd[r, c] == pytest.approx(d if mask[r, c] else -d, abs=1e-3), (r, c)


def test_silhouette_distance_is_bilinear_image_times_footprint(turning_ell):
    cams, images = turning_ell["cams"], turning_ell["images"][0]
    rng = np.random.default_rng(2)
    X = rng.uniform(-150, 150, size=(50, 3)) + CENTRE
    got = silhouette_distance(X, images, cams)
    for c, cam in enumerate(cams):
        uv, z = cam.project(X, return_depth=True)
        for i, ((u, v), zi) in enumerate(zip(uv, z)):
            u0, v0 = int(np.floor(u)), int(np.floor(v))
            a, b = u - u0, v - v0
            im = images[c]
            val = ((1 - a) * (1 - b) * im[v0, u0] + a * (1 - b) * im[v0, u0 + 1]
                   + (1 - a) * b * im[v0 + 1, u0] + a * b * im[v0 + 1, u0 + 1])
            assert got[c, i] == pytest.approx(val * zi / cam.K[0, 0], rel=1e-3, abs=1e-3)
    # a margin grows every silhouette by that many pixels: the footprint's worth more everywhere
    z = np.stack([cam.project(X, return_depth=True)[1] for cam in cams])
    footprint = z / np.array([cam.K[0, 0] for cam in cams])[:, None]
    np.testing.assert_allclose(silhouette_distance(X, images, cams, margin=1.5), got + 1.5 * footprint, rtol=1e-6, atol=1e-6)
    # one margin per camera: each camera's own
    each = np.arange(len(cams)) * 0.75
    np.testing.assert_allclose(silhouette_distance(X, images, cams, margin=each), got + each[:, None] * footprint,
                               rtol=1e-6, atol=1e-6)


def test_local_motions_match_a_kabsch_loop():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    P = rng.normal(size=(600, 3)) * 40
    Q = P @ _turn(0.4).T + [3.0, -2.0, 5.0] + rng.normal(size=P.shape) * 0.3
    R, c0, c1 = local_motions(P, Q, neighbours=30)
    nn = cKDTree(P).query(P, k=30)[1]
    for i in range(0, 600, 37):
        A, B = P[nn[i]], Q[nn[i]]
        U, _, Vt = np.linalg.svd((A - A.mean(0)).T @ (B - B.mean(0)))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        np.testing.assert_allclose(R[i], Vt.T @ D @ U.T, atol=1e-9)
        np.testing.assert_allclose(c0[i], A.mean(0), atol=1e-9)
        np.testing.assert_allclose(c1[i], B.mean(0), atol=1e-9)


def _surface_error(field, grid, sdf):
    """Mean and 95th percentile of the surface's distance to the true one, and its deepest point inside it (voxels)."""
    mesh = surface_from_field(field, grid, level=0.0, inside="above")
    d = sdf(np.asarray(mesh.vertices)) / grid.voxel
    return np.abs(d).mean(), np.percentile(np.abs(d), 95), d.min()


def test_carving_across_time_removes_the_hull_excess(turning_ell):
    t = turning_ell
    grid, sdf0 = t["grid"], _ell_sdf(0.0)
    alone = carve_across_time(grid, 0, {0: t["tracks"][0]}, t["images"], t["cams"])
    carved = carve_across_time(grid, 0, t["tracks"], t["images"], t["cams"])
    mean_alone, p95_alone, deepest_alone = _surface_error(alone, grid, sdf0)
    mean_carved, p95_carved, deepest = _surface_error(carved, grid, sdf0)
    # measured (voxels): the frame alone 0.70 / 2.82 (mean / 95th percentile), carved by all 8 frames 0.20 / 0.41
    assert mean_carved < 0.5 * mean_alone, (mean_carved, mean_alone)
    assert p95_carved < 0.25 * p95_alone, (p95_carved, p95_alone)
    # the true motion carves no deeper into the body than the frame's own silhouettes (a pixel is 1.4 voxels
    # there): measured -0.57 against -0.62
    assert deepest >= deepest_alone - 0.1, (deepest, deepest_alone)


def test_invalid_input(turning_ell):
    t = turning_ell
    with pytest.raises(ValueError, match="mask"):
        signed_distance_image(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match="points"):
        silhouette_distance(np.zeros((3, 2)), t["images"][0], t["cams"])
    with pytest.raises(ValueError, match="images"):
        silhouette_distance(np.zeros((3, 3)), t["images"][0][:2], t["cams"])
    assert len(t["cams"]) == 3
    for bad in (-1, np.nan, True, [1.0] * 4, [1.0, -1.0, 1.0]):
        with pytest.raises(ValueError, match="margin"):
            silhouette_distance(np.zeros((3, 3)), t["images"][0], t["cams"], margin=bad)
    with pytest.raises(ValueError, match="margin"):
        carve_across_time(t["grid"], 0, t["tracks"], t["images"], t["cams"], margin=[0.5])
    with pytest.raises(ValueError, match="images\\[0\\]"):
        silhouette_distance(np.zeros((3, 3)), [np.zeros((5, 5), np.float32)] * 3, t["cams"])
    with pytest.raises(ValueError, match="neighbours"):
        local_motions(np.zeros((5, 3)), np.zeros((5, 3)), neighbours=2)
    with pytest.raises(ValueError, match="after"):
        local_motions(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="grid"):
        carve_across_time(None, 0, t["tracks"], t["images"], t["cams"])
    with pytest.raises(ValueError, match="frame"):
        carve_across_time(t["grid"], 99, t["tracks"], t["images"], t["cams"])
    with pytest.raises(ValueError, match="band"):
        carve_across_time(t["grid"], 0, t["tracks"], t["images"], t["cams"], band=0)
    with pytest.raises(ValueError, match="ignore"):
        carve_across_time(t["grid"], 0, t["tracks"], t["images"], t["cams"], ignore=-1)
    with pytest.raises(ValueError, match="tracks\\[1\\]"):
        carve_across_time(t["grid"], 0, {0: t["tracks"][0], 1: t["tracks"][1][:10]}, t["images"], t["cams"])
