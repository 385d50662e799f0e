"""The options of the ``track`` and ``rig`` steps (``ProcessParams.track``, ``.rig``: an API job's ``parameters``): those
of ``stage track RESULTS_DIR`` (the armature rounds) and ``stage armature RESULTS_DIR`` (``--lambda-thr``,
``--samples``, ``--reference``), checked by the same rules and handed to the same functions with the same arguments."""

from __future__ import annotations

import contextlib
import json
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.process import ProcessError, ProcessParams, TrackParams
from pipeline.process.params import RigParams, check_params


@pytest.mark.parametrize("bad, said", [
    ({"armature_rounds": -1}, "track.armature_rounds.* greater than or equal to 0"),
    ({"armature_rounds": 5}, "track.armature_rounds.* less than or equal to 4"),  # a job's rounds: at most "auto"'s
    ({"armature_rounds": "often"}, "track.armature_rounds.* should be 'auto'"),
    ({"armature_rounds": 1.5}, "track.armature_rounds.* fractional part"),
    ({"spine_armature": "maybe"}, "track.spine_armature.* valid boolean"),
    ({"armature_parts": "bones"}, "track.armature_parts.* 'motion' or 'limbs'"),
    ({"carve_margin": 0.5}, r"track.carve_margin needs track.carve \("),  # stage track --carve-margin without --carve
    ({"carve_margin": 0.5, "carve": 0}, r"track.carve_margin needs track.carve \("),
    ({"spine_armature": True, "armature_rounds": 0}, r"track.spine_armature needs track.armature_rounds \("),
    ({"armature_parts": "limbs", "labels": True, "armature_rounds": 0},
     r"track.armature_parts 'limbs' needs track.armature_rounds \("),
    ({"armature_parts": "limbs", "armature_rounds": 1}, r"track.armature_parts 'limbs' needs track.labels \("),
    ({"armature_parts": "limbs"}, r"track.armature_parts 'limbs' needs track.labels \("),  # the default round
    ({"armature_parts": "limbs", "armature_rounds": 0},
     r"track.armature_parts 'limbs' needs track.armature_rounds and track.labels \("),
])
def test_invalid_input(bad, said):
    """Every bound and every rule of ``stage track``'s armature options is an error naming the parameter."""
    with pytest.raises(ValueError, match=f"(?s){said}"):
        check_params({"track": bad})


def test_docs_tracking_lists_every_rule_between_the_options():
    """docs/tracking.md's messages name every rule of :func:`pipeline.track.check_track_options` as ``stage track``
    says it (the option, then what it needs)."""
    from pathlib import Path

    from pipeline.track import check_track_options
    from stage.cli.track import _TRACK_RULES

    doc = (Path(__file__).resolve().parents[2] / "docs" / "tracking.md").read_text(encoding="utf-8")
    messages = doc.split("## Messages", 1)[1].split("\n## ", 1)[0]
    flags = {k: f"--{k.replace('_', '-')}" for k in _TRACK_RULES}
    for kw in ({"carve_margin": 1.0}, {"spine_armature": True}, {"armature_parts": "limbs", "armature_rounds": 1}):
        with pytest.raises(ValueError) as said:
            check_track_options(**kw, names=flags)
        assert f"`{str(said.value).split(' (', 1)[0]} (...)`" in messages, said.value


def test_the_rules_accept_what_stage_track_accepts():
    for ok in ({"armature_rounds": "auto"}, {"carve": 1, "carve_margin": 0.0}, {"armature_rounds": 4, "spine_armature": True},
               {"labels": True, "colour": True, "armature_rounds": 1, "armature_parts": "limbs"},
               {"spine_armature": True}, {"labels": True, "armature_parts": "limbs"}, {"armature_rounds": 0}):
        assert check_params({"track": ok}).track == TrackParams(**ok)
    # one armature round is the default (docs/tracking.md, "Options"); 0 turns it off
    assert TrackParams().armature_rounds == 1 and not TrackParams().spine_armature
    assert TrackParams().armature_parts == "motion"


def test_check_track_options_invalid_input():
    """The one check of the rules ``stage track`` and a job's track parameters share, naming the options as the caller
    does (the command's flags, the job's parameters)."""
    from pipeline.track import check_track_options

    check_track_options()
    check_track_options(carve=1, carve_margin=0.0, armature_rounds="auto", spine_armature=True, armature_parts="limbs",
                        labels=True)
    flags = {"carve": "--carve", "carve_margin": "--carve-margin", "armature_rounds": "--armature-rounds",
             "labels": "--labels", "armature_parts": "--armature-parts"}
    for kw, said in (({"carve_margin": 0.0}, r"^carve_margin needs carve \(the margin"),
                     ({"carve_margin": 1.0, "names": flags}, "^--carve-margin needs --carve "),
                     ({"spine_armature": True}, "^spine_armature needs armature_rounds "),
                     ({"armature_parts": "limbs", "armature_rounds": 2}, r"^armature_parts 'limbs' needs labels \("),
                     ({"armature_parts": "limbs", "names": flags},
                      r"^--armature-parts 'limbs' needs --armature-rounds and --labels \("),
                     ({"armature_parts": "limbs", "labels": True, "names": flags},
                      r"^--armature-parts 'limbs' needs --armature-rounds \(")):
        with pytest.raises(ValueError, match=said):
            check_track_options(**kw)


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

    seen, warned = [], []
    return SimpleNamespace(out=out, report_progress=lambda *a: seen.append(a), executor=executor, clock=Clock(),
                           warnings=warned, keep_warning=warned.append, params=ProcessParams(track=track),
                           steps=steps), seen


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


def test_the_track_step_runs_one_round_unless_told_otherwise(tmp_path, monkeypatch):
    """Without ``armature_rounds`` one round runs (the default, as ``stage track``'s), with 0 none; a job whose rig
    takes its parts from the limbs tracks with the labels and its rounds take them too."""
    from pipeline.process.steps import _step_track

    calls = _recording(monkeypatch)
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")
    ctx, _ = _ctx(tmp_path, {"colour": True})
    _step_track(ctx)
    assert [name for name, _ in calls] == ["track_with_carving", "track_with_armature"]
    assert calls[1][1]["rounds"] == 1 and calls[1][1]["colour"] is True and calls[1][1]["labels"] is None
    calls.clear()
    ctx, _ = _ctx(tmp_path, {"colour": True, "armature_rounds": 0})
    _step_track(ctx)
    assert [name for name, _ in calls] == ["track_with_carving"]
    calls.clear()
    ctx, _ = _ctx(tmp_path, {"armature_rounds": 2}, steps=("track", "rig"))
    ctx.params = ProcessParams(track={"armature_rounds": 2}, rig={"parts": "limbs"})
    _step_track(ctx)
    assert [(name, k["labels"]) for name, k in calls] == [("track_with_carving", "spine"), ("track_with_armature", "spine")]
    assert calls[1][1]["rounds"] == 2 and calls[1][1]["parts"] == "motion"


def test_a_rig_from_the_limbs_gives_the_armature_rounds_their_labels(tmp_path, monkeypatch, capsys):
    """``track.armature_parts`` 'limbs' without ``track.labels`` in a job whose ``rig.parts`` is 'limbs': its tracking
    has the labels (the rig's parts need them), so the rounds run as ``stage track --labels --armature-rounds 1
    --armature-parts limbs`` runs them (then ``stage armature --parts limbs``); without the rig's limbs it is refused
    naming ``track.labels``, as the command names ``--labels``."""
    from pipeline.process.steps import _step_track
    from stage.cli import main

    calls = _recording(monkeypatch)
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")
    track = {"armature_rounds": 1, "armature_parts": "limbs"}
    params = check_params({"track": track, "rig": {"parts": "limbs"}})
    assert params.track_labels and not params.track.labels
    assert main(["-q", "track", str(tmp_path), "--workers", "0", "--no-progress", "--labels", "--armature-rounds", "1",
                 "--armature-parts", "limbs"]) == 0
    cli = calls[:]
    calls.clear()
    ctx, _ = _ctx(tmp_path, {}, steps=("track", "rig"))
    ctx.params = params
    _step_track(ctx)
    assert [name for name, _ in calls] == [name for name, _ in cli] == ["track_with_carving", "track_with_armature"]
    defaults = {"template": None, "gamma": None, "gate": None, "spine_init": False, "choose": True, "predict": True}
    for (name, job), (_, by_cli) in zip(calls, cli):
        job.pop("progress"), by_cli.pop("progress")
        if name == "track_with_carving":  # options of stage track a job does not have, at their defaults
            assert {k: by_cli.pop(k) for k in defaults} == defaults
        assert job == by_cli, name
    assert calls[1][1]["parts"] == "limbs" and calls[1][1]["labels"] == "spine"
    with pytest.raises(ValueError, match=r"track.armature_parts 'limbs' needs track.labels \("):
        check_params({"track": track})
    assert main(["-q", "track", str(tmp_path), "--armature-rounds", "1", "--armature-parts", "limbs"]) == 2
    assert "--armature-parts 'limbs' needs --labels (" in capsys.readouterr().err


def test_the_track_step_announces_every_round_that_may_run():
    """The job's total counts every armature round that may run (the spine's first), as it does the carving's."""
    from pipeline.process.steps import _track_totals

    def totals(**track):
        return _track_totals(SimpleNamespace(params=ProcessParams(track=track), take=SimpleNamespace(n_sets=5)))

    assert totals() == [("track", 5), ("track with the rig round 1", 5)]  # the default round
    assert totals(armature_rounds=0) == [("track", 5)]
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


@pytest.mark.parametrize("bad, said", [
    ({"samples": 1}, "rig.samples.* samples must be >= 2, got 1"),
    ({"samples": 5001}, "rig.samples.* less than or equal to 5000"),  # a job's: the segmentation grows with its square
    ({"samples": "many"}, "rig.samples.* valid integer"),
    ({"lambda_thr": 0}, r"rig.lambda_thr.* lambda_thr must be within \(0, 2\), got 0"),
    ({"lambda_thr": 2}, r"rig.lambda_thr.* lambda_thr must be within \(0, 2\), got 2"),
    ({"lambda_thr": "nan"}, r"rig.lambda_thr.* lambda_thr must be within \(0, 2\), got nan"),
    ({"reference": -1}, r"rig.reference.* reference must be a position >= 0 \(0-based\), got -1"),
    ({"reference": 1.5}, "rig.reference.* fractional part"),
])
def test_invalid_rig_input(bad, said):
    """``stage armature``'s bounds of ``--samples``, ``--lambda-thr``, ``--reference``, in the parameters' names."""
    with pytest.raises(ValueError, match=f"(?s){said}"):
        check_params({"rig": bad})


def test_check_armature_options_invalid_input():
    """The one check of the bounds ``stage armature`` and a job's rig parameters share, naming the option as the caller
    does; an option not given is not checked."""
    from pipeline.armature import check_armature_options

    check_armature_options()
    check_armature_options(lambda_thr=0.98, n_samples=2, reference=0, frames=1)
    for kw, said in (({"n_samples": 1}, "n_samples must be >= 2, got 1"), ({"n_samples": 2.0}, "n_samples must be"),
                     ({"lambda_thr": float("inf")}, r"lambda_thr must be within \(0, 2\), got inf"),
                     ({"lambda_thr": True}, "lambda_thr must be"), ({"reference": -2}, "reference must be a position >= 0"),
                     ({"reference": 3, "frames": 3}, r"reference must be a position within 0..2 \(the sequence has 3 "
                                                     r"frames\), got 3"),
                     ({"n_samples": 0, "names": {"n_samples": "--samples"}}, "^--samples must be >= 2")):
        with pytest.raises(ValueError, match=said):
            check_armature_options(**kw)
    assert RigParams(lambda_thr=0.98, samples=5000, reference=3) == check_params(
        {"rig": {"lambda_thr": 0.98, "samples": 5000, "reference": 3}}).rig


def _tracked_bars(root, frames=8):
    from pipeline.results import ply_bytes
    from tests.pipeline.shapes import two_bars

    V, F, _ = two_bars(frames)
    (root / "tracked").mkdir(parents=True)
    for i, v in enumerate(V):
        (root / "tracked" / f"{i:06d}.ply").write_bytes(ply_bytes(v, F))
    return root


def _rig_ctx(out, rig: dict, steps=("rig",), n_sets=8):
    seen, warned = [], []
    take = SimpleNamespace(n_sets=n_sets, calibration=SimpleNamespace(units="mm"), fps=30.0)
    return SimpleNamespace(out=out, report_progress=lambda *a: seen.append(a), executor=None, warnings=warned,
                           warn=warned.append, keep_warning=warned.append, params=ProcessParams(rig=rig), steps=steps, take=take,
                           part=lambda name: contextlib.nullcontext())


def test_the_rig_step_builds_the_armature_as_stage_armature_does(tmp_path, monkeypatch):
    """``parameters.rig`` ``lambda_thr``, ``samples`` and ``reference`` reach the armature as ``stage armature
    --lambda-thr --samples --reference`` gives them (every argument but the progress callback the same)."""
    import pipeline.armature as armature
    import pipeline.armature_files as armature_files
    from pipeline.process.steps import _step_rig
    from stage.cli import main

    calls, real = [], armature.build_armature

    def build(*a, **k):
        calls.append(k)
        return real(*a, **k)

    monkeypatch.setattr(armature, "build_armature", build)
    monkeypatch.setattr(armature_files, "build_armature", build)
    res = _tracked_bars(tmp_path / "cli")
    assert main(["-q", "armature", str(res), "--samples", "300", "--lambda-thr", "0.98", "--reference", "2"]) == 0
    job = _tracked_bars(tmp_path / "job")
    _step_rig(_rig_ctx(job, {"samples": 300, "lambda_thr": 0.98, "reference": 2}))
    assert len(calls) == 2
    for k in calls:
        k.pop("progress")
    assert set(calls[0]) - set(calls[1]) == {"parts"} and calls[0]["parts"] is None  # (build_armature's default)
    assert all(np.array_equal(calls[0][k], calls[1][k]) for k in calls[1]), calls
    assert calls[1]["n_samples"] == 300 and calls[1]["lambda_thr"] == 0.98
    assert calls[1]["reference"] == 2
    assert json.loads((job / "rig" / "rig.json").read_text()) == json.loads((res / "rig" / "rig.json").read_text())


def test_a_rest_frame_past_the_take_is_refused_before_the_tracking(tmp_path, monkeypatch):
    """``rig.reference`` past the surfaces stops a job that tracks before the tracking (as ``stage armature
    --reference`` does), and past the tracked frames before the armature."""
    import pipeline.carve as carve
    from pipeline.process.steps import _step_rig, _step_track

    monkeypatch.setattr(carve, "track_with_carving", lambda *a, **k: pytest.fail("tracked"))
    (tmp_path / "meshes").mkdir()
    for k in range(3):
        (tmp_path / "meshes" / f"frame_{k:06d}.ply").write_text("ply")
    ctx = _rig_ctx(tmp_path, {"reference": 3}, steps=("track", "rig"), n_sets=3)
    said = r"rig: rig.reference must be a position within 0..2 \(the sequence has 3 frames\), got 3"
    with pytest.raises(ProcessError, match=said):
        _step_track(ctx)
    with pytest.raises(ProcessError, match=said):  # an untracked take: the rig step's tracking first
        _step_rig(_rig_ctx(tmp_path, {"reference": 3}, n_sets=3))
    _tracked_bars(tmp_path)
    with pytest.raises(ProcessError, match=r"rig: rig.reference must be a position within 0..7 \(the sequence has 8"):
        _step_rig(_rig_ctx(tmp_path, {"reference": 8}))


# ----------------------------------------------------------------------------- what the steps' functions warn of

def test_what_the_tracking_warns_of_is_in_the_jobs_warnings(tmp_path, monkeypatch):
    """The track step's functions say a fallback only in the log (the spine armature not used, the armature's parts
    from the motion when ``armature_parts`` 'limbs' was asked for, the first of the carve rounds' trackings starting
    over): the job's ``warnings`` hold each once, in the job's parameters; not the processing's own warnings (kept
    by ``ctx.warn``), nor another thread's (another job's), nor a warning said after the step."""
    import logging
    import threading

    import pipeline.carve as carve
    import pipeline.track_armature as ta
    from pipeline.process.steps import _step_track
    from pipeline.track_armature_labels import _limb_chain
    from pipeline.track_armature_models import _spine_rig

    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")
    report = {"frames": {}, "skipped": [], "worker_cpu_seconds": 0.0}
    track_log = logging.getLogger("pipeline.track")

    def carving(src, rounds, **k):
        track_log.warning("%s holds frames tracked with other settings (prior); tracking again", src)
        logging.getLogger("pipeline.process").warning("the processing's own")
        other = threading.Thread(target=track_log.warning, args=("another job's",))
        other.start()
        other.join()
        return report

    def rounds(src, **k):  # the real fallbacks: no spine.json for the spine armature, no labels for the limbs' parts
        assert _spine_rig(src, [0, 1, 2], np.zeros((3, 3)), np.zeros((1, 3), np.int64), 0) is None
        for _ in range(2):  # (a later round says it again)
            assert _limb_chain(src, None, 0, 3) is None
        return {**report, "rig_prior": {"worker_cpu_seconds": 0.0}}

    monkeypatch.setattr(carve, "track_with_carving", carving)
    monkeypatch.setattr(ta, "track_with_armature", rounds)
    handlers = list(logging.getLogger("pipeline").handlers)
    ctx, _ = _ctx(tmp_path, {"labels": True, "armature_rounds": 2, "spine_armature": True, "armature_parts": "limbs"})
    _step_track(ctx)
    track_log.warning("said after the step")
    assert logging.getLogger("pipeline").handlers == handlers
    assert len(ctx.warnings) == 3, ctx.warnings
    assert ctx.warnings[0] == f"track: {tmp_path} holds frames tracked with other settings (prior); tracking again"
    assert ctx.warnings[1].startswith("track: parameters track.spine_armature: the first armature is built from the "
                                      f"tracking: no usable spine in {tmp_path / 'spine.json'} (")
    assert ctx.warnings[2] == ("track: parameters track.armature_parts 'limbs': the armature's parts come from the "
                               "motion: no labels")
    assert not any("--" in w or "='" in w for w in ctx.warnings), ctx.warnings  # the job's words, not the command's


@pytest.mark.parametrize("pool", ["process", "thread"])
def test_what_the_tracking_warns_of_in_a_worker_is_in_the_jobs_warnings(tmp_path, monkeypatch, pool):
    """What the track step's functions say in their tasks on the job's executor (the carve's and the tracking's half
    of the frames aside) is in the job's warnings as what they say in the step's thread: a worker process's (the
    server's pool: started by forkserver, no handler of this process) and a thread pool's thread's; the tasks here are
    the armature rounds' real fallbacks, run on the executor."""
    import concurrent.futures as cf
    from functools import partial

    import pipeline.carve as carve
    import pipeline.track_armature as ta
    from pipeline.process.steps import _step_track
    from pipeline.run import submit_aside
    from pipeline.track_armature_labels import _limb_chain
    from pipeline.track_armature_models import _spine_rig
    from stage.workers import process_pool

    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "frame_000000.ply").write_text("ply")
    report = {"frames": {}, "skipped": [], "worker_cpu_seconds": 0.0}

    def aside(k, task):
        return submit_aside(k["executor"], task, unavailable="no pool ({exc})").result()

    def carving(src, rounds, **k):
        assert aside(k, partial(_spine_rig, src, [0, 1, 2], np.zeros((3, 3)), np.zeros((1, 3), np.int64), 0)) is None
        return report

    def rounds(src, **k):
        assert aside(k, partial(_limb_chain, src, None, 0, 3)) is None
        return {**report, "rig_prior": {"worker_cpu_seconds": 0.0}}

    monkeypatch.setattr(carve, "track_with_carving", carving)
    monkeypatch.setattr(ta, "track_with_armature", rounds)
    with (process_pool(1) if pool == "process" else cf.ThreadPoolExecutor(1)) as ex:
        ctx, _ = _ctx(tmp_path, {"labels": True, "armature_rounds": 1, "spine_armature": True,
                                 "armature_parts": "limbs"}, executor=ex)
        _step_track(ctx)
    assert len(ctx.warnings) == 2, ctx.warnings
    assert ctx.warnings[0].startswith("track: parameters track.spine_armature: the first armature is built from the "
                                      f"tracking: no usable spine in {tmp_path / 'spine.json'} (")
    assert ctx.warnings[1] == ("track: parameters track.armature_parts 'limbs': the armature's parts come from the "
                               "motion: no labels")


def test_what_the_armature_warns_of_is_in_the_jobs_warnings(tmp_path, monkeypatch):
    """The rig step: ``rig.parts`` 'limbs' on a template tracked without its labels falls back to the motion
    segmentation; the job's warnings say so, and why, in the job's parameters (not ``stage track --labels``)."""
    import pipeline.armature_files as armature_files
    from pipeline.process.steps import _step_rig

    _tracked_bars(tmp_path)
    (tmp_path / "tracked" / "track.json").write_text(json.dumps({"patch_labels": None}))

    def build(root, *, parts, **k):
        assert parts == "limbs" and armature_files.limb_parts(root, None, None, None) is None  # the real fallback
        return SimpleNamespace(segmentation=SimpleNamespace(source="motion", n_segments=3))

    monkeypatch.setattr(armature_files, "armature_results", build)
    ctx = _rig_ctx(tmp_path, {"parts": "limbs"})
    _step_rig(ctx)
    assert ctx.warnings == ["rig: parameters rig.parts 'limbs': the armature's parts come from the motion "
                            "segmentation: the template was not tracked with the spine's labels (parameters "
                            "track.labels)"]


def test_every_warning_of_the_pipeline_that_names_an_option_says_it_in_a_jobs_words_too():
    """Every ``log.warning`` (or ``warn_once``) of the pipeline (but the processing's own, pipeline/process), the
    keying and the take store whose message names a command line option, a ``stage`` command or a function's keyword
    (``parts='limbs'``) gives ``extra={"job_message": ...}`` naming none: what a job's warnings show
    (:func:`pipeline.process.steps._job_warnings`; read from the source)."""
    import ast
    from pathlib import Path

    import pipeline

    def text(node) -> str:  # the literal parts of a message (f-strings' too; the arguments' conditional literals)
        return " ".join(n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str))

    def named(s: str) -> bool:
        return "--" in s or "`stage " in s or "stage track" in s or "='" in s

    root = Path(pipeline.__file__).parent
    seen, bad = 0, []
    # (and the keying's and the take store's, whose warnings the processing steps keep too)
    stage = [p for d in ("keying", "store") for p in sorted((root.parent / "stage" / d).rglob("*.py"))]
    for path in sorted(root.rglob("*.py")) + stage:
        if path.is_relative_to(root) and path.relative_to(root).parts[0] == "process":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            once = isinstance(node, ast.Call) and getattr(node.func, "id", None) == "warn_once"  # (logger, msg, ...)
            if not (isinstance(node, ast.Call) and (getattr(node.func, "attr", None) == "warning" or once)
                    and len(node.args) > once):
                continue
            seen += 1
            extra = [k.value for k in node.keywords if k.arg == "extra" and isinstance(k.value, ast.Dict)]
            job = [v for d in extra for key, v in zip(d.keys, d.values) if getattr(key, "value", None) == "job_message"]
            if named(" ".join(text(a) for a in node.args[once:])) and (not job or named(text(job[0]))):
                bad.append(f"{path.relative_to(root.parent)}:{node.lineno}")
    assert seen >= 30 and not bad, (seen, bad)
