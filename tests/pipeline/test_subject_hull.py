"""The surface step's hull (pipeline.silhouette_refine.subject_hull): silhouette parts the subject
does not explain are dropped before carving, clean silhouettes give the carver's own hull."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.consistency import mesh_silhouette
from pipeline.hull import HullCarver
from pipeline.silhouette_refine import subject_hull
from pipeline.volume import grid_from_volume
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


def test_invalid_input():
    cal, masks, carver = _scene()
    with pytest.raises(ValueError, match="view_slack"):
        subject_hull(masks, carver, view_slack=-1)
    with pytest.raises(ValueError, match="view_slack"):
        subject_hull(masks, carver, view_slack=True)
    with pytest.raises(ValueError):
        subject_hull(masks[:3], carver)
