"""Keying layers for partial backdrops: the plate from the take, the volume prior, the graph cut,
the footage's default mode (each against a slow reference or a constructed truth)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from calib.camera import Camera
from pipeline.silhouette_refine import refine_silhouette
from stage.keying.background import take_plate
from stage.keying.chroma import backdrop_share
from stage.keying.keyer import estimate_model
from stage.keying.params import KeyParams
from stage.keying.take import _warn_stuck
from stage.keying.volume_prior import volume_image


def _frames(rng, n=24, h=40, w=60, sigma=2.0):
    """A textured room with noise; a square that sits on one place in 70 % of the frames (with
    changing colours) and a square that never leaves another place."""
    room = rng.integers(30, 220, (h, w, 3)).astype(np.float64)
    fr = room[None] + rng.normal(0, sigma, (n, h, w, 3))
    for k in range(n):
        if k % 10 < 7:
            fr[k, 5:15, 5:15] = rng.integers(0, 255, 3)  # the subject covers it most of the time
        fr[k, 25:35, 40:50] = rng.integers(0, 255, 3)  # never leaves
    return np.clip(np.round(fr), 0, 255).astype(np.uint8), room


def test_plate_from_the_take_against_the_room():
    rng = np.random.default_rng(0)
    frames, room = _frames(rng)
    est = take_plate(frames, band=7)
    free = np.ones(room.shape[:2], bool)
    free[25:35, 40:50] = False
    err = np.abs(est.plate.astype(float) - room)[free]
    assert err.max() <= 4.0, err.max()  # the mode recovers the room where the subject stays 70 % of the time
    assert est.stuck[27:33, 42:48].all() and not est.stuck[free].any()
    assert 1.6 <= est.sigma <= 2.4  # the noise measured on the plate: 2 grey levels


def test_stuck_pixels_are_uncertain_and_warned(caplog):
    rng = np.random.default_rng(1)
    frames, _ = _frames(rng)
    params = estimate_model(frames, params=KeyParams(mode="plate"))
    assert params.model["source"] == "take" and params.model["stuck_fraction"] == pytest.approx(100 / 2400, abs=0.01)
    with caplog.at_level(logging.WARNING, logger="stage.keying"):
        _warn_stuck("camX", params)
    assert "camX" in caplog.text and "4.1" in caplog.text and "--plate EMPTY_TAKE" in caplog.text


def _slow_volume_image(cam: Camera, lo, hi) -> np.ndarray:
    """Per pixel, the slab test of its ray against the box (the reference)."""
    w, h = cam.size
    out = np.zeros((h, w), bool)
    for v in range(h):
        for u in range(w):
            o, d = cam.rays(np.array([[u, v]], float))
            d = d[0]
            with np.errstate(divide="ignore", invalid="ignore"):
                t0, t1 = (lo - o) / d, (hi - o) / d
            tmin = np.nanmax(np.minimum(t0, t1))
            tmax = np.nanmin(np.maximum(t0, t1))
            out[v, u] = tmax >= max(tmin, 0)
    return out


def test_volume_image_against_ray_box_intersections():
    from calib.camera import rodrigues_to_matrix

    R = rodrigues_to_matrix(np.array([2.2, 0.0, 0.0]))  # looking down at the box
    cam = Camera("c", K=[[60, 0, 40], [0, 60, 30], [0, 0, 1]], dist=np.zeros(5), R=R, t=-R @ np.array([0, -1500, 1200.0]),
                 size=(80, 60))
    lo, hi = np.array([-400.0, -400, 0]), np.array([400.0, 400, 800])
    fast = volume_image(cam, np.r_[lo, hi], margin=0)
    slow = _slow_volume_image(cam, lo, hi)
    from scipy.ndimage import binary_dilation, binary_erosion

    band = binary_dilation(slow) & ~binary_erosion(slow)  # the outline, one pixel either side
    assert slow.sum() > 200 and not ((fast ^ slow) & ~band).any()
    assert volume_image(cam, np.r_[lo, hi], margin=3).sum() > fast.sum()
    inside = cam.replace(t=-R @ np.array([0, 0, 400.0]))
    assert volume_image(inside, np.r_[lo, hi]).all()


def test_graph_cut_drops_what_the_keyer_kept_beside_the_subject():
    import cv2

    rng = np.random.default_rng(2)
    h, w = 120, 160
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = (40, 160, 50)  # green floor
    img[:30] = (90, 80, 70)  # a wall
    img[:30, ::8] = (200, 200, 200)  # with stripes
    truth = np.zeros((h, w), np.uint8)
    cv2.circle(truth, (80, 40), 22, 1, -1)
    img[truth > 0] = (60, 120, 210)
    img = np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    truth = truth.view(bool)
    keyed = truth.copy()
    keyed[:30] = True  # the chroma keyer keeps the wall
    hull = cv2.dilate(truth.view(np.uint8), np.ones((7, 7), np.uint8)).view(bool)
    out = refine_silhouette(img, keyed, hull, footprint=2.0)
    assert (out & truth).sum() / (out | truth).sum() >= 0.97


def test_backdrop_share():
    green = np.tile([[40.0, 170.0, 50.0]], (600, 1))
    grey = np.tile([[120.0, 118.0, 121.0]], (400, 1))
    share, hue = backdrop_share(np.vstack([green, grey]))
    assert share == pytest.approx(0.6) and abs(hue) > 0
    assert backdrop_share(grey)[0] == 0.0


def test_invalid_input():
    with pytest.raises(ValueError, match="frames"):
        take_plate(np.zeros((2, 4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="frames"):
        take_plate(np.zeros((5, 4, 4), np.uint8))
    cam = Camera("c", K=[[60, 0, 40], [0, 60, 30], [0, 0, 1]], dist=np.zeros(5), R=np.eye(3), t=[0, 0, 1000.0],
                 size=(80, 60))
    with pytest.raises(ValueError, match="bounds"):
        volume_image(cam, [0, 0, 0, -1, 1, 1])
    with pytest.raises(ValueError, match="margin"):
        volume_image(cam, [0, 0, 0, 1, 1, 1], margin=-1)
    img = np.zeros((10, 10, 3), np.uint8)
    m = np.zeros((10, 10), bool)
    with pytest.raises(ValueError, match="mask"):
        refine_silhouette(img, m[:5], m)
    with pytest.raises(ValueError, match="image"):
        refine_silhouette(img[..., 0], m, m)
    with pytest.raises(ValueError, match="footprint"):
        refine_silhouette(img, m, m, footprint=0)
    with pytest.raises(ValueError, match="samples"):
        backdrop_share(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="min_relative_area"):
        KeyParams(min_relative_area=1.5)


def test_plates_from_an_empty_take(tmp_path, capsys):
    """``--plate EMPTY_TAKE``: every camera's plate and noise from an empty recording, stored in
    the take, then used by the plate keyer (the subject may stand still: nothing is taken from
    the take itself)."""
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from stage.cli import main
    from stage.keying import iou
    from stage.keying.take import store_plates
    from stage.store import TakeReader

    sim = simulate_take("starfish", n_cameras=4, frames=3, size=(160, 120), seed=5)
    empty = simulate_take("empty", n_cameras=4, frames=12, size=(160, 120), seed=5)
    take = record_take(sim, tmp_path / "t.h5")  # holds the renderer's clean plate
    bare = record_take(empty, tmp_path / "empty.h5")
    assert main(["key", str(take), "--key-mode", "plate", "--no-progress"]) == 0
    with TakeReader(take) as r:
        clean = [min(iou(r.masks(n)[f], sim.masks[f, c]) for f in range(3)) for c, n in enumerate(sim.calibration.names)]
    noise = store_plates(take, bare)
    assert set(noise) == set(sim.calibration.names) and all(1.0 <= v <= 3.0 for v in noise.values())  # sigma 2
    assert main(["key", str(take), "--plate", str(bare), "--no-progress"]) == 0
    assert "mode plate" in capsys.readouterr().out
    with TakeReader(take) as r:
        for c, name in enumerate(sim.calibration.names):
            assert r.mask_params(name)["key"]["model"]["source"] == "plate"
            m = r.masks(name)
            # as good as the renderer's own clean plate, within 0.03
            assert min(iou(m[f], sim.masks[f, c]) for f in range(3)) >= clean[c] - 0.03, (name, clean[c])
    other = simulate_take("empty", n_cameras=4, frames=3, size=(80, 60), seed=5)
    with pytest.raises(ValueError, match="camera cam00 is"):
        store_plates(take, record_take(other, tmp_path / "small.h5"))


def test_cli_layers_and_plate(tmp_path, capsys):
    """`stage key --key-layer volume --key-layer graphcut --volume ...` and `stage process --plate`
    run the layers the functions above test, and say so; the surface step bridges one camera's
    miss with the keyer's closing radius for plate-keyed masks only."""
    import json
    from types import SimpleNamespace

    from fake_cameras.dome import make_dome
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take, stage_backdrop
    from pipeline.process.steps import _bridge_gaps
    from stage.cli import main
    from stage.keying.params import PLATE_CLOSE_RELATIVE
    from stage.rig import Volume
    from stage.store import TakeReader

    vol = Volume()
    calib = make_dome(4, size=(160, 120), volume=vol, seed=3, distortion=False)
    sim = simulate_take("starfish", calibration=calib, frames=3, volume=vol, seed=3,
                        backdrop=stage_backdrop("floor", calibration=calib, volume=vol))
    take = record_take(sim, tmp_path / "t.h5")
    lo, hi = vol.bounds
    args = ["key", str(take), "--key-mode", "chroma", "--key-layer", "volume", "--key-layer", "graphcut",
            "--volume", *map(str, (*lo, *hi)), "--no-progress"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "mode chroma + volume, graphcut" in out and "graph-cut refinement: 12 masks refined" in out
    with TakeReader(take) as r:
        assert r.mask_params("cam00")["refined"]["method"] == "graphcut"
        cameras = list(r.cameras)
    said: dict = {}
    ctx = SimpleNamespace(take=SimpleNamespace(path=take, cameras=cameras), add_to_record=said.update)
    assert _bridge_gaps(ctx) == 0.0 and said["bridge_gaps"]["relative"] == 0.0
    empty = record_take(simulate_take("empty", calibration=calib, frames=4, volume=vol, seed=3,
                                      backdrop=stage_backdrop("floor", calibration=calib, volume=vol)), tmp_path / "e.h5")
    assert main(["process", str(take), "--out", str(tmp_path / "res"), "--plate", str(empty), "--until", "key",
                 "--no-progress"]) == 0
    assert "plates from" in capsys.readouterr().out
    record = json.loads((tmp_path / "res" / "process.json").read_text())
    assert record["params"]["key_mode"] == "plate" and record["key"]["mode"] == "plate"
    assert _bridge_gaps(ctx) == PLATE_CLOSE_RELATIVE and "plate" in said["bridge_gaps"]["why"]
