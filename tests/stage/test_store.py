"""HDF5 take store: round trips, SWMR reading while writing, killed writers, damaged files."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from stage.frame import Frame
from stage.store import (
    CameraSpec,
    TakeError,
    TakeReader,
    TakeWriter,
    attach_calibration,
    have_lz4,
    recover_take,
    write_array,
    write_masks,
)
from tests.stage.frames import H, W, calibration, make_frame, make_image

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("compression", ["none", "gzip", "lz4"])
def test_roundtrip_raw(tmp_path, compression):
    if compression == "lz4" and not have_lz4():
        pytest.skip("hdf5plugin not installed")
    path = tmp_path / "t.h5"
    specs = [CameraSpec("a", W, H), CameraSpec("b", W, H, depth=True)]
    cal = calibration(["a", "b"])
    rig = {"name": "unit", "fps": 30}
    with TakeWriter(path, specs, rig=rig, calibration=cal, compression=compression, fps=30, block=4) as w:
        for k in range(10):
            fb = make_frame("b", 1, k, depth=True) if k != 3 else None  # b missing in set 3
            w.write_set({"a": make_frame("a", 0, k), "b": fb})
        w.update_sync_stats({"sets": 10, "cameras": {"b": {"missing": 1}}})
    with TakeReader(path) as r:
        assert r.complete and r.cameras == ["a", "b"] and len(r) == 10
        assert r.frame_counts() == {"a": 10, "b": 9}
        assert r.compression == compression and r.fps == 30
        assert r.rig == rig and r.calibration == cal
        assert r.sync_stats["cameras"]["b"]["missing"] == 1
        table = r.set_table()
        assert table[3, 1] == -1 and table[4, 1] == 3 and (table[:, 0] == np.arange(10)).all()
        for k in range(10):
            fs = r.frame_set(k)
            np.testing.assert_array_equal(fs["a"], make_image(0, k))
            if k == 3:
                assert fs["b"] is None
        np.testing.assert_array_equal(r.frame("b", 3), make_image(1, 4))
        # frames(camera, start, stop): one read, the rows frame() gives
        np.testing.assert_array_equal(r.frames("b", 2, 6), np.stack([r.frame("b", i) for i in range(2, 6)]))
        assert r.frames("a", 4, 4).shape == (0, H, W, 3)
        for bad in ((-1, 2), (3, 2), (0, 11)):
            with pytest.raises(IndexError, match="out of range"):
                r.frames("a", *bad)
        np.testing.assert_array_equal(r.depth("b", 3), np.full((H, W), 1004, np.uint16))
        assert r.depth("a", 0) is None
        ts = r.timestamps("b")
        assert list(ts["sequence"]) == [k for k in range(10) if k != 3]
        assert list(ts["set_index"]) == [k for k in range(10) if k != 3]
        assert (ts["valid"] == 1).all()
        assert ts["timestamp_ns"][3] == 2 * 10**12 + 4 * 33_333_333
        assert ts["host_timestamp_ns"][0] == 5 * 10**9 + 1000
        md = r.metadata
        assert md["format"] == "capture-stage/take@1" and "software_version" in md
        assert md["anchor_wall_ns"] > 1.6e18 and md["anchor_monotonic_ns"] > 0
        assert len(list(iter(r))) == 10
        # the file was trimmed to its frames on close
        assert r._f["cameras/a/image"].shape[0] == 10


def test_roundtrip_jpeg_bytes_kept(tmp_path):
    path = tmp_path / "j.h5"
    frames = [make_frame("a", 0, k, jpeg=True) for k in range(5)]
    with TakeWriter(path, [CameraSpec("a", W, H, storage="jpeg")], block=2) as w:
        for fr in frames:
            w.write_set({"a": fr})
    with TakeReader(path) as r:
        assert r.storage("a") == "jpeg"
        for k, fr in enumerate(frames):
            assert r.encoded("a", k) == fr.encoded  # byte for byte, nothing re-encoded
            np.testing.assert_array_equal(r.frame("a", k), cv2.imdecode(np.frombuffer(fr.encoded, np.uint8), cv2.IMREAD_COLOR))
        np.testing.assert_array_equal(r.frames("a", 1, 4), np.stack([r.frame("a", k) for k in range(1, 4)]))


def test_wrong_size_frame_marked_invalid(tmp_path, caplog):
    path = tmp_path / "v.h5"
    with TakeWriter(path, [CameraSpec("a", W, H)]) as w:
        w.write_set({"a": make_frame("a", 0, 0)})
        big = Frame(np.zeros((H * 2, W * 2, 3), np.uint8), "a", 1, 0, 0)
        w.write_set({"a": big})
    assert "expects" in caplog.text
    with TakeReader(path) as r:
        assert list(r.timestamps("a")["valid"]) == [1, 0]


def test_derived_arrays_and_masks(tmp_path):
    path = tmp_path / "m.h5"
    with TakeWriter(path, [CameraSpec("a", W, H)]) as w:
        for k in range(3):
            w.write_set({"a": make_frame("a", 0, k)})
    m = np.zeros((3, H, W), bool)
    m[:, 10:50, 20:70] = True
    write_masks(path, "a", m, {"mode": "chroma", "thresholds": [0.2, 0.4]})
    write_array(path, "cameras/a", "plate", make_image(0, 99), attrs={"source": "test"})
    cal = calibration(["a"])
    attach_calibration(path, cal)
    with TakeReader(path) as r:
        np.testing.assert_array_equal(r.masks("a"), m)
        assert r.mask_params("a") == {"mode": "chroma", "thresholds": [0.2, 0.4]}
        assert r.masks_present() == ["a"]
        plate, attrs = r.read_array("cameras/a", "plate")
        np.testing.assert_array_equal(plate, make_image(0, 99))
        assert attrs["source"] == "test"
        assert r.calibration == cal
    with pytest.raises(ValueError, match="shape"):
        write_masks(path, "a", m[:2])
    with pytest.raises(ValueError, match="reserved"):
        write_array(path, "cameras/a", "image", m)


WRITER_CHILD = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    from tests.stage.frames import make_frame, W, H
    from stage.store import TakeWriter, CameraSpec
    specs = [CameraSpec("a", W, H), CameraSpec("b", W, H, storage="jpeg")]
    w = TakeWriter({path!r}, specs, compression="none", fps=30, block=8)
    k = 0
    while True:
        w.write_set({{"a": make_frame("a", 0, k), "b": make_frame("b", 1, k, jpeg=True)}})
        k += 1
        print(k, flush=True)
        time.sleep({sleep})
    """
)


def _start_writer(path: Path, sleep: float) -> subprocess.Popen:
    code = WRITER_CHILD.format(root=str(ROOT), path=str(path), sleep=sleep)
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)


@contextlib.contextmanager
def _running_writer(path: Path, sleep: float):
    """The writer child (:func:`_start_writer`), killed when the block ends."""
    proc = _start_writer(path, sleep)
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()


def _wait_sets(proc: subprocess.Popen, n: int, timeout: float = 30.0) -> int:
    t0 = time.monotonic()
    last = 0
    while last < n:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"writer died: {proc.stderr.read()}")
        last = int(line)
        assert time.monotonic() - t0 < timeout
    return last


def _check_frames(r: TakeReader, n: int, start: int = 0) -> None:
    for k in range(start, n):
        np.testing.assert_array_equal(r.frame("a", k), make_image(0, k))
        assert r.encoded("b", k) == make_frame("b", 1, k, jpeg=True).encoded


def test_reader_while_writer_runs(tmp_path):
    path = tmp_path / "live.h5"
    with _running_writer(path, 0.02) as proc:
        _wait_sets(proc, 3)
        with TakeReader(path) as r:
            n0 = len(r)
            assert n0 >= 3 and not r.complete
            _check_frames(r, n0)
            n1 = _wait_sets(proc, n0 + 5)
            assert r.refresh() >= n0 + 5 - 1 and n1 >= n0 + 5
            _check_frames(r, len(r))


class _TornChunk:
    """A dataset whose first ``fails`` reads fail as a chunk rewritten during the read does."""

    def __init__(self, ds, fails: int) -> None:
        self.ds, self.fails, self.refreshed = ds, fails, 0

    def __getitem__(self, sel):
        if self.fails:
            self.fails -= 1
            raise OSError("Can't synchronously read data (filter returned failure during read)")
        return self.ds[sel]

    def refresh(self) -> None:
        self.refreshed += 1


def test_live_reads_meet_chunks_being_rewritten(tmp_path, monkeypatch):
    # the writer rewrites a chunk that holds committed and new records (the JPEG stream) in place;
    # a read during the rewrite fails the chunk's checksum: on a live take the read is tried again
    path = tmp_path / "live.h5"
    with _running_writer(path, 0.0) as proc:
        _wait_sets(proc, 3)
        with TakeReader(path) as r:
            torn = _TornChunk(r._f["sets/frames"], 2)
            np.testing.assert_array_equal(r._read(torn, 0, "set 0"), r._f["sets/frames"][0])
            assert torn.refreshed == 2
            with pytest.raises(TakeError, match="cannot read set 0: .*filter returned failure"):
                r._read(_TornChunk(r._f["sets/frames"], 99), 0, "set 0")
            # refresh's own reads (the commit counter, the JPEG offsets and lengths) are live reads too
            torn_once, read = {"/sets/commit", "/cameras/b/jpeg_offset", "/cameras/b/jpeg_length"}, h5py.Dataset.__getitem__

            def tearing(ds, sel):
                if ds.name in torn_once:
                    torn_once.discard(ds.name)
                    raise OSError("Can't synchronously read data (filter returned failure during read)")
                return read(ds, sel)

            with monkeypatch.context() as m:
                m.setattr(h5py.Dataset, "__getitem__", tearing)
                assert r.refresh() >= 3 and not torn_once
            # and the real thing: the newest frames read while the writer runs flat out
            t0 = time.monotonic()
            while time.monotonic() - t0 < 3.0:
                n = r.refresh()
                _check_frames(r, n, start=max(0, n - 4))
    # a complete take's damage is not transient: no second try
    done = tmp_path / "done.h5"
    with TakeWriter(done, [CameraSpec("a", W, H)], compression="none") as w:
        w.write_set({"a": make_frame("a", 0, 0)})
    with TakeReader(done) as r:
        assert r.complete
        with pytest.raises(TakeError, match="cannot read set 0"):
            r._read(_TornChunk(r._f["sets/frames"], 1), 0, "set 0")


def test_sigkill_mid_take_keeps_flushed_sets(tmp_path):
    path = tmp_path / "killed.h5"
    proc = _start_writer(path, 0.0)
    flushed = _wait_sets(proc, 12)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with TakeReader(path) as r:
        assert not r.complete
        assert len(r) >= flushed
        assert r.frame_counts()["a"] == len(r)
        _check_frames(r, len(r))
    with pytest.raises(TakeError, match="not closed cleanly"):
        write_array(path, "cameras/a", "x", np.zeros((2, 2)))
    # the killed take, truncated as well (e.g. a disk that filled up): a clear error, no zeros served
    cut = tmp_path / "killed_cut.h5"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with pytest.raises(TakeError, match="truncated|damaged|cannot"):
        with TakeReader(cut) as r:
            _check_frames(r, len(r))
    # a clean copy of the committed sets
    fixed = tmp_path / "fixed.h5"
    n = recover_take(path, fixed)
    assert n >= flushed
    with TakeReader(fixed) as r:
        assert r.complete and len(r) == n
        _check_frames(r, n)
    write_array(fixed, "cameras/a", "x", np.zeros((2, 2)))


@pytest.fixture
def small_take(tmp_path):
    path = tmp_path / "small.h5"
    with TakeWriter(path, [CameraSpec("a", W, H)], compression="none") as w:
        for k in range(4):
            w.write_set({"a": make_frame("a", 0, k)})
    return path


MASK_WRITER_CHILD = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    import h5py
    f = h5py.File({path!r}, "r+")          # what write_masks does, without SWMR
    f.create_group("scratch")
    f.flush()
    print("open", flush=True)
    time.sleep(60)
    """
)


def test_killed_mask_writer_leaves_a_readable_take(tmp_path, caplog):
    """A process killed while it had the take open to write masks (non-SWMR) left the
    superblock flagged "open for write": neither a plain nor a SWMR reader could open it
    (a killed API job could not resume). The flag is cleared when no process holds the file,
    every frame reads back, and masks can be written; while a writer lives, it is left alone."""
    path = tmp_path / "t.h5"
    with TakeWriter(path, [CameraSpec("a", W, H)]) as w:
        for k in range(3):
            w.write_set({"a": make_frame("a", 0, k)})
    live = subprocess.Popen([sys.executable, "-c", MASK_WRITER_CHILD.format(root=str(ROOT), path=str(path))],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert live.stdout.readline().strip() == "open"
        with pytest.raises(TakeError, match="cannot open|not closed cleanly"):
            TakeReader(path)
        assert path.read_bytes()[11] & 1  # still flagged: not touched while its writer lives
    finally:
        live.kill()  # SIGKILL: the flag stays set
        live.wait()
    assert path.read_bytes()[11] & 1
    with caplog.at_level(logging.WARNING):
        with TakeReader(path) as r:
            assert r.n_sets == 3
            for k in range(3):
                np.testing.assert_array_equal(r.frame("a", k), make_image(0, k))
    assert "h5clear" in caplog.text and path.read_bytes()[11] == 0
    write_masks(path, "a", np.ones((3, H, W), bool))
    with TakeReader(path) as r:
        assert r.masks("a").all()


def test_superblock_checksum_is_hdf5s():
    """The lookup3 checksum written when clearing the flag is the one HDF5 computes."""
    import io

    from stage.store.h5repair import _lookup3

    buf = io.BytesIO()
    with h5py.File(buf, "w", libver="latest"):
        pass
    head = buf.getvalue()[:48]
    assert head[8] == 3 and head[9] == 8
    assert _lookup3(head[:44]) == int.from_bytes(head[44:48], "little")
    assert _lookup3(b"") == 0xDEADBEEF


def test_truncated_take(small_take, tmp_path):
    data = small_take.read_bytes()
    for cut in (len(data) // 2, len(data) - 100):
        bad = tmp_path / f"trunc{cut}.h5"
        bad.write_bytes(data[:cut])
        with pytest.raises(TakeError, match=str(bad.name)) as ei:
            with TakeReader(bad) as r:
                [r.frame("a", i) for i in range(len(r))]
        assert "truncated" in str(ei.value) or "cannot read" in str(ei.value)


def test_corrupt_take(small_take, tmp_path):
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(TakeError, match="not an HDF5 file"):
        TakeReader(garbage)
    # an HDF5 file that is not a take
    import h5py

    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(TakeError, match="not a capture-stage take"):
        TakeReader(other)
    # garbage in the middle of a valid file: opening or reading fails clearly, never silently
    data = bytearray(small_take.read_bytes())
    data[2048:2048 + 512] = bytes(512)
    hurt = tmp_path / "hurt.h5"
    hurt.write_bytes(bytes(data))
    try:
        with TakeReader(hurt) as r:
            for i in range(len(r)):
                r.frame("a", i)
    except TakeError as exc:
        assert "hurt.h5" in str(exc)


def test_invalid_input(tmp_path, small_take):
    with pytest.raises(ValueError, match="cameras"):
        TakeWriter(tmp_path / "x.h5", [])
    with pytest.raises(ValueError, match="duplicate"):
        TakeWriter(tmp_path / "x.h5", [CameraSpec("a", W, H), CameraSpec("a", W, H)])
    with pytest.raises(ValueError, match="compression"):
        TakeWriter(tmp_path / "x.h5", [CameraSpec("a", W, H)], compression="zstd")
    with pytest.raises(ValueError, match="storage"):
        CameraSpec("a", W, H, storage="png")
    with pytest.raises(ValueError, match="camera id"):
        CameraSpec("a/b", W, H)
    with pytest.raises(FileExistsError):
        TakeWriter(small_take, [CameraSpec("a", W, H)])
    with TakeWriter(tmp_path / "y.h5", [CameraSpec("a", W, H)]) as w:
        with pytest.raises(ValueError, match="unknown camera"):
            w.write_set({"zz": None})
        with pytest.raises(ValueError, match="Frame"):
            w.write_set({"a": "not a frame"})
    with pytest.raises(ValueError, match="closed"):
        w.write_set({})
    with pytest.raises(FileNotFoundError):
        TakeReader(tmp_path / "nope.h5")
    with TakeReader(small_take) as r:
        with pytest.raises(KeyError, match="no camera"):
            r.frame("zz", 0)
        with pytest.raises(IndexError, match="out of range"):
            r.frame("a", 99)
        with pytest.raises(IndexError, match="out of range"):
            r.frame_set(4)
    with pytest.raises(ValueError, match="name"):
        write_array(small_take, "cameras/a", "", np.zeros(3))
    with pytest.raises(ValueError, match="dtype"):
        write_array(small_take, "cameras/a", "s", np.array(["x"]))
    with pytest.raises(ValueError, match="camera"):
        write_masks(small_take, "zz", np.zeros((4, H, W), bool))
    with pytest.raises(ValueError, match="calibration"):
        attach_calibration(small_take, {"cameras": []})
