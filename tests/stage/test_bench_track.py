"""`stage bench track`'s options (stage.benchmarks.track): checked before any work."""

from __future__ import annotations

import argparse

import numpy as np
import pytest


def test_the_take_seeds_reach_the_fast_takes(monkeypatch):
    """``--take-seeds 3,4`` hands both seeds to the fast and slow takes, after the other benchmarks."""
    import stage.benchmarks.track as bench

    calls = []
    for fn in ("armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy"):
        monkeypatch.setattr(bench, fn, lambda *a, _fn=fn, **k: calls.append(_fn))
    monkeypatch.setattr(bench, "fast_accuracy", lambda *, seeds, copies: calls.append(("fast", list(seeds), copies)))
    monkeypatch.setattr(bench, "_timings", lambda frames: calls.append("timings"))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    assert bench.run(p.parse_args(["--accuracy", "--take-seeds", "3,4"])) == 0
    assert calls == ["timings", "armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy",
                     ("fast", [3, 4], 0)]
    calls.clear()
    assert bench.run(p.parse_args(["--accuracy", "--copies", "2"])) == 0
    assert calls[-1] == ("fast", [3], 2)


def test_the_fast_takes_run_every_seed(monkeypatch):
    """Every fast and slow take of the first seed, then of the next, each in the one scratch directory."""
    import stage.benchmarks.track as bench

    made = []
    monkeypatch.setattr(bench, "_fast_take", lambda creature, fps, frames, *, seed, root, copies: made.append(
        (creature, fps, frames, seed, copies, root)))
    bench.fast_accuracy(seeds=(4, 5), copies=2)
    assert [m[:5] for m in made] == [(*take, seed, 2) for seed in (4, 5) for take in bench.FAST_TAKES]
    assert len({m[5] for m in made}) == 1


def test_every_row_has_its_copies_spread_under_it(tmp_path, monkeypatch, capsys):
    """`--copies 2`: the take's rows are tracked from its processed surfaces and from two copies of them moved
    by 0.001 mm (seeds 1 and 2), and every row is printed with the spread of its figures over the three under
    it; without copies the rows are printed as they come, with nothing under them."""
    from types import SimpleNamespace

    import fake_cameras.record
    import fake_cameras.take
    import pipeline.process
    import stage.benchmarks.track as bench
    from pipeline.meshio import load_mesh
    from pipeline.results import ply_bytes
    from stage.benchmarks import spread_figures

    verts = np.random.default_rng(0).normal(scale=100.0, size=(2, 100, 3))

    def process(take, res, executor=None):
        (res / "meshes").mkdir(parents=True)
        for t, v in enumerate(verts):
            (res / "meshes" / f"frame_{t:06d}.ply").write_bytes(ply_bytes(v, np.array([[0, 1, 2]])))

    def rows_of(name, fps, sim, res, frames, *, rows=None):  # two rows: how far the surfaces moved, in 0.001 mm
        moved = np.stack([load_mesh(p, largest=False)[0] for p in sorted((res / "meshes").glob("*.ply"))]) - verts
        for i in range(2):
            err = 1000 * np.abs(moved[..., i])
            row = {"line": f"  {name} row {i}: {err.mean():.4f}", "mean": err.mean(), "p95": np.percentile(err, 95),
                   "worst": (err.mean(1).max(), np.percentile(err, 95, axis=1).max())}
            seen.append((res.name, i, row))
            if rows is None:
                print(row["line"])
            else:
                rows.append(row)

    monkeypatch.setattr(fake_cameras.take, "simulate_take", lambda *a, **k: SimpleNamespace())
    monkeypatch.setattr(fake_cameras.record, "record_take", lambda sim, path: path)
    monkeypatch.setattr(pipeline.process, "process_take", process)
    monkeypatch.setattr(bench, "_take_rows", rows_of)
    seen = []
    bench._fast_take("biped", 10.0, 2, seed=3, root=tmp_path, copies=2)
    out = capsys.readouterr().out.splitlines()
    assert [(name, i) for name, i, _ in seen] == [(f"biped_10_s3_results{c}", i) for c in ("", "_copy1", "_copy2")
                                                   for i in range(2)]
    assert seen[0][2]["mean"] == 0 and all(abs(r["mean"] / (1000 * 0.001 * np.sqrt(2 / np.pi)) - 1) < 0.2
                                           for _, _, r in seen[2:])
    for i in range(2):
        assert out[2 * i] == seen[i][2]["line"]
        assert out[2 * i + 1] == ("    the take and 2 copies moved by 1 um, mean (least..most): "
                                  + spread_figures([seen[i][2], seen[2 + i][2], seen[4 + i][2]]))
    assert len(out) == 4
    seen.clear()
    bench._fast_take("biped", 10.0, 2, seed=4, root=tmp_path)
    assert capsys.readouterr().out.splitlines() == [r["line"] for _, _, r in seen] and len(seen) == 2


def test_invalid_input(monkeypatch):
    import stage.benchmarks.track as bench
    from stage.benchmarks import seeds_option

    assert seeds_option("3, 5,") == [3, 5]
    monkeypatch.setattr(bench, "_timings", lambda frames: pytest.fail("worked before checking its options"))
    for value in ("3,x", ",", "", "-1", "3,3"):
        with pytest.raises(ValueError, match="--take-seeds"):
            bench.run(argparse.Namespace(frames=5, accuracy=True, take_seeds=value))
    with pytest.raises(ValueError, match="--take-seeds"):
        bench.run(argparse.Namespace(frames=5, accuracy=False, take_seeds="x"))
    for seeds in ("34", [3.5], [True], [-1], [3, 3]):
        with pytest.raises(ValueError, match="seeds"):
            bench.fast_accuracy(seeds=seeds)
    for copies in (-1, 1.5, True):
        with pytest.raises(ValueError, match="^--copies"):
            bench.run(argparse.Namespace(frames=5, accuracy=True, take_seeds="3", copies=copies))
        with pytest.raises(ValueError, match="^copies"):
            bench.fast_accuracy(copies=copies)
    with pytest.raises(ValueError, match="^--copies needs --accuracy"):
        bench.run(argparse.Namespace(frames=5, accuracy=False, take_seeds="3", copies=2))


def test_the_copies_count_takes_numpys_integers_as_the_seeds_do(monkeypatch):
    """``copies`` is an integer >= 0 as ``seeds`` are: numpy's integers too, handed on as Python ints."""
    import stage.benchmarks.track as bench
    from stage.benchmarks import check_copies

    for n in (np.int64(2), np.uint8(0), 3):
        assert check_copies(n) == n and type(check_copies(n)) is int
    made = []
    monkeypatch.setattr(bench, "_fast_take", lambda creature, fps, frames, *, seed, root, copies: made.append(
        (seed, copies)))
    bench.fast_accuracy(seeds=[np.int64(4)], copies=np.int64(1))
    assert made == [(4, 1)] * len(bench.FAST_TAKES) and type(made[0][1]) is int
