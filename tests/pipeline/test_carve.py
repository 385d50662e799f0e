"""``stage track --carve``: surfaces carved across time with the tracked motion (:mod:`pipeline.carve`).

The results directory is the turning sphere of ``tests/pipeline/test_track.py`` (6 dome cameras,
its true masks in the take, the same icosphere as every frame's surface) with a grid: the carved
surfaces come from the take's masks and calibration alone, so their distance to the true sphere
says that both were read right. Accuracy of the carving itself: ``test_temporal_hull.py``; on the
simulated creatures: docs/tracking.md.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.carve import CarveError, carve_results, carved_path, track_with_carving
from pipeline.meshio import load_mesh
from pipeline.volume import Grid
from stage.cli import main
from tests.pipeline.tracking_takes import turning_sphere_results

CENTRE, RADIUS = np.array([0.0, 0.0, 300.0]), 150.0


def _results(root, frames=4, calib_meta=None):
    res, _ = turning_sphere_results(root, frames=frames, size=(160, 120), calib_meta=calib_meta)
    grid = Grid(lo=CENTRE - 200, shape=(40, 40, 40), voxel=10.0)
    (res / "grid.json").write_text(json.dumps(grid.to_dict()))
    return res


def _sphere_error(path):
    v, _ = load_mesh(path, largest=False)
    return np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS) / 10.0  # voxels


def test_cli_carve_tracks_the_carved_surfaces_and_records_them(tmp_path, capsys):
    res = _results(tmp_path)
    assert main(["track", str(res), "--carve", "1", "--workers", "0", "--no-progress", "--armature-rounds", "0"]) == 0
    assert "surfaces: carved across time" in capsys.readouterr().out
    rep = json.loads((res / "tracked" / "track.json").read_text())
    carve = json.loads((res / "carved" / "carve.json").read_text())
    assert rep["surfaces"] == "carved" and sorted(rep["frames"]) == ["0", "1", "2", "3"]
    assert rep["surfaces_sha256"] == hashlib.sha256((res / "carved" / "carve.json").read_bytes()).hexdigest()
    assert rep["template"] == str(carved_path(res, 0))
    for k in range(4):
        err = _sphere_error(carved_path(res, k))
        # measured 0.24 / 1.18 voxels (mean / max; 6 cameras at 160x120, a pixel about a voxel); masks or
        # cameras read wrong would be many voxels off
        assert err.mean() < 0.35 and err.max() < 1.5, (k, err.mean(), err.max())
        assert carve["frames"][str(k)]["vertices"] > 100


def _set_hull_margin(res, margin):
    process = json.loads((res / "process.json").read_text())
    (res / "process.json").write_text(json.dumps({**process, "params": {"silhouette_margin": margin}}))


def test_carving_grows_the_silhouettes_by_the_margin_process_carved_with(tmp_path):
    """With a calibration that says nothing of its accuracy (imported), ``process.json``'s
    ``silhouette_margin`` (pixels) holds for every frame's silhouettes: the carved sphere grows by
    about that many pixels' footprint."""
    from pipeline.track import track_results

    res = _results(tmp_path, frames=3, calib_meta={})
    track_results(res)
    radius = {}
    for margin in (0, 2):
        _set_hull_margin(res, margin)
        assert set(carve_results(res)["margin_px"].values()) == {margin}
        v, _ = load_mesh(carved_path(res, 1), largest=False)
        radius[margin] = np.linalg.norm(v - CENTRE, axis=1).mean()
    # measured: 2 px grow the mean radius by 19.7 mm (2 px at the sphere's centre are 22..27 mm from these cameras)
    assert 15.0 < radius[2] - radius[0] < 35.0, radius


@pytest.mark.parametrize("meta, expected", [
    ({"exact": True}, [0.0] * 6),  # the simulator's true cameras: the silhouettes as keyed
    # twice the held-out RMS where the calibration measured it, at most the hull's margin, that margin where it did not
    ({"held_out_rms_px": {"cam00": 0.25, "cam01": 0.5, "cam02": 2.0}}, [0.5, 1.0, 2.0, 2.0, 2.0, 2.0]),
])
def test_each_camera_grows_by_what_its_calibration_says_of_itself(tmp_path, meta, expected):
    from pipeline.track import track_results

    res = _results(tmp_path, frames=2, calib_meta=meta)
    _set_hull_margin(res, 2)
    track_results(res)
    got = carve_results(res)["margin_px"]
    assert list(got) == [f"cam{i:02d}" for i in range(6)]
    assert list(got.values()) == expected


def test_carving_in_a_worker_process_equals_carving_here(tmp_path):
    """``carve_results(executor=)`` carves the second half of the frames in a worker process: the
    same surfaces, and one report with every frame."""
    import concurrent.futures as cf
    import multiprocessing

    from pipeline.track import track_results

    res = _results(tmp_path, frames=4)
    track_results(res)
    carve_results(res)
    here = {k: carved_path(res, k).read_bytes() for k in range(4)}
    for k in range(4):
        carved_path(res, k).unlink()
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver")) as ex:
        rep = carve_results(res, executor=ex)
    assert sorted(rep["frames"]) == ["0", "1", "2", "3"]
    assert all(carved_path(res, k).read_bytes() == here[k] for k in range(4))


def test_carving_again_resumes_and_other_motion_starts_over(tmp_path):
    res = _results(tmp_path, frames=3)
    from pipeline.track import track_results

    track_results(res)
    first = carve_results(res)
    stamps = [carved_path(res, k).stat().st_mtime_ns for k in range(3)]
    assert carve_results(res)["frames"] == first["frames"]
    assert [carved_path(res, k).stat().st_mtime_ns for k in range(3)] == stamps  # kept, not carved again
    track_results(res, gate=5.0)  # another tracking: another motion
    again = carve_results(res)
    assert again["tracked_sha256"] != first["tracked_sha256"]
    assert all(carved_path(res, k).stat().st_mtime_ns != s for k, s in zip(range(3), stamps))


def test_carving_without_tracking_or_take_is_one_clear_error(tmp_path, capsys):
    res = _results(tmp_path, frames=3)
    with pytest.raises(ValueError, match="run `stage track` first"):
        carve_results(res)
    from pipeline.track import remove_tracking, track_results

    track_results(res)
    take = Path(json.loads((res / "process.json").read_text())["take"])
    take.rename(tmp_path / "elsewhere.h5")
    with pytest.raises(ValueError, match="is not there"):
        carve_results(res)
    assert main(["-q", "track", str(res), "--carve", "1", "--workers", "0"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--carve" in err[0] and "is not there" in err[0], err
    (tmp_path / "elsewhere.h5").rename(take)
    (res / "tracked" / "000001.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")  # truncated
    with pytest.raises(ValueError, match="000001.ply: unreadable"):
        carve_results(res)
    track_results(res)  # tracked again: the frame is whole
    carve_results(res)
    assert "carved" in remove_tracking(res) and not (res / "carved").exists()  # process starting over removes them


def test_invalid_input(tmp_path):
    res = _results(tmp_path, frames=2)
    with pytest.raises(ValueError, match="window"):
        carve_results(res, window=0)
    with pytest.raises(ValueError, match="surfaces"):
        from pipeline.track import track_results

        track_results(res, surfaces="hull")
    with pytest.raises(FileNotFoundError, match="stage track --carve"):
        track_results(res, surfaces="carved")
    assert main(["-q", "track", str(res), "--carve", "-1"]) != 0
    assert main(["-q", "track", str(res), "--carve-margin", "1"]) != 0  # without --carve
    assert main(["-q", "track", str(res), "--carve", "1", "--carve-margin", "-1"]) != 0
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="rounds"):
            track_with_carving(res, bad)
    # a carving that cannot run (the take is gone) is a CarveError after the first tracking, nothing carved
    process = json.loads((res / "process.json").read_text())
    (res / "process.json").write_text(json.dumps({**process, "take": str(tmp_path / "gone.h5")}))
    with pytest.raises(CarveError, match="gone.h5"):
        track_with_carving(res, 1)
    assert not (res / "carved").exists() and (res / "tracked" / "000001.ply").is_file()


def test_cli_carve_margin_is_recorded(tmp_path):
    res = _results(tmp_path, frames=2)
    assert main(["-q", "track", str(res), "--carve", "1", "--carve-margin", "0.5", "--workers", "0",
                 "--armature-rounds", "0"]) == 0
    assert json.loads((res / "carved" / "carve.json").read_text())["margin_px"] == 0.5


def test_an_unreadable_mask_carves_nothing_with_one_warning(tmp_path, monkeypatch, caplog):
    """A camera whose mask cannot be read on some frames (truncated masks, corrupt data) gives those
    views no say, with one warning for that camera; every frame is still carved."""
    import logging

    from pipeline.track import track_results
    from stage.store import TakeError, TakeReader

    res = _results(tmp_path, frames=3)
    track_results(res)
    real = TakeReader.mask

    def flaky(self, cam_id, r):
        if cam_id == "cam00" and r >= 1:
            raise TakeError("corrupt mask")
        return real(self, cam_id, r)

    monkeypatch.setattr(TakeReader, "mask", flaky)
    with caplog.at_level(logging.WARNING, logger="pipeline.carve"):
        rep = carve_results(res)
    lines = [r.getMessage() for r in caplog.records if r.name == "pipeline.carve"]
    assert len(lines) == 1 and "cam00" in lines[0] and "corrupt mask" in lines[0], lines
    assert sorted(rep["frames"]) == ["0", "1", "2"] and all(f["vertices"] > 100 for f in rep["frames"].values())


def test_frames_whose_carved_surface_is_left_out_are_said_once_with_their_frame_sets(tmp_path, monkeypatch, caplog):
    """Frames 1 and 2 carve no surface: one warning says so with the frame sets (the ``track`` step's, and so a
    job's: ``track: carving: ...``), not one per frame; each frame's figures keep theirs, the log has each at DEBUG;
    a carving that resumes says nothing of the frames it keeps."""
    import logging

    import pipeline.surface
    from pipeline.track import track_results

    res = _results(tmp_path, frames=4)
    track_results(res)
    real = pipeline.surface.surface_from_field
    carving = [0]

    def empty_at_1_and_2(*a, **k):  # (the frames are carved in order: 0, 1, 2, 3)
        carving[0] += 1
        if carving[0] in (2, 3):
            raise pipeline.surface.EmptySurfaceError("nothing inside the carved field")
        return real(*a, **k)

    monkeypatch.setattr(pipeline.surface, "surface_from_field", empty_at_1_and_2)
    with caplog.at_level(logging.DEBUG, logger="pipeline.carve"):
        rep = carve_results(res)
    said = [r.getMessage() for r in caplog.records if r.name == "pipeline.carve" and r.levelno == logging.WARNING]
    left_out = "nothing inside the carved field; the carved surface is left out"
    assert said == [f"carving: {left_out} (2 frame sets: 1, 2)"], said
    assert [rep["frames"][str(k)].get("warnings") for k in range(4)] == [None, [left_out], [left_out], None]
    assert [f"frame set {k}: {left_out}" for k in (1, 2)] == [
        r.getMessage() for r in caplog.records if r.name == "pipeline.carve" and r.levelno == logging.DEBUG]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.carve"):
        carve_results(res)
    assert not caplog.records


def test_track_with_carving_sums_every_workers_cpu_seconds(tmp_path, monkeypatch):
    """The ``track`` step's CPU seconds: every tracking's and carving's task in another process, not the last's."""
    import pipeline.carve as carve
    import pipeline.track as track

    trackings = iter([1.5, 0.25, 2.0])
    monkeypatch.setattr(track, "track_results", lambda *a, **k: {"frames": {}, "worker_cpu_seconds": next(trackings)})
    monkeypatch.setattr(carve, "carve_results", lambda *a, **k: {"worker_cpu_seconds": 0.5})
    rep = track_with_carving(tmp_path, 2)
    assert rep["worker_cpu_seconds"] == pytest.approx(1.5 + 0.5 + 0.25 + 0.5 + 2.0, abs=1e-9)
    assert rep["frames"] == {}
