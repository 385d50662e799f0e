"""Template tracking of simulated multi-view takes.

The takes and their ``stage process`` results are the ones of the spine pipeline test
(8 cameras, 640x480, 30 frames, cached per session); the ``track`` step runs on them and
every template vertex is compared with the true surface point it started on (the template
vertex snapped onto the creature at the template's frame and carried with its capsule,
:mod:`fake_cameras.surface_motion`). Tolerances: mean over all vertices and frames
at most one voxel, 95th percentile at most two voxels; the volume within 5 % of the template's.
"""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.surface_motion import tracking_errors
from pipeline.process import process_take
from tests.pipeline.test_spine_pipeline import N_FRAMES, run


def _tracking_errors(name, tmp_path_factory):
    r = run(name, tmp_path_factory)
    results = r["res"].out
    process_take(results.parent / f"{name}.h5", results, steps=("track",), executor=None)
    err, vols, rep = tracking_errors(r["sim"].creature, r["sim"].times, results, frames=N_FRAMES)
    return err.ravel(), vols, rep


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    # measured: mean 0.91 voxels, 95th percentile 1.99 (1.97 before the 1e-5 CG tolerance), volume 1.00..1.02
    # (photo_refine: 0.67 / 1.67, 0.97..1.02; with the colour tracks, --colour: 0.84 / 1.92;
    # --carve 1 --shape-memory --colour: 0.51 / 1.31, 0.47 / 1.17 with --carve-margin 0)
    "starfish",
    pytest.param("quadruped", marks=pytest.mark.xfail(strict=True, reason=(
        "not met: mean 1.47 voxels, 95th percentile 3.38 (1.18 / 3.09 with the colour tracks, `stage track --colour`). "
        "The gap is the hull's surfaces and the template taken from them, together: the template is 0.84 / 2.5 voxels "
        "(mean / 95th percentile) off the true surface at its own frame. With the best surfaces the product makes "
        "(`silhouette_margin=0` and `photo_refine`: 0.40 / 1.78 at that frame) and `--shape-memory --colour` the "
        "tracking gives 0.87 / 2.49; on the true surfaces (`stage bench track --accuracy`) 1.00 / 2.75 by default, "
        "0.53 / 1.54 with `--shape-memory --colour`. Surfaces carved across time with the tracked motion, "
        "`stage track --carve 2 --shape-memory --colour`: 0.84 / 2.21 with the silhouettes grown by the 1-px margin "
        "they were processed with, 0.71 / 1.94 (volume 0.978..1.001) with `--carve-margin 0`, about five minutes more "
        "than CI allows for this take (`stage bench track --accuracy` measures it); see docs/tracking.md"))),
])


def test_multiview_tracking_follows_every_surface_point(name, tmp_path_factory):
    err, vols, rep = _tracking_errors(name, tmp_path_factory)
    assert rep["mode"] == "multi-view" and rep["skipped"] == []
    assert np.all(np.abs(vols - 1) <= 0.05)
    assert err.mean() <= 1.0, err.mean()
    assert np.percentile(err, 95) <= 2.0, np.percentile(err, 95)
