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
from stage.cli import main
from tests.pipeline.test_spine_pipeline import N_FRAMES, run


def _tracking_errors(name, options, tmp_path_factory):
    r = run(name, tmp_path_factory)
    results = r["res"].out
    if options:  # as the CLI runs them
        assert main(["-q", "track", str(results), *options]) == 0
    else:  # the default, as the job step runs it
        process_take(results.parent / f"{name}.h5", results, steps=("track",), executor=None)
    err, vols, rep = tracking_errors(r["sim"].creature, r["sim"].times, results, frames=N_FRAMES)
    return err.ravel(), vols, rep


@pytest.mark.slow
@pytest.mark.parametrize("name, options", [
    # the default tracking; measured: mean 0.91 voxels, 95th percentile 1.99, volume 1.00..1.02
    # (--colour: 0.84 / 1.92; the accurate mode below, --carve 2 --shape-memory --colour: 0.50 / 1.24)
    ("starfish", ()),
    # the accurate mode (docs/tracking.md, "Surfaces carved across time"): two rounds of surfaces carved across
    # time with the tracked motion, tracked with shape memory and the colour tracks; measured 0.71 / 1.94,
    # volume 0.978..1.001 (the default tracking gives 1.47 / 3.38: the hull's surfaces hold it back)
    ("quadruped", ("--carve", "2", "--shape-memory", "--colour")),
])
def test_multiview_tracking_follows_every_surface_point(name, options, tmp_path_factory):
    err, vols, rep = _tracking_errors(name, options, tmp_path_factory)
    assert rep["mode"] == "multi-view" and rep["skipped"] == []
    assert np.all(np.abs(vols - 1) <= 0.05)
    assert err.mean() <= 1.0, err.mean()
    assert np.percentile(err, 95) <= 2.0, np.percentile(err, 95)
