"""The whole pipeline on a simulated take: keying -> hull -> surface -> spine, resumable."""

import contextlib
import json
import threading

import numpy as np
import pytest

from fake_cameras.evaluate import evaluate_spine
from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from pipeline.process import ProcessError, ProcessParams, process_take


@pytest.fixture(scope="module")
def starfish(tmp_path_factory):
    sim = simulate_take("starfish", n_cameras=8, frames=8, size=(640, 480), seed=3)
    path = record_take(sim, tmp_path_factory.mktemp("take") / "starfish.h5")
    return sim, path


@pytest.fixture(scope="module")
def processed(starfish, tmp_path_factory):
    sim, path = starfish
    out = tmp_path_factory.mktemp("results")
    seen = []
    res = process_take(path, out, progress=lambda s, d, t: seen.append((s, d, t)))
    return res, out, seen


def test_pipeline_end_to_end(starfish, processed):
    sim, _ = starfish
    res, out, seen = processed
    assert res.frames == sim.n_frames and res.empty_frames == []
    spine = json.loads((out / "spine.json").read_text())
    assert spine["format"] == "capture-stage/spine@1" and len(spine["frames"]) == sim.n_frames
    axes = {n: np.stack([a[n] for a in sim.axes]) for n in sim.limb_names}
    acc = evaluate_spine(spine, sim.tip_array(), axes, list(sim.limb_names))
    # stated tolerances: K right, tips within 3 % of size, identities consistent
    assert acc["K"] == len(sim.limb_names) == 5
    assert acc["tip_within_tol"] >= 0.9
    assert acc["identity_consistent"] == 1.0
    assert acc["axis_error_mean"] <= 0.025  # measured 0.019 (8 cameras, 640x480)
    # meshes are watertight and per-frame quality is reported
    rep = json.loads((out / "report.json").read_text())
    assert all(f["quality"]["watertight"] for f in rep["per_frame"])
    assert rep["limb_count"] == {"K": 5, "rule": "mode"}  # how K was chosen (a borderline count says so here)
    assert {s for s, _, _ in seen} >= {"key", "surface", "skeleton", "spine"}
    # summed as a job sums them: the total counts every step from the first report on, so the run
    # reads done == total once, at its end (never n/n while steps are still to come)
    latest, sums = {}, []
    for s, d, t in seen:
        latest[s] = (d, t)
        sums.append((sum(v[0] for v in latest.values()), sum(v[1] for v in latest.values())))
    first_work = next(t for d, t in sums if d > 0)
    assert sums[-1][0] == sums[-1][1] == first_work == 8 * 8 + 8 + 8 + 8 + 1  # key, box, surface, skeleton, spine
    assert all(d < t for d, t in sums[:-1]), [x for x in zip(seen, sums) if x[1][0] >= x[1][1]]
    assert [d for d, _ in sums] == sorted(d for d, _ in sums)  # done never goes back


def test_resume_gives_the_same_spine(starfish, processed, tmp_path):
    _, path = starfish
    _, out, _ = processed
    # a run interrupted after the surfaces of some frames: delete the rest, re-run
    import shutil

    out2 = tmp_path / "again"
    shutil.copytree(out, out2)
    for sub in ("skeletons",):
        shutil.rmtree(out2 / sub)
    for f in sorted((out2 / "frames").glob("frame_*.json"))[3:]:
        f.unlink()
    (out2 / "spine.json").unlink()
    # process.json records the results dir's take: same take, same params -> resume
    res = process_take(path, out2)
    assert json.loads((out2 / "spine.json").read_text())["frames"] == json.loads((out / "spine.json").read_text())["frames"]
    assert res.frames == 8


def test_resume_recomputes_skeleton_records_of_an_older_format(starfish, processed, tmp_path):
    """A record written before alternates existed (no ``format``, no ``n_alternates``: it would
    read as "no alternates"), an empty one and a cut one are recomputed on a resume: each comes
    back in the current format with the arrays of the fresh run's record, and the spine is the
    fresh run's. (The starfish has no alternates; their round trip through a record is tested in
    tests/pipeline/test_spine.py.)"""
    import shutil

    _, path = starfish
    _, out, _ = processed
    out2 = tmp_path / "again"
    shutil.copytree(out, out2)
    records = sorted((out2 / "skeletons").glob("frame_*.npz"))
    old, empty, cut = records[0], records[1], records[2]
    with np.load(old) as z:
        arrays = {k: z[k] for k in z.files if k not in ("format", "n_alternates") and not k.startswith("alternate")}
    np.savez(old, **arrays)
    empty.write_bytes(b"")
    cut.write_bytes(cut.read_bytes()[:100])
    (out2 / "spine.json").unlink()
    process_take(path, out2)
    for rec in (old, empty, cut):
        with np.load(rec) as z, np.load(out / "skeletons" / rec.name) as fresh:
            assert "format" in z.files and sorted(z.files) == sorted(fresh.files), rec.name
            assert all(np.array_equal(z[k], fresh[k]) for k in fresh.files), rec.name
    assert json.loads((out2 / "spine.json").read_text())["frames"] == json.loads((out / "spine.json").read_text())["frames"]


def test_invalid_input(starfish, tmp_path):
    _, path = starfish
    with pytest.raises(ValueError, match="steps"):
        process_take(path, tmp_path / "o", steps=("carve",))
    with pytest.raises(ValueError, match="params"):
        process_take(path, tmp_path / "o", params={"resolution": 3})
    with pytest.raises(ValueError, match="warn must be a callable"):
        process_take(path, tmp_path / "o", warn=["a list"])
    from pipeline.process.records import frame_said, said_fields, skeleton_said

    for said in ("mask all foreground", [("mask all foreground",)], [(None, None)]):
        with pytest.raises(ValueError, match="said must be a list"):
            said_fields(said)
    for k in ("1", 1.0, True):
        with pytest.raises(ValueError, match="k must be an integer"):
            frame_said(tmp_path, k)
        with pytest.raises(ValueError, match="k must be an integer"):
            skeleton_said(tmp_path, k)
    with pytest.raises(FileNotFoundError):
        process_take(tmp_path / "missing.h5", tmp_path / "o")
    with pytest.raises(ValueError, match="out"):
        process_take(path, path)
    sim = simulate_take("starfish", n_cameras=4, frames=2, size=(160, 120), seed=1)
    nocal = record_take(sim, tmp_path / "nocal.h5", with_calibration=False)
    with pytest.raises(ProcessError, match="no calibration"):
        process_take(nocal, tmp_path / "o2")
    with pytest.raises(ProcessError, match="surfaces are missing"):
        process_take(path, tmp_path / "o3", steps=("spine",))
    assert ProcessParams().resolution is None  # from the rig


def test_empty_take_reports_no_subject(tmp_path):
    sim = simulate_take("empty", n_cameras=4, frames=2, size=(320, 240), seed=0)
    path = record_take(sim, tmp_path / "empty.h5")
    with pytest.raises(ValueError, match="no subject|backdrop|mask"):
        process_take(path, tmp_path / "out")


def test_rgbd_take_fuses_depth(tmp_path):
    """Simulated RGB-D cameras: the surface is the zero level set of the depth TSDF intersected
    with the hull, and lies within 2 voxels of the true creature surface."""
    sim = simulate_take("starfish", n_cameras=8, frames=2, size=(320, 240), seed=1, depth=True)
    path = record_take(sim, tmp_path / "rgbd.h5")
    out = tmp_path / "out"
    # keying at 320x240 loses thin limbs (see test_keying); the GT masks isolate the depth path
    from stage.store import write_masks

    for c, name in enumerate(sim.calibration.names):
        write_masks(path, name, sim.masks[:, c], params={"source": "ground truth"})
    # exact masks and calibration: no silhouette margin (the default 1 px guards real rigs'
    # sub-pixel errors; with it the hull-bound pockets grow and the 99th percentile is 2.15)
    # 56 voxels along the subject's box: about 8.4 mm, the scale the tolerance below is stated at
    # (the pockets no camera sees stay hull-bound, about 15 mm whatever the voxel)
    exact = {"resolution": 56, "silhouette_margin": 0}
    process_take(path, out, steps=("key", "surface"), params=exact)
    rep = json.loads((out / "report.json").read_text())
    assert [f["source"] for f in rep["per_frame"]] == ["depth+hull"] * 2
    grid = json.loads((out / "grid.json").read_text())
    from pipeline.results import ResultsStore

    def errors(results):
        mesh = ResultsStore(results).read_mesh(0)
        return np.abs(sim.poses[0].sdf(np.asarray(mesh.vertices))) / grid["voxel"]

    # measured: 99th percentile 1.8 voxels (hull alone: 2.0); pockets no camera sees stay hull-bound
    d = errors(out)
    assert np.percentile(d, 99) <= 2.0
    # "off" gives the hull's surface, which depth improves on
    res2 = process_take(path, tmp_path / "hull", steps=("surface",), params={**exact, "depth": "off"})
    assert json.loads((tmp_path / "hull" / "report.json").read_text())["per_frame"][0]["source"] == "hull"
    assert res2.frames == 2
    assert np.percentile(d, 95) < np.percentile(errors(tmp_path / "hull"), 95)


def test_the_blind_side_warning_names_the_support_plane_as_command_and_job_both_call_it():
    """Every camera 500 mm above a ring of 1000 mm (26.6 degrees down on the subject): the warning gives the plane
    (0, 0, 1: the cameras' side) as the support plane, which ``stage process --support-plane`` and a job's
    ``parameters.support_plane`` both are, and names neither's spelling."""
    from types import SimpleNamespace

    from calib.calibration import Calibration
    from calib.camera import Camera
    from pipeline.process.grid import blind_side_hint

    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    centres = [(1000 * np.cos(a), 1000 * np.sin(a), 500.0) for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    cal = Calibration(tuple(Camera(f"cam{i}", K, np.zeros(5), np.eye(3), -np.asarray(c), size=(32, 24))
                            for i, c in enumerate(centres)))
    w = blind_side_hint(cal, SimpleNamespace(lo=np.full(3, -100.0), hi=np.full(3, 100.0)))
    assert "at least 26.6 deg above" in w and "the support plane a b c D: 0.000 0.000 1.000 D" in w
    assert "--" not in w and "parameters" not in w


def test_support_plane_and_margin_reach_the_carver(tmp_path):
    """``stage process --support-plane A B C D --margin M``: no surface below the plane."""
    from pipeline.results import ResultsStore
    from stage.cli import main

    sim = simulate_take("starfish", n_cameras=4, frames=2, size=(160, 120), seed=1)
    path = record_take(sim, tmp_path / "take.h5")
    z_mid = float(np.mean([t[2] for t in sim.tips[0].values()]))
    args = ["process", str(path), "--until", "surface", "--workers", "0", "--no-progress", "--margin", "2"]
    assert main(args + ["--out", str(tmp_path / "free")]) == 0
    assert main(args + ["--out", str(tmp_path / "cut"), "--support-plane", "0", "0", "2", str(-2 * z_mid)]) == 0
    free, cut = ResultsStore(tmp_path / "free"), ResultsStore(tmp_path / "cut")
    voxel = json.loads((tmp_path / "cut" / "grid.json").read_text())["voxel"]
    for k in free.frames():
        a, b = free.read_mesh(k), cut.read_mesh(k)
        assert a.bounds[0, 2] < z_mid - voxel  # the creature reaches below the plane...
        # ...but its surface does not: it passes half way between the last voxel centre kept above
        # the plane and the first carved below it, so at most half a voxel below (plus smoothing)
        assert b.bounds[0, 2] >= z_mid - 0.5 * voxel - 1.0
    with pytest.raises(ValueError, match="support.plane"):
        ProcessParams(support_plane=(0, 0, 0, 1))
    assert ProcessParams(support_plane=(0, 0, 2, -4)).support_plane == (0.0, 0.0, 1.0, -2.0)


def _reference_results(sim, tmp_path, params: ProcessParams, grid_dict: dict):
    """The plain path, one call per part: key_take, then per frame set carve -> surface ->
    skeleton from files, then build_spine."""
    from pipeline.frame_skeleton import SpineParams, frame_skeleton
    from pipeline.hull import HullCarver
    from pipeline.spine import build_spine
    from pipeline.surface import surface_from_occupancy
    from pipeline.volume import Grid
    from stage.keying.take import key_take
    from stage.store import TakeReader

    ref = record_take(sim, tmp_path / "reference.h5")
    key_take(ref)
    grid = Grid.from_dict(grid_dict)
    with TakeReader(ref) as r:
        cams = list(r.cameras)
        masks = {c: r.masks(c) for c in cams}
        cal = r.calibration
    carver = HullCarver(type(cal)(tuple(cal[c] for c in cams), units=cal.units), grid)
    meshes, skeletons = [], []
    for k in range(sim.n_frames):
        hull = carver.carve([masks[c][k] for c in cams], tolerance=params.tolerance, margin=params.silhouette_margin)
        mesh = surface_from_occupancy(
            hull.occupancy, grid, taubin_iterations=params.smooth_iterations, face_budget=params.face_budget
        )
        meshes.append(mesh)
        skeletons.append(frame_skeleton(mesh.vertices, mesh.faces))
    spine = build_spine(skeletons, fps=sim.fps, units=cal.units, params=SpineParams())
    return masks, meshes, spine.to_dict()


def _same_results(path, out, reference):
    from pipeline.results import ResultsStore
    from stage.store import TakeReader

    masks, meshes, spine = reference
    with TakeReader(path) as r:
        for cam, m in masks.items():
            assert np.array_equal(r.masks(cam), m), cam
    store = ResultsStore(out)
    for k, ref in enumerate(meshes):
        mesh = store.read_mesh(k)
        assert np.array_equal(mesh.faces, ref.faces)
        np.testing.assert_allclose(mesh.vertices, ref.vertices, rtol=0, atol=1e-9)
    got = json.loads((out / "spine.json").read_text())
    want = json.loads(json.dumps(spine))
    assert got["graph"] == want["graph"]
    for a, b in zip(got["frames"], want["frames"]):
        assert a["tips"].keys() == b["tips"].keys()
        for name in a["tips"]:
            np.testing.assert_allclose(np.asarray(a["tips"][name], float), np.asarray(b["tips"][name], float), atol=1e-9)


@pytest.fixture(scope="module")
def small_processed(tmp_path_factory):
    """A smaller starfish take (6 cameras, 320x240, 4 frames: all 5 limbs found) processed as
    :func:`processed` is, for the tests that process a take again and compare: the same code
    paths at a fraction of the cost -> (sim, take, results directory)."""
    sim = simulate_take("starfish", n_cameras=6, frames=4, size=(320, 240), seed=3)
    path = record_take(sim, tmp_path_factory.mktemp("small_take") / "starfish.h5")
    out = tmp_path_factory.mktemp("small_results")
    process_take(path, out)
    assert json.loads((out / "spine.json").read_text())["meta"]["K"] == 5
    return sim, path, out


def test_fast_path_equals_the_plain_path(small_processed, tmp_path):
    """In process and on 2 worker processes, `stage process` gives the masks, meshes and
    spine of the parts called one by one."""
    import concurrent.futures as cf

    sim, path, out = small_processed
    params = ProcessParams()
    reference = _reference_results(sim, tmp_path, params, json.loads((out / "grid.json").read_text()))
    _same_results(path, out, reference)
    import multiprocessing

    pooled = record_take(sim, tmp_path / "pooled.h5")
    with cf.ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("forkserver")) as ex:
        process_take(pooled, tmp_path / "pooled", executor=ex)
    _same_results(pooled, tmp_path / "pooled", reference)


def test_masks_over_the_memory_budget_are_read_from_the_take(small_processed, tmp_path, monkeypatch):
    """Keyed masks beyond the budget kept in memory: the surface tasks read them from the take
    (as a resumed run does), with the same results."""
    import pipeline.process.steps as sp

    sim, _, out = small_processed
    monkeypatch.setattr(sp, "_KEEP_MASKS_BYTES", 1)
    seen = []
    real = sp.surface_task
    monkeypatch.setattr(sp, "surface_task", lambda *a, **k: seen.append(k.get("masks")) or real(*a, **k))
    again = record_take(sim, tmp_path / "again.h5")
    process_take(again, tmp_path / "again")
    assert seen and all(m is None for m in seen)
    for sub in ("meshes", "frames"):
        assert sorted(p.name for p in (out / sub).iterdir()) == sorted(p.name for p in (tmp_path / "again" / sub).iterdir())
    from pipeline.results import ResultsStore

    for k in range(sim.n_frames):
        a, b = ResultsStore(out).read_mesh(k), ResultsStore(tmp_path / "again").read_mesh(k)
        assert np.array_equal(a.faces, b.faces) and np.allclose(a.vertices, b.vertices, rtol=0, atol=1e-9)
    spines = [json.loads((d / "spine.json").read_text()) for d in (out, tmp_path / "again")]
    assert spines[0]["graph"] == spines[1]["graph"]


@pytest.fixture(scope="module")
def thin_tail(tmp_path_factory):
    """The thin-tail take (rendered once, cached on disk like every simulated take): its first 8
    frames (the 24 frames of docs/reconstruction.md's table cost three times as much)."""
    from fake_cameras.rigs import thin_tail_setup

    sim = simulate_take(frames=8, seed=0, **thin_tail_setup())
    return sim, record_take(sim, tmp_path_factory.mktemp("tail") / "tail.h5")


def _limbs_seen(spine: dict) -> list[int]:
    """Limbs with a tip, per frame of a spine file."""
    return [sum(v is not None for v in fr["tips"].values()) for fr in spine["frames"]]


def test_thin_tail_survives_the_default_grid(thin_tail, tmp_path):
    """The tailed quadruped (tail 36 -> 16 mm thick, about 6 px at its end) filmed by ten
    480x360 cameras, 2.6 mm a pixel at the subject: the default grid follows the pixel
    footprint (a 5.2 mm voxel), and the spine has all 6 limbs in every frame with consistent
    identities. A grid coarse enough (16.6 mm = 6.5 px voxels) loses the tail in some frames, so
    the grid is what keeps it (measured on these 8 frames: 5.6 px voxels keep it in all 8, 6 px
    lose it in 2, 6.5 px in 3, 7 px in all of them)."""
    sim, path = thin_tail
    res = process_take(path, tmp_path / "out")
    choice = json.loads((tmp_path / "out" / "process.json").read_text())["grid"]
    assert choice["source"] == "rig" and choice["limited_by"] == "pixel footprint"
    assert 2.4 < choice["pixel_footprint"] < 2.8
    assert choice["voxel"] == pytest.approx(2 * choice["pixel_footprint"], rel=0.1)
    assert res.report["grid"] == choice
    spine = json.loads((tmp_path / "out" / "spine.json").read_text())
    assert _limbs_seen(spine) == [6] * sim.n_frames
    axes = {n: np.stack([a[n] for a in sim.axes]) for n in sim.limb_names}
    acc = evaluate_spine(spine, sim.tip_array(), axes, list(sim.limb_names))
    assert acc["K"] == 6
    assert acc["identity_consistent"] == 1.0
    assert acc["tip_within_tol"] >= 0.95

    # a voxel of 6.5 pixel footprints over the same box
    coarse_res = int(np.ceil(max(choice["box"]["size"]) / (6.5 * choice["pixel_footprint"])))
    process_take(path, tmp_path / "coarse", steps=("key", "surface", "spine"), params={"resolution": coarse_res})
    coarse = json.loads((tmp_path / "coarse" / "spine.json").read_text())
    assert coarse["meta"]["K"] == 6 and min(_limbs_seen(coarse)) < 6


@pytest.fixture(scope="module")
def tail_at_4px(tmp_path_factory):
    """The thin-tail rig with 256x192 cameras: the tail's 16 mm end is about 4 pixels wide."""
    from fake_cameras.rigs import thin_tail_setup

    sim = simulate_take(frames=8, seed=0, **thin_tail_setup(size=(256, 192)))
    return sim, record_take(sim, tmp_path_factory.mktemp("tail4") / "tail.h5")


def test_a_limb_4_pixels_wide_survives_the_default_grid(tail_at_4px, tmp_path):
    """The rule's boundary: a limb the cameras resolve (at least 4 pixels wide in most views)
    survives at default settings. The tail's end (16 mm thick) is 4.1 px wide in the median
    view of every frame (4 px or more in 5-6 of the 10 views); the default voxel of two pixel
    footprints makes it under 2 voxels across, and the spine still has all 6 limbs (in every
    frame but at most one) with consistent identities."""
    from pipeline.volume import pixel_footprint

    sim, path = tail_at_4px
    tail = sim.limb_names.index("tail")
    width = 16.0 / pixel_footprint(sim.calibration, sim.tip_array()[:, tail])  # (C, F) pixels across the tail's end
    median = np.nanmedian(width, axis=0)
    assert 4.0 <= median.min() and median.max() < 4.3, median
    assert (np.mean(width >= 4.0, axis=0) >= 0.5).all()
    res = process_take(path, tmp_path / "out")
    assert res.report["grid"]["source"] == "rig"
    assert 16.0 / res.report["grid"]["voxel"] < 2.0  # the tail's end is under 2 voxels across
    spine = json.loads((tmp_path / "out" / "spine.json").read_text())
    # at the boundary the tail's end may break off in one frame, depending on where the voxel
    # grid falls (measured over grid offsets of 0, 1/4, 1/2 and 3/4 voxel: 0 or 1 frame of 8)
    assert sum(n == 6 for n in _limbs_seen(spine)) >= sim.n_frames - 1
    axes = {n: np.stack([a[n] for a in sim.axes]) for n in sim.limb_names}
    acc = evaluate_spine(spine, sim.tip_array(), axes, list(sim.limb_names))
    assert acc["K"] == 6 and acc["identity_consistent"] == 1.0 and acc["tip_within_tol"] >= 0.95


def test_steps_are_a_registry(starfish, processed, tmp_path):
    """A step registered after another runs in order on the same context; bad registrations fail."""
    import pipeline.process as sp

    _, path = starfish
    seen = []
    try:
        sp.register_step("count", lambda ctx: seen.append((ctx.take.n_sets, ctx.steps)), after="surface")
        assert sp.STEPS.index("count") == sp.STEPS.index("surface") + 1
        res = process_take(path, tmp_path / "o", steps=("count",))
        assert seen == [(8, ("count",))] and res.steps == ("count",)
    finally:
        sp.STEPS.remove("count")
    with pytest.raises(ValueError, match="name"):
        sp.register_step("not a name", lambda ctx: None)
    with pytest.raises(ValueError, match="after"):
        sp.register_step("x", lambda ctx: None, after="nothing")
    assert "count" not in sp.STEPS and "x" not in sp.STEPS


_AFTER_OPENCV_THREADS = """
import concurrent.futures as cf, multiprocessing, sys
import cv2, numpy as np
from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from pipeline.process import process_take

cv2.setNumThreads(2)  # OpenCV's thread pool running in this process before the workers start
cv2.GaussianBlur(np.zeros((2000, 2000), np.float32), (31, 31), 5)
sim = simulate_take("starfish", n_cameras=4, frames=2, size=(320, 240), seed=1)
path = record_take(sim, sys.argv[1] + "/t.h5")
for method in ("fork", "forkserver"):
    with cf.ProcessPoolExecutor(2, mp_context=multiprocessing.get_context(method)) as ex:
        process_take(path, sys.argv[1] + "/out-" + method, steps=("key", "surface"), params={"rekey": True}, executor=ex)
print("finished")
"""


def test_worker_pools_survive_opencv_threads_in_the_parent(tmp_path):
    """A parent that used OpenCV's thread pool, then a forked or forkserver pool: no deadlock
    (a forked worker hung in cv2.setNumThreads; `stage demo` calibrates before it processes)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    run = subprocess.run([sys.executable, "-c", _AFTER_OPENCV_THREADS, str(tmp_path)], capture_output=True, text=True,
                         timeout=300, env=env, cwd=tmp_path)
    assert run.returncode == 0 and "finished" in run.stdout, run.stderr[-2000:]


class _Clock:
    """The run's clocks (``time.perf_counter`` and ``time.process_time`` as ``pipeline.run.context`` reads them),
    moved only by :meth:`burn`: the process's CPU seconds count every thread of the pytest process, so a real
    clock's bounds fail whenever another test's thread is busy."""

    def __init__(self):
        self.now = 0.0
        self.lock = threading.Lock()

    def burn(self, seconds: float) -> None:
        with self.lock:
            self.now += seconds

    def perf_counter(self) -> float:
        return self.now

    process_time = perf_counter


@pytest.fixture
def clock(monkeypatch):
    import pipeline.run.context as context

    fake = _Clock()
    monkeypatch.setattr(context, "time", fake)
    return fake


def test_cpu_seconds_of_a_thread_pool_count_once_and_parts_count_apart(clock):
    """A thread pool's tasks run in this process: their CPU is the step's own, not added again as
    workers'; a part of a step (the surface step's grid) is counted on its own, not in the step.
    Exact to 1e-9 s on the fake clock."""
    import concurrent.futures as cf
    from functools import partial
    from pathlib import Path

    from pipeline.run import Run

    def step(ctx):
        with ctx.part("inner"):
            clock.burn(0.1)
        list(ctx.map_tasks([partial(clock.burn, 0.1)]))

    with cf.ThreadPoolExecutor(1) as ex:
        ctx = Run(out=Path("out"), executor=ex)
        ctx.run_step("burn", step)
    c = ctx.clock
    assert c.worker_cpu == {}
    assert c.cpu["inner"] == pytest.approx(0.1, abs=1e-9) and c.wall["inner"] == pytest.approx(0.1, abs=1e-9)
    assert c.cpu["burn"] == pytest.approx(0.1, abs=1e-9), c.cpu  # the task counted once (twice, and its part again: 0.3)
    assert c.wall["burn"] == pytest.approx(0.1, abs=1e-9)  # the step's own wall seconds, apart from its part's
    assert c.in_parts["burn"] == pytest.approx((0.1, 0.1), abs=1e-9)


def test_a_part_run_several_times_counts_every_run(clock):
    """``Run.part`` adds up: wall and CPU seconds of every run of a part, none of them in the step's.
    Exact to 1e-9 s on the fake clock."""
    from pathlib import Path

    from pipeline.run import Run

    def step(ctx):
        for _ in range(2):
            with ctx.part("inner"):
                clock.burn(0.05)
        clock.burn(0.05)

    ctx = Run(out=Path("out"))
    ctx.run_step("burn_twice", step)
    c = ctx.clock
    assert c.cpu["inner"] == pytest.approx(0.1, abs=1e-9), c.cpu  # 0.05: the last run only
    assert c.wall["inner"] == pytest.approx(0.1, abs=1e-9), c.wall
    assert c.cpu["burn_twice"] == pytest.approx(0.05, abs=1e-9), c.cpu  # the parts' seconds not counted twice
    assert c.wall["burn_twice"] == pytest.approx(0.05, abs=1e-9), c.wall


# ----------------------------------------------------------------------------- start-over and what follows the surfaces

_SMALL = {"resolution": 32}
_ALL_STEPS = ("key", "surface", "spine", "track", "rig")


@pytest.fixture(scope="module")
def small_tracked(tmp_path_factory):
    """A small take processed, tracked and rigged (``tracked/``, ``rig/``), with a report and the
    spine's rig export beside them."""
    from pipeline.gltf_export import export_rig
    from pipeline.report import write_report

    sim = simulate_take("starfish", n_cameras=4, frames=3, size=(160, 120), seed=3)
    take = record_take(sim, tmp_path_factory.mktemp("small") / "t.h5")
    out = tmp_path_factory.mktemp("small_results") / "out"
    process_take(take, out, steps=_ALL_STEPS, params=_SMALL)
    write_report(out)
    export_rig(out)
    assert (out / "tracked" / "000002.ply").is_file() and (out / "rig" / "rig.json").is_file()
    return take, out


def _consistency_warning(msg: str) -> bool:
    """The silhouette consistency's warning: at 160x120 one camera's keyed masks hold about half
    as much again as its true ones (IoU 0.52-0.65 with them), which the warning names (median
    0.50, the others 0.96); the tests below are about the other warnings."""
    return "silhouette consistency" in msg


def _said(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if not _consistency_warning(r.getMessage())]


def _warned(res) -> list[str]:
    return [w for w in res.report["warnings"] if not _consistency_warning(w)]


def _files_under(out, *subs) -> dict:
    return {str(p.relative_to(out)): (p.stat().st_mtime_ns, p.read_bytes()) for s in subs
            for p in sorted((out / s).rglob("*")) if p.is_file()}


def test_starting_over_removes_the_tracking_and_rig_of_the_old_surfaces(small_tracked, tmp_path, caplog):
    """Other parameters: the frames tracked on the old surfaces, the rig built on them, the report,
    the spine export and the exported meshes go too, said in the one start-over warning, which the
    job report carries; the user's own files stay."""
    import shutil

    from pipeline.results import ResultsStore

    take, first = small_tracked
    out = tmp_path / "out"
    shutil.copytree(first, out)
    (out / "rig" / "notes.txt").write_text("the user's")
    (out / "tracked" / "1_fixed.ply").write_text("the user's, a name starting with a digit")
    store = ResultsStore(out)
    store.export(0, "ply")
    store.export(2, "glb")
    (out / "export" / "mine.ply").write_text("the user's")
    with caplog.at_level("WARNING"):
        res = process_take(take, out, params={"resolution": 28})
    said = [r.getMessage() for r in caplog.records if r.name in ("pipeline.process", "pipeline.track")
            and not _consistency_warning(r.getMessage())]
    assert said == [f"{out} holds results of other parameters or another take; starting over; removed report.html, "
                    f"spine_rig.glb, 2 exported mesh files ({out / 'export'}); removed the frames tracked on the old "
                    f"surfaces ({out / 'tracked'}); removed the rig built on them ({out / 'rig'})"], said
    assert [p.name for p in (out / "export").iterdir()] == ["mine.ply"]
    assert said[0] in res.report["warnings"] and json.loads((out / "report.json").read_text())["warnings"] == res.report["warnings"]
    assert [p.name for p in (out / "tracked").iterdir()] == ["1_fixed.ply"]
    assert sorted(p.name for p in (out / "rig").iterdir()) == ["notes.txt"]
    (out / "tracked" / "1_fixed.ply").unlink()
    assert not (out / "report.html").exists() and not (out / "spine_rig.glb").exists()
    assert json.loads((out / "process.json").read_text())["params"]["resolution"] == 28
    # tracking again now tracks the new surfaces (nothing of the old settings is left to compare)
    caplog.clear()
    with caplog.at_level("WARNING", logger="pipeline.track"):
        rep = process_take(take, out, steps=("track",), params={"resolution": 28})
    assert not _said(caplog) and _warned(rep) == [] and (out / "tracked" / "000002.ply").is_file()


def test_an_unreadable_process_json_starts_over(tmp_path):
    """A ``process.json`` cut short (a full disk, a kill while an older version wrote it) says nothing of
    the results beside it: the run starts over, in one warning, and writes its own."""
    from pipeline.process import RunContext
    from pipeline.process.context import TakeFacts
    from pipeline.process.driver import _start_record

    out = tmp_path / "out"
    (out / "meshes").mkdir(parents=True)
    (out / "meshes" / "frame_000000.ply").write_text("of unknown parameters")
    (out / "process.json").write_text('{"take": "t.h5", "par')
    take = TakeFacts(path=tmp_path / "t.h5", calibration=None, cameras=["a"], n_sets=1, fps=30.0, rig={})
    ctx = RunContext(out=out, params=ProcessParams(), need_key=False, take=take)
    _start_record(ctx)
    assert not (out / "meshes" / "frame_000000.ply").exists()
    assert len(ctx.warnings) == 1 and "starting over" in ctx.warnings[0], ctx.warnings
    assert json.loads((out / "process.json").read_text())["params"] == ProcessParams().model_dump()


def test_track_options_track_again_and_keep_every_other_result(small_tracked, tmp_path, caplog):
    """``ProcessParams.track`` (the API job's ``parameters.track``) is what ``stage track`` takes: with
    ``carve`` the surfaces are carved across time and tracked again, with ``shape_memory`` the prior keeps
    the previous shape, with ``labels`` the template's patches follow the limbs of the take's spine. Changing
    them tracks again (track.json says so) and starts nothing else over."""
    import shutil

    take, first = small_tracked
    out = tmp_path / "out"
    shutil.copytree(first, out)
    surfaces = _files_under(out, "meshes", "frames")
    with caplog.at_level("WARNING"):
        res = process_take(take, out, steps=("track",),
                           params={**_SMALL, "track": {"carve": 1, "shape_memory": True, "carve_margin": 0.5,
                                                       "labels": True}})
    rep = json.loads((out / "tracked" / "track.json").read_text())
    assert rep["surfaces"] == "carved" and rep["prior"] == "previous" and sorted(rep["frames"]) == ["0", "1", "2"]
    assert rep["patch_labels"] == "spine" and "patch_labels_sha256" in rep
    assert json.loads((out / "carved" / "carve.json").read_text())["margin_px"] == 0.5
    assert _files_under(out, "meshes", "frames") == surfaces  # the surfaces were not made again
    said = [r.getMessage() for r in caplog.records]
    assert not any("starting over" in m and "pipeline.process" == r.name for m, r in zip(said, caplog.records)), said
    assert res.report["warnings"] and "tracked" in res.report["warnings"][0]  # the tracking started over, said once
    assert json.loads((out / "process.json").read_text())["params"]["track"]["carve"] == 1
    # the options are checked before any step runs
    for bad in ({"carve": -1}, {"carve": "two"}, {"colour": "maybe"}, {"carve_margin": -0.5}, {"rounds": 2},
                {"labels": "heat"}):
        with pytest.raises(ValueError, match="track"):
            process_take(take, out, steps=("track",), params={**_SMALL, "track": bad})


def test_rig_parts_from_the_limbs_track_with_the_labels_and_say_when_they_cannot(small_tracked, tmp_path):
    """``ProcessParams.rig`` (the API job's ``parameters.rig``) is what ``stage armature`` takes: ``parts="limbs"``
    on a template tracked without its labels is one warning and the motion segmentation; a job that tracks
    too tracks with the labels; neither starts the other results over."""
    import shutil

    take, first = small_tracked
    out = tmp_path / "out"
    shutil.copytree(first, out)
    surfaces = _files_under(out, "meshes", "frames")
    res = process_take(take, out, steps=("rig",), params={**_SMALL, "rig": {"parts": "limbs"}})
    said = ("rig: parameters rig.parts 'limbs': the armature's parts come from the motion segmentation: the template "
            "was not tracked with the spine's labels (parameters track.labels)")  # the job's words, not the command's
    assert said in res.report["warnings"], res.report["warnings"]
    assert json.loads((out / "rig" / "rig.json").read_text())["segmentation"]["source"] == "motion"
    process_take(take, out, steps=("track", "rig"), params={**_SMALL, "rig": {"parts": "limbs"}})
    assert json.loads((out / "tracked" / "track.json").read_text())["patch_labels"] == "spine"
    assert _files_under(out, "meshes", "frames") == surfaces
    with pytest.raises(ValueError, match="rig"):
        process_take(take, out, steps=("rig",), params={**_SMALL, "rig": {"parts": "bones"}})


def test_the_report_of_a_run_with_the_rig_step_shows_its_segments_and_joints(small_tracked, tmp_path):
    """report.json (a job's ``result.report``) of a run with the rig step holds the armature's segments and joints
    as rig.json has them; a run without the step says nothing of a rig."""
    import shutil

    take, first = small_tracked
    out = tmp_path / "out"
    shutil.copytree(first, out)
    res = process_take(take, out, steps=("rig",), params=_SMALL)
    doc = json.loads((out / "rig" / "rig.json").read_text())
    rig = res.report["rig"]
    assert rig["segments"] == doc["segmentation"]["segments"] == len(np.unique(np.load(out / "rig" / "segments.npy")))
    assert [j["name"] for j in rig["joints"]] == [j["name"] for j in doc["joints"]]
    assert rig["articulations"] == sum(j["kind"] == "joint" for j in doc["joints"]) >= 1
    assert [j["rest"] for j in rig["joints"]] == [j["rest"] for j in doc["joints"]] and rig["units"] == "mm"
    assert rig["mean_vertex_error"] == doc["fit"]["mean_vertex_error"]
    assert json.loads((out / "report.json").read_text())["rig"] == rig
    assert "rig" not in process_take(take, out, steps=("spine",), params=_SMALL).report


def test_a_resume_with_the_same_parameters_keeps_the_tracking_and_rig(small_tracked, tmp_path, caplog):
    """The same parameters (a run stopped after some surfaces): tracked/ and rig/ are not touched."""
    import shutil

    take, first = small_tracked
    out = tmp_path / "out"
    shutil.copytree(first, out)
    before = _files_under(out, "tracked", "rig")
    (out / "frames" / "frame_000002.json").unlink()
    (out / "spine.json").unlink()
    with caplog.at_level("WARNING", logger="pipeline.process"):
        res = process_take(take, out, params=_SMALL)
    assert not _said(caplog) and _warned(res) == []
    assert _files_under(out, "tracked", "rig") == before and len(before) >= 9  # 3 frames, track.json, 5 rig files
    assert (out / "report.html").is_file() and (out / "spine_rig.glb").is_file()


@pytest.mark.parametrize("pool", [None, "threads"])
def test_what_the_frames_warn_of_is_said_once_per_kind_with_the_frame_sets(tmp_path, caplog, pool):
    """A camera whose masks are all foreground in three frame sets, a frame set with no subject: the run's warnings
    (a job's, report.json's) and its log say each once, with how many frame sets and which, not one line per frame
    set; each frame set's record keeps its own (the report's ``per_frame``), the log has each at DEBUG."""
    import concurrent.futures as cf
    import logging

    from tests.pipeline.hull_scenes import FAILED_MASKS_SAID, take_with_failed_masks

    take = take_with_failed_masks(tmp_path / "t.h5")
    with (cf.ThreadPoolExecutor(2) if pool else contextlib.nullcontext()) as ex, caplog.at_level(logging.DEBUG):
        res = process_take(take, tmp_path / "out", steps=["surface", "spine"], params={"resolution": 32}, executor=ex)
    warned = [w for w in res.report["warnings"] if "silhouette consistency" not in w]  # (cam02's, rightly)
    assert warned == FAILED_MASKS_SAID
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert [m for m in said if "foreground" in m] == FAILED_MASKS_SAID, said
    per_frame = res.report["per_frame"]
    assert [f.get("warnings") for f in per_frame] == [None] + [[
        "camera cam02: mask is all foreground (keying failed?); ignored for this frame"]] * 3 + [[
        "no foreground in any camera's mask: the frame is empty"], None]
    debug = {r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG and r.name.startswith("pipeline")}
    assert {f"frame set {k}: camera cam02: mask is all foreground (keying failed?); ignored for this frame"
            for k in (1, 2, 3)} | {"frame set 4: no foreground in any camera's mask: the frame is empty"} <= debug


def _skeleton_warns_in_frame_sets_1_and_2(monkeypatch):
    """The skeleton step's records (``skeleton_task``) warn of frame sets 1 and 2, once of them in a job's words."""
    import logging

    from pipeline.process import tasks

    made = tasks.skeleton_record

    def record(k, mesh, params, **kw):
        if k in (1, 2):
            logging.getLogger("pipeline.process").warning("its skeleton is thin (see --spine)",
                                                          extra={"job_message": "its skeleton is thin (see spine)"})
        return made(k, mesh, params, **kw)

    monkeypatch.setattr(tasks, "skeleton_record", record)


def test_a_resumed_run_says_what_the_frame_sets_made_before_it_said(tmp_path, monkeypatch):
    """The failed-masks take's surface step, then its spine step (its skeletons warning of frame sets 1 and 2), each
    stopped after its first chunk (frame sets 0 and 1) and run again on the folder: each second run's warnings (a
    job's, report.json's) are those of one run that made every frame set, in the job's words, the frame sets made
    by the run that stopped included; the frame's records keep them (``warnings``, ``job_warnings``). The folder,
    made by the first run, keeps the frame sets it finished before it was cancelled."""
    import threading

    from pipeline.process.records import frame_said, skeleton_said
    from tests.pipeline.hull_scenes import take_with_failed_masks

    _skeleton_warns_in_frame_sets_1_and_2(monkeypatch)
    take = take_with_failed_masks(tmp_path / "t.h5")
    params = {"resolution": 32, "chunk": 2}
    whole = [process_take(take, tmp_path / "whole", steps=[step], params=params).report["warnings"]
             for step in ("surface", "spine")]
    assert whole[1] == ["skeleton: its skeleton is thin (see spine) (2 frame sets: 1, 2)"], whole
    again = []
    for step, name in (("surface", "surface"), ("spine", "skeleton")):
        cancel = threading.Event()

        def stop(what, done, total, name=name, cancel=cancel):
            if what == name and done >= 2:  # (the first chunk done)
                cancel.set()

        with pytest.raises(InterruptedError):
            process_take(take, tmp_path / "out", steps=[step], params=params, progress=stop, cancel=cancel)
        if step == "surface":  # (a folder the cancelled run made keeps its finished frames, and no others)
            assert sorted(p.name for p in (tmp_path / "out" / "frames").iterdir()) == [
                "frame_000000.json", "frame_000001.json"]
        again.append(process_take(take, tmp_path / "out", steps=[step], params=params).report["warnings"])
    assert again == whole, again
    foreground = "camera cam02: mask is all foreground (keying failed?); ignored for this frame"
    assert frame_said(tmp_path / "out", 1) == [(foreground, None)] and frame_said(tmp_path / "out", 0) == []
    assert skeleton_said(tmp_path / "out", 1) == [("its skeleton is thin (see --spine)",
                                                   "its skeleton is thin (see spine)")]
    assert skeleton_said(tmp_path / "out", 0) == [] and skeleton_said(tmp_path / "nowhere", 1) == []


def test_what_the_keying_says_of_a_camera_is_in_the_runs_warnings_once_per_reason(tmp_path, caplog, monkeypatch):
    """Camera cam01's frames 2 and 3 black: the key step's warnings (a job's, report.json's) and its log say its
    invalid masks once, with the take's frame numbers and the reason (the keyer said one line per frame, numbered
    within its chunk of frames: here 2 frames a chunk)."""
    import logging

    import stage.keying.take

    monkeypatch.setattr(stage.keying.take, "_CHUNK", 2)

    sim = simulate_take("starfish", n_cameras=4, frames=6, size=(160, 120), seed=3)
    sim.images[2:4, 1] = 0
    take = record_take(sim, tmp_path / "t.h5")
    with caplog.at_level(logging.WARNING):
        res = process_take(take, tmp_path / "out", steps=["key"])
    said = "cam01: mask invalid in 2 frames (2, 3): frame is black (99.5th-percentile luma 0.0 < black_level 12)"
    assert res.report["warnings"] == [f"key: {said}"]
    assert [r.getMessage() for r in caplog.records if "mask invalid" in r.getMessage()] == [said]
