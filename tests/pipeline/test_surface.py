"""Surface: marching cubes + cleanup on hulls and fields; quality report; the Middlebury dino."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.hull import HullCarver
from pipeline.surface import (
    EmptySurfaceError,
    clean_mesh,
    surface_from_field,
    surface_from_occupancy,
    surface_quality,
)
from pipeline.volume import Grid, grid_from_volume, volume_from_cameras
from tests.conftest import shared_dataset
from tests.pipeline.hull_scenes import sim_grid, sim_take


def _ball_grid(n=24, voxel=2.0):
    return Grid(np.full(3, -n * voxel / 2), (n, n, n), voxel)


def test_surface_of_simulated_hull_is_watertight_and_within_one_voxel_of_the_hull():
    from scipy.ndimage import binary_erosion
    from scipy.spatial import cKDTree

    take = sim_take()
    grid = sim_grid(64)
    occ = HullCarver(take.calibration, grid).carve(take.masks[0]).occupancy
    mesh = surface_from_occupancy(occ, grid)
    q = surface_quality(mesh)
    assert q.watertight and q.bodies == 1 and q.volume > 0
    # the surface runs between kept and carved voxel centres: every vertex is within one
    # voxel of a kept boundary voxel and of a carved voxel next to it
    inner = occ & ~binary_erosion(occ)
    outer = ~occ & binary_erosion(~occ, border_value=1) ^ ~occ
    kept = grid.index_to_world(np.argwhere(inner))
    carved = grid.index_to_world(np.argwhere(outer))
    d_in, _ = cKDTree(kept).query(mesh.vertices)
    d_out, _ = cKDTree(carved).query(mesh.vertices)
    assert d_in.max() <= grid.voxel and d_out.max() <= grid.voxel
    # its volume matches the voxel count within a few percent (Taubin does not shrink it)
    assert abs(q.volume - occ.sum() * grid.voxel**3) < 0.1 * occ.sum() * grid.voxel**3


def test_surface_from_field_follows_an_exact_sdf():
    grid = _ball_grid()
    c = grid.centers()
    sdf = (np.linalg.norm(c - [1.0, -2.0, 0.5], axis=1) - 15.0).reshape(grid.shape)
    mesh = surface_from_field(sdf, grid, taubin_iterations=0)
    err = np.abs(np.linalg.norm(mesh.vertices - [1.0, -2.0, 0.5], axis=1) - 15.0)
    assert err.max() < 0.1 * grid.voxel  # linear interpolation of an exact distance
    q = surface_quality(mesh)
    assert q.watertight and q.genus == 0 and q.euler == 2
    assert abs(q.volume - 4 / 3 * np.pi * 15.0**3) < 0.02 * 4 / 3 * np.pi * 15.0**3


def test_quality_report_of_a_torus():
    torus = trimesh.creation.torus(major_radius=10, minor_radius=3)
    q = surface_quality(torus)
    assert q.watertight and q.genus == 1 and q.euler == 0 and q.bodies == 1
    assert q.vertices == len(torus.vertices) and q.faces == len(torus.faces)
    assert set(q.to_dict()) >= {"vertices", "faces", "watertight", "genus", "volume"}
    open_mesh = torus.submesh([np.arange(len(torus.faces) - 3)], append=True)
    q2 = surface_quality(open_mesh)
    assert not q2.watertight and q2.genus is None and q2.volume is None


def _trimesh_quality(mesh) -> dict:
    """The quality report from trimesh's own properties (the slow reference)."""
    watertight = bool(mesh.is_watertight) and bool(mesh.is_winding_consistent)
    euler = int(mesh.euler_number)
    labels = trimesh.graph.connected_component_labels(mesh.edges, node_count=len(mesh.vertices))
    bodies = len(np.unique(labels[mesh.faces[:, 0]]))
    return {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "watertight": watertight, "euler": euler,
            "genus": (2 * bodies - euler) // 2 if watertight else None, "bodies": bodies,
            "volume": float(mesh.volume) if watertight else None, "area": float(mesh.area)}


def test_quality_equals_trimesh_properties():
    """The one-pass numpy report = trimesh's properties (volume and area to 1e-12 relative) on
    closed, multi-body, open, mis-wound and non-manifold meshes."""
    torus = trimesh.creation.torus(major_radius=10, minor_radius=3)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=4.0).apply_translation([30.0, 0, 0])
    two = trimesh.util.concatenate([torus, ball])
    flipped = trimesh.Trimesh(torus.vertices, np.vstack([torus.faces[:1, ::-1], torus.faces[1:]]), process=False)
    holed = trimesh.Trimesh(torus.vertices, torus.faces[5:], process=False)
    fin = trimesh.Trimesh(np.vstack([torus.vertices, [[0.0, 0.0, 50.0]]]),
                          np.vstack([torus.faces, [[*torus.faces[0, :2], len(torus.vertices)]]]), process=False)
    for mesh in (torus, two, flipped, holed, fin):
        got, want = surface_quality(mesh).to_dict(), _trimesh_quality(mesh)
        for key in ("volume", "area"):
            if want[key] is None:
                assert got[key] is None
            else:
                assert got[key] == pytest.approx(want[key], rel=1e-12)
        assert {k: v for k, v in got.items() if k not in ("volume", "area")} == {
            k: v for k, v in want.items() if k not in ("volume", "area")}


def test_cleanup_keeps_the_largest_piece_and_fills_cavities():
    grid = _ball_grid(32, 1.0)
    c = grid.centers()
    r = np.linalg.norm(c, axis=1).reshape(grid.shape)
    occ = (r < 10) & ~(r < 4)  # a hollow ball
    speck = np.linalg.norm(c - [13, 13, 13], axis=1).reshape(grid.shape) < 1.5
    occ |= speck
    mesh = surface_from_occupancy(occ, grid)
    q = surface_quality(mesh)
    assert q.bodies == 1 and q.genus == 0 and q.watertight
    assert np.linalg.norm(mesh.vertices, axis=1).min() > 8  # no inner shell, no speck
    assert np.linalg.norm(mesh.vertices, axis=1).max() < 11
    both = surface_from_occupancy(occ, grid, keep_largest=False, fill_cavities=False)
    assert surface_quality(both).bodies == 3


def test_decimation_to_a_face_budget_stays_watertight():
    take = sim_take()
    grid = sim_grid(64)
    occ = HullCarver(take.calibration, grid).carve(take.masks[0]).occupancy
    full = surface_from_occupancy(occ, grid)
    budget = len(full.faces) // 2
    small = surface_from_occupancy(occ, grid, face_budget=budget)
    q = surface_quality(small)
    assert q.faces <= budget and q.watertight and q.bodies == 1
    # without fast-simplification the fallback re-runs marching cubes with a coarser step,
    # which thins the limbs: measured -9 % volume at step 2 on this small creature
    assert abs(q.volume - surface_quality(full).volume) < 0.2 * surface_quality(full).volume


def test_empty_occupancy_raises_empty_surface_error():
    grid = _ball_grid(8)
    with pytest.raises(EmptySurfaceError):
        surface_from_occupancy(np.zeros(grid.shape, bool), grid)
    with pytest.raises(EmptySurfaceError):
        surface_from_field(np.ones(grid.shape), grid)


def test_invalid_input():
    grid = _ball_grid(8)
    occ = np.zeros(grid.shape, bool)
    occ[2:6, 2:6, 2:6] = True
    with pytest.raises(ValueError, match="grid"):
        surface_from_occupancy(occ, None)
    with pytest.raises(ValueError, match="occupancy"):
        surface_from_occupancy(occ[:4], grid)
    with pytest.raises(ValueError, match="occupancy"):
        surface_from_occupancy(occ.astype(float), grid)
    with pytest.raises(ValueError, match="smooth_sigma"):
        surface_from_occupancy(occ, grid, smooth_sigma=-1)
    with pytest.raises(ValueError, match="face_budget"):
        surface_from_occupancy(occ, grid, face_budget=2)
    with pytest.raises(ValueError, match="taubin_iterations"):
        surface_from_occupancy(occ, grid, taubin_iterations=-1)
    with pytest.raises(ValueError, match="field"):
        surface_from_field(np.zeros((3, 3, 3)), grid)
    with pytest.raises(ValueError, match="inside"):
        surface_from_field(occ.astype(float), grid, inside="left")
    with pytest.raises(ValueError, match="mesh"):
        clean_mesh("mesh")
    with pytest.raises(ValueError, match="mesh"):
        surface_quality(None)


# -- real data: the Middlebury dino -----------------------------------------------------------------

DINO_TIGHT_BOX = np.array([[-0.061897, -0.018874, -0.057845], [0.010897, 0.068227, 0.015495]])  # README.txt


def _dino_take(folder: Path):
    """The 15 good views, keyed in luma mode (automatic threshold, defaults)."""
    import cv2

    from calib import formats
    from calib.calibration import Calibration
    from stage.keying import key_frames
    cal = formats.read_middlebury_par(folder / "dinoSR_par.txt")
    good = [ln.strip() for ln in (folder / "dinoSR_good_silhouette_images.txt").read_text().splitlines() if ln.strip()]
    by_name = {c.name: c for c in cal.cameras}
    cal = Calibration(tuple(by_name[Path(n).stem] for n in good), units=cal.units)
    masks = []
    for n in good:
        res = key_frames(cv2.imread(str(folder / n)), mode="luma")
        assert res.valid[0], res.reasons
        masks.append(res.masks[0])
    return cal, np.stack(masks)


def _hidden_by(occ_above: np.ndarray, grid: Grid, cameras, points: np.ndarray, reach: float) -> np.ndarray:
    """Which points no camera sees past ``occ_above``: every ray towards a camera crosses it."""
    hidden = np.ones(len(points), bool)
    for cam in cameras:
        d = cam.center - points
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hit = np.zeros(len(points), bool)
        for s in np.arange(0.0, reach, grid.voxel / 2):
            ijk = np.floor((points + s * d - grid.lo) / grid.voxel).astype(int)
            ok = np.all((ijk >= 0) & (ijk < np.array(grid.shape)), axis=1)
            hit[ok] |= occ_above[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]]
        hidden &= hit
    return hidden


@pytest.mark.slow
def test_middlebury_dino_surface_bounding_box():
    """Luma-keyed silhouettes of the dino give a surface within 5 % of the published box.

    All 15 views sit ~17 degrees above the dino on a ring around +y, so no silhouette can
    carve the region under its base: a visual hull from these cameras alone reaches ~6 mm
    below the published box (+7 % on y; the dataset README's own hull is +5.3 %). Given the
    plane it stands on (``support_plane``, here the published box's floor, as a lab knows
    its turntable) the box is within 5 % on every axis. Without it, every voxel of the hull
    below that plane is one that no camera can see past the dino: the excess is geometry,
    not keying or calibration.
    """
    from scipy import ndimage

    folder = shared_dataset("middlebury_dino_sparse_ring")
    cal, masks = _dino_take(folder)
    vol = volume_from_cameras(cal, masks)  # imported footage: no capture volume
    grid = grid_from_volume(vol, 128)
    carver = HullCarver(cal, grid)
    pub = DINO_TIGHT_BOX[1] - DINO_TIGHT_BOX[0]
    floor_y = DINO_TIGHT_BOX[0, 1]

    occ = carver.carve(masks, margin=1, support_plane=(0.0, 1.0, 0.0, -floor_y)).occupancy
    mesh = surface_from_occupancy(occ, grid)
    assert surface_quality(mesh).watertight
    rel = (mesh.bounds[1] - mesh.bounds[0] - pub) / pub
    assert np.all(np.abs(rel) <= 0.05), rel  # measured -0.5 %, -0.4 %, +0.1 % at 128^3
    assert np.all(np.abs(mesh.bounds - DINO_TIGHT_BOX) <= 0.05 * pub), mesh.bounds - DINO_TIGHT_BOX

    free = carver.carve(masks, margin=1).occupancy
    lab, _ = ndimage.label(free)
    free = lab == 1 + np.argmax(np.bincount(lab.ravel())[1:])
    mesh_free = surface_from_occupancy(free, grid)
    below_mm = (floor_y - mesh_free.bounds[0, 1]) * 1000
    assert 2.0 <= below_mm <= 12.0, below_mm  # measured 6.4 mm
    np.testing.assert_allclose(mesh_free.bounds[1], mesh.bounds[1], atol=grid.voxel)  # only the bottom differs
    ay = grid.axes()[1]
    below = np.argwhere(free & (ay < floor_y)[None, :, None])
    assert len(below) > 100
    hidden = _hidden_by(free & (ay >= floor_y)[None, :, None], grid, cal.cameras, grid.index_to_world(below), 0.06)
    assert hidden.mean() >= 0.99, hidden.mean()  # measured 1.0


def _dino_silhouettes(folder: Path, names: list[str]) -> np.ndarray:
    """The dataset README's recipe: luma > 0.19, dilate 10 px, erode 7 px."""
    import cv2

    out = []
    for n in names:
        img = cv2.imread(str(folder / n))
        luma = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0
        m = (luma > 0.19).astype(np.uint8)
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21)))
        m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15)))
        out.append(m.astype(bool))
    return np.stack(out)


@pytest.mark.slow
def test_middlebury_dino_recipe_silhouettes_match_published_box_above_the_floor():
    from calib import formats
    from calib.calibration import Calibration
    folder = shared_dataset("middlebury_dino_sparse_ring")
    cal = formats.read_middlebury_par(folder / "dinoSR_par.txt")
    good = [ln.strip() for ln in (folder / "dinoSR_good_silhouette_images.txt").read_text().splitlines() if ln.strip()]
    cal = Calibration(tuple(cal[Path(n).stem] for n in good), units=cal.units)
    masks = _dino_silhouettes(folder, good)
    vol = volume_from_cameras(cal, masks)  # imported footage: no capture volume
    grid = grid_from_volume(vol, 128)
    occ = HullCarver(cal, grid).carve(masks).occupancy
    mesh = surface_from_occupancy(occ, grid)
    assert surface_quality(mesh).watertight
    ext = mesh.bounds[1] - mesh.bounds[0]
    pub = DINO_TIGHT_BOX[1] - DINO_TIGHT_BOX[0]
    rel = (ext - pub) / pub
    # x and z: within 5 % of the published tight box (measured +0.6 %, -1.3 %); y reaches
    # under the base (+8.1 %), see test_middlebury_dino_surface_bounding_box
    assert abs(rel[0]) <= 0.05 and abs(rel[2]) <= 0.05, rel
    assert abs(mesh.bounds[1, 1] - DINO_TIGHT_BOX[1, 1]) <= 2 * grid.voxel
    occ = HullCarver(cal, grid).carve(masks, support_plane=(0, 1, 0, -DINO_TIGHT_BOX[0, 1])).occupancy
    ext = np.ptp(surface_from_occupancy(occ, grid).bounds, axis=0)
    assert np.all(np.abs(ext - pub) <= 0.05 * pub), (ext - pub) / pub  # measured +0.6 %, +0.5 %, -1.3 %
