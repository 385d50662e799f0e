import numpy as np
import pytest

from fake_cameras.render import Backdrop, render_view
from fake_cameras.take import load_ground_truth, simulate_take, write_ground_truth

KW = dict(n_cameras=4, frames=3, size=(160, 120), seed=3)


@pytest.fixture(autouse=True)
def _private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path_factory.getbasetemp() / "simcache"))


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import os

    os.environ["CAPTURE_STAGE_CACHE"] = str(tmp_path_factory.getbasetemp() / "simcache")
    return simulate_take("quadruped", depth=True, **KW)


def test_shapes_and_ground_truth(take):
    F, C, (w, h) = 3, 4, (160, 120)
    assert take.images.shape == (F, C, h, w, 3) and take.images.dtype == np.uint8
    assert take.masks.shape == (F, C, h, w) and take.masks.dtype == bool
    assert take.depth.shape == (F, C, h, w) and take.depth.dtype == np.uint16
    assert take.plate.shape == (C, h, w, 3)
    assert len(take.poses) == len(take.tips) == len(take.axes) == F
    assert take.tip_array().shape == (F, 6, 3)
    assert np.allclose(take.times, np.arange(F) / 30.0)
    assert len(take.calibration) == C and take.size == (w, h)
    # every camera sees the creature in every frame
    assert take.masks.reshape(F, C, -1).any(-1).all()
    # the plate has no creature but is the same studio
    diff = np.abs(take.plate.astype(int) - take.images[0].astype(int)).sum(-1)
    assert np.median(diff[~take.masks[0]]) < 12


def test_take_frames_are_the_rendered_views(take):
    f, c = 2, 1
    v = render_view(
        take.calibration[c], take.poses[f], rng=np.random.default_rng([3, c, f]), depth=True, backdrop=_backdrop(take)
    )
    assert np.array_equal(v.mask, take.masks[f, c])
    assert np.array_equal(v.image, take.images[f, c])
    assert np.array_equal(v.depth, take.depth[f, c])
    assert np.array_equal(v.label, take.labels[f, c])


def _backdrop(take):
    cal = take.calibration
    reach = max(np.linalg.norm(cal.centers()[:, :2], axis=1).max(), 1.0)
    top = max(float(cal.centers()[:, 2].max()), 750.0)
    return Backdrop(wall_radius=float(max(3200.0, 1.6 * reach)), wall_height=float(max(3200.0, 1.5 * top)))


def test_tips_project_onto_their_limb(take):
    names = take.limb_names
    hits = total = 0
    for f in range(take.n_frames):
        for c, cam in enumerate(take.calibration):
            for li, n in enumerate(names):
                ax = take.axes[f][n]
                u = (ax[-1] - ax[-2]) / np.linalg.norm(ax[-1] - ax[-2])
                q = np.round(cam.project((ax[-1] - 3 * u)[None])[0]).astype(int)
                total += 1
                hits += int(np.any(take.labels[f, c, q[1] - 1 : q[1] + 2, q[0] - 1 : q[0] + 2] == li))
    # a point 3 mm inside each tip shows that limb (within a pixel) unless something occludes it
    assert hits / total > 0.85


def test_cache_round_trip(take):
    again = simulate_take("quadruped", depth=True, **KW)
    assert np.array_equal(again.images, take.images)
    assert np.array_equal(again.masks, take.masks)
    assert np.array_equal(again.depth, take.depth)
    assert np.array_equal(again.plate, take.plate)
    again.images[0, 0, 0, 0] = 7  # cached arrays are writable without touching the cache
    third = simulate_take("quadruped", depth=True, **KW)
    assert np.array_equal(third.images, take.images)
    fresh = simulate_take("quadruped", depth=True, cache=False, **KW)
    assert np.array_equal(fresh.images, take.images)


def test_ground_truth_file_round_trip(take, tmp_path):
    path = write_ground_truth(take, tmp_path / "take.h5")
    assert path.name == "take.gt.npz"
    gt = load_ground_truth(tmp_path / "take.h5")
    assert np.array_equal(gt["masks"], take.masks)
    assert gt["calibration"] == take.calibration
    assert gt["limb_names"] == list(take.limb_names)
    assert np.allclose(gt["tips"], take.tip_array())
    for n in take.limb_names:
        assert np.allclose(gt["axes"][n], np.stack([a[n] for a in take.axes]))
    pts = np.random.default_rng(0).uniform(-300, 300, (50, 3)) + [0, 0, 300]
    assert np.allclose(gt["poses"][1].sdf(pts), take.poses[1].sdf(pts))
    assert gt["fps"] == 30.0 and gt["subject"] == "quadruped"


def test_ground_truth_poses_keep_their_rest_motions_and_render_the_same(take, tmp_path):
    """Re-read poses carry ``Pose.rest`` (the body-painted texture renders as in the take); a file
    without it (written before it was stored) loads as before: rest None, texture fixed in the world."""
    assert all(p.rest is not None for p in take.poses)
    write_ground_truth(take, tmp_path / "take.h5")
    gt = load_ground_truth(tmp_path / "take.h5")
    assert all(np.array_equal(g.rest, p.rest) for g, p in zip(gt["poses"], take.poses))
    cam = take.calibration[0]
    bd = Backdrop(texture=0.3, texture_scale=0.5)
    image = [render_view(cam, p, backdrop=bd, rng=np.random.default_rng(1)).image for p in (take.poses[2], gt["poses"][2])]
    assert np.array_equal(*image)
    with np.load(tmp_path / "take.gt.npz") as z:  # an older file: no rest motions
        np.savez_compressed(tmp_path / "old.npz", **{k: z[k] for k in z.files if k not in ("rest", "has_rest")})
    old = load_ground_truth(tmp_path / "old.npz")
    assert all(p.rest is None for p in old["poses"])
    assert all(np.array_equal(o.p0, g.p0) and np.array_equal(o.limb, g.limb) for o, g in zip(old["poses"], gt["poses"]))
    world = render_view(cam, old["poses"][2], backdrop=bd, rng=np.random.default_rng(1)).image
    assert not np.array_equal(world, image[0])


def test_empty_subject_and_hard_cases(tmp_path):
    empty = simulate_take("empty", n_cameras=4, frames=2, size=(64, 48), cache=False)
    assert not empty.masks.any() and empty.limb_names == () and empty.tips == [{}, {}]
    write_ground_truth(empty, tmp_path / "e.npz")
    assert load_ground_truth(tmp_path / "e.npz")["tips"].shape == (2, 0, 3)
    hard = simulate_take("starfish", n_cameras=4, frames=3, size=(64, 48), spur=(1 / 30, 2 / 30), cache=False)
    assert [p.n_capsules for p in hard.poses] == [25, 26, 25]
    write_ground_truth(hard, tmp_path / "h.npz")  # rest motions padded to the largest count
    assert all(np.array_equal(g.rest, p.rest) for g, p in zip(load_ground_truth(tmp_path / "h.npz")["poses"], hard.poses))


def test_start_shows_the_default_takes_later_poses():
    """A take started ``start`` seconds in shows at frame 0 exactly the pose (capsules, rest motions, tips,
    axes, silhouettes) the default take shows at that time; the default take's times and parameters carry no
    offset (its cache key is the one made without it)."""
    kw = dict(n_cameras=4, size=(64, 48), seed=3, fps=10.0, cache=False)
    default = simulate_take("biped", frames=3, **kw)
    assert "start" not in default.params and np.array_equal(default.times, np.arange(3) / 10.0)
    later = simulate_take("biped", frames=1, start=0.2, **kw)
    assert later.params["start"] == 0.2 and later.times[0] == default.times[2] == 0.2
    a, b = later.poses[0], default.poses[2]
    for k in ("p0", "p1", "r0", "r1", "limb", "rest"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert all(np.array_equal(a.tips[n], b.tips[n]) and np.array_equal(a.axes[n], b.axes[n]) for n in later.limb_names)
    assert np.array_equal(later.masks[0], default.masks[2]) and np.array_equal(later.labels[0], default.labels[2])
    quarter = simulate_take("biped", frames=1, start=0.3125, **kw)  # between frames: the creature's own clock
    q, ref = quarter.poses[0], quarter.creature.pose(0.3125)
    assert np.array_equal(q.p0, ref.p0) and np.array_equal(q.p1, ref.p1) and np.array_equal(q.rest, ref.rest)
    assert not np.allclose(q.p1, default.poses[0].p1, atol=1.0)


def test_invalid_input():
    with pytest.raises(ValueError, match="subject"):
        simulate_take("dragon")
    with pytest.raises(ValueError, match="n_cameras"):
        simulate_take(n_cameras=2)
    with pytest.raises(ValueError, match="frames"):
        simulate_take(frames=0)
    with pytest.raises(ValueError, match="fps"):
        simulate_take(fps=-1)
    with pytest.raises(ValueError, match="size"):
        simulate_take(size=(10, 5))
    with pytest.raises(ValueError, match="noise_sigma"):
        simulate_take(noise_sigma=-2)
    with pytest.raises(ValueError, match="calibration"):
        simulate_take(calibration="dome")
    for bad in (-0.1, float("nan"), float("inf"), "1", True):
        with pytest.raises(ValueError, match="start"):
            simulate_take(start=bad)
    with pytest.raises(ValueError, match="take"):
        write_ground_truth("take", "x.npz")
    with pytest.raises(FileNotFoundError):
        load_ground_truth("/nonexistent/take.h5")


def test_cache_key_follows_the_creatures_shape(take):
    """The cached render is keyed by the posed capsules too: a creature whose shape changes
    under the same name gets a new key (is rendered anew), the same poses the same key."""
    from dataclasses import replace

    from fake_cameras.take import _poses_digest

    same = _poses_digest(list(take.poses))
    assert _poses_digest(list(take.poses)) == same
    thicker = [replace(p, r0=p.r0 * 1.01) for p in take.poses]
    assert _poses_digest(thicker) != same
