"""`stage bench patches`' grid patches (the rule the tracker's patches replaced) against the tracker's own."""

import numpy as np
import trimesh

from pipeline.tracking_patches import surface_patches
from stage.benchmarks.patches import _patches, grid_patches
from tests.stage.surfaces import random_surfaces


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


def _processed_results(root, T=3, V=200):
    """A results directory of ``T`` surfaces (random vertices, one face each), a spine and a tracking."""
    verts = random_surfaces(root / "meshes", "frame_{:06d}.ply", T=T, V=V)
    (root / "spine.json").write_text('{"spine": 1}')
    (root / "grid.json").write_text('{"voxel": 2.0}')
    for folder in ("tracked", "rig"):
        (root / folder).mkdir()
        (root / folder / "x.json").write_text("{}")
    return verts


def _surfaces(res):
    from pipeline.meshio import load_mesh

    return np.stack([load_mesh(p, largest=False)[0] for p in sorted((res / "meshes").glob("frame_*.ply"))])


def test_moved_surfaces_are_the_surfaces_moved_by_sigma(tmp_path):
    """Every surface's every vertex is moved by N(0, sigma) per coordinate (the sample standard deviation within
    10 % of sigma over 1800 coordinates, the mean within 4 standard errors of 0), seeded (the same copy twice,
    another seed another copy); the other files are the results' own, tracked/ and rig/ are left out, a copy
    already there is replaced and the results directory is untouched."""
    from stage.benchmarks import moved_surfaces

    res = tmp_path / "res"
    verts = _processed_results(res)
    before = {p: p.read_bytes() for p in res.rglob("*") if p.is_file()}
    copy = moved_surfaces(res, tmp_path / "copy", seed=1, sigma=0.01)
    assert copy == tmp_path / "copy"
    moved = _surfaces(copy) - verts
    assert abs(moved.std() / 0.01 - 1) < 0.1 and abs(moved.mean()) < 4 * 0.01 / np.sqrt(moved.size)
    assert np.array_equal(_surfaces(moved_surfaces(res, tmp_path / "copy", seed=1, sigma=0.01)) - verts, moved)
    assert not np.allclose(_surfaces(moved_surfaces(res, tmp_path / "other", seed=2, sigma=0.01)) - verts, moved)
    assert (copy / "spine.json").read_text() == '{"spine": 1}' and (copy / "grid.json").is_file()
    assert not (copy / "tracked").exists() and not (copy / "rig").exists()
    assert {p: p.read_bytes() for p in res.rglob("*") if p.is_file()} == before


def test_spread_figures_against_hand_written_rows():
    """Every figure's mean (least..most) over the tracking and its copies, in the row's order."""
    from stage.benchmarks import spread_figures

    rows = [{"mean": 1.0, "p95": 3.0, "worst": (2.0, 5.0)}, {"mean": 1.5, "p95": 2.5, "worst": (2.25, 6.0)},
            {"mean": 1.25, "p95": 3.25, "worst": (1.5, 4.0)}]
    assert spread_figures(rows) == "1.250 (1.000..1.500) / 2.917 (2.500..3.250); 1.92 (1.50..2.25) / 5.00 (4.00..6.00)"
    assert spread_figures(rows[:1]) == "1.000 (1.000..1.000) / 3.000 (3.000..3.000); 2.00 (2.00..2.00) / 5.00 (5.00..5.00)"


def test_spread_cell_against_the_formula():
    """mean (least..most) of the figures, by the sum over their number and a loop for the least and the most, at
    every precision; one figure gives itself three times."""
    from stage.benchmarks import spread_cell

    rng = np.random.default_rng(2)
    for n in (1, 2, 5):
        x = rng.normal(scale=3.0, size=n).tolist()
        least = most = x[0]
        for v in x[1:]:
            least, most = min(least, v), max(most, v)
        for d in (0, 2, 3):
            assert spread_cell(x, d) == f"{sum(x) / n:.{d}f} ({least:.{d}f}..{most:.{d}f})"
    assert spread_cell([1.0, 1.5, 1.25], 2) == "1.25 (1.00..1.50)" and spread_cell((2,), 1) == "2.0 (2.0..2.0)"


def test_copies_rows_track_the_moved_surfaces(tmp_path, monkeypatch, capsys):
    """`--copies 2`: every take is tracked on itself and on copies 1 and 2 of its surfaces (the tracking sees
    the moved vertices), and the row under the take's is the spread of the three trackings' figures."""
    import argparse
    import pickle
    from types import SimpleNamespace

    import fake_cameras.surface_motion
    import pipeline.track
    import stage.benchmarks.patches as bench
    from stage.benchmarks import spread_figures

    d = tmp_path / "biped_10_s3_f3"
    verts = _processed_results(d / "results")
    (d / "sim.pkl").write_bytes(pickle.dumps(SimpleNamespace(times=np.arange(3) / 10.0, creature=None)))
    tracked = []
    monkeypatch.setattr(pipeline.track, "track_results", lambda res, labels=None: tracked.append(_surfaces(res)))
    # the "error" of a vertex: how far its surfaces are from the take's own, in 0.001 mm
    monkeypatch.setattr(fake_cameras.surface_motion, "tracking_errors", lambda creature, times, res, frames: (
        1000 * np.linalg.norm(tracked[-1] - verts, axis=2), None, None))
    monkeypatch.setattr(bench, "take_dir", lambda root, spec: d)
    args = argparse.Namespace(root=str(tmp_path), takes="biped:10:3:3", labels=False, grid="", copies=2)
    assert bench.run(args) == 0
    assert len(tracked) == 3 and np.array_equal(tracked[0], verts)
    figures = []
    for k, surfaces in enumerate(tracked):
        moved = surfaces - verts
        assert (k == 0) == (np.abs(moved).max() == 0) and (k == 0 or abs(moved.std() / 0.001 - 1) < 0.1)
        err = 1000 * np.linalg.norm(moved, axis=2)
        figures.append({"mean": err.mean(), "p95": np.percentile(err, 95),
                        "worst": (err.mean(1).max(), np.percentile(err, 95, axis=1).max())})
    out = capsys.readouterr().out.splitlines()
    at = next(i for i, line in enumerate(out) if line.startswith("| biped_10_s3_f3 | default |"))
    assert out[at].startswith("| biped_10_s3_f3 | default | 0.000 / 0.000; 0.00 / 0.00 |")
    assert out[at + 1] == (f"| biped_10_s3_f3 | default and 2 copies moved by 1 um: mean (least..most) | "
                           f"{spread_figures(figures)} | | |")
    assert "(0.000.." in out[at + 1] and not out[at + 1].endswith("(0.000..0.000) | | |")


def test_invalid_input_copies(tmp_path):
    """`--copies` is checked before any take is tracked; moved_surfaces, move_meshes (before any mesh is read),
    check_sigma and spread_figures name their parameter."""
    import argparse

    import pytest

    import stage.benchmarks as shared
    import stage.benchmarks.patches as bench

    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="^--copies"):
            bench.run(argparse.Namespace(root=None, takes="biped:10:3:16", labels=False, grid="", copies=bad))
    for kw, match in (({"seed": -1}, "^seed"), ({"seed": 1.0}, "^seed"), ({"seed": True}, "^seed"),
                      ({"seed": 1, "sigma": 0}, "^sigma"), ({"seed": 1, "sigma": float("nan")}, "^sigma"),
                      ({"seed": 1, "sigma": True}, "^sigma"), ({"seed": 1}, "^results")):
        with pytest.raises(ValueError, match=match):
            shared.moved_surfaces("no-such-results", "copy", **kw)
        if match != "^results":
            with pytest.raises(ValueError, match=match):
                shared.move_meshes([tmp_path / "no-such-mesh.ply"], **kw)
    for bad in (0, -0.1, float("inf"), float("nan"), True, "0.1", None):
        with pytest.raises(ValueError, match="^width"):
            shared.check_sigma(bad, name="width")
    assert shared.check_sigma(2) == 2 and shared.check_sigma(0.5) == 0.5
    with pytest.raises(ValueError, match="^rows"):
        shared.spread_figures([])
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "kept.txt").write_text("kept")
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="^copy "):
            bench.track_row(tmp_path / "no-such-take", tmp_path, copy=bad)
    assert (tmp_path / "results" / "kept.txt").read_text() == "kept"
    with pytest.raises(ValueError, match="^values"):
        shared.spread_cell([], 2)
    for bad in (-1, 1.5, True, None):
        with pytest.raises(ValueError, match="^digits"):
            shared.spread_cell([1.0], bad)


def test_moved_surfaces_refuse_a_copy_over_its_results(tmp_path):
    """A ``dst`` that is ``results`` (also by another spelling), lies inside it or holds it is refused, naming
    ``dst``, before anything is written or removed: the results directory is the same file by file afterwards."""
    import pytest

    from stage.benchmarks import moved_surfaces

    res = tmp_path / "takes" / "res"
    _processed_results(res)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    for dst in (res, res / ".." / "res", res / "meshes", res / "copy", res.parent, tmp_path):
        with pytest.raises(ValueError, match="^dst"):
            moved_surfaces(res, dst, seed=1)
        assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (res / "copy").exists()
