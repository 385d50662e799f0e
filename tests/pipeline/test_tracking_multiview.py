"""Template tracking of simulated multi-view takes.

The takes and their ``stage process`` results are the ones of the spine pipeline test
(:mod:`tests.pipeline.spine_takes`: 8 cameras, 640x480, 30 frames, processed once per test
process); the ``track`` step runs on them and every template vertex is compared with the true surface point it started on (the template
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
from tests.pipeline.spine_takes import GROUP, N_FRAMES, run

pytestmark = pytest.mark.xdist_group(GROUP)  # the takes of the spine pipeline test, processed once


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
    # the default tracking (one armature round; its figures: docs/tracking.md, "Which tracking is the default"; the
    # tracking alone's, --armature-rounds 0: "Patches that follow the surface"), those with --colour, --carve and
    # --labels in its decisions file. The quadruped's tracking alone is over these targets: its accurate mode
    # is tests/pipeline/test_tracking_carved.py on a short take, and `stage bench track --accuracy` on
    # this one (docs/tracking.md)
    ("starfish", ()),
])
def test_multiview_tracking_follows_every_surface_point(name, options, tmp_path_factory):
    err, vols, rep = _tracking_errors(name, options, tmp_path_factory)
    assert rep["mode"] == "multi-view" and rep["skipped"] == []
    assert np.all(np.abs(vols - 1) <= 0.05)
    assert err.mean() <= 1.0, err.mean()
    assert np.percentile(err, 95) <= 2.0, np.percentile(err, 95)
