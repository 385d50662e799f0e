import time

import numpy as np
import pytest

from fake_cameras.device import FakeCamera, FakeCameraConfig
from fake_cameras.take import simulate_take
from stage.drivers.base import CameraDisconnectedError, CameraDriver, CameraError, CameraNotFoundError
from stage.drivers.opencv import OpenCVCameraConfig
from stage.rig import parse_rig

FPS = 30.0
PERIOD = int(1e9 / FPS)


class FakeClock:
    """A monotonic clock that only moves when the camera sleeps (or the test says so)."""

    def __init__(self, start=10**12):
        self.now = start

    def __call__(self):
        return self.now

    def sleep(self, s):
        self.now += int(round(s * 1e9))


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import os

    os.environ.setdefault("CAPTURE_STAGE_CACHE", str(tmp_path_factory.getbasetemp() / "simcache"))
    return simulate_take("starfish", n_cameras=4, frames=5, size=(64, 48), seed=1)


def _cam(take, clock, **kw):
    cfg = FakeCameraConfig(driver="fake", id=kw.pop("id", "c1"), index=kw.pop("index", 1), width=64, height=48, fps=FPS, **kw)
    return FakeCamera(cfg, take=take, epoch_ns=0, seed=3, clock=clock, sleep=clock.sleep, latency_ms=1.0)


def test_frames_replay_the_take_in_real_time(take):
    clock = FakeClock()
    cam = _cam(take, clock)
    assert isinstance(cam, CameraDriver)
    cam.open()
    g = cam.configure()
    assert (g.width, g.height, g.fps) == (64, 48, FPS)
    frames = [cam.grab() for _ in range(12)]
    idx = [f.index for f in frames]
    assert idx == list(range(12))
    ts = np.array([f.timestamp_ns for f in frames])
    assert np.all(np.diff(ts) == PERIOD)
    host = np.array([f.host_timestamp_ns for f in frames])
    assert np.all(host >= ts) and np.all(np.diff(host) == PERIOD)  # grab waited for each frame
    for f in frames:
        assert f.camera_id == "c1"
        assert np.array_equal(f.image, take.images[cam.scene_frame(f.index), 1])
    cam.close()
    with pytest.raises(CameraError):
        cam.grab()


def test_clock_offset_and_jitter(take):
    clock = FakeClock()
    cam = _cam(take, clock, clock_offset_ms=7.5, jitter_ms=1.0)
    cam.open()
    frames = [cam.grab() for _ in range(400)]
    k = np.array([f.index for f in frames]) + cam._k0
    err = np.array([f.timestamp_ns for f in frames]) - k * PERIOD  # device time - true capture time
    assert abs(err.mean() / 1e6 - 7.5) < 0.2
    assert 0.85 < err.std() / 1e6 < 1.15


def test_random_drops_skip_sequence_numbers(take):
    clock = FakeClock()
    cam = _cam(take, clock, drop_rate=0.3)
    cam.open()
    frames = [cam.grab() for _ in range(300)]
    idx = np.array([f.index for f in frames])
    gaps = np.diff(idx) - 1
    assert np.all(gaps >= 0)
    assert gaps.sum() == cam.dropped - (idx[0] - 0)
    assert 0.2 < cam.dropped / (idx[-1] + 1) < 0.4
    # a dropped frame is never replaced: timestamps follow the sequence numbers
    ts = np.array([f.timestamp_ns for f in frames])
    assert np.all(np.diff(ts) == np.diff(idx) * PERIOD)


def test_slow_reader_loses_overwritten_frames(take):
    clock = FakeClock()
    cam = _cam(take, clock)
    cam.open()
    a = cam.grab()
    clock.now += 10 * PERIOD  # the reader stalls for 10 frame periods; the device keeps 4
    b = cam.grab()
    assert b.index - a.index - 1 == cam.dropped > 0
    assert b.index >= a.index + 10 - 4


def test_disconnect_after(take):
    clock = FakeClock()
    cam = _cam(take, clock, disconnect_after=3)
    cam.open()
    for _ in range(3):
        cam.grab()
    with pytest.raises(CameraDisconnectedError, match="disconnect"):
        cam.grab()


def test_missing_index_is_not_found(take):
    cam = _cam(take, FakeClock(), index=4)
    with pytest.raises(CameraNotFoundError, match="index 4"):
        cam.open()


def test_depth_needs_a_depth_take(take):
    cam = _cam(take, FakeClock(), depth=True)
    with pytest.raises(CameraError, match="depth"):
        cam.open()


def test_rig_cameras_through_the_registry(tmp_path, monkeypatch):
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    from stage.drivers.registry import open_driver

    rig = parse_rig(
        {
            "fps": 60,
            "simulation": {"subject": "quadruped", "n_cameras": 4, "frames": 2},
            "cameras": [
                {"id": f"cam{i}", "driver": "fake", "index": i, "width": 80, "height": 60, "depth": i == 0}
                for i in range(2)
            ],
        }
    )
    cams = [open_driver(c, rig) for c in rig.cameras]
    for c in cams:
        c.open()
        assert c.configure().fps == 60
    t0 = time.monotonic_ns()
    frames = [[c.grab() for c in cams] for _ in range(3)]
    assert time.monotonic_ns() - t0 < 30e9  # grabs return (no hang); the pacing is checked on the timestamps below
    assert frames[0][0].depth is not None and frames[0][0].depth.shape == (60, 80)
    assert frames[0][1].depth is None
    assert all(f.image.shape == (60, 80, 3) for fs in frames for f in fs)
    # real time: the host timestamps of one camera follow its frame period
    host = np.array([fs[1].host_timestamp_ns for fs in frames])
    assert np.all(np.diff(host) > 0.5e9 / 60)
    assert cams[0].calibration is not None and cams[0].calibration.names == ["cam0", "cam1"]  # the rig's cameras


def test_the_calibration_names_the_rig_s_cameras(tmp_path, monkeypatch):
    """The simulated rig's true calibration under the rig file's camera ids, each the simulated camera at
    its index, in the rig's order (a take recorded from the cameras, and the live 3-D preview, name them so)."""
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    from fake_cameras.device import take_for_rig

    rig = parse_rig({"fps": 30, "simulation": {"subject": "starfish", "n_cameras": 4, "frames": 2},
                     "cameras": [{"id": "left", "driver": "fake", "index": 2, "width": 80, "height": 60},
                                 {"id": "right", "driver": "fake", "index": 0, "width": 80, "height": 60}]})
    cam = FakeCamera(rig.cameras[0], rig)
    assert cam.calibration is None  # before open
    cam.open()
    try:
        cal = cam.calibration
        true = take_for_rig(rig, size=(80, 60), fps=30.0).calibration
        assert cal.names == ["left", "right"] and true.names[2] != "left"
        for name, index in (("left", 2), ("right", 0)):
            for key in ("K", "dist", "R", "t"):
                np.testing.assert_array_equal(getattr(cal[name], key), getattr(true.cameras[index], key))
            assert cal[name].size == true.cameras[index].size
    finally:
        cam.close()


def test_invalid_input(take):
    with pytest.raises(ValueError, match="config"):
        FakeCamera(OpenCVCameraConfig(driver="opencv", id="x"), take=take)
    cfg = FakeCameraConfig(driver="fake", id="x")
    with pytest.raises(ValueError, match="simulation"):
        FakeCamera(cfg)
    with pytest.raises(ValueError, match="rig"):
        FakeCamera(cfg, rig={"simulation": {}})
    with pytest.raises(ValueError, match="take"):
        FakeCamera(cfg, take=np.zeros(3))
    with pytest.raises(ValueError, match="buffer"):
        FakeCamera(cfg, take=take, buffer=0)
    cam = _cam(take, FakeClock())
    with pytest.raises(CameraError, match="open"):
        cam.configure()


def test_the_simulator_registers_its_driver(monkeypatch):
    """fake_cameras registers ``fake`` itself; the ground floor holds no reference to it."""
    from stage.drivers import registry
    from stage.drivers.base import DriverUnavailableError

    assert "fake" in registry.registered_drivers()
    assert registry._driver_class("fake") == (FakeCamera, True)
    rig = parse_rig({"simulation": {"frames": 2}, "cameras": [{"id": "a", "driver": "fake", "width": 64, "height": 48}]})
    monkeypatch.delitem(registry._DRIVERS, "fake")
    with pytest.raises(DriverUnavailableError, match="'fake' is not registered.*fake_cameras"):
        registry.open_driver(rig.cameras[0], rig)


def test_register_driver_invalid_input():
    from stage.drivers.registry import register_driver

    with pytest.raises(ValueError, match="name"):
        register_driver("", FakeCamera)
    with pytest.raises(ValueError, match="cls"):
        register_driver("other", "fake_cameras.device:FakeCamera")  # a class, not an import path


def test_mirror_mode_delivers_mirrored_images_and_mirror_flips_them_back(take):
    """A simulated webcam in mirror mode delivers the scene flipped left-right (depth too);
    ``mirror = true`` on the camera says so, and the driver flips its frames back."""
    from fake_cameras.take import simulate_take

    dtake = simulate_take("starfish", n_cameras=4, frames=5, size=(64, 48), seed=1, depth=True)
    for mirror_mode, mirror, flipped in ((True, False, True), (True, True, False), (False, True, True)):
        clock = FakeClock()
        cam = _cam(dtake, clock, mirror_mode=mirror_mode, mirror=mirror, depth=True)
        cam.open()
        for f in (cam.grab() for _ in range(3)):
            k = cam.scene_frame(f.index)
            img, dep = dtake.images[k, 1], dtake.depth[k, 1]
            want = (img[:, ::-1], dep[:, ::-1]) if flipped else (img, dep)
            assert np.array_equal(f.image, want[0]) and np.array_equal(f.depth, want[1]), (mirror_mode, mirror)
            assert not np.array_equal(img, img[:, ::-1])  # the test can tell the two apart
            assert f.image.flags.c_contiguous


def test_capture_unmirrors_a_mirror_mode_camera_marked_in_the_rig_file(tmp_path, monkeypatch):
    """``stage capture`` of a rig file whose cam1 is in mirror mode: with ``mirror = true`` the take
    holds the scene as the camera really sees it, without it the mirrored images."""
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    from fake_cameras.device import take_for_rig
    from fake_cameras.rigs import dumps_toml
    from stage.cli import main
    from stage.store import TakeReader

    for mirror in (True, False):
        rig = {"name": "mirror", "fps": 30,
               "simulation": {"subject": "starfish", "n_cameras": 4, "frames": 3},
               "cameras": [{"id": "cam0", "driver": "fake", "index": 0, "width": 64, "height": 48},
                           {"id": "cam1", "driver": "fake", "index": 1, "width": 64, "height": 48,
                            "mirror_mode": True, "mirror": mirror}]}
        path = tmp_path / f"rig_{mirror}.toml"
        path.write_text(dumps_toml(rig), encoding="utf-8")
        out = tmp_path / f"cap_{mirror}.h5"
        assert main(["capture", "--rig", str(path), "--frames", "4", "--out", str(out), "--no-progress"]) == 0
        scene = take_for_rig(parse_rig(rig), size=(64, 48), fps=30.0).images
        n = scene.shape[0]
        want = [scene[i, 1] if mirror else scene[i, 1][:, ::-1] for i in range(n)]
        other = [w[:, ::-1] for w in want]
        with TakeReader(out) as r:
            # every stored frame of each camera, on its own: the capture is real-time, so a set may
            # miss a camera's frame or pair a neighbouring one (the devices are read one after the other)
            assert r.n_frames("cam0") >= 1 and r.n_frames("cam1") >= 1
            for k in range(r.n_frames("cam0")):
                assert any(np.array_equal(r.frame("cam0", k), scene[i, 0]) for i in range(n)), (mirror, k)
            for k in range(r.n_frames("cam1")):
                got = r.frame("cam1", k)
                assert any(np.array_equal(got, w) for w in want), (mirror, k)
                assert not any(np.array_equal(got, o) for o in other), (mirror, k)


def test_a_captured_take_films_the_scene_from_its_first_frame(tmp_path, monkeypatch):
    """A take captured live from simulated cameras starts at the simulator's frame 0 whenever the
    process started: rendering the simulator's pose k, and the pose k of the ground truth written
    the way ``stage demo`` writes it, gives the take's frame set k (not a neighbour, not a loop)."""
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    from fake_cameras.device import take_for_rig
    from fake_cameras.record import take_scene_frames
    from fake_cameras.render import render_view
    from fake_cameras.rigs import simulated_rig
    from fake_cameras.take import load_ground_truth, studio, write_ground_truth
    from stage.capture import capture_take
    from stage.store import TakeReader

    n = 6
    rig = simulated_rig(4, subject="starfish", frames=n, size=(96, 72), fps=30.0)
    sim = take_for_rig(rig, size=(96, 72), fps=30.0)
    time.sleep(0.3 + 0.1 * np.random.default_rng().random())  # the clock runs before the capture starts
    for attempt in range(2):  # a second capture of the same rig in the same process starts at frame 0 too
        path = tmp_path / f"t{attempt}.h5"
        capture_take(rig, path, frames=n)
        idx = take_scene_frames(path, n)
        write_ground_truth(sim.select(idx), path)
        gt = load_ground_truth(path)
        with TakeReader(path) as r:
            table = r.set_table()
            assert table.shape[0] == n
            stored = np.stack([[r.frame(c, int(table[k, i])) for i, c in enumerate(r.cameras)] for k in range(n)])
        np.testing.assert_array_equal(idx, np.arange(n))
        _, _, backdrop = studio(volume=rig.volume, n_cameras=4, size=(96, 72), seed=0, distortion=True,
                                calibration=sim.calibration, backdrop=None)
        for k in range(n):
            for pose in (sim.poses[k], gt["poses"][k]):
                for c in (0, 2):
                    img = render_view(sim.calibration[c], pose, backdrop=backdrop, noise_sigma=0).image.astype(float)
                    err = np.abs(stored[:, c].astype(float) - img).mean(axis=(1, 2, 3))
                    assert int(np.argmin(err)) == k, (attempt, k, c, err.round(2))
        np.testing.assert_allclose(gt["tips"], sim.tip_array())
        time.sleep(0.2)


def test_simulated_take_select_invalid_input(take):
    with pytest.raises(ValueError, match="frames"):
        take.select([0, 5])
    with pytest.raises(ValueError, match="frames"):
        take.select([[0]])
    assert take.select([2, 0]).images.shape[0] == 2



def test_board_views_are_rendered_once_and_read_back_from_the_disk_cache(tmp_path, monkeypatch):
    """A board rig's views (``subject = "board-charuco"``) go to the simulator's disk cache: a second
    process (the in-process memo cleared) reads back every array of the views as rendered; another
    noise level is rendered anew."""
    monkeypatch.setenv("CAPTURE_STAGE_CACHE", str(tmp_path))
    import fake_cameras.boards as boards
    from fake_cameras import device

    renders = []
    render = boards.render_board_views
    monkeypatch.setattr(boards, "render_board_views", lambda *a, **k: renders.append(1) or render(*a, **k))
    table = {"subject": "board-charuco", "n_cameras": 4, "frames": 2, "noise": 1.0}
    cams = [{"id": f"cam{i}", "driver": "fake", "index": i, "width": 96, "height": 72} for i in range(4)]

    def views(**sim):
        monkeypatch.setattr(device, "_TAKES", {})  # a new process
        rig = parse_rig({"fps": 4, "simulation": {**table, **sim}, "cameras": cams})
        return device.take_for_rig(rig, size=(96, 72), fps=4.0)

    first = views()
    assert isinstance(first, boards.BoardViews) and first.images.shape == (2, 4, 72, 96, 3) and len(renders) == 1
    again = views()
    assert again is not first and again.board == first.board and len(renders) == 1
    for name in ("images", "poses", "object_points", "corners_3d", "corners_2d", "visible"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)
    assert again.calibration.to_dict() == first.calibration.to_dict()
    quiet = views(noise=0.0)
    assert len(renders) == 2 and not np.array_equal(quiet.images, first.images)
    assert len(list((tmp_path / "sim").iterdir())) == 2
