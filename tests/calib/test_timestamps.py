"""Synchronising videos by a timestamps file (calib.timestamps) and the real-footage input checks
of ``stage calibrate --images`` (a video per camera folder, videos of different lengths)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.timestamps import TimestampsError, read_timestamps


def _write(path, header, rows):
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


def test_caliscope_layout_uses_sync_index(tmp_path):
    rows = [(s, c, 100 + 0.1 * s + 0.001 * c) for s in range(10, 15) for c in (0, 1)]
    f = _write(tmp_path / "timestamps.csv", "sync_index,cam_id,frame_time", rows)
    sets, warnings = read_timestamps(f, ["cam_0", "cam_1"])
    assert sets == {"cam_0": {i: 10 + i for i in range(5)}, "cam_1": {i: 10 + i for i in range(5)}}
    assert warnings == []


def test_caliscope_gap_is_reported_by_camera(tmp_path):
    rows = [(s, 0, s * 0.1) for s in range(6)] + [(s, 1, s * 0.1) for s in (0, 1, 4, 5)]
    f = _write(tmp_path / "timestamps.csv", "sync_index,cam_id,frame_time", rows)
    sets, warnings = read_timestamps(f, ["cam_0", "cam_1"])
    assert sets["cam_1"] == {0: 0, 1: 1, 2: 4, 3: 5}  # the n-th row of a camera is its n-th frame
    assert len(warnings) == 1 and warnings[0].startswith("cam_1") and "2 sync index" in warnings[0]


def test_plain_layout_nearest_time_within_half_a_period(tmp_path):
    period = 1 / 30
    rows = [("a", k, k * period) for k in range(30)]
    # b started 4 frames late, its clock 3 ms off; its frame 10 came 0.6 periods late (no partner)
    tb = [(k + 4) * period + 0.003 for k in range(20)]
    tb[10] += 0.6 * period
    rows += [("b", k, t) for k, t in enumerate(tb)]
    f = _write(tmp_path / "t.csv", "camera,frame,time_s", rows)
    sets, warnings = read_timestamps(f, ["a", "b"])
    assert sets["a"] == {k: k for k in range(30)}
    expect = {k: k + 4 for k in range(20) if k != 10}
    assert {k: v for k, v in sets["b"].items() if k != 10} == expect and 10 not in sets["b"]
    assert any(w.startswith("b:") and "1 frame(s)" in w for w in warnings)


def test_plain_layout_time_gap_warns(tmp_path):
    rows = [("a", k, k * 0.1) for k in range(10)] + [("b", i, t) for i, t in enumerate([0.0, 0.1, 0.2, 0.7, 0.8])]
    f = _write(tmp_path / "t.csv", "camera,frame,time_s", rows)
    _, warnings = read_timestamps(f, ["a", "b"])
    assert any(w.startswith("b:") and "jump" in w for w in warnings)


def test_invalid_input(tmp_path):
    f = _write(tmp_path / "t.csv", "sync_index,cam_id,frame_time", [(0, 0, 0.0), (0, 7, 0.0)])
    with pytest.raises(TimestampsError, match=r"line 3: unknown camera '7'"):
        read_timestamps(f, ["cam_0", "cam_1"])
    f = _write(tmp_path / "t.csv", "sync_index,cam_id,frame_time", [(0, 0, 0.0)])
    with pytest.raises(TimestampsError, match="no rows for camera.*cam_1"):
        read_timestamps(f, ["cam_0", "cam_1"])
    f = _write(tmp_path / "t.csv", "when,who", [(0, 0)])
    with pytest.raises(TimestampsError, match="expected the columns"):
        read_timestamps(f, ["cam_0"])
    f = _write(tmp_path / "t.csv", "camera,frame,time_s", [("a", 0, "soon")])
    with pytest.raises(TimestampsError, match="time_s 'soon' is not a number"):
        read_timestamps(f, ["a"])
    with pytest.raises(TimestampsError, match="no such file"):
        read_timestamps(tmp_path / "missing.csv", ["a"])


def _video(path, n, size=(64, 48)):
    import cv2

    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, size)
    if not w.isOpened():
        pytest.skip("this OpenCV cannot write mp4 videos")
    for k in range(n):
        w.write(np.full((size[1], size[0], 3), 10 * k, np.uint8))
    w.release()
    return path


def test_camera_folder_with_one_video_is_read(tmp_path):
    from stage.cli.calibrate import _frames, _sources

    (tmp_path / "cam_a").mkdir()
    _video(tmp_path / "cam_a" / "take.mp4", 4)
    _video(tmp_path / "cam_b.mp4", 3)
    src = _sources(tmp_path)
    assert src["cam_a"][0] == "video" and src["cam_a"][1].name == "take.mp4"
    assert len(list(_frames(*src["cam_a"], 1))) == 4
    _video(tmp_path / "cam_a" / "other.mp4", 2)
    with pytest.raises(ValueError, match="cam_a holds 2 videos"):
        _sources(tmp_path)


def test_shorter_video_is_named():
    from stage.cli.calibrate import _length_notes

    notes = _length_notes({"cam_0": 48, "cam_1": 40, "cam_2": 48}, None)
    assert len(notes) == 1 and notes[0].startswith("cam_1: 40 frames, the others up to 48")
    notes = _length_notes({"cam_0": 48, "cam_1": 40}, {"cam_0": dict.fromkeys(range(48), 0),
                                                        "cam_1": dict.fromkeys(range(48), 0)})
    assert len(notes) == 1 and notes[0].startswith("cam_1: the timestamps list 48 frames, its video holds 40")
