"""The subject's box (pipeline.subject_box) on a walking subject filmed by a ring of 8 cameras, and
its place in ``stage process``: the box follows the subject over the whole take, phantoms and a
spurious blob in one camera do not pass, the voxel follows the pixel footprint at the subject."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.calibration import Calibration
from fake_cameras.creatures import Pose, make_creature
from fake_cameras.evaluate import evaluate_spine
from pipeline.hull import EmptyHullError
from pipeline.subject_box import find_subject_box
from pipeline.volume import pixel_footprint, volume_from_cameras
from tests.pipeline.simrig import look_at

FRAMES = 10
WALK = 2000.0  # mm along x, centred on the ring
BLOB = (3, slice(30, 42), slice(20, 34))  # camera, rows, columns of a spurious blob in every frame


def ring(n: int = 8, *, size=(320, 240), radius: float = 3000.0, height: float = 1500.0) -> Calibration:
    """``n`` cameras in a ring ``radius`` mm from the centre, looking at (0, 0, 500), lenses distorting a little."""
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n + 0.2
        c = np.array([radius * np.cos(az), radius * np.sin(az), height])
        cams.append(look_at(f"cam{i}", c, (0, 0, 500), size=size, f=0.8 * size[0], dist=(-0.05, 0.01, 0, 0, 0)))
    return Calibration(tuple(cams))


def walked(pose: Pose, dx: float) -> Pose:
    """The pose moved ``dx`` mm along x (texture, tips and axes with it)."""
    d = np.array([dx, 0.0, 0.0])
    rest = pose.rest.copy()
    rest[:, :, 3] += d
    return Pose(p0=pose.p0 + d, p1=pose.p1 + d, r0=pose.r0, r1=pose.r1, limb=pose.limb, names=pose.names,
                tips={k: v + d for k, v in pose.tips.items()}, axes={k: v + d for k, v in pose.axes.items()},
                time=pose.time, rest=rest)


@pytest.fixture(scope="module")
def walk():
    """A quadruped (about 1 m long) walking 2 m across a ring of 8 cameras, 320x240, true silhouettes
    (the keying is not under test), rendered once (cached)."""
    from fake_cameras.render import render_view
    from fake_cameras.take import _poses_digest, cached_render

    cal = ring()
    creature = make_creature("quadruped", scale=2.0, seed=0)
    poses = [walked(creature.pose(f / 10), -WALK / 2 + WALK * f / (FRAMES - 1)) for f in range(FRAMES)]

    def render():
        views = [[render_view(c, p, noise_sigma=0.0, rng=np.random.default_rng(0)) for c in cal] for p in poses]
        masks = np.array([[v.mask for v in vs] for vs in views])
        return {"images": np.array([[v.image for v in vs] for vs in views]), "masks": masks,
                "labels": np.zeros(masks.shape, np.int8), "depth": None, "plate": np.zeros((1, 1, 1, 3), np.uint8)}

    key = json.dumps({"test": "subject_box walk", "calibration": cal.to_dict(), "poses": _poses_digest(poses)},
                     sort_keys=True)
    arrays = cached_render(key, render)
    masks = arrays["masks"].copy()
    c, rows, cols = BLOB
    masks[:, c, rows, cols] = True
    return cal, poses, arrays["images"], masks


def true_box(poses) -> np.ndarray:
    return np.stack([np.min([p.bounds()[0] for p in poses], axis=0), np.max([p.bounds()[1] for p in poses], axis=0)])


def holds(box: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    return bool(np.all(box[0] <= lo) and np.all(hi <= box[1]))


def test_box_follows_a_walking_subject(walk):
    """No rig volume (the cameras' shared view, about 8.7 x 8.7 x 5.4 m): the box holds the
    subject in every frame set, and is at most 1.5 x the subject's true box per axis plus the
    margin (one finest cube a side); every frame set's own box holds that frame's subject. The
    spurious blob in camera 3's silhouettes explains pixels in that camera alone: rejected."""
    cal, poses, _, masks = walk
    volume = volume_from_cameras(cal)
    sb = find_subject_box(masks, cal, volume)
    truth = true_box(poses)
    assert all(holds(sb.bounds, *p.bounds()) for p in poses)
    assert all(holds(sb.frame_boxes[k], *p.bounds()) for k, p in enumerate(poses))
    assert np.all(sb.bounds[1] - sb.bounds[0] <= 1.5 * (truth[1] - truth[0]) + 2 * sb.margin)
    assert sb.stats["with_subject"] == FRAMES and sb.stats["pieces_kept"] == FRAMES
    # the blob alone (no subject): nothing
    blob_only = np.zeros_like(masks[:2])
    c, rows, cols = BLOB
    blob_only[:, c, rows, cols] = True
    blob_only[:, (c + 4) % 8, 100:104, 100:104] = True
    with pytest.raises(EmptyHullError, match="no subject"):
        find_subject_box(blob_only, cal, volume)


def test_phantom_crossings_do_not_pass(walk):
    """Two subjects' worth of silhouettes crossing: a second true object beside the walker
    (a 300 mm ball, 1.5 m away) is kept; silhouette blobs placed in three cameras where their
    cones cross far from the subject (a phantom that every camera seeing it explains) are kept
    too only when they explain pixels alone in two cameras -- a blob in one camera never is."""
    from fake_cameras.render import render_view

    cal, poses, _, masks = walk
    volume = volume_from_cameras(cal)
    ball = Pose.spheres(np.array([[0.0, 1500.0, 600.0]]), np.array([150.0]))
    extra = np.array([[render_view(c, ball, noise_sigma=0.0, rng=np.random.default_rng(0)).mask for c in cal]])
    two = masks[:1] | extra
    sb = find_subject_box(two, cal, volume)
    assert holds(sb.bounds, *ball.bounds()) and holds(sb.bounds, *poses[0].bounds())
    assert sb.stats["pieces_kept"] == 2
    # the ball in one camera only: a spurious blob there, not an object
    one = masks[:1].copy()
    one[0, 5] |= extra[0, 5]
    sb = find_subject_box(one, cal, volume)
    assert not holds(sb.bounds, *ball.bounds()) and holds(sb.bounds, *poses[0].bounds())


def test_levels_and_pooling_follow_the_cameras(walk):
    """The finest cube is 4 pixel footprints at the volume's centre (median camera), each level
    half the one above; the silhouettes are pooled so the finest cube stays 2 pooled pixels wide."""
    cal, _, _, masks = walk
    volume = volume_from_cameras(cal)
    sb = find_subject_box(masks[:2], cal, volume)
    fp = np.nanmedian(pixel_footprint(cal, volume.mean(axis=0)))
    assert sb.voxels[0] == pytest.approx((volume[1] - volume[0]).max() / 16)
    assert np.allclose(np.diff(np.log2(sb.voxels)), -1)
    assert 4 * fp <= sb.voxels[-1] < 8 * fp
    finer = find_subject_box(masks[:2], cal, volume, finest_voxel=sb.voxels[-1] / 4)
    assert len(finer.voxels) == len(sb.voxels) + 2
    # the finer box is no larger, and still holds the subject
    assert np.all(finer.bounds[1] - finer.bounds[0] <= sb.bounds[1] - sb.bounds[0] + 1e-6)


def test_invalid_input(walk):
    cal, _, _, masks = walk
    volume = volume_from_cameras(cal)
    with pytest.raises(ValueError, match="calibration"):
        find_subject_box(masks, "cal", volume)
    with pytest.raises(ValueError, match="volume_bounds"):
        find_subject_box(masks, cal, [[0, 0, 0], [0, 1, 1]])
    with pytest.raises(ValueError, match="masks"):
        find_subject_box(masks[:0], cal, volume)
    with pytest.raises(ValueError, match="masks"):
        find_subject_box(3, cal, volume)
    with pytest.raises(ValueError, match="one mask per camera"):
        find_subject_box(masks[:1, :3], cal, volume)
    with pytest.raises(ValueError, match="cam0"):
        find_subject_box(masks[:1, :, :100], cal, volume)
    for kw, name in (({"tolerance": -1}, "tolerance"), ({"min_share": 0}, "min_share"),
                     ({"min_support": 0}, "min_support"), ({"support_share": 2}, "support_share"),
                     ({"finest_voxel": -1.0}, "finest_voxel"), ({"support_plane": (0, 0, 0, 1)}, "plane")):
        with pytest.raises(ValueError, match=name):
            find_subject_box(masks[:1], cal, volume, **kw)


@pytest.fixture(scope="module")
def walk_take(walk, tmp_path_factory):
    """The walk as a take with no rig volume (footage imported from another rig), its
    silhouettes stored as the take's masks (the spurious blob in camera 3 included)."""
    from stage.frame import Frame
    from stage.store import CameraSpec, TakeWriter, write_masks

    cal, _, images, masks = walk
    path = tmp_path_factory.mktemp("walk") / "walk.h5"
    w, h = cal[0].size
    period = int(1e9 / 10)
    with TakeWriter(path, [CameraSpec(n, w, h) for n in cal.names], calibration=cal, fps=10.0) as wr:
        for f in range(FRAMES):
            t = f * period
            wr.write_set({n: Frame(images[f, c], n, f, t, t) for c, n in enumerate(cal.names)}, time_ns=t)
    for c, n in enumerate(cal.names):
        write_masks(path, n, masks[:, c], params={"source": "ground truth"})
    return path


def test_process_finds_the_box_and_the_voxel(walk, walk_take, tmp_path):
    """``stage process`` with defaults on the walk (no rig volume): ``process.json`` says the box
    and why; the box holds the subject in every frame set within 1.5 x its true box per axis plus
    the margin; the voxel is 2 pixel footprints at the subject (the median over the frame sets of
    the median over the cameras); the spine is the one a hand-given box (``--volume``) gives:
    the same K (6: four legs, head, tail), each true limb found, the same tips within 1.5 voxels."""
    from pipeline.process import PIXELS_PER_VOXEL, process_take

    cal, poses, _, _ = walk
    auto = process_take(walk_take, tmp_path / "auto")
    choice = json.loads((tmp_path / "auto" / "process.json").read_text())["grid"]
    assert auto.report["grid"] == choice
    box = choice["box"]
    assert box["searched_in"] == "the cameras' shared view" and "frame sets" in box["why"]
    bounds = np.array([box["lo"], box["hi"]])
    truth = true_box(poses)
    assert all(holds(bounds, *p.bounds()) for p in poses)
    assert np.all(bounds[1] - bounds[0] <= 1.5 * (truth[1] - truth[0]) + 2 * box["margin"])
    centres = np.array([(p.bounds()[0] + p.bounds()[1]) / 2 for p in poses])
    fp = float(np.median(np.nanmedian(pixel_footprint(cal, centres), axis=0)))
    assert choice["limited_by"] == "pixel footprint"
    assert choice["pixel_footprint"] == pytest.approx(fp, rel=0.05)
    assert choice["voxel"] == pytest.approx(PIXELS_PER_VOXEL * fp, rel=0.05)

    hand = truth + np.array([[-150.0], [150.0]])
    process_take(walk_take, tmp_path / "hand", params={"volume": tuple(hand.reshape(-1))})
    voxel = json.loads((tmp_path / "hand" / "process.json").read_text())["grid"]["voxel"]
    spines = [json.loads((tmp_path / d / "spine.json").read_text()) for d in ("auto", "hand")]
    names = list(poses[0].names)
    tips = np.stack([p.tip_array() for p in poses])
    axes = {n: np.stack([p.axes[n] for p in poses]) for n in names}
    acc = [evaluate_spine(s, tips, axes, names) for s in spines]
    assert acc[0]["K"] == acc[1]["K"] == 6
    assert acc[0]["identity_consistent"] == acc[1]["identity_consistent"] == 1.0
    assert sorted(acc[0]["match"].values()) == sorted(acc[1]["match"].values()) == sorted(names)
    by_limb = [{true: s_id for s_id, true in a["match"].items()} for a in acc]
    for a, b in zip(spines[0]["frames"], spines[1]["frames"]):
        for limb in names:
            ta, tb = a["tips"][by_limb[0][limb]], b["tips"][by_limb[1][limb]]
            assert (ta is None) == (tb is None)
            if ta is not None:
                assert np.linalg.norm(np.subtract(ta, tb)) <= 1.5 * voxel
