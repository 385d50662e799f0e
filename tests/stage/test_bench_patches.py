"""`stage bench patches`' grid patches (the rule the tracker's patches replaced) against the tracker's own."""

import numpy as np
import trimesh

from pipeline.tracking_patches import surface_patches
from stage.benchmarks.patches import _patches, grid_patches


def _same_partition(a, b):
    return len(set(zip(a.tolist(), b.tolist()))) == len(set(a.tolist())) == len(set(b.tolist()))


def test_grid_patches_move_with_the_grid_and_the_trackers_do_not_move_with_the_template():
    """The grid moved by a whole cell is the same grid; by half a cell it cuts other patches (what the bench's
    `--grid` measures). The template moved by half a cell gets the tracker's same patches. While the bench runs a
    grid, the tracker cuts its patches without labels on it and with labels its own way; afterwards its own."""
    import pipeline.tracking as tracking

    m = trimesh.creation.capsule(height=200.0, radius=20.0, count=[12, 12])
    v, f = (np.asarray(x) for x in trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=14.0))
    v = v + np.random.default_rng(0).normal(0.0, 0.5, v.shape)
    size = 60.0
    at0, comp = grid_patches(v, f, size)
    assert _same_partition(at0, grid_patches(v, f, size, 1.0)[0]) and len(comp) == at0.max() + 1
    assert not _same_partition(at0, grid_patches(v, f, size, 0.5)[0])
    assert np.array_equal(surface_patches(v, f, size)[0], surface_patches(v + 0.5 * size, f, size)[0])
    own, counts = tracking.surface_patches, []
    labels = np.where(v[:, 2] > 0, 0, -1)
    with _patches(0.5, counts):
        assert np.array_equal(tracking.surface_patches(v, f, size)[0], grid_patches(v, f, size, 0.5)[0])
        assert np.array_equal(tracking.surface_patches(v, f, size, labels=labels)[0],
                              surface_patches(v, f, size, labels=labels)[0])
    assert tracking.surface_patches is own and len(counts) == 2


def test_takes_root_is_the_cache_unless_given(monkeypatch, tmp_path):
    """`stage bench labels` / `patches` keep their processed takes beside the simulated takes' cache, not in /tmp."""
    from stage.benchmarks.labels import takes_root

    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    assert takes_root(None) == tmp_path / "takes"
    assert takes_root(str(tmp_path / "mine")) == tmp_path / "mine"


def test_invalid_input():
    """The options are checked before any take is simulated or tracked, each error naming its option."""
    import pytest

    from stage.benchmarks.labels import take_specs
    from stage.benchmarks.patches import grid_offsets

    assert grid_offsets("0, 0.5,") == [0.0, 0.5] and grid_offsets("") == []
    for bad in ("x", "0,nan", "inf"):
        with pytest.raises(ValueError, match="--grid"):
            grid_offsets(bad)
    assert take_specs("biped:10:3:16,starfish:30:3:30") == ["biped:10:3:16", "starfish:30:3:30"]
    for bad in ("bogus", "biped:10:3", "biped:x:3:16", "biped:0:3:16", "biped:10:3:1", ":10:3:16", ","):
        with pytest.raises(ValueError, match="--takes"):
            take_specs(bad)
