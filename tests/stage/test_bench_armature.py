"""`stage bench armature`'s measure of what the motion segmentation sees where the body is rigid."""

import numpy as np
import pytest

from stage.benchmarks.armature import _parts, segmentation_noise
from tests.pipeline.shapes import two_bars
from tests.stage.surfaces import random_surfaces


def test_segmentation_noise_is_zero_within_a_rigid_part_and_grows_with_noise():
    """The hinged bar moved exactly: the distances and normals of one bar's samples do not change (0 up to
    float32 rounding) while those across the hinge do; noise on the vertices shows within the parts."""
    V, F, right = two_bars(T=4)
    exact = segmentation_noise(V, F, right.astype(int), n_samples=120)
    assert exact["dv_within"] < 1e-3 and exact["dn_within"] < 0.1
    assert exact["dv_across"] > 10 and exact["dn_across"] > 1
    assert 2 <= exact["below_small_motion"] <= 65
    noisy = V + np.random.default_rng(0).normal(scale=1.0, size=V.shape)  # 1 mm on a 200 mm bar
    seen = segmentation_noise(noisy, F, right.astype(int), n_samples=120)
    assert seen["dv_within"] > 1 and seen["dn_within"] > exact["dn_within"] + 1


def test_true_parts_bend_when_any_joint_between_them_does():
    """A limb capsule no vertex lies nearest to (a neck hidden between body and head) leaves two joints between
    the body and the head: the head's part bends against the body when the hidden one's joint does. The
    slow reference: the joints between two parts listed by hand."""
    from types import SimpleNamespace

    creature = SimpleNamespace(limbs=[SimpleNamespace(name="head"), SimpleNamespace(name="leg")])
    names = ["head.0", "head.1", "leg.0", "leg.1", "leg.2"]
    raw = np.array([-1, -1, 1, 1, 16, 18, 18])  # no vertex on head.0 (the neck) nor on leg.1
    for bends in ([True, False, False, True, False], [False, False, True, False, False], [False] * 5):
        part, parent, bent = _parts(raw, creature, names, np.array(bends))
        assert part.tolist() == [0, 0, 1, 1, 2, 3, 3] and parent.tolist() == [-1, 0, 0, 2]
        by_hand = [False, bends[0] or bends[1], bends[2], bends[3] or bends[4]]
        assert bent.tolist() == by_hand


def test_invalid_input():
    V, F, right = two_bars(T=3)
    with pytest.raises(ValueError, match="parts"):
        segmentation_noise(V, F, right[:-1].astype(int))
    with pytest.raises(ValueError, match="one frame"):
        segmentation_noise(V[:1], F, right.astype(int))


def test_take_armature_tracks_with_the_labels_for_the_limbs_parts(monkeypatch, tmp_path):
    """`stage bench armature --accuracy --parts limbs`: the take is tracked as `stage track --labels` tracks it
    (the track step with ``parameters.track.labels``) and its armature built as `stage armature --parts limbs`
    builds it; the default tracks and builds with the defaults. The steps stand in for the minutes-long ones."""
    import fake_cameras.record
    import fake_cameras.take
    import pipeline.armature_files
    import pipeline.process
    from stage.benchmarks.armature import take_armature

    calls = []
    monkeypatch.setattr(fake_cameras.take, "simulate_take", lambda name, **kw: ("sim", name, kw["seed"]))
    monkeypatch.setattr(fake_cameras.record, "record_take", lambda sim, path: path)
    monkeypatch.setattr(pipeline.process, "process_take",
                        lambda take, res, **kw: calls.append(("process", kw.get("steps"), kw.get("params"))))
    monkeypatch.setattr(pipeline.armature_files, "armature_results", lambda res, **kw: calls.append(("armature", kw)))
    sim, _, _, _ = take_armature("biped", tmp_path, seed=5, parts="limbs")
    assert sim == ("sim", "biped", 5)
    assert calls == [("process", None, None), ("process", ("track",), {"track": {"labels": True}}),
                     ("armature", {"parts": "limbs"})]
    calls.clear()
    take_armature("biped", tmp_path)
    assert calls == [("process", None, None), ("process", ("track",), None), ("armature", {})]


def test_take_armature_tracks_as_stage_track_with_the_armature_mode(monkeypatch, tmp_path):
    """`stage bench armature --accuracy --labels --colour --armature-rounds 1 --armature-parts limbs`: the track
    step with the labels, the colour tracks and the armature mode's rounds (``parameters.track``, as `stage track
    RESULTS_DIR` takes them; without ``armature_rounds`` the step's default, one round), then the armature with its
    parts; no round run apart. The steps stand in for the minutes-long ones."""
    import fake_cameras.record
    import fake_cameras.take
    import pipeline.armature_files
    import pipeline.process
    import pipeline.track_armature
    from stage.benchmarks.armature import take_armature

    calls = []
    monkeypatch.setattr(fake_cameras.take, "simulate_take", lambda name, **kw: "sim")
    monkeypatch.setattr(fake_cameras.record, "record_take", lambda sim, path: path)
    monkeypatch.setattr(pipeline.process, "process_take",
                        lambda take, res, **kw: calls.append(("process", kw.get("steps"), kw.get("params"))))
    monkeypatch.setattr(pipeline.track_armature, "track_with_armature",
                        lambda res, **kw: calls.append(("rounds", res == tmp_path / "results", kw)))
    monkeypatch.setattr(pipeline.armature_files, "armature_results", lambda res, **kw: calls.append(("armature", kw)))
    take_armature("biped", tmp_path, labels=True, colour=True, armature_rounds=1, armature_parts="limbs")
    assert calls == [("process", None, None),
                     ("process", ("track",), {"track": {"labels": True, "colour": True, "armature_rounds": 1,
                                                        "armature_parts": "limbs"}}),
                     ("armature", {})]
    calls.clear()
    take_armature("biped", tmp_path, colour=True, armature_rounds=2, parts="limbs")
    assert calls == [("process", None, None),
                     ("process", ("track",), {"track": {"labels": True, "colour": True, "armature_rounds": 2}}),
                     ("armature", {"parts": "limbs"})]
    calls.clear()
    take_armature("biped", tmp_path, colour=True)  # the step's default round
    assert calls == [("process", None, None), ("process", ("track",), {"track": {"colour": True}}), ("armature", {})]
    calls.clear()
    take_armature("biped", tmp_path, armature_rounds="auto")
    assert calls == [("process", None, None), ("process", ("track",), {"track": {"armature_rounds": "auto"}}),
                     ("armature", {})]
    calls.clear()
    take_armature("biped", tmp_path, armature_rounds=0)  # the tracking alone
    assert calls == [("process", None, None), ("process", ("track",), {"track": {"armature_rounds": 0}}),
                     ("armature", {})]


@pytest.mark.parametrize("kw, match", [({"parts": "spine"}, "^parts"), ({"armature_rounds": -1}, "^armature_rounds"),
                                       ({"armature_rounds": 1.5}, "^armature_rounds"),
                                       ({"armature_rounds": True}, "^armature_rounds"),
                                       ({"armature_rounds": "often"}, "^armature_rounds"),
                                       ({"armature_parts": "spine"}, "^armature_parts"),
                                       ({"armature_parts": "limbs", "labels": True, "armature_rounds": 0},
                                        "^armature_parts"),
                                       ({"armature_parts": "limbs", "armature_rounds": 1}, "^armature_parts")])
def test_invalid_input_take_armature(kw, match, monkeypatch, tmp_path):
    """Options checked before any work: the simulator is never reached."""
    import fake_cameras.take
    from stage.benchmarks.armature import take_armature

    monkeypatch.setattr(fake_cameras.take, "simulate_take", lambda name, **kw: pytest.fail("simulated"))
    with pytest.raises(ValueError, match=match):
        take_armature("biped", tmp_path, **kw)


def test_invalid_input_take_accuracy(monkeypatch, capsys):
    """The table's options checked before its header is printed or a take is made."""
    import stage.benchmarks.armature as bench

    monkeypatch.setattr(bench, "take_armature", lambda *a, **kw: pytest.fail("made a take"))
    for kw, match in (({"armature_rounds": -1}, "^armature_rounds"), ({"parts": "spine"}, "^parts"),
                      ({"armature_parts": "limbs"}, "^armature_parts")):
        with pytest.raises(ValueError, match=match):
            bench.take_accuracy(["biped"], **kw)
    with pytest.raises(TypeError):
        bench.take_accuracy(["biped"], lables=True)
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize("options, match", [({"parts": "spine"}, "--parts"), ({"take_seeds": "3,x"}, "--take-seeds"),
                                            ({"take_seeds": ","}, "--take-seeds"), ({"take_seeds": "-1"}, "--take-seeds"),
                                            ({"take_seeds": "3,3"}, "--take-seeds"),
                                            ({"armature_rounds": "often"}, "--armature-rounds"),
                                            ({"copies": -1}, "--copies"),
                                            ({"armature_rounds": -1}, "--armature-rounds"),
                                            ({"armature_parts": "spine"}, "--armature-parts"),
                                            ({"armature_parts": "limbs", "labels": True}, "--armature-parts"),
                                            ({"armature_parts": "limbs", "armature_rounds": 1}, "--armature-parts")])
def test_the_take_options_are_checked_before_any_work(options, match, monkeypatch):
    from argparse import Namespace

    import stage.benchmarks.armature as bench

    monkeypatch.setattr(bench, "accuracy", lambda **kw: pytest.fail("ran"))
    args = Namespace(accuracy=True, takes="biped", take_frames=30, take_seeds="3", parts="motion", skinned="2",
                     labels=False, colour=False, armature_rounds=0, armature_parts="motion", copies=0)
    for option, value in options.items():
        setattr(args, option, value)
    with pytest.raises(ValueError, match=match):
        bench.run(args)


def test_the_take_options_reach_the_takes(monkeypatch):
    """`--labels --colour --armature-rounds 1 --armature-parts limbs` parsed and handed to every take, as
    :func:`take_armature`'s keywords."""
    import argparse

    import stage.benchmarks.armature as bench

    seen = []
    monkeypatch.setattr(bench, "accuracy", lambda **kw: None)
    monkeypatch.setattr(bench, "take_accuracy", lambda names, **kw: seen.append((names, kw)))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    args = p.parse_args(["--accuracy", "--takes", "biped", "--take-seeds", "3,5", "--labels", "--colour",
                         "--armature-rounds", "1", "--armature-parts", "limbs", "--copies", "4"])
    assert bench.run(args) == 0
    assert seen == [(["biped"], {"frames": 30, "seeds": (3, 5), "parts": "motion", "labels": True, "colour": True,
                                 "armature_rounds": 1, "armature_parts": "limbs", "copies": 4})]
    seen.clear()
    assert bench.run(p.parse_args(["--accuracy", "--takes", "biped", "--labels", "--armature-rounds", "auto"])) == 0
    assert seen[0][1]["armature_rounds"] == "auto"


def _tracked_results(root, T=3, V=50):
    """A results directory with a tracked template of ``T`` frames (random vertices, one face) and its track.json."""
    import json

    verts = random_surfaces(root / "tracked", "{:06d}.ply", T=T, V=V)
    (root / "tracked" / "track.json").write_text(json.dumps({"reference_frame": 1}))
    (root / "spine.json").write_text("{}")
    return verts


def test_copies_are_the_tracking_moved_by_sigma(tmp_path, monkeypatch):
    """Every copy is the tracking moved by N(0, sigma) per coordinate (its sample standard deviation within 10 %
    of sigma over 450 coordinates), seeded (the same copies twice), the other files the take's own, and the
    results directory itself untouched; the armature is built and scored on each copy."""
    from types import SimpleNamespace

    import stage.benchmarks.armature as bench
    from pipeline.armature_files import load_sequence, tracked_meshes

    verts = _tracked_results(tmp_path / "res")
    before = {p.name: p.read_bytes() for p in (tmp_path / "res" / "tracked").iterdir()}
    built = []

    def build(copy, **kw):
        assert (copy / "spine.json").read_text() == "{}" and "parts" not in kw
        V, _, _ = load_sequence(tracked_meshes(copy))
        built.append(V)
        return SimpleNamespace(segmentation=SimpleNamespace(labels=np.arange(V.shape[1]) // 10, n_segments=5),
                               fit=SimpleNamespace(joints=np.zeros((3, 2, 3))), skeleton=SimpleNamespace(
                                   articulation=np.array([True, False])), size=1.0)

    import pipeline.armature_files
    import pipeline.armature_score

    monkeypatch.setattr(pipeline.armature_files, "armature_results", build)
    monkeypatch.setattr(bench, "_truth_take", lambda sim, rig, V, F, ref: {"joints": None, "bending": None})
    monkeypatch.setattr(pipeline.armature_score, "articulation_scores",
                        lambda found, true, size, bending: {"recall": 0.5, "precision": 0.25})
    rig = SimpleNamespace(segmentation=SimpleNamespace(labels=(np.arange(50) // 10 + 3) % 5))
    got = bench.copies_scores(None, tmp_path / "res", rig, copies=2, sigma=0.01)
    assert got == [{"recall": 0.5, "precision": 0.25, "segments": 5, "same": True}] * 2
    first = list(built)
    bench.copies_scores(None, tmp_path / "res", rig, copies=2, sigma=0.01)
    for a, b in zip(first, built[2:]):
        assert np.array_equal(a, b)
    assert not np.array_equal(first[0], first[1])
    for moved in first:
        assert abs(np.std(moved - verts) / 0.01 - 1) < 0.1
    assert {p.name: p.read_bytes() for p in (tmp_path / "res" / "tracked").iterdir()} == before


def test_copies_row_prints_the_spread_of_recall_and_precision():
    """The line under a take's row: recall and precision as mean (least..most) over the tracking and its copies,
    the copies' least and most segments, and in how many of them the tracking's segmentation came back."""
    from stage.benchmarks.armature import copies_row

    spread = [{"recall": 0.5, "precision": 0.75, "segments": 6, "same": True},
              {"recall": 0.25, "precision": 1.0, "segments": 4, "same": False}]
    assert copies_row({"recall": 0.75, "precision": 0.5}, spread) == (
        "  copies     the tracking and 2 copies moved by 1 um: recall 0.50 (0.25..0.75), precision 0.75 (0.50..1.00); "
        "segments 4..6, the tracking's segmentation in 1 of 2")


def test_same_partition_against_a_loop():
    """Two labellings make the same segments when every pair of vertices is together in both or apart in both."""
    from stage.benchmarks.armature import _same_partition

    rng = np.random.default_rng(1)
    for _ in range(50):
        a = rng.integers(0, 4, 12)
        b = rng.permutation(7)[a] if rng.random() < 0.5 else rng.integers(0, 4, 12)
        want = all((a[i] == a[j]) == (b[i] == b[j]) for i in range(12) for j in range(12))
        assert _same_partition(a, b) == want


def test_invalid_input_copies_scores(tmp_path):
    from stage.benchmarks.armature import copies_scores

    for kw, match in (({"copies": -1}, "^copies"), ({"copies": 1.5}, "^copies"), ({"copies": True}, "^copies"),
                      ({"copies": 1, "sigma": 0}, "^sigma"), ({"copies": 1, "sigma": float("nan")}, "^sigma"),
                      ({"copies": 1, "sigma": True}, "^sigma"),
                      ({"copies": 1, "parts": "spine"}, "^parts")):
        with pytest.raises(ValueError, match=match):
            copies_scores(None, tmp_path, None, **kw)


def test_take_rows_are_named_with_their_seed(monkeypatch, capsys):
    """Every take row names its seed, the default's too, as `stage bench track --accuracy` names its rows
    ("biped s3"), so the two benches' rows of one take read alike."""
    import stage.benchmarks.armature as bench

    monkeypatch.setattr(bench, "take_armature", lambda name, tmp, *, seed, **kw: (("sim", name, seed), tmp, "rig", {}))
    monkeypatch.setattr(bench, "take_scores", lambda sim, res, rig: {})
    monkeypatch.setattr(bench, "take_row", lambda label, frames, rig, sc, secs: f"row {label}")
    bench.take_accuracy(["biped", "starfish"], seeds=(3,))
    bench.take_accuracy(["biped"], seeds=(3, 5))
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("row ")]
    assert rows == ["row biped s3", "row starfish s3", "row biped s3", "row biped s5"]


@pytest.mark.parametrize("argv", [["--copies", "2"], ["--labels"], ["--take-seeds", "3,5"], ["--skinned", "1,2"],
                                  ["--armature-parts", "limbs"]])
def test_accuracy_options_without_accuracy_are_refused(argv, monkeypatch):
    """`stage bench armature --copies 2` (no --accuracy) would run the timings and ignore the option: refused in
    one line naming it, before any work."""
    import argparse

    import stage.benchmarks.armature as bench

    monkeypatch.setattr(bench, "_timing_row", lambda *a, **kw: pytest.fail("timed"))
    p = argparse.ArgumentParser()
    bench.add_arguments(p)
    with pytest.raises(ValueError, match=f"^{argv[0]} needs --accuracy"):
        bench.run(p.parse_args(argv))
    seen = []
    monkeypatch.setattr(bench, "_timing_row", lambda size, T, **kw: seen.append((size, T)))
    assert bench.run(p.parse_args(["--sizes", "6k", "--frames", "60"])) == 0 and seen == [("6k", 60)]
