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
    monkeypatch.setattr(bench, "fast_accuracy", lambda *, seeds, copies, starts: calls.append(
        ("fast", list(seeds), copies, list(starts))))
    monkeypatch.setattr(bench, "_timings", lambda frames: calls.append("timings"))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    assert bench.run(p.parse_args(["--accuracy", "--take-seeds", "3,4"])) == 0
    assert calls == ["timings", "armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy",
                     ("fast", [3, 4], 0, [0.0])]
    calls.clear()
    assert bench.run(p.parse_args(["--accuracy", "--copies", "2"])) == 0
    assert calls[-1] == ("fast", [3], 2, [0.0])
    calls.clear()
    assert bench.run(p.parse_args(["--accuracy", "--take-starts", "0,0.3125, 0.625,"])) == 0
    assert calls[-1] == ("fast", [3], 0, [0.0, 0.3125, 0.625]) and all(type(s) is float for s in calls[-1][3])


def test_the_fast_takes_run_every_seed(monkeypatch):
    """Every fast and slow take of the first seed, then of the next, each in the one scratch directory; by default
    each starts at 0, with ``starts`` every take of a seed at each start in turn."""
    import stage.benchmarks.track as bench

    made = []
    monkeypatch.setattr(bench, "_fast_take", lambda creature, fps, frames, *, seed, root, copies, start: made.append(
        (creature, fps, frames, seed, copies, start, root)))
    bench.fast_accuracy(seeds=(4, 5), copies=2)
    assert [m[:6] for m in made] == [(*take, seed, 2, 0.0) for seed in (4, 5) for take in bench.FAST_TAKES]
    assert len({m[6] for m in made}) == 1
    made.clear()
    bench.fast_accuracy(seeds=(4, 5), starts=(0, np.float64(0.3125)))
    assert [m[:6] for m in made] == [(*take, seed, 0, start) for seed in (4, 5) for start in (0.0, 0.3125)
                                     for take in bench.FAST_TAKES]
    assert all(type(m[5]) is float for m in made)


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
    for value in ("0,x", ",", "", "-0.5", "nan", "inf", "0,0.5,0.50", "0,-0"):
        with pytest.raises(ValueError, match="^--take-starts"):
            bench.run(argparse.Namespace(frames=5, accuracy=True, take_seeds="3", take_starts=value))
    with pytest.raises(ValueError, match="^--take-starts needs --accuracy"):
        bench.run(argparse.Namespace(frames=5, accuracy=False, take_seeds="3", take_starts="0.3125"))
    monkeypatch.setattr(bench, "_fast_take", lambda *a, **k: pytest.fail("a take simulated before the starts were checked"))
    for starts in ("0.5", 0.5, [], [-1.0], [float("nan")], [float("inf")], [True], ["0.5"], [0, 0.0], [None]):
        with pytest.raises(ValueError, match="^starts"):
            bench.fast_accuracy(starts=starts)
    with pytest.raises(TypeError):
        bench.fast_accuracy((3,), 0, (0.0,))  # keyword-only


def test_the_copies_count_takes_numpys_integers_as_the_seeds_do(monkeypatch):
    """``copies`` is an integer >= 0 as ``seeds`` are: numpy's integers too, handed on as Python ints."""
    import stage.benchmarks.track as bench
    from stage.benchmarks import check_copies

    for n in (np.int64(2), np.uint8(0), 3):
        assert check_copies(n) == n and type(check_copies(n)) is int
    made = []
    monkeypatch.setattr(bench, "_fast_take", lambda creature, fps, frames, *, seed, root, copies, start: made.append(
        (seed, copies)))
    bench.fast_accuracy(seeds=[np.int64(4)], copies=np.int64(1))
    assert made == [(4, 1)] * len(bench.FAST_TAKES) and type(made[0][1]) is int


def test_every_start_reaches_the_simulator_and_names_the_rows(tmp_path, monkeypatch):
    """A take started at S is simulated with ``start=S`` and its rows are named "creature sSEED tS" (and its files
    apart from the other starts'); at 0 the name and the simulation's call are as without starts."""
    from types import SimpleNamespace

    import fake_cameras.record
    import fake_cameras.take
    import pipeline.process
    import stage.benchmarks.track as bench

    calls, rows, paths = [], [], []

    def simulate(creature, **kw):
        calls.append((creature, kw))
        return SimpleNamespace()

    def process(take, res, executor=None):
        paths.append((take.name, res.name))
        (res / "meshes").mkdir(parents=True)

    monkeypatch.setattr(fake_cameras.take, "simulate_take", simulate)
    monkeypatch.setattr(fake_cameras.record, "record_take", lambda sim, path: path)
    monkeypatch.setattr(pipeline.process, "process_take", process)
    monkeypatch.setattr(bench, "_take_rows", lambda name, fps, sim, res, frames, *, rows=None, seen=rows: seen.append(
        (name, fps, res.name, frames)))
    for start in (0.0, 0.3125, 0.625):
        bench._fast_take("biped", 10.0, 16, seed=3, root=tmp_path, start=start)
    assert [kw["start"] for _, kw in calls] == [0.0, 0.3125, 0.625]
    assert all(c == "biped" and kw == {"n_cameras": 8, "frames": 16, "size": (640, 480), "seed": 3, "fps": 10.0,
                                       "start": kw["start"]} for c, kw in calls)
    assert rows == [("biped s3", 10.0, "biped_10_s3_results", 16), ("biped s3 t0.3125", 10.0, "biped_10_s3_t0.3125_results", 16),
                    ("biped s3 t0.625", 10.0, "biped_10_s3_t0.625_results", 16)]
    assert paths == [("biped_10_s3.h5", "biped_10_s3_results"), ("biped_10_s3_t0.3125.h5", "biped_10_s3_t0.3125_results"),
                     ("biped_10_s3_t0.625.h5", "biped_10_s3_t0.625_results")]
