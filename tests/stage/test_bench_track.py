"""`stage bench track`'s options (stage.benchmarks.track): checked before any work."""

from __future__ import annotations

import argparse

import pytest


def test_the_take_seeds_reach_the_fast_takes(monkeypatch):
    """``--take-seeds 3,4`` runs the fast and slow takes of both seeds, in that order, after the other benchmarks."""
    import stage.benchmarks.track as bench

    calls = []
    for fn in ("armature_seconds", "accuracy", "real_pipe_accuracy", "multiview_accuracy"):
        monkeypatch.setattr(bench, fn, lambda *a, _fn=fn, **k: calls.append(_fn))
    monkeypatch.setattr(bench, "fast_accuracy", lambda seeds: calls.append(("fast", list(seeds))))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    args = p.parse_args(["--accuracy", "--take-seeds", "3,4"])
    monkeypatch.setattr(bench, "_timings", lambda frames: calls.append("timings"))
    assert bench.run(args) == 0
    assert calls[-1] == ("fast", [3, 4]) and calls.count("armature_seconds") == 1


def test_invalid_input(monkeypatch):
    import stage.benchmarks.track as bench
    from stage.benchmarks import seeds_option

    assert seeds_option("3, 5,") == [3, 5]
    monkeypatch.setattr(bench, "_timings", lambda frames: pytest.fail("worked before checking its options"))
    for value in ("3,x", ",", ""):
        with pytest.raises(ValueError, match="--take-seeds"):
            bench.run(argparse.Namespace(frames=5, accuracy=True, take_seeds=value))
