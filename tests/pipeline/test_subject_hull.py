"""The surface step's hull (pipeline.silhouette_refine.subject_hull): silhouette parts the subject
does not explain are dropped before carving, clean silhouettes give the carver's own hull, one
camera's miss inside a gap of its silhouette is bridged, specks that explain nothing are left out."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from pipeline.consistency import mesh_silhouette
from pipeline.hull import HullCarver
from pipeline.silhouette_refine import _without_specks, hull_projection, subject_hull
from pipeline.volume import grid_from_volume
from stage.keying.params import PLATE_CLOSE_RELATIVE as BRIDGE_GAPS
from tests.pipeline.simrig import dome


def _scene():
    cal = dome(6, size=(160, 120))
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=200.0)
    v = mesh.vertices * [1.0, 0.7, 1.5] + [0.0, 0.0, 300.0]
    masks = [mesh_silhouette(v, mesh.faces, c) for c in cal]
    carver = HullCarver(cal, grid_from_volume(np.array([[-400.0, -400.0, -100.0], [400.0, 400.0, 700.0]]), 48))
    return cal, masks, carver


def test_parts_the_subject_does_not_explain_are_dropped():
    """Six cameras see an ellipsoid; camera 1's silhouette also holds a blob in an image corner
    (a shadow, a lamp): the blob is dropped (its share of camera 1's silhouette returned, 0 in the
    others) and the hull is the one the clean silhouettes give; clean silhouettes give exactly the
    carver's hull (one piece, nothing dropped)."""
    cal, masks, carver = _scene()
    clean = carver.carve(masks, margin=1).occupancy
    sh = subject_hull(masks, carver, margin=1)
    assert np.array_equal(sh.occupancy, clean) and np.all(sh.dropped == 0) and sh.pieces_dropped == 0
    assert sh.views == 6
    dirty = [m.copy() for m in masks]
    dirty[1][2:14, 2:20] = True
    assert not (dirty[1][2:14, 2:20] & masks[1][2:14, 2:20]).any()
    sh = subject_hull(dirty, carver, margin=1)
    assert np.array_equal(sh.occupancy, clean)
    assert np.array_equal(sh.masks[1], masks[1])
    blob = 12 * 18
    assert sh.dropped[1] == pytest.approx(blob / (blob + masks[1].sum()))
    assert np.all(np.delete(sh.dropped, 1) == 0)
    none = list(masks)
    none[2] = None
    sh = subject_hull(none, carver, margin=1)
    assert sh.masks[2] is None and np.isnan(sh.dropped[2])


def test_one_cameras_miss_inside_a_gap_is_bridged():
    """Camera 1's silhouette misses a band 2 pixels high across the middle (black shorts before a
    black floor): carved as it is, the hull loses what the band's rays cross for every camera;
    with ``bridge_gaps`` the voxels only camera 1 carves inside its silhouette's gap come back
    (the hull within 1 % of the clean one's voxels) and camera 1's silhouette is keyed again
    there, inside its true silhouette only. A band of 4 pixels that cuts the hull in two is
    joined across; clean silhouettes bridge nothing, and a band of 8 pixels is left carved."""
    cal, masks, carver = _scene()
    clean = carver.carve(masks, margin=0).occupancy
    sh = subject_hull(masks, carver, margin=0, bridge_gaps=BRIDGE_GAPS)
    assert sh.bridged == 0 and np.array_equal(sh.occupancy, clean)
    rows = np.flatnonzero(masks[1].any(axis=1))
    mid = (rows[0] + rows[-1]) // 2
    cut = [m.copy() for m in masks]
    cut[1][mid - 1:mid + 1] = False
    missed = np.count_nonzero(clean & ~subject_hull(cut, carver, margin=0).occupancy)
    assert missed > 0.05 * clean.sum()
    sh = subject_hull(cut, carver, margin=0, bridge_gaps=BRIDGE_GAPS)
    assert sh.bridged > 0.8 * missed
    assert np.count_nonzero(sh.occupancy ^ clean) < 0.01 * clean.sum()
    gap = masks[1] & ~cut[1]
    assert np.count_nonzero(sh.masks[1] & gap) > 0.75 * gap.sum()
    assert not (sh.masks[1] & ~masks[1]).any()
    assert all(np.array_equal(a, b) for i, (a, b) in enumerate(zip(sh.masks, masks)) if i != 1)
    # a band of 4 cuts the hull in two: the lower piece is joined across (gaps twice as wide,
    # on the shortest paths only) instead of being left out with camera 1's lower silhouette part
    split = [m.copy() for m in masks]
    split[1][mid - 2:mid + 2] = False
    assert ndimage.label(carver.carve(split).occupancy, structure=np.ones((3, 3, 3)))[1] == 2
    sh = subject_hull(split, carver, margin=0, bridge_gaps=BRIDGE_GAPS)
    assert sh.bridged > 0 and np.count_nonzero(sh.occupancy ^ clean) < 0.03 * clean.sum()
    assert ndimage.label(sh.occupancy, structure=np.ones((3, 3, 3)))[1] == 1
    assert not (sh.masks[1] & ~masks[1]).any()
    wide = [m.copy() for m in masks]
    wide[1][mid - 4:mid + 4] = False
    assert subject_hull(wide, carver, margin=0, bridge_gaps=BRIDGE_GAPS).bridged == 0


def test_specks_that_explain_nothing_are_left_out():
    """A hollow ball with a voxel in its hollow (every camera sees the voxel inside the ball's
    outline: it explains no pixel alone) and a cube beside it (its own pixels in every camera):
    the voxel is left out, the cube kept."""
    cal, masks, carver = _scene()
    grid = carver.grid
    g = np.indices(grid.shape).transpose(1, 2, 3, 0) - np.array(grid.shape) // 2
    r = np.linalg.norm(g, axis=-1)
    occ = (r <= 9) & (r > 5)
    occ[tuple(np.array(grid.shape) // 2)] = True
    occ[2:6, 2:6, 20:24] = True
    imgs, _ = hull_projection(occ, grid, cal)
    kept, dropped = _without_specks(occ, imgs, grid, cal)
    assert dropped == 1
    assert np.array_equal(kept, occ & ((r > 5) | (g[..., 0] < -10)))


def test_invalid_input():
    cal, masks, carver = _scene()
    with pytest.raises(ValueError, match="view_slack"):
        subject_hull(masks, carver, view_slack=-1)
    with pytest.raises(ValueError, match="view_slack"):
        subject_hull(masks, carver, view_slack=True)
    for bad in (-0.1, 0.6, True, float("nan")):
        with pytest.raises(ValueError, match="bridge_gaps"):
            subject_hull(masks, carver, bridge_gaps=bad)
    with pytest.raises(ValueError):
        subject_hull(masks[:3], carver)
