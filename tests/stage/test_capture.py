"""Synchronized capture into a take: real threads, paced test cameras, disconnects, SIGKILL."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from stage.capture import CaptureProgress, capture_take
from stage.store import TakeReader
from tests.stage.paced import make_drivers, pattern, rig_for

ROOT = Path(__file__).resolve().parents[2]


def test_capture_frames_grouped_and_stored(tmp_path):
    ids = ["a", "b", "c"]
    drivers = make_drivers(ids, b={"drop": {5, 6, 17}})
    seen: list[CaptureProgress] = []
    res = capture_take(rig_for(ids), tmp_path / "t.h5", frames=30, drivers=drivers, progress=seen.append)
    assert res.sets == 30 and res.stopped == "frames"
    assert all(d.closed for d in drivers.values())
    assert seen and seen[-1].sets == 30 and seen[-1].target_sets == 30
    with TakeReader(res.path) as r:
        assert r.complete and len(r) == 30
        table = r.set_table()
        # every set is one instant: same device sequence number in every camera present
        for k in range(30):
            seqs = {int(r.timestamps(c)["sequence"][row]) for c, row in zip(ids, table[k]) if row >= 0}
            assert len(seqs) == 1
            fs = r.frame_set(k)
            (seq,) = seqs
            for i, c in enumerate(ids):
                if fs[c] is not None:
                    np.testing.assert_array_equal(fs[c], pattern(i, seq))
        # b's dropped frames are missing in their sets, never duplicated
        b_seq = r.timestamps("b")["sequence"]
        assert len(set(b_seq.tolist())) == len(b_seq)
        a_seq = r.timestamps("a")["sequence"]
        missing_b = [int(a_seq[table[k, 0]]) for k in range(30) if table[k, 1] < 0]
        assert set(missing_b) == {5, 6, 17} & set(a_seq.tolist())
        st = r.sync_stats
        assert st["cameras"]["b"]["missing"] == len(missing_b) and st["cameras"]["b"]["sequence_gaps"] >= 2
        assert st["spread_max_ms"] < 1e3 / 60 and r.calibration is None and r.rig["fps"] == 60.0
    assert res.stats.cameras["b"].missing == len(missing_b)


def test_camera_disconnects_mid_take(tmp_path, caplog):
    ids = ["a", "b"]
    drivers = make_drivers(ids, b={"disconnect_after": 10})
    with caplog.at_level(logging.WARNING):
        res = capture_take(rig_for(ids), tmp_path / "d.h5", frames=25, drivers=drivers)
    assert "camera b disconnected" in caplog.text
    assert "b" in res.disconnected and "USB" in res.disconnected["b"]
    assert res.sets == 25
    with TakeReader(res.path) as r:
        assert r.complete and len(r) == 25
        assert r.frame_counts()["a"] == 25 and r.frame_counts()["b"] <= 10
        assert (r.set_table()[12:, 1] == -1).all()
        r.frame_set(24)


def test_all_cameras_gone_stops(tmp_path, caplog):
    ids = ["a", "b"]
    drivers = make_drivers(ids, a={"disconnect_after": 5}, b={"disconnect_after": 8})
    res = capture_take(rig_for(ids), tmp_path / "g.h5", frames=100, drivers=drivers)
    assert res.stopped == "all cameras disconnected"
    assert res.frames == {"a": 5, "b": 8} and 8 <= res.sets <= 13
    with TakeReader(res.path) as r:
        assert r.complete and len(r) == res.sets


def test_duration_stop(tmp_path):
    ids = ["a"]
    res = capture_take(rig_for(ids), tmp_path / "dur.h5", duration_s=0.4, drivers=make_drivers(ids))
    assert res.stopped == "duration" and 1 <= res.sets <= 0.4 * 60 + 2, res
    assert 0.4 <= res.duration_s < 3.0


CHILD = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {root!r})
    from tests.stage.paced import make_drivers, rig_for
    from stage.capture import capture_take
    ids = ["a", "b", "c"]
    capture_take(rig_for(ids, fps=60.0), {path!r}, frames=3000, drivers=make_drivers(ids, fps=60.0),
                 on_set=lambda n: print(n, flush=True))
    """
)


def test_capture_killed_with_sigkill_keeps_flushed_sets(tmp_path):
    path = tmp_path / "killed.h5"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(root=str(ROOT), path=str(path))],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )
    flushed = 0
    try:
        t0 = time.monotonic()
        while flushed < 15:
            line = proc.stdout.readline()
            if not line:
                raise AssertionError(f"capture child died: {proc.stderr.read()}")
            flushed = int(line)
            assert time.monotonic() - t0 < 30
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    from stage.cli.info import summarize

    summary = summarize(path)  # what `stage info` prints, on the killed take
    assert summary["sets"] >= flushed and summary["state"].startswith("open")
    with TakeReader(path) as r:
        assert not r.complete
        assert len(r) >= flushed
        table = r.set_table()
        for k in range(len(r)):
            for i, c in enumerate(["a", "b", "c"]):
                row = table[k, i]
                if row >= 0:
                    seq = int(r.timestamps(c)["sequence"][row])
                    np.testing.assert_array_equal(r.frame(c, row), pattern(i, seq))


def test_invalid_input(tmp_path):
    ids = ["a"]
    rig = rig_for(ids)
    with pytest.raises(ValueError, match="stop condition"):
        capture_take(rig, tmp_path / "x.h5", drivers=make_drivers(ids))
    with pytest.raises(ValueError, match="frames"):
        capture_take(rig, tmp_path / "x.h5", frames=0, drivers=make_drivers(ids))
    with pytest.raises(ValueError, match="duration_s"):
        capture_take(rig, tmp_path / "x.h5", duration_s=-1, drivers=make_drivers(ids))
    with pytest.raises(ValueError, match="rig"):
        capture_take({"cameras": []}, tmp_path / "x.h5", frames=1)
    with pytest.raises(ValueError, match="no driver"):
        capture_take(rig, tmp_path / "x.h5", frames=1, drivers={})
    (tmp_path / "exists.h5").write_bytes(b"")
    with pytest.raises(FileExistsError):
        capture_take(rig, tmp_path / "exists.h5", frames=1, drivers=make_drivers(ids))
    with pytest.raises(ValueError, match="compression"):
        capture_take(rig, tmp_path / "c.h5", frames=1, drivers=make_drivers(ids), compression="zip")
    assert not (tmp_path / "c.h5").exists() or TakeReader


def test_cli_capture_simulated_rig(tmp_path, capsys):
    """`stage capture` end to end through the registry and the fake driver (tiny images)."""
    from fake_cameras.rigs import write_simulated_rig
    from stage.cli import main

    rig = write_simulated_rig(tmp_path / "rig.toml", 2, size=(160, 120), frames=6, fps=30)
    out = tmp_path / "cap.h5"
    code = main(["capture", "--rig", str(rig), "--frames", "8", "--out", str(out), "--no-progress"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "8 frame sets" in text
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "8 frame sets" in text and "cam01: 160x120 raw" in text
    with TakeReader(out) as r:
        assert r.complete and len(r) == 8 and r.rig["name"] == "simulated"
    assert main(["capture", "--rig", str(rig), "--out", str(tmp_path / "x.h5")]) == 2
    assert "--frames" in capsys.readouterr().err
