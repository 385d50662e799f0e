"""The stage session: cameras opened once and kept running; takes recorded from them; live figures;
a camera unplugged while recording; one take at a time."""

from __future__ import annotations

import dataclasses
import shutil
import threading
from functools import partial

import numpy as np
import pytest

from stage.capture import TakeRecorder
from stage.drivers.base import CameraDisconnectedError, CameraError, Granted
from stage.session import NoRecordingError, RecordingBusyError, StageSession, recording_rate_bytes
from stage.store import TakeReader
from tests.polling import wait_until
from tests.stage.paced import H, PacedCamera, W, make_drivers, pattern, rig_for


class Unpluggable(PacedCamera):
    """A paced camera whose cable can be pulled (``unplug``) while it runs."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.gone = threading.Event()

    def grab(self):
        if self.gone.is_set():
            raise CameraDisconnectedError(f"camera {self.camera_id}: USB device went away")
        return super().grab()


_wait = partial(wait_until, timeout=10.0, poll=0.02)


def test_session_runs_and_records_from_the_running_cameras(tmp_path):
    ids = ["a", "b", "c"]
    drivers = make_drivers(ids)
    with StageSession(rig_for(ids), tmp_path / "takes", drivers=drivers) as s:
        assert all(d.opened and not d.closed for d in drivers.values())
        _wait(lambda: s.figures()["sets"] > 20, what="live frame sets")
        seq0, f0 = s.latest("a")
        _wait(lambda: s.latest("a")[0] > seq0, what="a new frame")
        seq1, f1 = s.latest("a")
        np.testing.assert_array_equal(f1.image, pattern(0, f1.index))  # the latest frame is the camera's frame
        fig = s.figures()
        cams = {c["id"]: c for c in fig["cameras"]}
        assert set(cams) == set(ids) and all(c["state"] == "running" for c in cams.values())
        assert all(40 < c["fps"] < 80 for c in cams.values()), [c["fps"] for c in cams.values()]  # 60 fps cameras
        assert fig["sync_spread_ms"]["n"] > 0 and fig["sync_spread_ms"]["max"] < 1e3 / 60
        assert fig["recording"] == {"state": "idle"}
        for take, n in (("t1", 30), ("t2", 20)):  # two takes from the same running cameras
            st = s.start_recording(tmp_path / "takes" / f"{take}.h5", take=take, frames=n)
            assert st["state"] == "recording" and s.recording_active
            s.wait_recording(20)
            rec = s.recording()
            assert rec["state"] == "done" and rec["take"] == take and rec["frames_written"] == n
            with TakeReader(tmp_path / "takes" / f"{take}.h5") as r:
                assert r.complete and len(r) == n
                assert r.sync_stats["sets"] == rec["result"]["sync"]["sets"] == n
                assert r.sync_stats["spread_median_ms"] == pytest.approx(rec["result"]["sync"]["spread_median_ms"])
                fs = r.frame_set(n - 1)
                for i, c in enumerate(ids):
                    if fs[c] is not None:
                        assert fs[c].shape == (H, W, 3) and int(fs[c][0, 0, 0]) == i * 50
            assert all(not d.closed for d in drivers.values())  # a take never closes the session's cameras
    assert all(d.closed for d in drivers.values())


class Metered(PacedCamera):
    """A paced camera whose frames say their exposure and gain (as OAK cameras do)."""

    def configure(self):
        return Granted(W, H, self.fps, exposure=5.0, extra={"gain": 1.0, "gain_unit": "ISO"})

    def grab(self):
        return dataclasses.replace(super().grab(), exposure_ms=4.0, gain=400.0)


def test_exposure_and_gain_as_the_frames_or_the_device_say(tmp_path):
    ids = ["m", "p"]
    drivers = {**make_drivers(["p"]), "m": Metered("m", 1, 60.0)}
    with StageSession(rig_for(ids), tmp_path / "takes", drivers=drivers) as s:
        _wait(lambda: all(s.latest(c)[1] is not None for c in ids), what="frames")
        cams = {c["id"]: c for c in s.figures()["cameras"]}
    assert (cams["m"]["exposure_ms"], cams["m"]["gain"], cams["m"]["gain_unit"]) == (4.0, 400.0, "ISO")
    assert (cams["p"]["exposure_ms"], cams["p"]["gain"], cams["p"]["gain_unit"]) == (None, None, None)  # none said


def test_one_take_at_a_time(tmp_path):
    ids = ["a", "b"]
    with StageSession(rig_for(ids), tmp_path, drivers=make_drivers(ids)) as s:
        s.start_recording(tmp_path / "one.h5", take="one")
        with pytest.raises(RecordingBusyError, match="'one' is being recorded"):
            s.start_recording(tmp_path / "two.h5", take="two")
        assert not (tmp_path / "two.h5").exists()
        _wait(lambda: s.recording().get("frames_written", 0) > 5, what="sets written")
        rec = s.stop_recording()
        assert rec["state"] == "done" and rec["result"]["stopped"] == "stopped" and rec["frames_written"] > 0
        with pytest.raises(NoRecordingError):
            s.stop_recording()
        with pytest.raises(FileExistsError, match="'one' already exists"):
            s.start_recording(tmp_path / "one.h5", take="one", frames=3)
        with TakeReader(tmp_path / "one.h5") as r:
            assert r.complete and len(r) == rec["frames_written"]


def test_camera_unplugged_while_recording(tmp_path):
    ids = ["a", "b", "c"]
    start: dict = {}
    drivers = {c: Unpluggable(c, i, 60.0, jitter_ms=0.3, seed=i, start=start) for i, c in enumerate(ids)}
    with StageSession(rig_for(ids), tmp_path, drivers=drivers) as s:
        _wait(lambda: s.figures()["sets"] > 5, what="live sets")
        s.start_recording(tmp_path / "u.h5", take="u", frames=150)
        _wait(lambda: s.recording().get("frames_written", 0) >= 20, what="20 sets")
        drivers["b"].gone.set()
        s.wait_recording(20)
        rec = s.recording()
        cams = {c["id"]: c for c in s.figures()["cameras"]}
        assert cams["b"]["state"] == "disconnected" and "went away" in cams["b"]["error"]
        assert cams["a"]["state"] == cams["c"]["state"] == "running"
        n_a = s.cameras["a"].delivered
        _wait(lambda: s.cameras["a"].delivered > n_a + 5, what="a goes on")
    assert rec["state"] == "done" and rec["frames_written"] == 150
    assert "b" in rec["result"]["disconnected"]
    with TakeReader(tmp_path / "u.h5") as r:
        assert r.complete and len(r) == 150
        counts = r.frame_counts()
        table = r.set_table()
        assert 15 <= counts["b"] < 120
        gap = np.flatnonzero(table[:, 1] < 0)
        assert gap.size and (table[gap[0]:, 1] == -1).all()  # b is missing from its unplugging on
        # a and c go on being recorded after b went; a busy machine may make them miss a set now and then (an
        # unpaced thread late past the set's tolerance), so: present in 80 % of the sets after the gap, and
        # the take's own sync figures say every set each camera misses
        after = table[gap[0]:]
        assert (after[:, 0] >= 0).mean() >= 0.8 and (after[:, 2] >= 0).mean() >= 0.8, (counts, after.shape)
        for i, c in enumerate(ids):
            assert r.sync_stats["cameras"][c]["missing"] == 150 - counts[c] == int((table[:, i] < 0).sum())


def test_a_camera_that_does_not_open(tmp_path):
    class Broken(PacedCamera):
        def open(self):
            raise CameraError("camera b: no such device /dev/video9")

    ids = ["a", "b"]
    drivers = {"a": PacedCamera("a", 0, 60.0), "b": Broken("b", 1, 60.0)}
    with StageSession(rig_for(ids), tmp_path, drivers=drivers) as s:
        cams = {c["id"]: c for c in s.figures()["cameras"]}
        assert cams["b"]["state"] == "failed" and "/dev/video9" in cams["b"]["error"]
        s.start_recording(tmp_path / "f.h5", take="f", frames=10)
        s.wait_recording(10)
        assert s.recording()["frames_written"] == 10
    with TakeReader(tmp_path / "f.h5") as r:
        assert r.frame_counts()["b"] == 0 and r.frame_counts()["a"] == 10
    with pytest.raises(CameraError, match="no camera of the rig could be opened"):
        StageSession(rig_for(["b"]), tmp_path, drivers={"b": Broken("b", 1, 60.0)}).open()


def test_disk_figures(tmp_path):
    ids = ["a", "b"]
    rig = rig_for(ids)
    assert recording_rate_bytes(rig) == 2 * W * H * 3 * 60.0  # raw BGR at the rig's fps
    s = StageSession(rig, tmp_path, drivers=make_drivers(ids))
    d = s.disk()
    free = shutil.disk_usage(tmp_path).free
    assert d["free_bytes"] == pytest.approx(free, rel=0.01)
    assert d["minutes_left"] == pytest.approx(free / (2 * W * H * 3 * 60.0) / 60.0, rel=0.01)


def test_invalid_input(tmp_path):
    ids = ["a", "b"]
    with pytest.raises(ValueError, match="rig"):
        StageSession(None, tmp_path)
    with pytest.raises(ValueError, match="stall_timeout_s"):
        StageSession(rig_for(ids), tmp_path, stall_timeout_s=0)
    with pytest.raises(ValueError, match="no driver for cameras"):
        StageSession(rig_for(ids), tmp_path, drivers={"a": PacedCamera("a", 0, 60.0)})
    s = StageSession(rig_for(ids), tmp_path, drivers=make_drivers(ids))
    with pytest.raises(RuntimeError, match="not running"):
        s.start_recording(tmp_path / "x.h5")
    g = {c: Granted(W, H, 60.0) for c in ids}
    with pytest.raises(ValueError, match="rig"):
        TakeRecorder(None, tmp_path / "x.h5", granted=g)
    with pytest.raises(ValueError, match="granted"):
        TakeRecorder(rig_for(ids), tmp_path / "x.h5", granted={"a": g["a"]})
    with pytest.raises(ValueError, match="frames"):
        TakeRecorder(rig_for(ids), tmp_path / "x.h5", granted=g, frames=0)
    with pytest.raises(ValueError, match="duration_s"):
        TakeRecorder(rig_for(ids), tmp_path / "x.h5", granted=g, duration_s=-1)
    (tmp_path / "y.h5").write_bytes(b"")
    with pytest.raises(FileExistsError):
        TakeRecorder(rig_for(ids), tmp_path / "y.h5", granted=g)


def test_a_session_take_groups_after_one_second_of_frames(tmp_path):
    """At a board take's few frames a second a session take's grouper trusts the clock offsets after
    one second of frames (at least 8), not capture_take's 30 frames: its first set is decided by the
    eighth frame of every camera at 4 fps, and 30 frames stay the window at 30 fps and above."""
    from stage.capture import live_sync_window
    from stage.frame import Frame

    assert [live_sync_window(f) for f in (1.0, 4.0, 15.0, 30.0, 120.0)] == [8, 8, 15, 30, 30]
    ids = ["a", "b"]
    rec = TakeRecorder(rig_for(ids, fps=4.0), tmp_path / "t.h5", granted={c: Granted(W, H, 4.0) for c in ids},
                       frames=10)
    period = 250_000_000
    decided = []
    for k in range(8):
        for i, c in enumerate(ids):
            t = 10**12 + k * period
            f = Frame(image=pattern(i, k), camera_id=c, index=k, timestamp_ns=t + 7_000_000 * i, host_timestamp_ns=t + 2_000_000)
            decided += rec.grouper.push(f, now_ns=f.host_timestamp_ns)
        assert bool(decided) == (k == 7), (k, len(decided))  # sets once every camera has 8 frames
    assert [sorted(fs.frames) for fs in decided] == [ids] * len(decided) and decided[0].frames["a"].index == 0
