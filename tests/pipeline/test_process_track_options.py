"""The ``track`` step's armature rounds (``ProcessParams.track``, an API job's ``parameters.track``): the options of
``stage track RESULTS_DIR`` checked by the same rules, and handed to the same functions with the same arguments."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.process import ProcessParams, TrackParams
from pipeline.process.params import check_params


@pytest.mark.parametrize("bad, said", [
    ({"armature_rounds": -1}, "track.armature_rounds.* greater than or equal to 0"),
    ({"armature_rounds": 5}, "track.armature_rounds.* less than or equal to 4"),  # a job's rounds: at most "auto"'s
    ({"armature_rounds": "often"}, "track.armature_rounds.* should be 'auto'"),
    ({"armature_rounds": 1.5}, "track.armature_rounds.* fractional part"),
    ({"spine_armature": "maybe"}, "track.spine_armature.* valid boolean"),
    ({"armature_parts": "bones"}, "track.armature_parts.* 'motion' or 'limbs'"),
    ({"spine_armature": True}, "track.* spine_armature needs armature_rounds"),
    ({"spine_armature": True, "armature_rounds": 0}, "track.* spine_armature needs armature_rounds"),
    ({"armature_parts": "limbs", "labels": True}, "track.* armature_parts 'limbs' needs armature_rounds and labels"),
    ({"armature_parts": "limbs", "armature_rounds": 1}, "track.* armature_parts 'limbs' needs armature_rounds and labels"),
])
def test_invalid_input(bad, said):
    """Every bound and every rule of ``stage track``'s armature options is an error naming the parameter."""
    with pytest.raises(ValueError, match=f"(?s){said}"):
        check_params({"track": bad})


def test_the_rules_accept_what_stage_track_accepts():
    for ok in ({"armature_rounds": "auto"}, {"armature_rounds": 4, "spine_armature": True},
               {"labels": True, "colour": True, "armature_rounds": 1, "armature_parts": "limbs"}):
        assert check_params({"track": ok}).track == TrackParams(**ok)
    assert TrackParams().armature_rounds == 0 and not TrackParams().spine_armature
    assert TrackParams().armature_parts == "motion"


def _recording(monkeypatch):
    """The tracking's two functions replaced by recorders: -> the calls, ``(name, kwargs)``."""
    import pipeline.carve as carve
    import pipeline.track_armature as ta

    calls = []
    report = {"frames": {}, "vertices": 8, "gamma": 0.05, "gate_mm": 10.0, "solver": "cg", "skipped": [],
              "worker_cpu_seconds": 1.5}

    def carving(src, rounds, **k):
        calls.append(("track_with_carving", {"rounds": rounds, **k}))
        return report

    def rounds(src, **k):
        calls.append(("track_with_armature", k))
        k["progress"]("track with the rig round 1", 2, 3)
        return {**report, "rig_rounds": 1, "rig_prior": {"worker_cpu_seconds": 2.0,
                                                         "rounds": [{"armature": "tracking", "segments": 3,
                                                                     "residual_mm": 1.0}]}}

    monkeypatch.setattr(carve, "track_with_carving", carving)
    monkeypatch.setattr(ta, "track_with_armature", rounds)
    return calls


def _ctx(out, track: dict, steps=("track",), executor=None):
    from pipeline.run import Clock

    seen = []
    return SimpleNamespace(out=out, report_progress=lambda *a: seen.append(a), executor=executor, clock=Clock(),
                           warnings=[], params=ProcessParams(track=track), steps=steps), seen


@pytest.mark.parametrize("flags, track", [
    (["--labels", "--colour", "--armature-rounds", "1", "--armature-parts", "limbs"],
     {"labels": True, "colour": True, "armature_rounds": 1, "armature_parts": "limbs"}),
    (["--armature-rounds", "auto", "--spine-armature", "--shape-memory"],
     {"armature_rounds": "auto", "spine_armature": True, "shape_memory": True}),
])
def test_the_track_step_runs_the_armature_rounds_as_stage_track_does(tmp_path, monkeypatch, flags, track):
    """The step calls the tracking and then the armature rounds with the arguments ``stage track`` gives them
    for the same options (the progress callback aside: the job's ``report_progress``), and the rounds' progress
    and worker CPU seconds reach the job."""
    from pipeline.process.steps import _step_track
    from stage.cli import main

    calls = _recording(monkeypatch)
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")  # the step asks for surfaces first
    assert main(["-q", "track", str(tmp_path), "--workers", "0", "--no-progress", *flags]) == 0
    cli = calls[:]
    calls.clear()
    ctx, seen = _ctx(tmp_path, track)
    _step_track(ctx)
    assert [name for name, _ in calls] == [name for name, _ in cli] == ["track_with_carving", "track_with_armature"]
    defaults = {"template": None, "gamma": None, "gate": None, "spine_init": False, "choose": True, "predict": True}
    for (name, job), (_, cli_kw) in zip(calls, cli):
        assert job.pop("progress") == ctx.report_progress
        cli_kw.pop("progress")
        if name == "track_with_carving":  # options of stage track a job does not have, at their defaults
            assert {k: cli_kw.pop(k) for k in defaults} == defaults
        assert job == cli_kw, name
    assert ("track with the rig round 1", 2, 3) in seen
    assert ctx.clock.worker_cpu["track"] == pytest.approx(3.5)  # the tracking's and the rounds'


def test_the_track_step_runs_no_rounds_unless_asked(tmp_path, monkeypatch):
    """Without ``armature_rounds`` no round runs; a job whose rig takes its parts from the limbs tracks with the
    labels and its rounds take them too."""
    from pipeline.process.steps import _step_track

    calls = _recording(monkeypatch)
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")
    ctx, _ = _ctx(tmp_path, {"colour": True})
    _step_track(ctx)
    assert [name for name, _ in calls] == ["track_with_carving"]
    calls.clear()
    ctx, _ = _ctx(tmp_path, {"armature_rounds": 2}, steps=("track", "rig"))
    ctx.params = ProcessParams(track={"armature_rounds": 2}, rig={"parts": "limbs"})
    _step_track(ctx)
    assert [(name, k["labels"]) for name, k in calls] == [("track_with_carving", "spine"), ("track_with_armature", "spine")]
    assert calls[1][1]["rounds"] == 2 and calls[1][1]["parts"] == "motion"


def test_the_track_step_announces_every_round_that_may_run():
    """The job's total counts every armature round that may run (the spine's first), as it does the carving's."""
    from pipeline.process.steps import _track_totals

    def totals(**track):
        return _track_totals(SimpleNamespace(params=ProcessParams(track=track), take=SimpleNamespace(n_sets=5)))

    assert totals() == [("track", 5)]
    assert totals(armature_rounds=2, carve=1) == [("track", 5), ("carve round 1", 5), ("track round 1", 5),
                                                  ("track with the rig round 1", 5), ("track with the rig round 2", 5)]
    assert [n for n, _ in totals(armature_rounds="auto", spine_armature=True)][1:] == [
        f"track with the rig round {r}" for r in range(1, 6)]


def test_a_job_tracks_a_take_again_with_its_armature(tmp_path):
    """The step on a small take (a turning sphere, 3 frames): the frames tracked again with the armature, the round
    recorded in tracked/track.json, its progress reported under the round's name."""
    from pipeline.process.steps import _step_track
    from pipeline.volume import Grid
    from tests.pipeline.tracking_takes import turning_sphere_results

    res, _ = turning_sphere_results(tmp_path, frames=3, size=(160, 120))
    (res / "grid.json").write_text(json.dumps(Grid(lo=np.array([-200.0, -200.0, 100.0]), shape=(40, 40, 40),
                                                   voxel=10.0).to_dict()))
    ctx, seen = _ctx(res, {"armature_rounds": 1})
    _step_track(ctx)
    rep = json.loads((res / "tracked" / "track.json").read_text())
    assert rep["rig_rounds"] == 1 and rep["rig_prior"]["max_rounds"] == 1 and sorted(rep["frames"]) == ["0", "1", "2"]
    assert {s for s, _, _ in seen} == {"track", "track with the rig round 1"}
    assert ("track with the rig round 1", 3, 3) in seen
