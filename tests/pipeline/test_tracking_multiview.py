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
    # measured: mean 0.91 voxels, 95th percentile 1.97, volume 1.00..1.02 (photo_refine: 0.67 / 1.67, 0.97..1.02;
    # with the colour tracks, --colour: 0.85 / 1.93)
    "starfish",
    pytest.param("quadruped", marks=pytest.mark.xfail(strict=True, reason=(
        "not met: mean 1.47 voxels, 95th percentile 3.36 (1.18 / 3.08 with the colour tracks, `stage track --colour`, "
        "warped object-only windows; 1.23 / 3.10 translated). "
        "What is left is a slide along the surface, not the surfaces: split into the distance to the true surface and "
        "the part along it, the errors are 0.79 / 2.30 (mean / 95th percentile) off and 1.09 / 2.86 along. Better "
        "surfaces do not move the 95th percentile: with `photo_refine` (pipeline.photo_refine; surfaces 0.44 / 1.98 "
        "from 0.80 / 2.28) tracking gives 1.36 / 3.50, with `silhouette_margin=0` (surfaces 0.39 / 1.66) 1.33 / 3.29. "
        "The slide is 0.8..1.1 voxels at the ends of the take, which the surfaces leave free; the colour tracks pin "
        "part of it (translated windows followed only about 93 % of the true step: the shading under fixed lights stays put). "
        "On the true surfaces (`stage bench track --accuracy`) the tracker gives 1.00 / 2.75, with `--shape-memory` 0.66 / "
        "1.85: the rest is the hull's surfaces, whose offset is 0.84 / 2.5 at the template's own frame; see "
        "docs/tracking.md"))),
])


def test_multiview_tracking_follows_every_surface_point(name, tmp_path_factory):
    err, vols, rep = _tracking_errors(name, tmp_path_factory)
    assert rep["mode"] == "multi-view" and rep["skipped"] == []
    assert np.all(np.abs(vols - 1) <= 0.05)
    assert err.mean() <= 1.0, err.mean()
    assert np.percentile(err, 95) <= 2.0, np.percentile(err, 95)
