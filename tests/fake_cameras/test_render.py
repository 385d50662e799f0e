"""The renderer against independent references: sphere tracing of the exact SDF, projection, statistics."""

import numpy as np
import pytest

from fake_cameras.creatures import Pose, make_creature, round_cone_sdf_pairs
from fake_cameras.dome import make_dome
from fake_cameras.render import BACKGROUND, Backdrop, intersect_round_cones, render_view


def sphere_trace(origin, dirs, sdf, *, t0=None, t_max=6000.0, eps=1e-5, iters=3000):
    """Slow reference: march along each ray by the exact signed distance."""
    n = dirs.shape[0]
    t = np.zeros(n) if t0 is None else t0.copy()
    hit = np.zeros(n, dtype=bool)
    dmin = np.full(n, np.inf)
    active = np.ones(n, dtype=bool)
    for _ in range(iters):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        o = origin if np.ndim(origin) == 1 else origin[idx]
        d = sdf(o + t[idx, None] * dirs[idx], idx)
        dmin[idx] = np.minimum(dmin[idx], d)
        h = d < eps
        hit[idx[h]] = True
        t[idx[~h]] += d[~h]
        active[idx[h]] = False
        active[idx[~h][t[idx[~h]] > t_max]] = False
    return hit, t, dmin


def test_ray_round_cone_intersection_matches_sphere_tracing():
    rng = np.random.default_rng(5)
    n = 4000
    pa = rng.uniform(-40, 40, (n, 3))
    pb = pa + rng.uniform(-60, 60, (n, 3))
    ra = rng.uniform(2, 30, n)
    rb = rng.uniform(2, 30, n)
    origins = rng.normal(size=(n, 3))
    origins = 400 * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    # a quarter of the rays look along the cone axis from beyond its small end (apex side)
    q = n // 4
    axis = (pb[:q] - pa[:q]) / np.linalg.norm(pb[:q] - pa[:q], axis=1, keepdims=True)
    small_b = rb[:q] < ra[:q]
    end = np.where(small_b[:, None], pb[:q], pa[:q])
    sgn = np.where(small_b, 1.0, -1.0)[:, None]
    origins[:q] = end + sgn * axis * rng.uniform(100, 900, (q, 1))
    target = (pa + pb) / 2 + rng.normal(scale=25, size=(n, 3))
    dirs = target - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, nrm = intersect_round_cones(origins, dirs, pa, pb, ra, rb)

    def sdf(p, idx):
        return round_cone_sdf_pairs(p, pa[idx], pb[idx], ra[idx], rb[idx])

    hit, tr, dmin = sphere_trace(origins, dirs, sdf, t_max=2000)
    clear = hit | (dmin > 1e-3)  # leave out rays that graze the surface
    assert clear.mean() > 0.99
    assert np.array_equal(np.isfinite(t)[clear], hit[clear])
    both = clear & hit
    assert both.sum() > n // 3
    assert np.max(np.abs(t[both] - tr[both])) < 1e-3
    # normals are unit and point against the ray at the first hit
    assert np.allclose(np.linalg.norm(nrm[both], axis=1), 1)
    assert np.all(np.einsum("ij,ij->i", nrm[both], dirs[both]) < 1e-9)
    # the normal is the SDF gradient
    p = origins[both] + t[both, None] * dirs[both]
    g = np.stack(
        [(sdf(p + e, np.flatnonzero(both)) - sdf(p - e, np.flatnonzero(both))) / 2e-4 for e in np.eye(3) * 1e-4], axis=1
    )
    assert np.max(np.linalg.norm(g - nrm[both], axis=1)) < 1e-3


@pytest.fixture(scope="module")
def small_dome():
    return make_dome(4, size=(160, 120), seed=1)


@pytest.mark.parametrize("name,time_s", [("quadruped", 0.4), ("starfish", 1.3), ("biped", 2.1)])
def test_silhouette_equals_sphere_traced_reference(small_dome, name, time_s):
    pose = make_creature(name).pose(time_s)
    for cam in small_dome:
        view = render_view(cam, pose, rng=np.random.default_rng(0), depth=True)
        w, h = cam.size
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        pix = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
        origin, dirs = cam.rays(pix)  # independent of the renderer's ray cache
        c, R = pose.bounding_sphere()
        oc = c - origin
        proj = dirs @ oc
        near = (oc @ oc - proj**2 <= (R + 1) ** 2) & (proj > 0)
        # rays missing the bounding sphere can't hit; trace the others from the sphere
        assert not view.mask.ravel()[~near].any()
        idx = np.flatnonzero(near)
        t0 = np.maximum(proj[idx] - np.sqrt(np.maximum((R + 1) ** 2 - (oc @ oc - proj[idx] ** 2), 0)), 0)
        hit, t, dmin = sphere_trace(origin, dirs[idx], lambda p, i: pose.sdf(p), t0=t0, t_max=proj[idx].max() + R + 10)
        clear = hit | (dmin > 1e-3)
        got = view.mask.ravel()[idx]
        assert np.array_equal(got[clear], hit[clear]), cam.name
        assert hit.sum() > 50
        # depth: camera-frame Z of the first hit, rounded to mm
        z_ref = t[hit] * (dirs[idx][hit] @ cam.R[2])
        z = view.depth.ravel()[idx][hit].astype(float)
        assert np.max(np.abs(z - z_ref)) <= 0.5 + 1e-6
        # labels: limb of the capsule nearest to the hit point
        pts = origin + t[hit, None] * dirs[idx][hit]
        lab = view.label.ravel()[idx][hit]
        caps = pose.capsule_sdf(pts)
        own = caps[np.arange(len(lab)), :]
        # the labelled limb owns a capsule that touches the hit point
        ok = [np.any(np.abs(own[k, pose.limb == lab[k]]) < 1e-3) for k in range(len(lab))]
        assert np.mean(ok) == 1.0
        assert np.all(view.label[~view.mask] == BACKGROUND)


def test_known_points_land_where_projected():
    cal = make_dome(4, size=(640, 480), seed=2)[:3]
    pts = np.array([[0, 0, 375], [300, -280, 80], [-310, 290, 660], [250, 300, 600], [-300, -300, 300]], float)
    worst = 0.0
    for X in pts:
        pose = Pose.spheres(X[None], 20.0)
        for cam in cal:
            v = render_view(cam, pose, noise_sigma=0, backdrop=Backdrop(blur_sigma=0))
            rr, cc = np.nonzero(v.mask)
            assert rr.size > 60
            centroid = np.array([cc.mean(), rr.mean()])
            err = np.linalg.norm(centroid - cam.project(X[None])[0])
            worst = max(worst, err)
    assert worst < 0.5


@pytest.fixture(scope="module")
def quad_views():
    cam = make_dome(4, size=(320, 240), seed=0)[1]
    pose = make_creature("quadruped").pose(0.5)
    clean = Backdrop(blur_sigma=0)
    return dict(
        cam=cam,
        pose=pose,
        noisy=render_view(cam, pose, rng=np.random.default_rng(1), noise_sigma=4.0, backdrop=clean),
        clean=render_view(cam, pose, noise_sigma=0, backdrop=clean),
        plate=render_view(cam, None, noise_sigma=0, backdrop=clean),
        default=render_view(cam, pose, rng=np.random.default_rng(2), depth=True),
    )


def test_backdrop_is_green_and_the_creature_is_not(quad_views):
    import cv2

    v = quad_views["default"]
    img = v.image.astype(int)
    b, g, r = img[..., 0], img[..., 1], img[..., 2]
    bg = ~v.mask
    assert np.mean(((g > b + 30) & (g > r + 30))[bg]) > 0.99
    # away from the green spill at the silhouette the creature is red-dominant
    inner = cv2.erode(v.mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert inner.sum() > 100
    assert np.mean((r > g)[inner]) > 0.95
    # uneven light: the backdrop is not flat
    assert np.std(g[bg]) > 8


def test_shadow_only_darkens_the_floor(quad_views):
    v, plate = quad_views["clean"], quad_views["plate"]
    diff = plate.image.astype(int) - v.image.astype(int)
    outside = ~v.mask
    assert diff[outside].min() >= 0  # nothing outside the creature gets brighter
    shadow = outside & (diff.sum(2) > 30)
    assert shadow.sum() > 100
    # the shadow is darker green, still green
    img = v.image.astype(int)
    assert np.all(img[shadow][:, 1] > img[shadow][:, 0]) and np.all(img[shadow][:, 1] > img[shadow][:, 2])


def test_green_spill_near_the_silhouette(quad_views):
    import cv2

    v = quad_views["clean"]
    m = v.mask.astype(np.uint8)
    edge = v.mask & ~cv2.erode(m, np.ones((3, 3), np.uint8)).astype(bool)
    inner = cv2.erode(m, np.ones((11, 11), np.uint8)).astype(bool)
    img = v.image.astype(float) + 1
    ratio = img[..., 1] / img[..., 2]
    assert ratio[edge].mean() > ratio[inner].mean() + 0.2


def test_noise_statistics(quad_views):
    d = quad_views["noisy"].image.astype(float) - quad_views["clean"].image.astype(float)
    assert np.array_equal(quad_views["noisy"].mask, quad_views["clean"].mask)
    assert abs(d.mean()) < 0.1
    assert d.std() == pytest.approx(4.0, rel=0.05)
    again = render_view(quad_views["cam"], quad_views["pose"], rng=np.random.default_rng(1), noise_sigma=4.0,
                        backdrop=Backdrop(blur_sigma=0))
    assert np.array_equal(again.image, quad_views["noisy"].image)


def test_background_depth_is_floor_or_wall(quad_views):
    v, cam = quad_views["default"], quad_views["cam"]
    bd = Backdrop()
    h, w = v.mask.shape
    rows, cols = np.nonzero(~v.mask)
    sel = np.random.default_rng(0).choice(rows.size, 2000, replace=False)
    pix = np.stack([cols[sel], rows[sel]], 1).astype(float)
    X = cam.unproject(pix, v.depth[rows[sel], cols[sel]].astype(float))
    on_floor = np.abs(X[:, 2]) < 4
    on_wall = np.abs(np.hypot(X[:, 0], X[:, 1]) - bd.wall_radius) < 6
    assert np.all(on_floor | on_wall)
    assert on_floor.any() and on_wall.any()
    assert v.depth.dtype == np.uint16 and v.depth.min() > 0


def test_empty_studio_and_types():
    cam = make_dome(4, size=(64, 48))[0]
    v = render_view(cam, None, rng=np.random.default_rng(0))
    assert v.image.shape == (48, 64, 3) and v.image.dtype == np.uint8
    assert not v.mask.any() and v.depth is None
    assert v.label.dtype == np.int16 and np.all(v.label == BACKGROUND)


def test_invalid_input():
    cam = make_dome(4, size=(64, 48))[0]
    pose = make_creature("starfish").pose(0)
    with pytest.raises(ValueError, match="camera"):
        render_view("cam00", pose)
    with pytest.raises(ValueError, match="pose"):
        render_view(cam, "starfish")
    with pytest.raises(ValueError, match="noise_sigma"):
        render_view(cam, pose, noise_sigma=-1)
    with pytest.raises(ValueError, match="backdrop"):
        render_view(cam, pose, backdrop={"wall_radius": 10})
    with pytest.raises(ValueError, match="outside the backdrop"):
        render_view(cam, pose, backdrop=Backdrop(wall_radius=500.0))
    with pytest.raises(ValueError, match="backdrop.vignette"):
        Backdrop(vignette=2.0)
    with pytest.raises(ValueError, match="texture_scale"):
        Backdrop(texture_scale=0.0)
    with pytest.raises(ValueError, match="rest"):
        Pose(p0=pose.p0, p1=pose.p1, r0=pose.r0, r1=pose.r1, limb=pose.limb, rest=np.zeros((1, 3, 4)))


def test_texture_painted_on_the_body_moves_with_it():
    """With ``rest``, the texture is evaluated at every point's rest position: a capsule shifted by
    ``t`` with ``rest = [I | t]`` shows, pixel for pixel, the texture that a capsule at rest shows
    at the point minus ``t`` (exact formula); identity ``rest`` renders like the world texture, and
    the render uses ``rest``: shifting it alone changes the body's colours, nothing else."""
    from fake_cameras.render import _rest_points

    cam = make_dome(4, size=(64, 48))[0]
    pose = make_creature("starfish").pose(0)
    eye = np.concatenate([np.tile(np.eye(3), (pose.n_capsules, 1, 1)), np.zeros((pose.n_capsules, 3, 1))], axis=2)
    same = Pose(p0=pose.p0, p1=pose.p1, r0=pose.r0, r1=pose.r1, limb=pose.limb, rest=eye)
    a = render_view(cam, pose, rng=np.random.default_rng(0))
    b = render_view(cam, same, rng=np.random.default_rng(0))
    assert np.array_equal(a.image, b.image)
    rng = np.random.default_rng(1)
    p = rng.uniform(-200, 200, (50, 3))
    t = np.array([30.0, -12.0, 5.0])
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    rest = np.tile(np.concatenate([R, t[:, None]], axis=1), (50, 1, 1))
    moved = p @ R.T + t
    assert np.allclose(_rest_points(rest, moved), p)
    # the render evaluates the texture at the rest position: shifting ``rest`` alone moves the
    # texture over the (unmoved) body: the same silhouette, labels and depth, other creature colours
    bd = Backdrop(texture=0.2, texture_scale=0.5, blur_sigma=0.0, spill=0.0)
    shifted = Pose(p0=pose.p0, p1=pose.p1, r0=pose.r0, r1=pose.r1, limb=pose.limb,
                   rest=np.concatenate([eye[:, :, :3], np.tile(t[:, None], (pose.n_capsules, 1, 1))], axis=2))
    c = render_view(cam, same, backdrop=bd, noise_sigma=0, depth=True)
    d = render_view(cam, shifted, backdrop=bd, noise_sigma=0, depth=True)
    assert c.mask.any() and np.array_equal(c.mask, d.mask) and np.array_equal(c.label, d.label)
    assert np.array_equal(c.depth, d.depth) and np.array_equal(c.image[~c.mask], d.image[~d.mask])
    changed = np.abs(c.image.astype(int) - d.image.astype(int)).max(axis=-1)[c.mask] > 1
    assert changed.mean() > 0.5, changed.mean()
