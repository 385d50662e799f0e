"""Keying: accuracy on the simulated rig, the Middlebury dino, bad frames, storage and CLI."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from stage.keying import (
    KeyingError,
    KeyParams,
    boundary_f_score,
    contact_sheet,
    despill,
    iou,
    key_frames,
    mask_boundary,
)
from stage.keying.chroma import estimate_chroma_model
from stage.keying.keyer import say_invalid_masks
from tests.conftest import shared_dataset

# -- reference implementations ------------------------------------------------


def _slow_boundary(mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    out = np.zeros_like(mask)
    for y in range(h):
        for x in range(w):
            if not mask[y, x]:
                continue
            for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w and not mask[yy, xx]:
                    out[y, x] = True
    return out


def _slow_bf(pred: np.ndarray, truth: np.ndarray, tol: float) -> float:
    bp, bt = np.argwhere(_slow_boundary(pred)), np.argwhere(_slow_boundary(truth))
    if len(bp) == 0 and len(bt) == 0:
        return 1.0
    if len(bp) == 0 or len(bt) == 0:
        return 0.0
    d = np.sqrt(((bp[:, None, :] - bt[None, :, :]) ** 2).sum(-1))
    p = np.mean(d.min(1) <= tol + 1e-9)
    r = np.mean(d.min(0) <= tol + 1e-9)
    return 0.0 if p + r == 0 else 2 * p * r / (p + r)


def _blobs(rng: np.random.Generator, shape=(40, 50)) -> np.ndarray:
    m = rng.random(shape) < 0.5
    m = cv2.GaussianBlur(m.astype(np.float32), (0, 0), 2.0) > 0.5
    return m


# -- metrics --------------------------------------------------------------------


def test_boundary_f_score_matches_slow_reference():
    rng = np.random.default_rng(1)
    for _ in range(6):
        a, b = _blobs(rng), _blobs(rng)
        np.testing.assert_array_equal(mask_boundary(a), _slow_boundary(a))
        for tol in (0.0, 1.0, 2.0, 3.5):
            assert boundary_f_score(a, b, tol=tol) == pytest.approx(_slow_bf(a, b, tol), abs=1e-12)
    a = _blobs(rng)
    assert boundary_f_score(a, a) == 1.0
    empty = np.zeros_like(a)
    assert boundary_f_score(empty, empty) == 1.0 and boundary_f_score(a, empty) == 0.0


def test_iou_exact():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    a[:5] = True
    b[2:7] = True
    assert iou(a, b) == pytest.approx(30 / 70)
    assert iou(np.zeros_like(a), np.zeros_like(a)) == 1.0


# -- simulated rig --------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_take():
    from fake_cameras import take as take_mod
    return take_mod.simulate_take("starfish", n_cameras=12, frames=2, size=(640, 480), seed=0)


@pytest.mark.slow
@pytest.mark.parametrize("creature, frames", [("starfish", 2), ("quadruped", 3), ("biped", 10)])
def test_simulated_rig_iou_and_boundary(creature, frames):
    """IoU >= 0.99 (pooled over the camera's frames) and boundary F >= 0.95 at 2 px, every camera.

    The biped's arms swing close to its torso and its legs cross: 1-3 px slits of
    backdrop that must stay open (holes of clean backdrop colour are not filled).
    """
    from fake_cameras import take as take_mod
    tk = take_mod.simulate_take(creature, n_cameras=12, frames=frames, size=(640, 480), seed=0)
    for c in range(tk.n_cameras):
        res = key_frames(tk.images[:, c], camera=tk.calibration.cameras[c].name)
        g = tk.masks[:, c]
        assert res.valid.all(), res.reasons
        pooled = np.count_nonzero(res.masks & g) / np.count_nonzero(res.masks | g)
        assert pooled >= 0.99, (c, pooled)
        for m, gg in zip(res.masks, g):
            assert boundary_f_score(m, gg, tol=2.0) >= 0.95, (c, boundary_f_score(m, gg, tol=2.0))
        # recorded parameters: derived thresholds and model
        d = res.params.to_dict()
        assert d["t_lo"] < d["t_hi"] and d["model"]["components"] and 0.1 <= d["coverage_fraction"] <= 0.5


@pytest.mark.slow
def test_simulated_rig_limb_tips_kept(sim_take):
    """Every visible true limb tip is inside (or within 1 px of) the keyed mask."""
    tk = sim_take
    kernel = np.ones((3, 3), np.uint8)
    checked = 0
    for c in range(tk.n_cameras):
        cam = tk.calibration.cameras[c]
        res = key_frames(tk.images[:, c])
        for f in range(tk.n_frames):
            tips = np.array(list(tk.tips[f].values()), float)
            px = np.round(cam.project(tips)).astype(int)
            grown = cv2.dilate(res.masks[f].view(np.uint8), kernel).view(bool)
            for x, y in px:
                if 0 <= x < tk.size[0] and 0 <= y < tk.size[1] and tk.masks[f, c, y, x]:
                    checked += 1
                    assert grown[y, x], (c, f, x, y)
    assert checked > 10


@pytest.mark.slow
def test_plate_modes_on_simulated_rig(sim_take):
    tk = sim_take
    for c in (0, 7):
        g = tk.masks[:, c]
        for mode in ("plate", "chroma"):
            res = key_frames(tk.images[:, c], mode=mode, plate=tk.plate[c])
            assert res.params.model["source"] == "plate"
            assert np.count_nonzero(res.masks & g) / np.count_nonzero(res.masks | g) >= 0.99


# -- Middlebury dino (luma mode) --------------------------------------------------


def test_middlebury_dino_luma_matches_recipe():
    """Luma keying (automatic threshold) vs the README recipe (0.19, dilate 10, erode 7) on the good views.

    The recipe grows the silhouette by 3 px (10 - 7); with the same ``grow=3`` the
    masks agree with IoU >= 0.95 on every good view.
    """
    root = shared_dataset("middlebury_dino_sparse_ring")
    good = (root / "dinoSR_good_silhouette_images.txt").read_text().split()
    assert len(good) == 15
    for name in good:
        im = cv2.imread(str(root / name))
        gray = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
        rec = (gray > 0.19 * 255).astype(np.uint8)
        rec = cv2.dilate(rec, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21)))
        rec = cv2.erode(rec, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15))).astype(bool)
        res = key_frames(im, params=KeyParams(mode="luma", grow=3))
        assert res.valid[0], res.reasons
        assert res.params.model["polarity"] == "dark"
        assert iou(res.masks[0], rec) >= 0.95, name


def test_luma_bright_backdrop_auto_polarity():
    img = np.full((60, 80, 3), 230, np.uint8)
    cv2.circle(img, (40, 30), 15, (40, 50, 60), -1)
    truth = np.zeros((60, 80), np.uint8)
    cv2.circle(truth, (40, 30), 15, 1, -1)
    res = key_frames(img, mode="luma")
    assert res.params.model["polarity"] == "bright"
    assert iou(res.masks[0], truth.astype(bool)) >= 0.97


@pytest.mark.parametrize("n_blobs", [2, 7])  # few components: OpenCV compares; many: a label table
def test_masks_are_canonical_booleans(n_blobs):
    """Every mask byte is 0 or 1 in every mode (with and without grow and hole filling).

    A NumPy bool holding OpenCV's 255 tests True but counts 255 wherever its bytes are read
    as uint8 (summed-area tables, ``cv2`` sums, ``view(np.uint8)``): the hull carver's
    coarse-to-fine blocks then kept whole regions the masks reject.
    """
    rng = np.random.default_rng(5)
    h, w = 120, 160
    plate = np.empty((h, w, 3), np.uint8)
    plate[:] = (45, 175, 55)
    img = plate.copy()
    truth = np.zeros((h, w), np.uint8)
    for k in range(n_blobs):
        c = (20 + (k % 4) * 38, 30 + (k // 4) * 55)
        cv2.circle(img, c, 12, (70, 125, 205), -1)
        cv2.circle(truth, c, 12, 1, -1)
    cv2.circle(img, (20, 30), 2, (45, 175, 55), -1)  # a small backdrop hole to fill
    noisy = np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    plate_n = np.clip(plate + rng.normal(0, 2, plate.shape), 0, 255).astype(np.uint8)
    for mode, kw in (("chroma", {}), ("luma", {}), ("plate", {"plate": plate_n})):
        for grow in (0, 2):
            res = key_frames(noisy, params=KeyParams(mode=mode, grow=grow), **kw)
            assert res.valid[0], (mode, res.reasons)
            assert res.masks.view(np.uint8).max() == 1, (mode, grow)
            if mode != "luma" and grow == 0:  # (luma: orange vs green is not a luma contrast)
                assert iou(res.masks[0], truth.astype(bool)) >= 0.97, mode


# -- bad input --------------------------------------------------------------------


def _small_sim():
    from fake_cameras import take as take_mod
    return take_mod.simulate_take("starfish", n_cameras=4, frames=5, size=(320, 240), seed=3)


def test_bad_frames_marked_invalid_rest_keyed(caplog):
    tk = _small_sim()
    frames = tk.images[:, 0].copy()
    h, w = frames.shape[1:3]
    rng = np.random.default_rng(0)
    frames[1] = 0  # all black
    wall = cv2.GaussianBlur(rng.normal(100, 30, (h, w, 3)).astype(np.float32), (0, 0), 4.0)
    frames[2] = np.clip(wall, 0, 255).astype(np.uint8)  # no backdrop visible (a grey wall)
    big = frames[3].copy()  # subject filling the image
    cv2.ellipse(big, (w // 2, h // 2), (int(0.62 * w), int(0.62 * h)), 0, 0, 360, (60, 100, 190), -1)
    frames[3] = big
    with caplog.at_level(logging.WARNING):
        res = key_frames(frames, camera="cam00")
    assert res.valid.tolist() == [True, False, False, False, True]
    assert "black" in res.reasons[1]
    assert "no backdrop" in res.reasons[2]
    assert "fills the image" in res.reasons[3]
    assert not res.masks[1:4].any()
    for i in (0, 4):
        assert iou(res.masks[i], tk.masks[i, 0]) >= 0.95
    assert sum("mask invalid" in r.message for r in caplog.records) == 3


def test_invalid_masks_are_said_once_per_reason_with_the_frames_numbers(caplog):
    """Two black frames and one frame of a grey wall: one warning per reason, with the count and the frames' numbers
    (``rows``: the take's; by default their positions), each frame at DEBUG; ``rows=False`` says nothing."""
    frames = _small_sim().images[:, 0].copy()
    frames[1] = frames[3] = 0
    rng = np.random.default_rng(0)
    frames[2] = np.clip(cv2.GaussianBlur(rng.normal(100, 30, frames.shape[1:]).astype(np.float32), (0, 0), 4.0), 0, 255)
    for rows, named in ((None, ("1, 3", "2")), ([10, 11, 12, 13, 14], ("11, 13", "12")), (False, None)):
        caplog.clear()
        with caplog.at_level(logging.DEBUG, logger="stage.keying"):
            res = key_frames(frames, camera="cam00", rows=rows)
        said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        if named is None:
            assert said == []
            continue
        assert said == [f"cam00: mask invalid in 2 frames ({named[0]}): {res.reasons[1]}",
                        f"cam00: mask invalid in 1 frame ({named[1]}): {res.reasons[2]}"], said
        assert res.reasons[1] == res.reasons[3] != res.reasons[2]
        each = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG and "mask invalid" in r.getMessage()]
        assert len(each) == 3
    with pytest.raises(ValueError, match="rows"):
        say_invalid_masks([1, 2], ["black"])


def test_no_backdrop_anywhere_raises_clear_error():
    grey = np.random.default_rng(0).integers(90, 110, (3, 40, 50, 3), dtype=np.uint8)
    with pytest.raises(KeyingError, match="no backdrop"):
        key_frames(grey)


# -- spill --------------------------------------------------------------------------


def test_despill_removes_backdrop_hue_only():
    samples = np.tile(np.array([[45.0, 175.0, 55.0]]), (200, 1)) * np.linspace(0.5, 1.0, 200)[:, None]
    model = estimate_chroma_model(samples + np.random.default_rng(0).normal(0, 1, samples.shape))
    px = np.array([[[60, 160, 120], [70, 125, 205], [45, 175, 55]]], np.uint8)  # spilled, clean orange, backdrop
    out = despill(px, model).astype(int)
    assert out[0, 0, 1] < 150  # green pulled down
    assert np.abs(out[0, 1] - px[0, 1]).max() <= 1  # colour opposite the backdrop hue untouched
    assert np.ptp(out[0, 2]) < 25  # the backdrop itself becomes (nearly) neutral


# -- contact sheet, params, storage, CLI ----------------------------------------------


def test_key_params_roundtrip_and_contact_sheet():
    tk = _small_sim()
    res = key_frames(tk.images[:, 1])
    d = res.params.to_dict()
    assert KeyParams.from_dict(d) == KeyParams.from_dict(d)
    assert KeyParams.from_dict(d).to_dict() == d
    sheet = contact_sheet(tk.images[:, 1], res, rows=3, width=160)
    assert sheet.dtype == np.uint8 and sheet.shape[1] == 3 * 160 and sheet.shape[0] == 3 * 120


def test_cli_key_and_masks(tmp_path):
    from stage import store
    from stage.cli import main
    from stage.frame import Frame

    tk = _small_sim()
    path = tmp_path / "take.h5"
    cams = ["cam00", "cam01"]
    h, w = tk.images.shape[2:4]
    with store.TakeWriter(path, [store.CameraSpec(c, w, h) for c in cams], fps=30.0) as wr:
        for f in range(tk.n_frames):
            wr.write_set(
                {c: Frame(tk.images[f, i], c, f, f * 33_000_000, f * 33_000_000) for i, c in enumerate(cams)},
                time_ns=f * 33_000_000,
            )
    assert main(["key", str(path), "--no-progress", "--preview", str(tmp_path / "prev")]) == 0
    with store.TakeReader(path) as r:
        m = r.masks("cam01")
        params = r.mask_params("cam01")
    expect = key_frames(tk.images[:, 1])
    np.testing.assert_array_equal(m, expect.masks)
    assert params["key"]["mode"] == "chroma" and params["valid"] == [True] * tk.n_frames
    assert (tmp_path / "prev" / "cam00.png").is_file()
    out = tmp_path / "png"
    assert main(["masks", str(path), "--out", str(out), "--no-progress"]) == 0
    png = cv2.imread(str(out / "cam01" / "000002.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(png > 0, expect.masks[2])
    assert (out / "masks.json").is_file()


def test_cli_errors(tmp_path, capsys):
    from stage.cli import main

    with pytest.raises(SystemExit):
        main(["key", str(tmp_path / "x.h5"), "--key-mode", "nope"])
    assert main(["key", str(tmp_path / "missing.h5"), "--no-progress"]) == 2


# -- invalid input per public entry point ------------------------------------------------


def test_small_holes_of_backdrop_colour_stay_open():
    """A closed 2-px slit of clean backdrop (arm against torso) stays open with the default
    ``uncertain`` rule; a speck of mixed colour inside the subject is filled; ``small``
    fills both, ``none`` neither. In luma mode the default is ``small``."""
    rng = np.random.default_rng(5)
    green, skin = np.array([40, 170, 50]), np.array([60, 90, 150])
    img = np.empty((120, 160, 3))
    img[:] = green
    truth = np.zeros((120, 160), bool)
    truth[30:90, 40:120] = True
    truth[45:75, 79:81] = False  # the slit: 60 px
    img[truth] = skin
    speck = (slice(55, 57), slice(100, 102))
    img[speck] = 0.7 * green + 0.3 * skin  # far from the backdrop, but below half the local contrast
    img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    slit = np.zeros_like(truth)
    slit[45:75, 79:81] = True
    p = KeyParams(min_area=0.005, coverage_fraction=0.5)  # 96 px: both holes are "small"
    res = {f: key_frames(img, params=p.replace(fill_holes=f)).masks[0] for f in ("uncertain", "small", "none")}
    assert not res["uncertain"][slit].any() and res["uncertain"][speck].all()
    assert res["small"][slit].all() and res["small"][speck].all()
    assert not res["none"][slit].any() and not res["none"][speck].all()
    assert key_frames(img, params=p).params.fill_holes == "uncertain"
    assert key_frames(img, params=p.replace(mode="luma")).params.fill_holes == "small"


def test_plate_mode_closes_doubtful_gaps_and_leaves_the_backdrop_open():
    """The plate mode's closing and hole filling on a distance image (noise units): a subject of
    80 x 60 px (distance 10) with a hole and a notch of doubtful pixels (2.6: beyond the 5 % tail
    of 1.96, below the candidate threshold) and a hole and a slit of clean backdrop (0.5): the
    doubtful ones close, the backdrop stays open; without the closing and filling the doubtful
    ones stay open too. The keyer resolves the plate mode's defaults to this."""
    from stage.keying.cleanup import mask_from_distance
    from stage.keying.params import PLATE_CLOSE_RELATIVE

    d = np.full((120, 160), 0.5, np.float32)
    d[30:90, 40:120] = 10.0
    doubtful_hole, clean_hole = (slice(50, 60), slice(50, 60)), (slice(50, 60), slice(95, 105))
    doubtful_notch, clean_slit = (slice(30, 45), slice(70, 72)), (slice(60, 90), slice(85, 87))
    for sl, v in ((doubtful_hole, 2.6), (clean_hole, 0.5), (doubtful_notch, 2.6), (clean_slit, 0.5)):
        d[sl] = v
    kw = {"t_lo": 3.29, "t_hi": 4.89, "min_area": 2e-4, "coverage_window": 1}
    m, stats = mask_from_distance(d, **kw, fill_holes="enclosed", close_relative=PLATE_CLOSE_RELATIVE, t_doubt=1.96)
    assert m[doubtful_hole].all() and m[31:45, 70:72].all() and stats["holes_filled"] >= 1  # the notch below its mouth
    assert not m[clean_hole].any() and not m[clean_slit].any()
    plain, _ = mask_from_distance(d, **kw, fill_holes="none")
    assert not plain[doubtful_hole].any() and not plain[doubtful_notch].any()
    rng = np.random.default_rng(1)
    plate = rng.integers(60, 200, (40, 50, 3)).astype(np.uint8)
    frame = plate.copy()
    frame[10:30, 15:35] = (230, 40, 40)
    p = key_frames(frame, mode="plate", plate=plate).params
    assert p.close_relative == PLATE_CLOSE_RELATIVE and p.fill_holes == "enclosed"
    p = key_frames(frame, mode="chroma", plate=plate).params
    assert p.close_relative == 0.0 and p.fill_holes == "uncertain"


def test_invalid_input():
    ok = np.zeros((2, 20, 20, 3), np.uint8)
    with pytest.raises(ValueError, match="frames"):
        key_frames(np.zeros((2, 20, 20), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        key_frames(ok.astype(np.float32))
    with pytest.raises(ValueError, match="frames"):
        key_frames([[1, 2, 3]])
    with pytest.raises(ValueError, match="mode"):
        key_frames(ok, mode="magic")
    with pytest.raises(ValueError, match="plate"):
        key_frames(ok, plate=np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="plate"):
        key_frames(ok, plate=np.zeros((20, 20, 3), np.float32))
    with pytest.raises(ValueError, match="workers"):
        key_frames(ok, workers=0)
    with pytest.raises(ValueError, match="params"):
        key_frames(ok, params={"mode": "chroma"})
    with pytest.raises(ValueError, match="mode"):
        KeyParams(mode="magic")
    with pytest.raises(ValueError, match="t_hi"):
        KeyParams(t_lo=5.0, t_hi=4.0)
    with pytest.raises(ValueError, match="coverage_window"):
        KeyParams(coverage_window=4)
    with pytest.raises(ValueError, match="fill_holes"):
        KeyParams(fill_holes="all")
    with pytest.raises(ValueError, match="close_relative"):
        KeyParams(close_relative=0.7)
    with pytest.raises(ValueError, match="unknown keys"):
        KeyParams.from_dict({"colour": "green"})
    a = np.zeros((5, 5), bool)
    with pytest.raises(ValueError, match="same shape"):
        iou(a, np.zeros((5, 6), bool))
    with pytest.raises(ValueError, match="bool"):
        boundary_f_score(a.astype(np.uint8), a)
    with pytest.raises(ValueError, match="tol"):
        boundary_f_score(a, a, tol=-1)
    with pytest.raises(ValueError, match="mask"):
        mask_boundary(np.zeros((2, 5, 5), bool))
    with pytest.raises(ValueError, match="image"):
        despill(np.zeros((5, 5), np.uint8), {"hue": 0.0})
    with pytest.raises(ValueError, match="samples"):
        estimate_chroma_model(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="backdrop_color"):
        estimate_chroma_model(np.zeros((50, 3)), backdrop_color="black")
