"""``stage track`` on simulated takes: single RGB-D and multi-view results directories."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fake_cameras.rgbd import load_rgbd_ground_truth, record_rgbd_take, simulate_rgbd_take, template_path
from pipeline.mesh_primitives import mesh_volume
from pipeline.meshio import load_mesh
from pipeline.results import atomic_write_bytes, ply_bytes
from stage.cli import main
from tests.pipeline.tracking_takes import turning_sphere_results


@pytest.fixture(scope="module")
def lamp_take(tmp_path_factory):
    root = tmp_path_factory.mktemp("track_lamp")
    tk = simulate_rgbd_take("lamp", frames=6, bend=0.0)
    return record_rgbd_take(tk, root / "lamp.h5", drop_depth=[3])


def test_rgbd_track_static_lamp_accuracy_skips_and_resumes(lamp_take, capsys):
    out = lamp_take.parent / "out"
    assert main(["-q", "track", str(lamp_take), "--template", str(template_path(lamp_take)), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "skipped 1 frame without data: 3" in text and " through 5 frames " in text
    rep = json.loads((out / "tracked" / "track.json").read_text())
    assert rep["skipped"] == [3] and rep["mode"] == "rgbd"
    gt = load_rgbd_ground_truth(lamp_take)
    V0, F0 = load_mesh(template_path(lamp_take), largest=False)
    for k in (0, 1, 2, 4, 5):
        v, f = load_mesh(out / "tracked" / f"{k:06d}.ply", largest=False)
        assert v.shape == V0.shape and np.array_equal(f, F0)  # template vertex order
        err = np.linalg.norm(v - gt["truth"][k], axis=1).mean()
        assert err <= 0.01 * gt["length"], (k, err)  # measured 0.2 % of the length
        assert abs(mesh_volume(v, f) / mesh_volume(V0, F0) - 1) <= 0.05
    assert not (out / "tracked" / "000003.ply").exists()
    # resume: a lost frame is tracked again, the others are kept
    kept = (out / "tracked" / "000001.ply").stat().st_mtime_ns
    (out / "tracked" / "000004.ply").unlink()
    assert main(["-q", "track", str(lamp_take), "--template", str(template_path(lamp_take)), "--out", str(out)]) == 0
    assert (out / "tracked" / "000004.ply").exists()
    assert (out / "tracked" / "000001.ply").stat().st_mtime_ns == kept
    assert sorted(json.loads((out / "tracked" / "track.json").read_text())["frames"], key=int) == ["0", "1", "2", "4", "5"]
    # other settings: the frames are tracked again
    assert main(["-q", "track", str(lamp_take), "--template", str(template_path(lamp_take)), "--out", str(out),
                 "--no-predict"]) == 0
    assert (out / "tracked" / "000001.ply").stat().st_mtime_ns != kept
    assert json.loads((out / "tracked" / "track.json").read_text())["predict"] is False


def test_rgbd_template_far_from_the_data_is_a_clear_error_and_writes_nothing(lamp_take, capsys):
    V0, F0 = load_mesh(template_path(lamp_take), largest=False)
    far = lamp_take.parent / "far.ply"
    trimesh.Trimesh(V0 + [0, 0, 2000.0], F0, process=False).export(far)
    out = lamp_take.parent / "far_out"
    assert main(["track", str(lamp_take), "--template", str(far), "--out", str(out)]) == 2
    assert "cannot place the template" in capsys.readouterr().err
    assert not out.exists()


def test_multiview_results_directory_with_holes_and_no_spine(tmp_path):
    """Per-frame surfaces of a moving sphere; template with a hole; no spine.json: still tracks."""
    meshes = tmp_path / "meshes"
    for k in range(4):
        m = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
        atomic_write_bytes(meshes / f"frame_{k:06d}.ply", ply_bytes(m.vertices + [2.0 * k, 0, 0], m.faces))
    t = trimesh.creation.icosphere(subdivisions=2, radius=60.0)
    holed = tmp_path / "template.ply"
    trimesh.Trimesh(t.vertices, t.faces[:-6], process=False).export(holed)
    assert main(["-q", "track", str(tmp_path), "--template", str(holed)]) == 0
    rep = json.loads((tmp_path / "tracked" / "track.json").read_text())
    assert rep["mode"] == "multi-view" and sorted(rep["frames"]) == ["0", "1", "2", "3"]
    v, _ = load_mesh(tmp_path / "tracked" / "000003.ply", largest=False)
    assert v.shape == t.vertices.shape
    assert np.abs(np.linalg.norm(v - [6.0, 0, 0], axis=1) - 60.0).mean() < 0.5


def test_invalid_input(tmp_path, capsys):
    assert main(["track", str(tmp_path / "nothing")]) == 2
    assert "no such results directory" in capsys.readouterr().err
    f = tmp_path / "take.h5"
    f.write_bytes(b"")
    assert main(["track", str(f)]) == 2
    assert "--template" in capsys.readouterr().err
    assert main(["track", str(tmp_path)]) == 2  # a directory without meshes
    assert "stage process" in capsys.readouterr().err
    for args, msg in (([str(tmp_path), "--no-colour"], "--no-colour applies to a take file"),
                      ([str(tmp_path), "--out", str(tmp_path / "o")], "--out applies to a take file"),
                      ([str(f), "--template", str(f), "--colour"], "--colour applies to a results directory"),
                      ([str(f), "--template", str(f), "--shape-memory"], "--shape-memory applies to a results directory"),
                      ([str(f), "--template", str(f), "--prediction-only"],
                       "--prediction-only applies to a results directory"),
                      ([str(f), "--template", str(f), "--labels"], "--labels applies to a results directory")):
        assert main(["track", *args]) == 2  # a flag of the other mode would be ignored
        assert msg in capsys.readouterr().err
    assert main(["track", str(f), "--template", str(f), "--workers", "2"]) == 2
    assert "--workers applies to a results directory" in capsys.readouterr().err
    assert main(["track", str(tmp_path / "missing.h5"), "--template", str(f), "--out", str(tmp_path / "o")]) == 2
    assert "no such results directory or take file" in capsys.readouterr().err  # not a mode error
    assert not (tmp_path / "tracked").exists() and not (tmp_path / "o").exists()


def test_track_is_an_opt_in_step_of_process_and_of_api_jobs():
    from api.jobs import load_work
    from pipeline.process import DEFAULT_STEPS, STEPS

    assert "track" in STEPS and "track" not in DEFAULT_STEPS
    spec = load_work("pipeline.process:process_take")
    assert spec.validate(None, {})[0] == DEFAULT_STEPS
    assert spec.validate(["track", "spine", "surface"], {})[0] == ("surface", "spine", "track")  # in the steps' order


def test_demo_rgbd_runs_the_single_camera_path_end_to_end(tmp_path, capsys):
    assert main(["-q", "demo", "--rgbd", "--frames", "4", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "accuracy: mean vertex error" in text
    assert (tmp_path / "results" / "tracked" / "000003.ply").exists()


@pytest.fixture(scope="module")
def bent_tracks(tmp_path_factory):
    """Each bent object's 30-frame take tracked once for the module: name -> (take, out, errors, volumes)."""
    cache = {}

    def get(name):
        if name not in cache:
            root = tmp_path_factory.mktemp(f"bent_{name}")
            tk = simulate_rgbd_take(name, frames=30, spacing=4.0 if name != "lamp" else None)
            take = record_rgbd_take(tk, root / f"{name}.h5")
            out = root / "out"
            assert main(["-q", "track", str(take), "--template", str(template_path(take)), "--out", str(out)]) == 0
            V0, F0 = tk.template_vertices, tk.template_faces
            errs, vols = [], []
            for k in range(tk.n_frames):
                v, _ = load_mesh(out / "tracked" / f"{k:06d}.ply", largest=False)
                errs.append(np.linalg.norm(v - tk.truth[k], axis=1).mean())
                vols.append(mesh_volume(v, F0) / mesh_volume(V0, F0))
            cache[name] = (tk, out, np.array(errs), np.array(vols))
        return cache[name]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pipe_half", "pipe_3q", "lamp"])  # figures: docs/tracking.md, the RGB-D rows
def test_rgbd_bent_objects_tracked_to_one_percent(name, bent_tracks):
    tk, _, errs, vols = bent_tracks(name)
    assert max(abs(vols - 1)) <= 0.05  # no thinning over the whole take
    assert errs.mean() <= 0.01 * tk.size, errs.mean() / tk.size


@pytest.mark.slow
@pytest.mark.parametrize("name, articulations", [
    ("pipe_half", 1),  # the figures: docs/tracking.md, the RGB-D rows
    ("pipe_3q", 1),
    ("lamp", 3),
])
def test_rgbd_bent_objects_rigged(name, articulations, bent_tracks):
    from pipeline.armature_files import armature_results

    tk, out, _, _ = bent_tracks(name)
    rig = armature_results(out)
    assert int(rig.skeleton.articulation.sum()) == articulations
    sk = rig.skeleton
    found = sk.rest[sk.articulation]  # articulated joints in the template's (rest) frame
    d = np.linalg.norm(found[:, None, :] - tk.joint_positions[0][None], axis=2).min(axis=0)
    assert np.all(d <= 0.05 * tk.size)  # every true joint has an articulation within 5 % of the length


def test_multiview_halves_in_a_worker_process_equal_the_frames_tracked_in_order(tmp_path, monkeypatch):
    """Reference frame 3 of 7 (as a spine would choose it): the backward half tracked on a process pool
    gives the same vertices as tracking in order, and progress reaches every frame; while this process
    waits for a late worker, progress counts the worker's frames as they are written."""
    import concurrent.futures as cf
    import multiprocessing
    import threading

    from pipeline import track

    t = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [6.0, 0, 0], t.faces, 3, [2.0, 0, 0]))
    monkeypatch.setattr(track, "_POLL_SECONDS", 0.01)
    forward_done = threading.Event()

    class LateWorker(cf.ThreadPoolExecutor):  # starts the backward half once this process has tracked its own
        def submit(self, fn, *args, **kwargs):
            return super().submit(lambda: forward_done.wait(60) and fn(*args, **kwargs))

    runs, seen_by = {}, {}
    for how in ("in_order", "pool", "late"):
        root = tmp_path / how
        for k in range(7):
            atomic_write_bytes(root / "meshes" / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [2.0 * k, 0, 0], t.faces))
        (root / "spine.json").write_text('{"frames": 7}')
        seen = seen_by[how] = []
        forward_done.clear()

        def progress(s, d, n, seen=seen):
            seen.append((d, n))
            if d >= 4:  # the reference frame and the 3 after it
                forward_done.set()

        if how == "pool":  # the fake spine is not in the worker process: the prediction only
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver")) as ex:
                rep = track.track_results(root, executor=ex, progress=progress, choose=False)
        elif how == "late":  # the default: per patch the prediction or the skinned step (choose)
            with LateWorker(max_workers=1) as ex:
                rep = track.track_results(root, executor=ex, progress=progress)
                stamps = [track.tracked_path(root, k).stat().st_mtime_ns for k in range(7)]
                assert track.track_results(root, executor=ex)["frames"] == rep["frames"]  # resumed
                assert [track.tracked_path(root, k).stat().st_mtime_ns for k in range(7)] == stamps
            assert rep["spine_start"] == "choose" and len(rep["spine_sha256"]) == 64
            # every step within reach of the prediction: no patch takes the skinned step
            assert [rep["frames"][str(k)].get("spine_start_patches") for k in range(7)] == [0.0] * 3 + [None] + [0.0] * 3
        else:
            rep = track.track_results(root, progress=progress, choose=False)
            assert rep["spine_start"] == "none" and "spine_sha256" not in rep
        assert rep["reference_frame"] == 3 and list(rep["frames"]) == [str(k) for k in range(7)]
        assert ("worker_cpu_seconds" in rep) == (how == "pool")  # a thread's CPU is already this process's
        assert seen[-1] == (7, 7) and all(d <= n for d, n in seen)
        runs[how] = [load_mesh(root / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(7)]
    assert {5, 6} <= {d for d, _ in seen_by["late"]}  # the worker's frames 2 and 1, counted while waiting
    for how in ("pool", "late"):
        for k in range(7):
            assert np.array_equal(runs[how][k], runs["in_order"][k]), (how, k)
    for k in range(7):
        assert np.abs(np.linalg.norm(runs["pool"][k] - [2.0 * k, 0, 0], axis=1) - 60.0).mean() < 0.5


def test_worker_progress_counts_frames_without_a_surface_and_looks_at_each_file_a_bounded_number_of_times(
        tmp_path, monkeypatch):
    import pathlib

    from pipeline import track

    frames = list(range(40, 0, -1))
    count = track._written_count(tmp_path, frames)
    looks = []
    is_file = pathlib.Path.is_file
    monkeypatch.setattr(pathlib.Path, "is_file", lambda self: looks.append(self) or is_file(self))
    assert count() == 0
    (tmp_path / "tracked").mkdir()
    for i, k in enumerate(frames):
        if k != 30:  # frame 30 has no surface: no tracked file
            track.tracked_path(tmp_path, k).write_bytes(b"ply")
        assert count() == (i + 1 if k != 30 else i)
    assert count() == 40
    # each count: the files it passes, the first missing one and a few after it (linear; 820 looks if quadratic)
    assert len(looks) <= len(frames) + 42 * (1 + track._LOOK_AHEAD)


def test_reference_frame_without_a_surface_says_so_in_one_line(tmp_path, caplog):
    from pipeline.track import track_results

    t = trimesh.creation.icosphere(subdivisions=2, radius=60.0)
    atomic_write_bytes(tmp_path / "meshes" / "frame_000000.ply", ply_bytes(np.zeros((0, 3)), np.zeros((0, 3), int)))
    for k in (1, 2):
        atomic_write_bytes(tmp_path / "meshes" / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [1.0 * k, 0, 0], t.faces))
    with caplog.at_level("WARNING", logger="pipeline.track"):
        rep = track_results(tmp_path, template=(t.vertices, t.faces))
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [f"reference frame 0 has no surface ({tmp_path / 'meshes' / 'frame_000000.ply'} has no triangles): "
                     "both halves start from the template"]
    assert rep["skipped"] == [0] and sorted(rep["frames"]) == ["1", "2"]


def test_a_missing_surface_is_an_error_naming_it_not_a_frame_skipped(tmp_path, capsys):
    """``stage process`` writes a surface per frame set (an empty one where nothing was seen): a
    missing ``frame_000002.ply`` is one error naming it (against process.json's frame count, or a
    gap in the numbering), and nothing is tracked."""
    t = _sphere_results(tmp_path, frames=5)
    (tmp_path / "meshes" / "frame_000002.ply").unlink()
    assert main(["-q", "track", str(tmp_path), "--template", str(_template_file(tmp_path, t))]) == 2
    err = capsys.readouterr().err
    assert "1 of 5 surfaces missing (frame_000002.ply)" in err and "stage process" in err
    assert not (tmp_path / "tracked").exists()
    (tmp_path / "meshes" / "frame_000004.ply").unlink()  # the last frames: only process.json knows them
    (tmp_path / "process.json").write_text(json.dumps({"frames": 5}))
    atomic_write_bytes(tmp_path / "meshes" / "frame_000002.ply", ply_bytes(t.vertices, t.faces))
    assert main(["-q", "track", str(tmp_path), "--template", str(_template_file(tmp_path, t))]) == 2
    assert "frame_000004.ply" in capsys.readouterr().err


def _template_file(root, t):
    path = root / "template.ply"
    trimesh.Trimesh(t.vertices, t.faces, process=False).export(path)
    return path


def _sphere_results(root, frames=5):
    t = trimesh.creation.icosphere(subdivisions=2, radius=60.0)
    for k in range(frames):
        atomic_write_bytes(root / "meshes" / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [1.5 * k, 0, 0], t.faces))
    return t


def _fake_spine(V, F, ref, step):
    """``spine_model``'s stand-in: reference ``ref``, the template ``V`` and a skinned pose moving by ``step`` a frame."""
    from types import SimpleNamespace

    V = np.asarray(V, float)
    model = SimpleNamespace(vertices=V, faces=F, deform=lambda i: V + np.multiply(step, i - ref))
    return lambda *a: (ref, model)


def test_frames_tracked_with_the_grids_patches_are_tracked_again(tmp_path, caplog):
    """A track.json without ``patches`` was written when the patches were a grid's cells: its frames
    (and a rig built on them) are not resumed under the patches that follow the surface."""
    import json

    from pipeline import track

    _sphere_results(tmp_path, frames=3)
    first = track.track_results(tmp_path)
    assert first["patches"] == "surface"
    path = tmp_path / "tracked" / "track.json"
    old = json.loads(path.read_text())
    del old["patches"]
    path.write_text(json.dumps(old))
    with caplog.at_level("WARNING", logger="pipeline.track"):
        again = track.track_results(tmp_path)
    assert "patches 'grid' -> 'surface'" in again["started_over"]
    assert [r.getMessage() for r in caplog.records] == [again["started_over"]]


def test_a_tracking_without_armature_rounds_removes_an_earlier_rounds_segments(tmp_path):
    """``tracked/rig_segments.npy`` belongs to the armature round whose digest ``track.json`` records: a tracking
    without armature rounds (its ``track.json`` names none) removes an earlier one's file, resumed or started over."""
    import json

    from pipeline import track
    from pipeline.track_frames import write_round_segments

    t = _sphere_results(tmp_path, frames=3)
    track.track_results(tmp_path)
    path, seg = tmp_path / "tracked" / "track.json", tmp_path / "tracked" / "rig_segments.npy"
    plain = json.loads(path.read_text())
    for report in (plain, {**plain, "rig_rounds": 1}):  # resumed (a killed round's file), started over
        prior = {}
        write_round_segments(tmp_path, np.zeros(len(t.vertices), np.int64), prior)
        path.write_text(json.dumps({**report, "rig_prior": prior}))
        again = track.track_results(tmp_path)
        assert not seg.exists() and "rig_prior" not in json.loads(path.read_text())
        assert ("started_over" in again) == (report is not plain)


def test_rebuilt_spine_starts_over_with_one_warning_and_the_same_spine_resumes(tmp_path, monkeypatch, caplog):
    from pipeline import track

    t = _sphere_results(tmp_path, frames=3)
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    (tmp_path / "spine.json").write_text('{"frames": 3}')
    first = track.track_results(tmp_path)
    assert first["spine_start"] == "choose" and len(first["spine_sha256"]) == 64
    stamp = track.tracked_path(tmp_path, 2).stat().st_mtime_ns
    with caplog.at_level("WARNING", logger="pipeline.track"):
        again = track.track_results(tmp_path)  # the same spine: resumed, nothing fitted
        assert not caplog.records and again["frames"] == first["frames"]
        assert track.tracked_path(tmp_path, 2).stat().st_mtime_ns == stamp
        (tmp_path / "spine.json").write_text('{"frames": 3, "rebuilt": true}')
        other = track.track_results(tmp_path)
    assert [r.getMessage() for r in caplog.records] == [other["started_over"]]
    assert "other settings (spine.json changed)" in other["started_over"]
    assert other["spine_sha256"] != first["spine_sha256"] and track.tracked_path(tmp_path, 2).stat().st_mtime_ns != stamp


def test_track_json_of_the_earlier_version_without_spine_start_keeps_frames_of_the_same_behaviour(
        tmp_path, monkeypatch, caplog):
    """An earlier track.json (no spine_start, no spine_sha256) reads as "none" without --spine-init
    and "all" with it: the same run resumes; the new default with a spine (choose) starts over."""
    from pipeline import track

    def older(root):  # track.json as the earlier version wrote it
        path = root / "tracked" / "track.json"
        rep = json.loads(path.read_text())
        del rep["spine_start"]
        rep.pop("spine_sha256", None)
        path.write_text(json.dumps(rep))

    t = _sphere_results(tmp_path / "no_spine", frames=3)
    first = track.track_results(tmp_path / "no_spine")
    older(tmp_path / "no_spine")
    t = _sphere_results(tmp_path / "spine_init", frames=3)
    (tmp_path / "spine_init" / "spine.json").write_text('{"frames": 3}')
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    init = track.track_results(tmp_path / "spine_init", spine_init=True)
    older(tmp_path / "spine_init")
    monkeypatch.undo()
    stamps = {d: track.tracked_path(tmp_path / d, 2).stat().st_mtime_ns for d in ("no_spine", "spine_init")}
    with caplog.at_level("WARNING", logger="pipeline.track"):
        assert track.track_results(tmp_path / "no_spine")["frames"] == first["frames"]
        monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
        assert track.track_results(tmp_path / "spine_init", spine_init=True)["frames"] == init["frames"]
        assert not caplog.records
        assert all(track.tracked_path(tmp_path / d, 2).stat().st_mtime_ns == s for d, s in stamps.items())
        older(tmp_path / "spine_init")
        track.track_results(tmp_path / "spine_init")  # the new default with a spine: another start
    assert len(caplog.records) == 1 and "spine_start 'all' -> 'choose'" in caplog.records[0].getMessage()


def test_track_json_of_the_earlier_version_starts_over_when_the_spine_was_rewritten_since(tmp_path, monkeypatch, caplog):
    """An earlier track.json records no spine digest: its --spine-init frames are kept while
    spine.json is older than it, and tracked again (one warning) once spine.json was written after it."""
    import os

    from pipeline import track

    t = _sphere_results(tmp_path, frames=3)
    (tmp_path / "spine.json").write_text('{"frames": 3}')
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    track.track_results(tmp_path, spine_init=True)
    path = tmp_path / "tracked" / "track.json"
    rep = json.loads(path.read_text())
    del rep["spine_start"], rep["spine_sha256"]
    path.write_text(json.dumps(rep))
    stamp = track.tracked_path(tmp_path, 2).stat().st_mtime_ns
    with caplog.at_level("WARNING", logger="pipeline.track"):
        track.track_results(tmp_path, spine_init=True)
        assert not caplog.records and track.tracked_path(tmp_path, 2).stat().st_mtime_ns == stamp
        path.write_text(json.dumps(rep))
        later = path.stat().st_mtime_ns + 10**9
        os.utime(tmp_path / "spine.json", ns=(later, later))
        again = track.track_results(tmp_path, spine_init=True)
    assert [r.getMessage() for r in caplog.records] == [again["started_over"]]
    assert "spine.json changed" in again["started_over"] and track.tracked_path(tmp_path, 2).stat().st_mtime_ns != stamp


def test_cli_prediction_only_never_starts_from_the_spine(tmp_path, monkeypatch, capsys, caplog):
    from pipeline import track

    t = _sphere_results(tmp_path, frames=3)
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    assert main(["-q", "track", str(tmp_path), "--spine-init", "--prediction-only"]) == 2
    assert "exclude each other" in capsys.readouterr().err and not (tmp_path / "tracked").exists()
    with caplog.at_level("WARNING", logger="pipeline.track"):
        assert main(["-q", "track", str(tmp_path), "--prediction-only", "--workers", "0"]) == 0
    assert not any("no effect" in r.getMessage() for r in caplog.records)  # a spine is there: the option acts
    rep = json.loads((tmp_path / "tracked" / "track.json").read_text())
    assert rep["spine_start"] == "none" and not any("spine_start_patches" in f for f in rep["frames"].values())
    (tmp_path / "spine.json").write_text('{"frames": 3}')
    assert main(["-q", "track", str(tmp_path), "--workers", "0"]) == 0  # the default: choose
    rep = json.loads((tmp_path / "tracked" / "track.json").read_text())
    assert rep["spine_start"] == "choose" and all("spine_start_patches" in rep["frames"][k] for k in ("0", "2"))


@pytest.mark.parametrize("flag", ["--spine-init", "--prediction-only"])
def test_cli_spine_options_without_a_spine_say_so(tmp_path, caplog, flag):
    """Without a spine.json, --spine-init and --prediction-only have nothing to act on: one warning, tracking runs."""
    _sphere_results(tmp_path, frames=3)
    with caplog.at_level("WARNING", logger="pipeline.track"):
        assert main(["-q", "track", str(tmp_path), flag, "--workers", "0"]) == 0
    said = [r.getMessage() for r in caplog.records if "no effect" in r.getMessage()]
    assert len(said) == 1 and f"({flag}) has no effect" in said[0] and "spine.json" in said[0]
    rep = json.loads((tmp_path / "tracked" / "track.json").read_text())
    assert rep["spine_start"] == "none" and len(rep["frames"]) == 3


def test_start_for_computes_only_the_start_it_uses():
    from pipeline.track_frames import start_for as _start_for

    def unused(*a):
        raise AssertionError("computed and thrown away")

    prev, before = np.zeros((4, 3)), (1, np.ones((4, 3)))
    skinned = lambda k, kp, p: p + 2.0  # noqa: E731
    start, share = _start_for(3, 2, prev, before, None, None, None, predict=unused, init_for=skinned, choose=None)
    assert np.array_equal(start, prev + 2.0) and share is None  # --spine-init: no prediction
    start, share = _start_for(3, 2, prev, before, None, None, None, predict=lambda p, b, s: p - b, init_for=None,
                              choose=unused)
    assert np.array_equal(start, -np.ones((4, 3))) and share is None
    assert _start_for(5, 2, prev, before, None, None, None, predict=unused, init_for=None, choose=None) == (None, None)
    picked = _start_for(3, 2, prev, before, None, "pts", "nrm", predict=lambda p, b, s: p - b, init_for=skinned,
                        choose=lambda c, x, n: (c[int(x == "pts")], 1.0))
    assert np.array_equal(picked[0], prev + 2.0) and picked[1] == 1.0


def test_a_patch_out_of_reach_may_start_where_the_limb_slowed_or_stopped():
    """A sphere of radius 60 mm stepping 150 mm a frame stops (or halves its step): the prediction and the
    spine's skinned step are both out of the gate's (10 mm) reach of the data on every patch, so before
    the slowed starts the frame started 75..150 mm off; it now starts from the previous frame itself (or
    half the step), exactly."""
    from pipeline.track_frames import slowed_starts, start_for
    from pipeline.tracking import choose_start
    from pipeline.tracking_patches import surface_patches

    t = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    v, f = np.asarray(t.vertices, float), np.asarray(t.faces)
    patches, _ = surface_patches(v, f, 30.0)
    step = np.array([150.0, 0.0, 0.0])
    before = (1, v - step)

    def predict(p, b, s):
        return p + (p - b)

    def choose(cands, x, n):
        start, chosen = choose_start(cands, x, n, f, patches, gate=10.0, smoothing=0)
        return start, float(np.mean(chosen == 1))

    for data, want in ((v, v), (v + step / 2, v + step / 2)):
        start, share = start_for(3, 2, v, before, None, data, t.vertex_normals, predict=predict,
                                 init_for=lambda k, kp, p: p + [0.0, 150.0, 0.0], choose=choose)
        np.testing.assert_allclose(start, want, rtol=0, atol=1e-12)
        assert share == 0.0
    stopped, half = slowed_starts(v, v + step)
    assert np.array_equal(stopped, v) and stopped is not v
    np.testing.assert_allclose(half, v + step / 2, rtol=0, atol=1e-12)


def test_slowed_starts_invalid_input():
    from pipeline.track_frames import slowed_starts

    v = np.zeros((4, 3))
    for a, b in ((v, np.zeros((5, 3))), (np.zeros((4, 2)), np.zeros((4, 2))), (np.zeros(3), np.zeros(3)),
                 (v, np.full((4, 3), np.nan))):
        with pytest.raises(ValueError, match="previous and predicted"):
            slowed_starts(a, b)


def test_frames_tracked_without_the_slowed_starts_are_tracked_again(tmp_path, monkeypatch, caplog):
    """With a spine, track.json records the slowed starts; a tracking written before them (no such
    entry) is tracked again with one warning; without a spine it has none to record and resumes."""
    from pipeline import track

    def older(root):
        path = root / "tracked" / "track.json"
        rep = json.loads(path.read_text())
        del rep["slowed_starts"]
        path.write_text(json.dumps(rep))

    plain = _sphere_results(tmp_path / "no_spine", frames=3)
    assert track.track_results(tmp_path / "no_spine")["slowed_starts"] is False
    older(tmp_path / "no_spine")
    t = _sphere_results(tmp_path / "spine", frames=3)
    (tmp_path / "spine" / "spine.json").write_text('{"frames": 3}')
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    first = track.track_results(tmp_path / "spine")
    assert first["spine_start"] == "choose" and first["slowed_starts"] is True
    older(tmp_path / "spine")
    with caplog.at_level("WARNING", logger="pipeline.track"):
        again = track.track_results(tmp_path / "spine")
    assert "slowed_starts False -> True" in again["started_over"]
    assert [r.getMessage() for r in caplog.records] == [again["started_over"]]
    monkeypatch.setattr(track, "spine_model", lambda *a: None)
    stamp = track.tracked_path(tmp_path / "no_spine", 2).stat().st_mtime_ns
    assert "started_over" not in track.track_results(tmp_path / "no_spine") and len(plain.vertices)
    assert track.tracked_path(tmp_path / "no_spine", 2).stat().st_mtime_ns == stamp


def test_killed_worker_process_frames_are_tracked_here(tmp_path, monkeypatch, caplog):
    """A backward half whose process died (BrokenProcessPool) is tracked in this process, with one
    warning; the vertices are those of a run in order."""
    import concurrent.futures as cf
    from concurrent.futures.process import BrokenProcessPool
    from types import SimpleNamespace

    from pipeline import track

    class Killed(cf.Executor):
        def submit(self, fn, *args, **kwargs):
            fut = cf.Future()
            fut.set_exception(BrokenProcessPool("a child process terminated abruptly"))
            return fut

    class Broken(cf.Executor):  # the pool broke before: submitting fails
        def submit(self, fn, *args, **kwargs):
            raise BrokenProcessPool("a child process terminated abruptly")

    runs = {}
    for how, ex in (("in_order", None), ("killed", Killed()), ("broken", Broken())):
        t = _sphere_results(tmp_path / how)
        monkeypatch.setattr(track, "spine_model", lambda *a, t=t: (2, SimpleNamespace(vertices=t.vertices, faces=t.faces)))
        with caplog.at_level("WARNING", logger="pipeline.track"):
            rep = track.track_results(tmp_path / how, executor=ex, choose=False)
        assert list(rep["frames"]) == [str(k) for k in range(5)] and "worker_cpu_seconds" not in rep
        runs[how] = [load_mesh(track.tracked_path(tmp_path / how, k), largest=False)[0] for k in range(5)]
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == ["the second tracking process stopped",
                                                                       "the second tracking process is not available"]
    for how in ("killed", "broken"):
        for k in range(5):
            assert np.array_equal(runs[how][k], runs["in_order"][k]), (how, k)


def test_tracking_again_with_other_settings_starts_over_and_same_settings_keep_figures(tmp_path, caplog):
    from pipeline.track import track_results, tracked_path

    t = _sphere_results(tmp_path, frames=3)
    first = track_results(tmp_path, template=(t.vertices, t.faces))
    again = track_results(tmp_path, template=(t.vertices, t.faces))  # resumed: nothing fitted, figures kept
    assert again["frames"] == first["frames"] and not caplog.records
    stamp = tracked_path(tmp_path, 1).stat().st_mtime_ns
    assert json.loads((tmp_path / "tracked" / "track.json").read_text())["template_sha256"] == first["template_sha256"]
    with caplog.at_level("WARNING", logger="pipeline.track"):
        other = track_results(tmp_path, template=(t.vertices, t.faces), predict=False)
    assert len(caplog.records) == 1 and "other settings (predict True -> False)" in caplog.records[0].getMessage()
    assert other["predict"] is False and list(other["frames"]) == ["0", "1", "2"]
    assert tracked_path(tmp_path, 1).stat().st_mtime_ns != stamp  # fitted again


def test_multiview_labels_cut_the_patches_of_both_halves_and_other_labels_start_over(tmp_path, monkeypatch, caplog):
    """``labels`` (a callable of the template this call picks, or its array) reach the tracker of this process
    and the worker's half; the same labels again resume, other labels (or none) start over with one warning."""
    import concurrent.futures as cf

    from pipeline import track

    t = _sphere_results(tmp_path, frames=3)
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [1.5, 0, 0], t.faces, 1, [1.5, 0, 0]))
    (tmp_path / "spine.json").write_text('{"frames": 3}')
    built, asked = [], []
    real = track.TemplateTracker

    class Recorder(real):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            built.append(self.patches)

    monkeypatch.setattr(track, "TemplateTracker", Recorder)
    upper = np.where(t.vertices[:, 2] > 0, 0, -1)

    def labels(vertices, faces, frame):
        asked.append((frame, np.array_equal(vertices, t.vertices + [1.5, 0, 0]), len(faces)))
        return upper

    for bad in (upper[:-1], upper - 1, lambda *a: upper.astype(float)):
        with pytest.raises(ValueError, match="labels must give one integer per template vertex"):
            track.track_results(tmp_path, labels=bad)
    assert not (tmp_path / "tracked").exists()
    built.clear()
    with cf.ThreadPoolExecutor(max_workers=1) as ex:  # the frame before the reference: the worker's half
        first = track.track_results(tmp_path, labels=labels, executor=ex)
    assert asked == [(1, True, len(t.faces))] and first["patch_labels"] == "given"
    written = np.load(tmp_path / "tracked" / "labels.npy")  # the labels used, beside their digest
    assert written.dtype == np.int64 and np.array_equal(written, upper)
    from pipeline.track_frames import read_labels

    assert np.array_equal(read_labels(tmp_path, first, len(upper)), upper)
    assert len(built) == 2 and all(np.array_equal(p, built[0]) for p in built)
    assert len(set(built[0][upper == -1])) == 1 and not set(built[0][upper == -1]) & set(built[0][upper == 0])
    assert list(first["frames"]) == ["0", "1", "2"]
    stamp = track.tracked_path(tmp_path, 2).stat().st_mtime_ns
    assert track.track_results(tmp_path, labels=upper)["frames"] == first["frames"]  # the same labels: resumed
    assert track.tracked_path(tmp_path, 2).stat().st_mtime_ns == stamp
    for other in (np.where(t.vertices[:, 0] > 0, 0, -1), None):
        caplog.clear()
        with caplog.at_level("WARNING", logger="pipeline.track"):
            rep = track.track_results(tmp_path, labels=other)
        assert len(caplog.records) == 1 and "patch_labels" in caplog.records[0].getMessage()
        assert rep["patch_labels"] == (None if other is None else "given")
        assert other is None or np.array_equal(np.load(tmp_path / "tracked" / "labels.npy"), other)
    assert "patch_labels_sha256" not in rep and not (tmp_path / "tracked" / "labels.npy").exists()


def test_removing_a_tracking_removes_its_labels(tmp_path):
    """``remove_tracking`` (``stage process`` starting over) removes ``tracked/labels.npy`` with the frames and
    track.json; a file of the user's stays."""
    from pipeline.track import remove_tracking
    from pipeline.track_frames import labels_digest, read_labels, write_frame, write_labels, write_report

    t = trimesh.creation.icosahedron()
    labels = np.where(t.vertices[:, 2] > 0, 0, -1)
    write_frame(tmp_path, 0, t.vertices, t.faces)
    write_labels(tmp_path, labels)
    write_report(tmp_path, {"patch_labels": "given", "patch_labels_sha256": labels_digest(labels)})
    assert np.array_equal(read_labels(tmp_path, {"patch_labels_sha256": labels_digest(labels)}, len(labels)), labels)
    assert read_labels(tmp_path, {}, len(labels)) is None  # track.json names no labels
    (tmp_path / "tracked" / "notes.txt").write_text("the user's")
    assert "removed the frames" in remove_tracking(tmp_path)
    assert sorted(p.name for p in (tmp_path / "tracked").iterdir()) == ["notes.txt"]


def test_multiview_labels_from_the_takes_spine(tmp_path, monkeypatch, caplog):
    """``labels="spine"`` (``stage track --labels``): the template's labels from the take's spine and its own
    sections (``template_labels``) cut the patches; without a usable spine one line says so and the grid alone cuts them."""
    from pipeline import track
    from pipeline.template_labels import template_labels
    from pipeline.tracking_patches import surface_patches
    from tests.pipeline.tracking_takes import creature_spine_results

    _, F = creature_spine_results(tmp_path)
    limbs = 4  # the quadruped's
    built = []
    real = track.TemplateTracker

    class Recorder(real):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            built.append((self.template, self.patches, self.patch_size))

    monkeypatch.setattr(track, "TemplateTracker", Recorder)
    assert main(["-q", "track", str(tmp_path), "--labels", "--workers", "0"]) == 0  # `stage track --labels`
    rep = json.loads((tmp_path / "tracked" / "track.json").read_text())
    assert rep["patch_labels"] == "spine" and rep["spine_start"] == "choose" and list(rep["frames"]) == ["0", "1", "2"]
    V0, patches, size = built[0]
    ref = rep["reference_frame"]
    expected = template_labels(tmp_path, V0, F, reference=ref)
    assert len(set(expected.tolist())) == limbs + 1  # every limb and the body
    assert np.array_equal(patches, surface_patches(V0, F, size, labels=expected)[0])
    (tmp_path / "spine.json").unlink()
    with caplog.at_level("WARNING", logger="pipeline.track"):
        rep = track.track_results(tmp_path, labels="spine")
    assert rep["patch_labels"] is None
    assert any("labels='spine' (--labels) has no effect" in r.getMessage() for r in caplog.records)
    with pytest.raises(ValueError, match="labels must be 'spine'"):
        track.track_results(tmp_path, labels="heat")


def test_tracking_again_with_other_settings_removes_the_rig_built_on_the_old_frames(tmp_path, caplog):
    """A start-over removes the rig of the old frames (rig.json, GLB, BVH, segments, posed/NNNNNN.ply) in
    the same warning, which names a report still showing it; other files in rig/ stay (posed/1_user.ply too). The `track` step of
    `stage process` does the same and puts the warning in the job report."""
    from types import SimpleNamespace

    from pipeline.armature_files import armature_results, remove_armature
    from pipeline.process import ProcessParams
    from pipeline.process.steps import _step_track
    from pipeline.report import write_report
    from pipeline.run import Clock
    from pipeline.track import track_results

    t = _sphere_results(tmp_path, frames=3)
    track_results(tmp_path, template=(t.vertices, t.faces))
    armature_results(tmp_path)
    (tmp_path / "report.json").write_text("{}")
    assert '<section id="rig">' in write_report(tmp_path).read_text()
    (tmp_path / "rig" / "notes.txt").write_text("the user's")
    (tmp_path / "rig" / "posed" / "1_user.ply").write_text("the user's, a name starting with a digit")
    made = {"rig.json", "rig.glb", "rig.bvh", "segments.npy", "posed"}
    assert made <= {p.name for p in (tmp_path / "rig").iterdir()}
    caplog.clear()
    with caplog.at_level("WARNING", logger="pipeline.track"):
        rep = track_results(tmp_path, template=(t.vertices, t.faces), predict=False)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "other settings (predict True -> False)" in lines[0], lines
    assert f"removed the rig built on them ({tmp_path / 'rig'})" in lines[0]
    assert f"{tmp_path / 'report.html'} still shows it until `stage report` runs again" in lines[0]
    assert rep["started_over"] == lines[0]
    assert sorted(p.name for p in (tmp_path / "rig").iterdir()) == ["notes.txt", "posed"]
    assert [p.name for p in (tmp_path / "rig" / "posed").iterdir()] == ["1_user.ply"]
    assert remove_armature(tmp_path / "rig") is False and remove_armature(tmp_path / "no_rig") is False  # nothing left
    # the same settings again: nothing removed, nothing said
    armature_results(tmp_path)
    caplog.clear()
    track_results(tmp_path, template=(t.vertices, t.faces), predict=False)
    assert not caplog.records and (tmp_path / "rig" / "rig.glb").is_file()
    # `stage process ... steps track` (its defaults: predict on, the first frame's surface) starts over too
    warned = []
    ctx = SimpleNamespace(out=tmp_path, progress=None, report_progress=lambda *a: None, executor=None, clock=Clock(),
                          warnings=warned, keep_warning=warned.append, params=ProcessParams(), steps=("track",))
    (tmp_path / "rig" / "notes.txt").unlink()
    (tmp_path / "rig" / "posed" / "1_user.ply").unlink()
    _step_track(ctx)  # (and its default armature round, whose armature's own warnings may follow)
    assert [w for w in ctx.warnings if "other settings" in w] == ctx.warnings[:1] and "predict False -> True" in ctx.warnings[0]
    assert "removed the rig built on them" in ctx.warnings[0] and not (tmp_path / "rig").exists()


def test_multiview_colour_tracks_follow_a_turn_the_surfaces_cannot_see(tmp_path):
    """A sphere turning 2 degrees a frame (5.2 mm at the equator) has the same surface every frame:
    closest-point pairs leave every vertex where it was. The per-camera colour tracks (the images of
    the take that process.json names) follow the turn: measured mean error 1.0..4.8 mm over
    frames 1..5 with the windows warped by the frame's start (0.25..0.20 of the error without them,
    4.1..20.5 mm; 1.0..3.7 with translated windows)."""
    from pipeline.track import track_results

    res, truth = turning_sphere_results(tmp_path)
    errors = {}
    for colour in (False, True):
        if colour:  # the command line's opt-in
            assert main(["-q", "track", str(res), "--colour", "--workers", "0"]) == 0
            rep = json.loads((res / "tracked" / "track.json").read_text())
        else:
            rep = track_results(res)
        assert rep["colour_tracks"] is colour
        assert all(("colour_tracks" in rep["frames"][str(k)]) is colour for k in range(1, 6))
        tracked = [load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(6)]
        errors[colour] = np.array([np.linalg.norm(v - t, axis=1).mean() for v, t in zip(tracked, truth)])
        (res / "tracked").rename(tmp_path / f"tracked_{colour}")
    assert np.allclose(errors[False][1:], np.linalg.norm(truth[1:] - truth[0], axis=2).mean(1), rtol=0.05)  # does not move
    assert np.all(errors[True][1:] <= 0.35 * errors[False][1:]) and errors[True][-1] <= 0.25 * errors[False][-1], errors


def test_multiview_colour_tracks_without_the_take_or_masks_are_off(tmp_path):
    """process.json names a take without masks, or a take that is gone: tracking runs on the surfaces alone."""
    from pipeline.track import track_results
    from stage.store import TakeReader

    res, _ = turning_sphere_results(tmp_path, frames=3, size=(160, 120))
    take = Path(json.loads((res / "process.json").read_text())["take"])
    with TakeReader(take) as rd:
        rd.derived_path.unlink()  # the keyed masks
    rep = track_results(res, colour=True)
    assert rep["colour_tracks"] is False and sorted(rep["frames"]) == ["0", "1", "2"]
    take.unlink()
    (res / "tracked").rename(tmp_path / "first")
    assert track_results(res, colour=True)["colour_tracks"] is False


def test_agreeing_rays_equal_a_per_vertex_reference():
    """Vectorised ray check against a per-vertex loop (least-squares point of the rays, 3x median)."""
    from pipeline.track_colour import agreeing_rays as _agreeing_rays

    rng = np.random.default_rng(4)
    n = 40
    truth = rng.normal(size=(n, 3)) * 100
    idx = np.concatenate([np.arange(n), np.arange(0, n, 2), np.arange(0, n, 3), [7]])  # 1..3 rays a vertex
    rays = rng.normal(size=(len(idx), 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    targets = truth[idx] + rng.normal(size=(len(idx), 3)) * 0.5 + rays * rng.uniform(-50, 50, (len(idx), 1))
    targets[0] += 30.0  # a track off its vertex's two other rays (vertex 0 has three)
    ki, kt, kr = _agreeing_rays(idx, targets, rays, n)
    dist = {}
    for v in np.unique(idx):
        t = np.flatnonzero(idx == v)
        if len(t) < 2:
            continue
        P = [np.eye(3) - np.outer(rays[j], rays[j]) for j in t]
        x = np.linalg.solve(sum(P), sum(p @ targets[j] for p, j in zip(P, t)))
        for p, j in zip(P, t):
            dist[j] = np.linalg.norm(p @ (x - targets[j]))
    med = np.median(list(dist.values()))
    keep = sorted(j for j, d in dist.items() if d <= 3 * med)
    assert np.array_equal(ki, idx[keep]) and np.allclose(kt, targets[keep]) and np.allclose(kr, rays[keep])
    assert 0 not in keep and 5 not in keep and len(keep) > 0.6 * len(idx)  # 5: vertex 5's one ray


def test_multiview_colour_halves_in_a_worker_process_equal_the_frames_tracked_in_order(tmp_path, monkeypatch):
    """With colour tracks, the backward half tracked in another process (which opens the take itself)
    gives the same vertices as tracking in order."""
    import concurrent.futures as cf
    import multiprocessing
    from types import SimpleNamespace

    from pipeline import track

    res, _ = turning_sphere_results(tmp_path, frames=5, size=(160, 120))
    V0, F0 = load_mesh(res / "meshes" / "frame_000002.ply", largest=False)
    monkeypatch.setattr(track, "spine_model", lambda *a: (2, SimpleNamespace(vertices=V0, faces=F0)))
    runs = {}
    for how in ("in_order", "pool"):
        if how == "pool":
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver")) as ex:
                rep = track.track_results(res, colour=True, executor=ex, choose=False)
        else:
            rep = track.track_results(res, colour=True, choose=False)
        assert rep["reference_frame"] == 2 and all("colour_tracks" in rep["frames"][str(k)] for k in (0, 1, 3, 4))
        runs[how] = [load_mesh(res / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(5)]
        (res / "tracked").rename(tmp_path / how)
    assert all(np.array_equal(a, b) for a, b in zip(runs["pool"], runs["in_order"]))


def test_multiview_colour_tracks_open_the_take_once_in_this_process(tmp_path, monkeypatch):
    """Both halves tracked here (reference frame 1 of 3): the take is opened once, for knowing that
    colour tracks are available and for following them (it was opened for each)."""
    from types import SimpleNamespace

    import stage.store
    from pipeline import track

    opened = []

    class Counting(stage.store.TakeReader):
        def __init__(self, path, *args, **kwargs):
            opened.append(path)
            super().__init__(path, *args, **kwargs)

    res, _ = turning_sphere_results(tmp_path, frames=3, size=(160, 120))
    V0, F0 = load_mesh(res / "meshes" / "frame_000001.ply", largest=False)
    monkeypatch.setattr(track, "spine_model", lambda *a: (1, SimpleNamespace(vertices=V0, faces=F0)))
    monkeypatch.setattr(stage.store, "TakeReader", Counting)
    rep = track.track_results(res, colour=True, choose=False)
    assert rep["colour_tracks"] is True and all("colour_tracks" in rep["frames"][str(k)] for k in (0, 2))
    assert len(opened) == 1


def test_multiview_colour_tracks_skip_an_unreadable_view_with_one_warning(tmp_path, caplog):
    """A camera whose mask cannot be read (truncated dataset: IndexError; corrupt image: TakeError)
    on some frames gives no colour tracks there, with one warning for that camera; the other cameras'
    tracks are those of a run without it."""
    import logging

    from pipeline.track_colour import colour_cameras as _colour_cameras
    from pipeline.track_colour import multiview_tracks_for as _multiview_tracks_for
    from stage.store import TakeError, TakeReader

    res, _ = turning_sphere_results(tmp_path, frames=3, size=(160, 120))
    V0, F0 = load_mesh(res / "meshes" / "frame_000000.ply", largest=False)
    take = Path(json.loads((res / "process.json").read_text())["take"])

    class Flaky:  # a reader whose mask of one camera fails from frame 1 on
        def __init__(self, rd, bad, error):
            self._rd, self._bad, self._error = rd, bad, error

        def __getattr__(self, name):
            return getattr(self._rd, name)

        def mask(self, cam_id, r):
            if cam_id == self._bad and r >= 1:
                raise self._error
            return self._rd.mask(cam_id, r)

    with TakeReader(take) as rd:
        cams = _colour_cameras(rd)
        bad = sorted(cams)[0]
        rest = {c: cam for c, cam in cams.items() if c != bad}
        want = [_multiview_tracks_for(rd, rest, F0, 2.0)(k, k - 1, V0, None, None) for k in (1, 2)]
        for error in (IndexError("mask row 1 out of range"), TakeError("corrupt JPEG")):
            caplog.clear()
            tracks_for = _multiview_tracks_for(Flaky(rd, bad, error), cams, F0, 2.0)
            with caplog.at_level(logging.WARNING, logger="pipeline.track"):
                got = [tracks_for(k, k - 1, V0, None, None) for k in (1, 2)]
            lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
            assert len(lines) == 1 and bad in lines[0] and str(error) in lines[0], lines
            for g, w in zip(got, want):
                assert len(g[0]) > 0 and all(np.array_equal(a, b) for a, b in zip(g, w))


def test_multiview_shape_memory_in_both_halves(tmp_path, monkeypatch, caplog):
    """``shape_memory=True`` (``--shape-memory``): the rigid prior keeps the previous frame's shape
    (``prior: previous`` in track.json), in the backward half's worker process too (the same
    vertices as in order, exactly), the moving sphere followed within 0.5 mm of its radius on
    average; tracking again without it starts over with one warning; a non-bool is refused."""
    import concurrent.futures as cf
    import multiprocessing

    from pipeline import track

    t = trimesh.creation.icosphere(subdivisions=3, radius=60.0)
    monkeypatch.setattr(track, "spine_model", _fake_spine(t.vertices + [6.0, 0, 0], t.faces, 3, [2.0, 0, 0]))
    runs = {}
    for how in ("in_order", "pool"):
        root = tmp_path / how
        for k in range(7):
            atomic_write_bytes(root / "meshes" / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [2.0 * k, 0, 0], t.faces))
        (root / "spine.json").write_text('{"frames": 7}')
        if how == "pool":
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver")) as ex:
                rep = track.track_results(root, executor=ex, choose=False, shape_memory=True)
            assert "worker_cpu_seconds" in rep
        else:
            rep = track.track_results(root, choose=False, shape_memory=True)
        assert rep["prior"] == "previous" and rep["reference_frame"] == 3
        runs[how] = [load_mesh(root / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(7)]
    for k in range(7):
        assert np.array_equal(runs["pool"][k], runs["in_order"][k]), k
        assert np.abs(np.linalg.norm(runs["pool"][k] - [2.0 * k, 0, 0], axis=1) - 60.0).mean() < 0.5
    with caplog.at_level("WARNING", logger="pipeline.track"):
        other = track.track_results(tmp_path / "in_order", choose=False)
    assert other["prior"] == "round"
    assert len(caplog.records) == 1 and "prior 'previous' -> 'round'" in caplog.records[0].getMessage()
    # the prior changes the backward half's vertices: so the worker's equal ones were tracked with it
    rounds = [load_mesh(tmp_path / "in_order" / "tracked" / f"{k:06d}.ply", largest=False)[0] for k in range(3)]
    assert all(np.abs(r - v).max() > 1e-9 for r, v in zip(rounds, runs["pool"][:3]))
    with pytest.raises(ValueError, match="shape_memory"):
        track.track_results(tmp_path / "in_order", shape_memory="yes")


def test_cli_shape_memory_says_so_and_records_the_prior(tmp_path, capsys):
    """``stage track RESULTS_DIR --shape-memory``: track.json's prior is "previous" and the summary
    says shape memory is on; without the flag the prior is "round" and nothing is said of it."""
    meshes = tmp_path / "meshes"
    t = trimesh.creation.icosphere(subdivisions=2, radius=60.0)
    for k in range(3):
        atomic_write_bytes(meshes / f"frame_{k:06d}.ply", ply_bytes(t.vertices + [2.0 * k, 0, 0], t.faces))
    assert main(["track", str(tmp_path), "--shape-memory", "--workers", "0", "--no-progress"]) == 0
    assert "shape memory: on" in capsys.readouterr().out
    assert json.loads((tmp_path / "tracked" / "track.json").read_text())["prior"] == "previous"
    assert main(["track", str(tmp_path), "--workers", "0", "--no-progress"]) == 0
    assert "shape memory" not in capsys.readouterr().out
    assert json.loads((tmp_path / "tracked" / "track.json").read_text())["prior"] == "round"
