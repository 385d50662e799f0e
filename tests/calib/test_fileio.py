"""calib.fileio: atomic, durable writes and the JSON default for numpy values."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from calib.fileio import atomic_write, fsync_dir, json_default, plain, replace_durably, strict_json


def test_atomic_write_replaces_whole_files_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "a" / "b.json"
    assert atomic_write(p, '{"x": 1}') == p and p.read_text() == '{"x": 1}'
    atomic_write(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01" and os.listdir(p.parent) == ["b.json"]


def test_a_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    p = tmp_path / "f.txt"
    atomic_write(p, "old")

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OSError, match="No space"):
        atomic_write(p, "new")
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["f.txt"]


def test_writes_flush_the_file_and_its_folder(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(os.path.realpath(f"/proc/self/fd/{fd}")) or real(fd))
    atomic_write(tmp_path / "g.bin", b"1")
    assert len(synced) == 2 and synced[1] == str(tmp_path.resolve())  # the temporary file, then the folder
    tmp = tmp_path / "h.part"
    tmp.write_bytes(b"2")
    synced.clear()
    replace_durably(tmp, tmp_path / "h.bin")
    assert (tmp_path / "h.bin").read_bytes() == b"2" and not tmp.exists() and synced[-1] == str(tmp_path.resolve())
    fsync_dir(tmp_path / "missing")  # nothing to flush: no error


def test_json_default_equals_python_values():
    obj = {"i": np.int64(3), "f": np.float32(0.5), "b": np.bool_(True), "a": np.arange(3).reshape(1, 3)}
    assert json.loads(json.dumps(obj, default=json_default)) == {"i": 3, "f": 0.5, "b": True, "a": [[0, 1, 2]]}
    kept = plain({np.int64(1): (np.float64(2.5), [np.arange(2)])})
    assert kept == {"1": [2.5, [[0, 1]]]} and type(kept["1"][0]) is float and type(kept["1"][1][0][0]) is int


def test_invalid_input(tmp_path):
    with pytest.raises(ValueError, match="data"):
        atomic_write(tmp_path / "x", 3)
    with pytest.raises(TypeError, match="set"):
        json.dumps({1, 2}, default=json_default)
    with pytest.raises(FileNotFoundError):
        replace_durably(tmp_path / "nope", tmp_path / "y")
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "no" / "dir" / "z", "1", parents=False)
    assert not (tmp_path / "no").exists()


def test_strict_json_writes_non_finite_numbers_as_null():
    """What JSON.parse reads: NaN and infinities (Python's and numpy's, in arrays and records too) become null,
    every other value as ``json_default`` writes it; the text never holds NaN or Infinity."""
    from dataclasses import dataclass
    from pathlib import Path

    @dataclass
    class Record:
        rms: float

    x = {"a": float("nan"), "b": [1.5, np.float32(2.5), np.inf], "c": np.array([[0.0, -np.inf]]), 3: np.int64(7),
         "rec": Record(float("nan")), "path": Path("x/y"), "other": object}

    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    back = json.loads(strict_json(x), parse_constant=refuse)
    assert back == {"a": None, "b": [1.5, 2.5, None], "c": [[0.0, None]], "3": 7, "rec": {"rms": None},
                    "path": "x/y", "other": str(object)}
    assert json.loads(strict_json({"k": 1}, indent=None)) == {"k": 1} and "\n" not in strict_json([1, 2], indent=None)
