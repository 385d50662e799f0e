"""Template tracking on surfaces carved across time (``stage track --carve``), on a short
simulated quadruped take of its own (8 cameras, 640x480, the gait's first 6 frames).

The hull's surfaces hold the tracking alone (``--armature-rounds 0``) back on the quadruped: on this take it scores
1.11 / 3.18 voxels (mean / 95th percentile over all vertices and frames), over the targets. One
round of carving across time with shape memory (``--carve 1 --shape-memory``, through the CLI)
brings it to 0.57 / 1.69 (volume 0.974..1.004). Tolerances, as the multi-view tracking test's:
mean at most one voxel, 95th percentile at most two, volume within 5 % of the template's. Every
template vertex is scored against the true surface point it started on
(:func:`fake_cameras.surface_motion.tracking_errors`). The 30-frame take in the documented
accurate mode (``--carve 2 --shape-memory --colour``) takes minutes: ``stage bench track
--accuracy`` (figures in docs/tracking.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from fake_cameras.record import record_take
from fake_cameras.surface_motion import tracking_errors
from fake_cameras.take import simulate_take
from pipeline.process import process_take
from stage.cli import main

FRAMES = 6


@pytest.mark.slow
def test_carved_surfaces_bring_the_quadruped_within_a_voxel(tmp_path):
    sim = simulate_take("quadruped", n_cameras=8, frames=FRAMES, size=(640, 480), seed=3)
    results = tmp_path / "results"
    process_take(record_take(sim, tmp_path / "quadruped.h5"), results, executor=None)
    # the carving as measured (docs/tracking.md), without the default's armature round
    assert main(["-q", "track", str(results), "--carve", "1", "--shape-memory", "--armature-rounds", "0"]) == 0
    err, vols, rep = tracking_errors(sim.creature, sim.times, results, frames=FRAMES)
    assert rep["mode"] == "multi-view" and rep["skipped"] == [] and rep["surfaces"] == "carved"
    assert np.all(np.abs(vols - 1) <= 0.05), vols
    assert err.mean() <= 1.0, err.mean()
    assert np.percentile(err, 95) <= 2.0, np.percentile(err, 95)
