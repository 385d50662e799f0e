"""Damaged takes: flipped bytes in a frame chunk or in the header, a truncated file, an old take
without checksums. `stage verify` names the damage; `stage info` / `process` / `verify` never
print a traceback (one line, exit 2) and `stage process` stops before any work."""

import contextlib
import io
import os
import shutil
import subprocess

import h5py
import numpy as np
import pytest

from stage.frame import Frame
from stage.store import CameraSpec, TakeError, TakeReader, TakeWriter
from stage.store.verify import frames_text, verify_take

N = 40  # more than one read block (32 rows)


def _write(path, *, rng_seed=0):
    rng = np.random.default_rng(rng_seed)
    specs = [CameraSpec("a", 32, 24, depth=True), CameraSpec("b", 32, 24, storage="jpeg")]
    with TakeWriter(path, specs, fps=30.0) as w:
        for k in range(N):
            img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
            dep = rng.integers(0, 4000, (24, 32), dtype=np.uint16)
            w.write_set({"a": Frame(img, "a", k, k, k, depth=dep), "b": Frame(img, "b", k, k, k)})
    return path


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("verify") / "t.h5")


def _flip(src, dst, offset, n=16):
    if src != dst:
        shutil.copy(src, dst)
    with open(dst, "r+b") as fh:
        fh.seek(offset)
        data = bytearray(fh.read(n))
        fh.seek(offset)
        fh.write(bytes(x ^ 0xFF for x in data))
    return dst


def _chunk_offset(path, name, coord, into=None):
    """A byte inside the stored chunk (``into`` bytes in; default its middle)."""
    with h5py.File(path, "r") as f:
        info = f[name].id.get_chunk_info_by_coord(coord)
        return info.byte_offset + (info.size // 2 if into is None else into)


def _header_offset(path, name):
    with h5py.File(path, "r") as f:
        return h5py.h5o.get_info(f[name].id).addr + 6


def _stage(*args, cwd):
    """``stage ARGS`` in this process (an exception it does not handle fails the test)."""
    from stage.cli import main

    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in args])
    finally:
        os.chdir(old)
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


def _one_line(res):
    assert res.returncode == 2, res
    assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    return res.stderr


def test_an_intact_take_has_checksums_on_every_chunk(take):
    with TakeReader(take) as r:
        assert r.checksums
        for c in r.cameras:
            for name, ds in r._f["cameras"][c].items():
                assert ds.fletcher32, (c, name)
    d = verify_take(take)
    assert d.ok and d.checksums and d.n_sets == N and not d.frames


def test_flipped_bytes_in_frame_chunks_are_named(take, tmp_path):
    bad = _flip(take, tmp_path / "frames.h5", _chunk_offset(take, "cameras/a/image", (33, 0, 0, 0)))
    _flip(bad, bad, _chunk_offset(bad, "cameras/a/depth", (5, 0, 0)), n=4)
    d = verify_take(bad)
    assert not d.ok
    assert d.frames == {"a": [5, 33]} and d.sets == [5, 33]
    assert "camera a frames 5, 33" in d.summary()
    with TakeReader(bad) as r:  # a read of the damaged frame is an error, never wrong pixels
        with pytest.raises(TakeError, match="camera a frame 33"):
            r.frame("a", 33)
        r.frame("a", 32)
    bj = _flip(take, tmp_path / "jpeg.h5", _chunk_offset(take, "cameras/b/jpeg", (0,), into=4000))
    d = verify_take(bj)
    # a chunk of the byte stream holds many frames: all of them are named
    assert list(d.frames) == ["b"] and d.frames["b"] == list(range(N)) and "JPEG" in " ".join(d.problems)

    res = _stage("verify", bad.name, cwd=tmp_path)
    assert res.returncode == 1 and "camera a frames 5, 33" in res.stdout and "frame sets 5, 33" in res.stdout


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A small simulated take (4 cameras, 3 frame sets) with a calibration."""
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    folder = tmp_path_factory.mktemp("simulated")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CAPTURE_STAGE_CACHE", str(folder / "cache"))
        return record_take(simulate_take("starfish", n_cameras=4, frames=3, size=(64, 48), seed=1), folder / "s.h5")


def test_process_stops_on_a_damaged_take_naming_the_frames(tmp_path, simulated):
    bad = _flip(simulated, tmp_path / "bad.h5", _chunk_offset(simulated, "cameras/cam02/image", (1, 0, 0, 0)))
    res = _stage("process", bad.name, "--out", "r", "--workers", "0", "--no-progress", cwd=tmp_path)
    err = _one_line(res)
    assert "camera cam02 frames 1" in err and "nothing was processed" in err and "--skip-damaged" in err
    assert not (tmp_path / "r").exists()
    res = _stage("info", bad.name, cwd=tmp_path)  # the summary does not read frames
    assert res.returncode == 0 and "checksums: every chunk" in res.stdout


def test_process_skip_damaged_skips_the_sets_and_lists_them(tmp_path, simulated, caplog):
    import json

    bad = _flip(simulated, tmp_path / "bad.h5", _chunk_offset(simulated, "cameras/cam02/image", (1, 0, 0, 0)))
    res = _stage("process", bad.name, "--out", "r", "--workers", "0", "--no-progress", "--skip-damaged", cwd=tmp_path)
    assert res.returncode == 0, res
    assert "skipped frame sets (damaged frames): [1]" in res.stdout
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("camera cam02 frames 1" in m and "skipped" in m for m in said), said  # the log names them
    assert not any("frame 1: mask invalid" in m for m in said), said  # the damaged frame is not keyed
    out = tmp_path / "r"
    record = json.loads((out / "process.json").read_text())
    assert record["damaged"]["sets"] == [1] and record["damaged"]["frames"] == {"cam02": [1]}
    report = json.loads((out / "report.json").read_text())
    assert report["damaged_sets"] == [1] and any("cam02" in w for w in report["warnings"])
    assert report["per_frame"][1]["status"] == "damaged" and "cam02" in report["per_frame"][1]["reason"]
    assert report["per_frame"][1]["reason"].endswith("the set was skipped, as asked")  # no option: a job's report too
    assert [report["per_frame"][k]["status"] for k in (0, 2)] == ["ok", "ok"] and report["tip_counts"][1] == 0
    assert not (out / "meshes" / "frame_000001.ply").exists() and (out / "meshes" / "frame_000002.ply").exists()
    with TakeReader(bad) as r:  # the damaged frame was never keyed (nor read): its mask is marked invalid
        valid = r.read_array("cameras/cam02", "mask_valid")[0]
        assert not valid[1] and valid[0] and valid[2]
    # the tracking goes past the skipped set, saying so (no "surfaces missing: run stage process again")
    caplog.clear()
    assert _stage("track", "r", "--workers", "0", "--no-progress", cwd=tmp_path).returncode == 0
    assert any("tracked past: 1 (damaged)" in r.getMessage() for r in caplog.records)
    assert not (out / "tracked" / "000001.ply").exists() and (out / "tracked" / "000002.ply").exists()
    # a resumed run still skips the set (the take keeps its damage), and says so again
    res = _stage("process", bad.name, "--out", "r", "--workers", "0", "--no-progress", "--until", "surface",
                 "--skip-damaged", cwd=tmp_path)
    assert res.returncode == 0 and json.loads((out / "report.json").read_text())["damaged_sets"] == [1], res


@pytest.mark.parametrize("name", ["meta/rig", "sets/frames", "cameras/a/image", "cameras/b"])
def test_flipped_bytes_in_the_header_are_one_line(take, tmp_path, name):
    bad = _flip(take, tmp_path / "hdr.h5", _header_offset(take, name))
    with pytest.raises(TakeError, match="damaged take"):
        TakeReader(bad)
    for cmd in (["info", bad.name], ["verify", bad.name], ["process", bad.name, "--out", "r", "--workers", "0", "--no-progress"]):
        assert "damaged take" in _one_line(_stage(*cmd, cwd=tmp_path)), cmd


def test_a_truncated_take_is_one_line(take, tmp_path):
    bad = tmp_path / "cut.h5"
    shutil.copy(take, bad)
    os.truncate(bad, os.path.getsize(bad) * 2 // 3)
    for cmd in (["info", bad.name], ["verify", bad.name], ["process", bad.name, "--out", "r", "--workers", "0", "--no-progress"]):
        assert "truncated" in _one_line(_stage(*cmd, cwd=tmp_path)), cmd


def test_an_old_take_without_checksums_still_reads(tmp_path, monkeypatch):
    import stage.store.writer as writer

    monkeypatch.setattr(writer, "_SUM", {})
    old = _write(tmp_path / "old.h5")
    monkeypatch.undo()
    with TakeReader(old) as r:
        assert not r.checksums and r.n_sets == N
        assert r.frame("a", 3).shape == (24, 32, 3)
    d = verify_take(old)
    assert d.ok and not d.checksums
    res = _stage("info", old.name, cwd=tmp_path)
    assert res.returncode == 0 and "checksums: none" in res.stdout
    res = _stage("verify", old.name, cwd=tmp_path)
    assert res.returncode == 0 and "without checksums" in res.stdout


def test_frames_text():
    assert frames_text([9, 0, 1, 2, 3, 7]) == "0-3, 7, 9"
    assert frames_text(range(0, 40, 2), limit=2) == "0, 2, ... (20 in all)"


def test_invalid_input(tmp_path):
    with pytest.raises(FileNotFoundError):
        verify_take(tmp_path / "none.h5")
    (tmp_path / "x.h5").write_bytes(b"not hdf5")
    with pytest.raises(TakeError):
        verify_take(tmp_path / "x.h5")
