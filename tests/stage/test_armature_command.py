"""``stage armature`` and the ``rig`` process step: files written, clear messages without tracking."""

from __future__ import annotations

import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.results import ply_bytes
from stage.cli import main
from tests.pipeline.shapes import two_bars


def _write_seq(d, V, F):
    d.mkdir(parents=True, exist_ok=True)
    for i, v in enumerate(V):
        (d / f"{i:06d}.ply").write_bytes(ply_bytes(v, F))


def test_rig_meshes_writes_the_rig(tmp_path, capsys, monkeypatch):
    import pipeline.armature_files as files

    monkeypatch.setattr(files, "spine_limbs", None)  # a mesh sequence has no take's spine: never asked
    V, F, _ = two_bars(10)
    _write_seq(tmp_path / "seq", V, F)
    out = tmp_path / "rig"
    assert main(["-q", "armature", "--meshes", str(tmp_path / "seq" / "*.ply"), "--out", str(out), "--samples", "300"]) == 0
    doc = json.loads((out / "rig.json").read_text())
    assert doc["format"] == "capture-stage/rig@1" and doc["frame_count"] == 10 and "spine" not in doc
    assert sum(j["kind"] == "joint" for j in doc["joints"]) == 1
    assert (out / "rig.glb").stat().st_size > 0 and (out / "rig.bvh").is_file()
    assert len(list((out / "posed").glob("*.ply"))) == 10
    assert "2 segments, 1 articulation, " in capsys.readouterr().out


def test_rig_of_a_rigid_sequence_says_one_segment(tmp_path, capsys):
    V, F, _ = two_bars(6)
    _write_seq(tmp_path / "seq", np.repeat(V[:1], 6, axis=0) + np.linspace(0, 30, 6)[:, None, None], F)
    # `stage rig`: the old name of the command, an alias for one release
    assert main(["-q", "rig", "--meshes", str(tmp_path / "seq" / "*.ply"), "--out", str(tmp_path / "rig"),
                 "--samples", "300"]) == 0
    assert "1 segment, 0 articulations, " in capsys.readouterr().out


def test_a_sequence_given_no_units_whose_span_is_no_subject_in_millimetres_is_said(tmp_path, capsys):
    """Meshes in metres (or scaled to a unit box, as the Sumner & Popovic cat and horse are) were taken as
    millimetres without a word: a 2 mm armature, GLB and BVH. The 200 mm bars in metres: said, one line naming
    --units m; given --units, or in millimetres: nothing said."""
    V, F, _ = two_bars(6)
    _write_seq(tmp_path / "metres", V / 1000, F)
    _write_seq(tmp_path / "mm", V, F)
    args = ["-q", "armature", "--samples", "300", "--meshes"]
    assert main([*args, str(tmp_path / "metres" / "*.ply"), "--out", str(tmp_path / "a")]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning:")]
    assert len(said) == 1 and "span 0.2 units, taken as millimetres" in said[0] and "--units m: a 0.2 m" in said[0]
    assert json.loads((tmp_path / "a" / "rig.json").read_text())["units"] == "mm"
    assert main([*args, str(tmp_path / "metres" / "*.ply"), "--out", str(tmp_path / "b"), "--units", "m"]) == 0
    assert "warning:" not in capsys.readouterr().out
    assert json.loads((tmp_path / "b" / "rig.json").read_text())["units"] == "m"
    assert main([*args, str(tmp_path / "mm" / "*.ply"), "--out", str(tmp_path / "c")]) == 0
    assert "warning:" not in capsys.readouterr().out


def test_units_warning():
    """Under 10 and over 100 000 units (a subject under 1 cm or over 100 m if in millimetres) only, the edges
    kept; invalid input names the parameter."""
    from stage.cli._args import units_warning

    assert units_warning(10.0) is None and units_warning(1e5) is None and units_warning(1800.0) is None
    assert "--units m: a 9.99 m subject" in units_warning(9.99)
    assert "--units um: a 100 mm subject" in units_warning(1e5 + 1)
    for bad in (float("nan"), -1.0, "2", True, float("inf")):
        with pytest.raises(ValueError, match="span"):
            units_warning(bad)


def test_rig_is_the_old_name_of_armature_and_help_says_so():
    from stage.cli import build_parser

    top = build_parser().format_help()
    assert "armature (rig)" in top and "the old name, kept for one release" in top


def test_counted_is_singular_for_one():
    from pipeline.armature import armature_counts, counted

    assert [counted(n, "joint") for n in (0, 1, 2)] == ["0 joints", "1 joint", "2 joints"]
    assert armature_counts(1, 1, 2) == "1 segment, 1 articulation, 2 joints"


def test_rig_results_dir_needs_tracking(tmp_path, capsys):
    (tmp_path / "meshes").mkdir()
    assert main(["armature", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "tracked" in err and "stage track" in err


def test_rig_results_dir_tracks_first(tmp_path, capsys, monkeypatch):
    """A processed take without a tracked template: ``stage armature`` tracks it first (and says so), then rigs it
    with the take's spine limbs (:func:`pipeline.armature_files.spine_limbs`; rig.json says what they decided)."""
    import pipeline.armature_files as files
    from pipeline.armature_limbs import VertexLimbs

    V, F, right = two_bars(12)
    limbs = VertexLimbs(right.astype(np.int64) - 1, ("limb0",))  # the left bar the body, the right one a limb
    monkeypatch.setattr(files, "spine_limbs", lambda d, v, f, n: limbs)
    (tmp_path / "meshes").mkdir()
    for i, v in enumerate(V):
        (tmp_path / "meshes" / f"frame_{i:06d}.ply").write_bytes(ply_bytes(v, F))
    assert main(["-q", "armature", str(tmp_path), "--samples", "300"]) == 0
    out = capsys.readouterr().out
    assert "tracking the template through the take first" in out and f"stage track {tmp_path}" in out
    assert len(list((tmp_path / "tracked").glob("0*.ply"))) == 12
    doc = json.loads((tmp_path / "rig" / "rig.json").read_text())
    assert sum(j["kind"] == "joint" for j in doc["joints"]) == 1 and "1 articulation" in out
    assert doc["spine"]["limbs"] == ["limb0"] and sorted(doc["spine"]["segment_limbs"]) == ["body", "limb0"]


@pytest.mark.parametrize("progress", [False, True])
def test_the_tracking_of_stage_armature_shows_progress_bars_as_the_command_does(tmp_path, capsys, progress):
    """The tracking ``stage armature RESULTS_DIR`` runs first draws its progress bars as the command's own are
    drawn: not when stderr is no terminal (here: captured), unless ``--progress`` is given."""
    V, F, _ = two_bars(4)
    (tmp_path / "meshes").mkdir()
    for i, v in enumerate(V):
        (tmp_path / "meshes" / f"frame_{i:06d}.ply").write_bytes(ply_bytes(v, F))
    assert main(["armature", str(tmp_path), "--samples", "300", *(["--progress"] if progress else [])]) == 0
    err = capsys.readouterr().err
    assert ("track: 100%" in err) == progress and ("write: 100%" in err) == progress, err


def test_armature_parts_limbs_of_an_untracked_take_track_with_the_labels_first(tmp_path, capsys):
    """``stage armature RESULTS_DIR --parts limbs`` on a processed take without a tracked template tracks it with
    the template's labels first (``stage track --labels``, said), so its parts come from the limbs."""
    from tests.pipeline.tracking_takes import creature_spine_results

    creature_spine_results(tmp_path, frames=3)
    assert main(["-q", "armature", str(tmp_path), "--parts", "limbs"]) == 0
    assert f"stage track {tmp_path} --labels" in capsys.readouterr().out
    assert json.loads((tmp_path / "tracked" / "track.json").read_text())["patch_labels"] == "spine"
    assert json.loads((tmp_path / "rig" / "rig.json").read_text())["segmentation"]["source"] == "limbs"


def test_a_sequence_of_one_frame_is_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    """One frame has no motion to find an armature from: ``--meshes`` matching one file, and a results directory of
    one surface, are one line naming it, before the results directory's tracking (which could not help)."""
    import stage.cli.armature as command

    monkeypatch.setattr(command, "_track_first", lambda *a, **k: pytest.fail("tracked a take of one frame"))
    V, F, _ = two_bars(1)
    _write_seq(tmp_path / "seq", V, F)
    assert main(["armature", "--meshes", str(tmp_path / "seq" / "*.ply"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err == (f"stage armature: error: {tmp_path / 'seq' / '000000.ply'} is the only frame: an armature is found "
                   "from how the subject moves; it needs 2 frames or more\n"), err
    (tmp_path / "res" / "meshes").mkdir(parents=True)
    (tmp_path / "res" / "meshes" / "frame_000004.ply").write_bytes(ply_bytes(V[0], F))
    assert main(["rig", str(tmp_path / "res")]) == 2
    assert capsys.readouterr().err == (f"stage rig: error: {tmp_path / 'res'} has one frame (meshes/frame_000004.ply): an "
                                       "armature is found from how the subject moves; it needs 2 frames or more\n")


def test_rig_meshes_without_shared_connectivity(tmp_path, capsys):
    V, F, _ = two_bars(3)
    _write_seq(tmp_path / "seq", V, F)
    (tmp_path / "seq" / "000002.ply").write_bytes(ply_bytes(V[2][:-3], F[:10]))
    assert main(["armature", "--meshes", str(tmp_path / "seq"), "--out", str(tmp_path / "o")]) == 2
    assert "share connectivity" in capsys.readouterr().err


def test_armature_parts_limbs_of_a_take_tracked_with_labels(tmp_path, capsys):
    from tests.pipeline.labelled_take import labelled_results

    res, labels = labelled_results(tmp_path)
    assert main(["-q", "armature", str(res), "--parts", "limbs"]) == 0
    doc = json.loads((res / "rig" / "rig.json").read_text())
    assert doc["segmentation"]["source"] == "limbs"
    seg = np.load(res / "rig" / "segments.npy")
    assert all(len(np.unique(labels[seg == s])) == 1 for s in np.unique(seg))  # no part spans two labels
    assert main(["-q", "armature", "--meshes", str(res / "tracked" / "*.ply"), "--out", str(tmp_path / "o"),
                 "--parts", "limbs"]) == 2
    assert "--parts limbs needs RESULTS_DIR" in capsys.readouterr().err


def test_invalid_input(tmp_path, capsys, monkeypatch):
    import pipeline.armature
    import stage.cli.armature as command

    assert main(["armature"]) == 2
    assert main(["armature", "--meshes", "x/*.ply"]) == 2  # no --out
    assert "--out" in capsys.readouterr().err
    # the options' values before any work, in their names: an untracked take is not tracked first
    monkeypatch.setattr(command, "_track_first", lambda *a, **k: pytest.fail("tracked before the options were checked"))
    V, F, _ = two_bars(3)
    (tmp_path / "res" / "meshes").mkdir(parents=True)
    (tmp_path / "res" / "meshes" / "frame_000000.ply").write_bytes(ply_bytes(V[0], F))
    (tmp_path / "a-file").write_text("not a directory")
    for bad, said in ((["--samples", "1"], "--samples must be"), (["--lambda-thr", "2"], "--lambda-thr must be"),
                      (["--fps", "0"], "--fps must be"), (["--fps", "nan"], "--fps must be"),
                      (["--reference", "-1"], "--reference must be"),
                      (["--out", str(tmp_path / "a-file")], f"--out {tmp_path / 'a-file'} is a file: give the directory")):
        assert main(["armature", str(tmp_path / "res"), *bad]) == 2
        assert f"stage armature: error: {said}" in capsys.readouterr().err
    # --reference past the sequence's end: said in the option's words before the segmentation
    monkeypatch.setattr(pipeline.armature, "build_armature", lambda *a, **k: pytest.fail("built before the check"))
    _write_seq(tmp_path / "seq", V, F)
    assert main(["armature", "--meshes", str(tmp_path / "seq" / "*.ply"), "--out", str(tmp_path / "o"),
                 "--reference", "3"]) == 2
    assert "error: --reference must be a position within 0..2 (the sequence has 3 frames), got 3" in capsys.readouterr().err
    # ... and before an untracked take's tracking, whose frames are its surfaces (still _track_first failing the test)
    for i in (1, 2):
        (tmp_path / "res" / "meshes" / f"frame_{i:06d}.ply").write_bytes(ply_bytes(V[i], F))
    assert main(["armature", str(tmp_path / "res"), "--reference", "3"]) == 2
    assert "error: --reference must be a position within 0..2 (the sequence has 3 frames), got 3" in capsys.readouterr().err


def test_rig_step(tmp_path, caplog):
    from pipeline.process import STEPS, ProcessError, ProcessParams
    from pipeline.process.steps import _step_rig

    # the rig runs on what tracking wrote, so it comes after the spine and the tracking
    assert STEPS.index("rig") > STEPS.index("track") > STEPS.index("spine")
    take = SimpleNamespace(calibration=SimpleNamespace(units="mm"), fps=25.0, n_sets=1)
    warned = []
    ctx = SimpleNamespace(out=tmp_path, take=take, progress=None, report_progress=lambda *a: None,
                          steps=("rig",), warnings=warned, keep_warning=warned.append, params=ProcessParams())
    # a take of one frame set: nothing moves, said before any tracking (no warning that the track step ran)
    with pytest.raises(ProcessError, match="rig: the take has one frame set: an armature is found from how the "
                       "subject moves; it needs 2 frame sets or more"):
        _step_rig(ctx)
    assert ctx.warnings == []
    take.n_sets = 8
    # no tracked template and nothing to track: one line in the words of the job's steps, no CLI command
    with caplog.at_level(logging.WARNING), pytest.raises(ProcessError, match="run the surface step first") as exc:
        _step_rig(ctx)
    assert "stage " not in str(exc.value) and "track step ran first" in ctx.warnings[0]
    V, F, _ = two_bars(8)
    _write_seq(tmp_path / "tracked", V, F)
    _step_rig(ctx)
    doc = json.loads((tmp_path / "rig" / "rig.json").read_text())
    assert doc["fps"] == 25.0 and doc["units"] == "mm"
    assert np.isfinite(doc["fit"]["mean_vertex_error"])


def test_the_rig_step_of_a_rigid_take_says_one_segment(tmp_path):
    """A job's take that moves rigidly: the rig step's armature is one segment, and the job's report says why in one
    warning, as ``stage armature`` does (nothing bends), not only a count of one."""
    from pipeline.process import ProcessParams
    from pipeline.process.steps import _step_rig

    V, F, _ = two_bars(6)
    _write_seq(tmp_path / "tracked", np.repeat(V[:1], 6, axis=0) + np.linspace(0, 30, 6)[:, None, None], F)
    warnings = []
    ctx = SimpleNamespace(out=tmp_path, take=SimpleNamespace(calibration=SimpleNamespace(units="mm"), fps=25.0, n_sets=6),
                          report_progress=lambda *a: None, steps=("rig",), warnings=warnings, warn=warnings.append,
                          keep_warning=warnings.append, params=ProcessParams())
    _step_rig(ctx)
    assert json.loads((tmp_path / "rig" / "rig.json").read_text())["segmentation"]["segments"] == 1
    assert warnings == ["rig: nothing bends in this sequence (one eigenvalue below the threshold 0.7): one segment",
                        "rig: nothing bends in this take: one segment, the armature moves rigidly"]  # (why, then what)


def test_report_shows_the_rig(tmp_path):
    from pipeline.report import render_report

    V, F, _ = two_bars(10)
    _write_seq(tmp_path / "seq", V, F)
    assert main(["-q", "armature", "--meshes", str(tmp_path / "seq"), "--out", str(tmp_path / "res" / "rig"),
                 "--samples", "300"]) == 0
    (tmp_path / "res" / "report.json").write_text(json.dumps({"frames": 10, "steps": ["rig"]}))
    html = render_report(tmp_path / "res")
    assert 'id="rig"' in html and "rig-view" in html
    assert "Armature: 2 motion segments, 1 articulation, " in html
    assert "Colours: motion segments;" in html and "limb segment" not in html
    # parts from the limbs (stage armature --parts limbs): named so, not as the motion segmentation's
    doc = json.loads((tmp_path / "res" / "rig" / "rig.json").read_text())
    doc["segmentation"]["source"] = "limbs"
    (tmp_path / "res" / "rig" / "rig.json").write_text(json.dumps(doc))
    html = render_report(tmp_path / "res")
    assert "Armature: 2 limb segments, 1 articulation, " in html and "Armature: limb segments and joints" in html
    assert "Colours: limb segments;" in html and "motion segment" not in html


def test_export_bvh_of_a_rig(tmp_path, capsys):
    """``stage export --format bvh``: the rig of ``stage armature`` as BVH that two parsers read, whose forward
    kinematics gives rig.json's joint positions in every frame."""
    from scipy.spatial.transform import Rotation

    from tests.pipeline.bvh import parse_bvh

    V, F, _ = two_bars(10)
    _write_seq(tmp_path / "seq", V, F)
    res = tmp_path / "results"
    assert main(["-q", "armature", "--meshes", str(tmp_path / "seq" / "*.ply"), "--out", str(res / "rig"),
                 "--samples", "300"]) == 0
    assert main(["export", str(res), "--format", "bvh"]) == 0
    assert "rig.bvh" in capsys.readouterr().out
    doc = json.loads((res / "rig" / "rig.json").read_text())
    text = (res / "rig.bvh").read_text()
    joints, rows = parse_bvh(text)
    assert [j["name"] for j in joints] == [j["name"] for j in doc["joints"]] and len(rows) == 10
    tol = 1e-4 * doc["size"]
    for t in range(10):  # forward kinematics of the file (intrinsic Z-X-Y, degrees)
        pos, rot, col = {}, {}, 0
        for j in joints:
            vals = rows[t, col : col + len(j["channels"])]
            col += len(j["channels"])
            R = Rotation.from_euler("ZXY", vals[-3:], degrees=True).as_matrix()
            par = None if j["parent"] is None else joints[j["parent"]]["name"]
            pos[j["name"]] = vals[:3] if par is None else pos[par] + rot[par] @ np.asarray(j["offset"])
            rot[j["name"]] = R if par is None else rot[par] @ R
        for name, p in pos.items():
            assert np.linalg.norm(p - np.asarray(doc["frames"][t]["joints"][name])) < tol
    # a rig directory itself, and another parser (bvhio: world positions per frame)
    assert main(["-q", "export", str(res / "rig"), "--format", "bvh", "--out", str(tmp_path / "b.bvh")]) == 0
    bvhio = pytest.importorskip("bvhio", reason="bvhio (a test dependency) is not installed")
    h = bvhio.readAsHierarchy(str(tmp_path / "b.bvh"))
    assert bvhio.readAsBvh(str(tmp_path / "b.bvh")).FrameCount == 10
    for t in (0, 4, 9):
        h.loadPose(t)
        for j, _, _ in h.layout():
            assert np.linalg.norm(np.asarray(j.PositionWorld) - doc["frames"][t]["joints"][j.Name]) < tol


def test_export_bvh_needs_a_rig(tmp_path, capsys):
    (tmp_path / "meshes").mkdir()
    assert main(["export", str(tmp_path), "--format", "bvh"]) == 2
    assert f"stage armature {tmp_path}" in capsys.readouterr().err
    (tmp_path / "rig").mkdir()
    (tmp_path / "rig" / "rig.json").write_text(json.dumps({"format": "capture-stage/rig@1", "fps": 30, "joints": [
        {"name": "root", "parent": None, "rest": [0, 0, 0]}], "frames": [{"index": 0, "joints": {"root": [0, 0, 0]}}]}))
    assert main(["export", str(tmp_path), "--format", "bvh"]) == 2
    assert "run stage armature again" in capsys.readouterr().err
    (tmp_path / "rig" / "rig.json").write_text("{not json")
    assert main(["export", str(tmp_path), "--format", "bvh"]) == 2
    assert "unreadable" in capsys.readouterr().err


def test_export_refuses_the_options_its_format_does_not_use(tmp_path, capsys):
    """``stage export --format bvh --reference 3`` would write the armature's own rest pose and say nothing: an
    option the format does not use is refused in one line naming it, before anything is read."""
    for fmt, options, named in (("bvh", ["--reference", "3"], "--reference"),
                                ("bvh", ["--reference", "0"], "--reference"),  # frame 0 is given too (0 == False)
                                ("bvh", ["--segments", "0"], "--segments"),
                                ("bvh", ["--segments", "6", "--no-spine-tubes"], "--segments, --no-spine-tubes"),
                                ("spine-glb", ["--no-spine-tubes"], "--no-spine-tubes")):
        assert main(["export", str(tmp_path), "--format", fmt, *options]) == 2
        err = capsys.readouterr().err
        assert f"error: {named}: not an option of --format {fmt}" in err and len(err.splitlines()) == 1, err
        assert ("stage armature --reference POS" in err) == (fmt == "bvh"), err  # where the BVH's rest pose is chosen
