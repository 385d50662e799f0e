"""`stage bench track`'s options (stage.benchmarks.track): checked before any work."""

from __future__ import annotations

import argparse

import pytest


def test_the_take_seeds_reach_the_fast_takes(monkeypatch):
    """``--take-seeds 3,4`` hands both seeds to the fast and slow takes, after the other benchmarks."""
    import stage.benchmarks.track as bench

    calls = []
    for fn in ("armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy"):
        monkeypatch.setattr(bench, fn, lambda *a, _fn=fn, **k: calls.append(_fn))
    monkeypatch.setattr(bench, "fast_accuracy", lambda *, seeds: calls.append(("fast", list(seeds))))
    monkeypatch.setattr(bench, "_timings", lambda frames: calls.append("timings"))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    assert bench.run(p.parse_args(["--accuracy", "--take-seeds", "3,4"])) == 0
    assert calls == ["timings", "armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy",
                     ("fast", [3, 4])]


def test_the_fast_takes_run_every_seed(monkeypatch):
    """Every fast and slow take of the first seed, then of the next, each in the one scratch directory."""
    import stage.benchmarks.track as bench

    made = []
    monkeypatch.setattr(bench, "_fast_take", lambda creature, fps, frames, *, seed, root: made.append(
        (creature, fps, frames, seed, root)))
    bench.fast_accuracy(seeds=(4, 5))
    assert [m[:4] for m in made] == [(*take, seed) for seed in (4, 5) for take in bench.FAST_TAKES]
    assert len({m[4] for m in made}) == 1


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
