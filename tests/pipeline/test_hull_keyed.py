"""Visual hull from *keyed* silhouettes: on the simulated rig the hull
carved from the chroma keyer's masks matches the hull carved from the ground-truth masks.

The grid is fitted to the creature (as ``stage process`` does): at 128^3 over the whole
750 mm capture volume the starfish is only ~8000 voxels, most of them on its boundary, and
voxel IoU measures the voxel size rather than the masks."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from pipeline.hull import HullCarver
from pipeline.volume import Grid, grid_from_volume

N_FRAMES = 2
RESOLUTION = 128  # voxels along the longest side of the subject's box


@lru_cache(maxsize=None)
def keyed_take(creature: str = "starfish"):
    """A creature on the 12-camera dome at 640x480 (rendering cached on disk), GT and keyed masks."""
    from fake_cameras import take as take_mod
    from stage.keying import key_frames

    tk = take_mod.simulate_take(creature, n_cameras=12, frames=N_FRAMES, size=(640, 480), seed=0)
    keyed = np.zeros_like(tk.masks)
    for c in range(tk.n_cameras):
        # no plate: the backdrop model is estimated from the frames themselves
        res = key_frames(tk.images[:, c], camera=tk.calibration.cameras[c].name)
        assert res.valid.all(), res.reasons
        keyed[:, c] = res.masks
    return tk, keyed


@lru_cache(maxsize=None)
def subject_grid(creature: str = "starfish") -> Grid:
    """``RESOLUTION`` voxels along the longest side of the ground-truth hulls' box, padded."""
    tk, _ = keyed_take(creature)
    coarse = grid_from_volume(tk.volume.bounds, 64)
    carver = HullCarver(tk.calibration, coarse)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for f in range(tk.n_frames):
        idx = np.argwhere(carver.carve(tk.masks[f]).occupancy)
        lo = np.minimum(lo, coarse.index_to_world(idx.min(0)[None])[0])
        hi = np.maximum(hi, coarse.index_to_world(idx.max(0)[None])[0])
    pad = 3 * coarse.voxel
    return grid_from_volume(np.array([lo - pad, hi + pad]), RESOLUTION)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


@pytest.mark.slow
@pytest.mark.parametrize("creature", ["starfish", "quadruped", "biped"])
def test_keyed_hull_matches_ground_truth_hull(creature):
    """Voxel IoU >= 0.98 against the hull of the ground-truth masks on the same grid.

    Measured (frames 0, 1): starfish 0.9932 / 0.9927, quadruped 0.9974 / 0.9967, biped 0.9938 /
    0.9949 (0.981 / 0.984 while the keyer filled the backdrop slits between arm and torso).
    Starfish: a 128x128x64 grid of 3.5 mm voxels (~39000
    voxels inside); the keyed hull loses ~250 boundary voxels and gains 12-34 (the keyed masks
    are a fraction of a pixel thinner where green spill darkens the silhouette's edge). Before
    the keyer emitted canonical 0/1 booleans the coarse-to-fine carver counted its foreground
    pixels 255 times and this was 0.86-0.90.
    """
    tk, keyed = keyed_take(creature)
    grid = subject_grid(creature)
    assert max(grid.shape) == RESOLUTION
    carver = HullCarver(tk.calibration, grid)
    for f in range(tk.n_frames):
        truth = carver.carve(tk.masks[f]).occupancy
        got = carver.carve(keyed[f]).occupancy
        assert truth.sum() > 20000  # the grid is fitted to the subject: the hull is well resolved
        score = _iou(got, truth)
        print(f"{creature} frame {f}: voxel IoU {score:.4f}")
        assert score >= 0.98, (f, score, int((got & ~truth).sum()), int((truth & ~got).sum()))


@pytest.mark.slow
def test_keyed_masks_carve_exactly_coarse_to_fine():
    """The keyed masks are plain 0/1 booleans: the hierarchy (summed-area tables over the
    masks' bytes) gives exactly the voxel-by-voxel table gather."""
    tk, keyed = keyed_take()
    assert keyed.view(np.uint8).max() == 1
    carver = HullCarver(tk.calibration, subject_grid())
    fast = carver.carve(keyed[0]).occupancy
    flat = carver.carve(keyed[0], coarse_to_fine=False).occupancy
    np.testing.assert_array_equal(fast, flat)
