"""Visual hull: lookup-table carving vs a slow direct reference, coarse-to-fine exactness,
visibility, tolerance, bad masks, memory refusal, derived capture volumes."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from calib.calibration import Calibration
from pipeline.hull import EmptyHullError, HullCarver, carve_direct, hull_memory_bytes
from pipeline.volume import (
    Grid,
    above_plane,
    check_plane,
    grid_from_volume,
    pixel_index,
    view_elevation,
    volume_from_cameras,
)
from stage.rig import Volume
from tests.pipeline import simrig
from tests.pipeline.hull_scenes import analytic, sim_grid, sim_take

# -- fixtures ------------------------------------------------------------------------------------


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


def slow_reference(masks, cal: Calibration, grid: Grid, *, tolerance=0, min_views=2) -> np.ndarray:
    """Voxel by voxel, camera by camera, with Camera.project on a single point."""
    ax, ay, az = grid.axes()
    mv = min(min_views, len(cal))
    out = np.zeros(grid.shape, dtype=bool)
    for i, x in enumerate(ax):
        for j, y in enumerate(ay):
            for k, z in enumerate(az):
                carved = seen = 0
                for c, cam in enumerate(cal):
                    (u, v), = cam.project(np.array([[x, y, z]]))
                    depth = (cam.R @ np.array([x, y, z]) + cam.t)[2]
                    col, row = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
                    if depth <= 0 or not (0 <= col < cam.size[0] and 0 <= row < cam.size[1]):
                        continue
                    seen += 1
                    carved += not masks[c][row, col]
                out[i, j, k] = carved <= tolerance and seen >= mv
    return out


# -- exactness -----------------------------------------------------------------------------------


def test_lut_equals_slow_direct_reference_exactly():
    cal, creature, masks, _ = analytic()
    b = creature.bounds()
    # a small grid that sticks out of some cameras' views (so visibility matters)
    grid = grid_from_volume(np.stack([b[0] - 150, b[1] + 400]), 14)
    hc = HullCarver(cal, grid, levels=())
    for tol in (0, 1):
        ref = slow_reference(masks, cal, grid, tolerance=tol)
        assert ref.any() and not ref.all()
        got = hc.carve(masks, tolerance=tol, coarse_to_fine=False).occupancy
        assert np.array_equal(got, ref)
        assert np.array_equal(carve_direct(masks, cal, grid, tolerance=tol), ref)
    # the tables themselves: one pixel per voxel, -1 where the camera does not see it
    pts = grid.centers()
    for c, cam in enumerate(cal):
        lut = hc.lut(c).ravel()
        ref_idx = np.array([pixel_index(cam, p[None])[0][0] for p in pts[::7]])
        assert np.array_equal(lut[::7], ref_idx)
    assert any((hc.lut(c) < 0).any() for c in range(len(cal)))  # some voxels are unseen


@pytest.mark.parametrize("levels", [None, (8, 4), (16, 4), (8, 2), (4,)])
@pytest.mark.parametrize("tolerance", [0, 1])
def test_coarse_to_fine_equals_full_resolution_exactly(levels, tolerance):
    take = sim_take()
    grid = Grid(sim_grid(48).lo, (45, 48, 37), sim_grid(48).voxel)  # odd shape: padding is cropped
    masks = take.masks[0]
    hc = HullCarver(take.calibration, grid, levels=levels)
    full = hc.carve(masks, tolerance=tolerance, coarse_to_fine=False).occupancy
    c2f = hc.carve(masks, tolerance=tolerance)
    assert np.array_equal(c2f.occupancy, full)
    assert c2f.stats["refined"] < grid.n_voxels / 4 or not hc.levels  # it did skip most voxels
    assert np.array_equal(full, carve_direct(masks, take.calibration, grid, tolerance=tolerance))


def test_simulated_rig_hull_matches_ground_truth_hull_and_contains_creature():
    take = sim_take()
    grid = sim_grid(64)
    hc = HullCarver(take.calibration, grid)
    occ = hc.carve(take.masks[0]).occupancy
    ref = carve_direct(take.masks[0], take.calibration, grid)
    assert iou(occ, ref) >= 0.98  # measured: 1.0 (exact)
    # the hull contains the creature: voxels deeper than a voxel inside it are all kept
    sdf = take.poses[0].sdf(grid.centers()).reshape(grid.shape)
    deep = sdf < -grid.voxel
    assert deep.sum() > 50
    assert occ[deep].all()
    # and it is not much more than the creature (8 cameras: a loose hull, still bounded)
    assert occ.sum() < 3.0 * (sdf < 0).sum()


# -- visibility, tolerance, bad masks -------------------------------------------------------------


def test_tolerance_keeps_a_limb_a_bad_mask_removed():
    take = sim_take()
    grid = sim_grid(48)
    hc = HullCarver(take.calibration, grid)
    masks = take.masks[0].copy()
    clean = hc.carve(masks).occupancy
    bad = masks.copy()
    rows, cols = np.nonzero(bad[2])
    keep_half = cols < np.median(cols)
    bad[2][rows[~keep_half], cols[~keep_half]] = False  # camera 2 loses half the subject
    amputated = hc.carve(bad).occupancy
    assert amputated.sum() < 0.9 * clean.sum()
    tolerant = hc.carve(bad, tolerance=1).occupancy
    assert np.all(tolerant[clean])  # nothing of the clean hull is lost
    assert np.array_equal(tolerant, carve_direct(bad, take.calibration, grid, tolerance=1))


def test_all_foreground_camera_is_flagged_and_ignored(caplog):
    take = sim_take()
    cal = take.calibration
    grid = sim_grid(40)
    masks = take.masks[0].copy()
    masks[3] = True
    with caplog.at_level(logging.WARNING, logger="pipeline.hull"):
        res = HullCarver(cal, grid).carve(masks)
    assert res.ignored == (cal[3].name,)
    assert cal[3].name in caplog.text
    others = [i for i in range(len(cal)) if i != 3]
    sub = Calibration(tuple(cal[i] for i in others))
    assert np.array_equal(res.occupancy, HullCarver(sub, grid).carve(masks[others]).occupancy)


def test_empty_masks_everywhere_report_an_empty_frame():
    take = sim_take()
    grid = sim_grid(32)
    empty = np.zeros_like(take.masks[0])
    hc = HullCarver(take.calibration, grid)
    with pytest.raises(EmptyHullError, match="empty"):
        hc.carve(empty)
    with pytest.raises(EmptyHullError):
        carve_direct(empty, take.calibration, grid)
    # silhouettes that do not agree anywhere carve everything: also reported empty
    disjoint = take.masks[0].copy()
    disjoint[1] = False
    disjoint[1][:4, :4] = True  # a speck in a corner, away from the subject
    assert not take.masks[0][1][:4, :4].any()
    with pytest.raises(EmptyHullError, match="carved"):
        hc.carve(disjoint)


def test_a_subject_outside_the_grid_is_said_to_be_outside_it():
    """The true silhouettes carved on a grid beside the subject (the capture volume moved 1.5 m along x): every
    voxel carved, and the message says the subject may be outside the volume, not only that the silhouettes
    disagree (a creature that walked out of the capture volume was said to have silhouettes that do not agree)."""
    from pipeline.volume import grid_from_volume

    take = sim_take()
    lo, hi = np.asarray(Volume().bounds, dtype=float)
    grid = grid_from_volume(np.stack([lo + [1500.0, 0, 0], hi + [1500.0, 0, 0]]), 32)
    for carve in (lambda: HullCarver(take.calibration, grid).carve(take.masks[0]),
                  lambda: carve_direct(take.masks[0], take.calibration, grid)):
        with pytest.raises(EmptyHullError, match="every voxel was carved.*a subject outside the capture volume"):
            carve()


def test_voxels_outside_a_camera_are_not_carved_by_it():
    cal, creature, masks, _ = analytic()
    b = creature.bounds()
    grid = grid_from_volume(b, 24)
    # cut camera 0's image in half: its right half is "not seen" once the camera is cropped
    cam0 = cal[0]
    w, h = cam0.size
    narrow = cam0.replace(size=(w // 2, h))
    cal2 = Calibration((narrow,) + tuple(cal)[1:])
    m2 = [masks[0][:, : w // 2]] + [m for m in masks[1:]]
    occ_full = HullCarver(cal, grid).carve(masks).occupancy
    occ_narrow = HullCarver(cal2, grid).carve(m2).occupancy
    assert np.all(occ_narrow[occ_full])  # fewer constraints, never fewer voxels
    assert occ_narrow.sum() >= occ_full.sum()


def test_grid_too_large_is_refused_up_front_with_the_memory_it_needs():
    take = sim_take()
    grid = grid_from_volume(Volume().bounds, 4096)
    need = hull_memory_bytes(grid, take.calibration)
    with pytest.raises(ValueError, match=r"needs \d+\.\d+ GiB") as exc:
        HullCarver(take.calibration, grid)
    assert f"{need / 1024**3:.2f} GiB" in str(exc.value)
    with pytest.raises(ValueError, match="GiB"):
        HullCarver(take.calibration, sim_grid(64), memory_limit=1024)


# -- capture volume --------------------------------------------------------------------------------


def test_volume_from_cameras_contains_the_subject_and_the_rig_volume():
    take = sim_take()
    lo, hi = take.poses[0].bounds()
    vol = volume_from_cameras(take.calibration, take.masks)
    assert np.all(vol[0] <= lo) and np.all(vol[1] >= hi)
    assert np.all((vol[1] - vol[0]) < 3.0 * (hi - lo) + 100)  # bounded by the silhouettes
    rig = Volume().bounds
    no_masks = volume_from_cameras(take.calibration)
    assert np.all(no_masks[0] <= np.asarray(rig[0]) + 1) and np.all(no_masks[1] >= np.asarray(rig[1]) - 1)
    # carving in the derived volume gives the same hull as in the rig volume (where they overlap)
    grid = grid_from_volume(vol, 40)
    occ = HullCarver(take.calibration, grid).carve(take.masks[0]).occupancy
    assert np.array_equal(occ, carve_direct(take.masks[0], take.calibration, grid))


def test_grid_from_volume():
    g = grid_from_volume(np.array([[0, 0, 0], [100, 50, 25.0]]), 20)
    assert g.shape == (20, 10, 5) and g.voxel == 5.0
    np.testing.assert_allclose(g.bounds, [[0, 0, 0], [100, 50, 25]])
    g2 = grid_from_volume(Volume(), 16)
    assert g2.shape == (16, 16, 16)
    assert Grid.from_dict(g2.to_dict()) == g2
    np.testing.assert_allclose(g2.world_to_index(g2.index_to_world(np.array([[1.0, 2, 3]]))), [[1, 2, 3]])
    c = g.centers()
    assert c.shape == (1000, 3)
    np.testing.assert_allclose(c[0], [2.5, 2.5, 2.5])


# -- invalid input ---------------------------------------------------------------------------------


def test_support_plane_and_margin_equal_the_slow_reference():
    """A support plane removes exactly the voxels whose centre lies below it; a margin of m px
    carves exactly like masks dilated by a (2m+1)-px disk."""
    import cv2

    take = sim_take()
    cal, masks = take.calibration, take.masks[0]
    grid = sim_grid(40)
    hc = HullCarver(cal, grid)
    plain = hc.carve(masks).occupancy
    zs = np.flatnonzero(plain.any(axis=(0, 1)))
    z_cut = grid.axes()[2][zs[len(zs) // 2]] + 0.25 * grid.voxel  # between two voxel layers
    plane = (0.0, 0.0, 2.0, -2.0 * z_cut)  # z >= z_cut, normal not unit on purpose
    cut = hc.carve(masks, support_plane=plane).occupancy
    ref = plain & (grid.centers()[:, 2] >= z_cut).reshape(grid.shape)
    assert np.array_equal(cut, ref) and cut.sum() < plain.sum()
    # a tilted plane, slow reference point by point
    tilted = np.array([0.3137, -0.2071, 1.0, -z_cut - 0.1234])  # no voxel centre on the plane
    pts = grid.centers()
    slow = np.array([p @ tilted[:3] + tilted[3] >= 0 for p in pts]).reshape(grid.shape)
    assert np.array_equal(above_plane(grid, tilted), slow)
    np.testing.assert_allclose(check_plane(tilted)[:3] @ check_plane(tilted)[:3], 1.0)
    # margin
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    grown = np.stack([cv2.dilate(m.astype(np.uint8), disk).astype(bool) for m in masks])
    wide = hc.carve(masks, margin=2).occupancy
    assert np.array_equal(wide, carve_direct(grown, cal, grid))
    assert np.array_equal(wide, hc.carve(grown).occupancy) and wide.sum() > plain.sum()
    assert np.array_equal(hc.carve(masks, margin=0).occupancy, plain)


def test_view_elevation_of_a_ring_and_of_cameras_all_around():
    """A tilted ring of cameras 17 degrees above the subject: up = the ring's axis, 17 degrees
    (to 0.01); cameras above and below the subject: no blind side (negative)."""
    axis = np.array([0.2, -0.3, 1.0])
    axis /= np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    target = np.array([10.0, -20.0, 300.0])
    el = np.radians(17.0)
    cams = []
    for i in range(15):
        az = 2 * np.pi * i / 15 + 0.05 * np.sin(3 * i)
        d = np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * axis
        cams.append(simrig.look_at(f"c{i}", target + 600 * d, target))
    up, elev = view_elevation(Calibration(tuple(cams)), target)
    assert elev == pytest.approx(17.0, abs=0.01) and up @ axis > 0.99999
    below = [simrig.look_at(f"b{i}", target + 600 * np.array([np.cos(a), np.sin(a), -0.5]), target)
             for i, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]
    assert view_elevation(Calibration(tuple(cams[::3] + below)), target)[1] < 0


def test_invalid_input():
    take = sim_take()
    cal = take.calibration
    grid = sim_grid(16)
    masks = take.masks[0]
    with pytest.raises(ValueError, match="resolution"):
        grid_from_volume(Volume().bounds, 0)
    with pytest.raises(ValueError, match="volume_bounds"):
        grid_from_volume([[0, 0, 0], [0, 1, 1]], 8)
    with pytest.raises(ValueError, match="volume_bounds"):
        grid_from_volume([1, 2, 3], 8)
    with pytest.raises(ValueError, match="shape"):
        Grid(np.zeros(3), (0, 2, 2), 1.0)
    with pytest.raises(ValueError, match="voxel"):
        Grid(np.zeros(3), (2, 2, 2), -1.0)
    with pytest.raises(ValueError, match="calibration"):
        HullCarver("cams", grid)
    with pytest.raises(ValueError, match="grid"):
        HullCarver(cal, (16, 16, 16))
    with pytest.raises(ValueError, match="levels"):
        HullCarver(cal, grid, levels=(4, 8))
    hc = HullCarver(cal, grid)
    with pytest.raises(ValueError, match="masks"):
        hc.carve(masks[:3])
    with pytest.raises(ValueError, match="masks"):
        hc.carve(masks[:, :10])
    with pytest.raises(ValueError, match="masks"):
        hc.carve("masks")
    with pytest.raises(ValueError, match="tolerance"):
        hc.carve(masks, tolerance=-1)
    with pytest.raises(ValueError, match="tolerance"):
        hc.carve(masks, tolerance=len(cal))
    with pytest.raises(ValueError, match="min_views"):
        hc.carve(masks, min_views=0)
    with pytest.raises(ValueError, match="support_plane"):
        hc.carve(masks, support_plane=(0, 0, 0, 1))
    with pytest.raises(ValueError, match="support_plane"):
        hc.carve(masks, support_plane=(0, 0, 1))
    with pytest.raises(ValueError, match="support_plane"):
        hc.carve(masks, support_plane=(0, 0, 1, np.nan))
    with pytest.raises(ValueError, match="margin"):
        hc.carve(masks, margin=-1)
    with pytest.raises(ValueError, match="margin"):
        hc.carve(masks, margin=1.5)
    with pytest.raises(ValueError, match="grid"):
        above_plane(None, (0, 0, 1, 0))
    with pytest.raises(ValueError, match="calibration"):
        view_elevation(None, (0, 0, 0))
    with pytest.raises(ValueError, match="point"):
        view_elevation(cal, (0, 0))
    with pytest.raises(ValueError, match="masks"):
        carve_direct(masks[:2], cal, grid)
    with pytest.raises(ValueError, match="grid"):
        carve_direct(masks, cal, None)
    with pytest.raises(ValueError, match="calibration"):
        volume_from_cameras(None)
    with pytest.raises(ValueError, match="min_fraction"):
        volume_from_cameras(cal, min_fraction=0)
    with pytest.raises(ValueError, match="masks"):
        volume_from_cameras(cal, masks[:2])
    with pytest.raises(ValueError, match="no foreground"):
        volume_from_cameras(cal, np.zeros_like(masks))


def test_bool_masks_holding_255_bytes_carve_like_clean_ones():
    """OpenCV's 0/255 output viewed as bool must not change the coarse-to-fine result."""
    take = sim_take()
    from pipeline.hull import HullCarver
    from pipeline.volume import grid_from_volume

    carver = HullCarver(take.calibration, grid_from_volume(take.volume, 48))
    clean = take.masks[0]
    dirty = (clean.astype(np.uint8) * 255).view(bool)
    a = carver.carve(clean).occupancy
    b = carver.carve(dirty).occupancy
    assert np.array_equal(a, b)


def test_missing_camera_is_none_and_neither_carves_nor_warns(caplog):
    """A camera with no frame in a set (None) is left out like an all-foreground mask, silently."""
    take = sim_take()
    from pipeline.hull import HullCarver
    from pipeline.volume import grid_from_volume

    carver = HullCarver(take.calibration, grid_from_volume(take.volume, 32))
    masks = list(take.masks[0])
    full = [m if i else np.ones_like(m) for i, m in enumerate(masks)]
    with caplog.at_level("WARNING"):
        a = carver.carve([None] + masks[1:])
    assert not [r for r in caplog.records if "all foreground" in r.getMessage()]
    b = carver.carve(full)
    assert np.array_equal(a.occupancy, b.occupancy) and a.ignored == (take.calibration.names[0],)
