"""A bad-input corpus for the `stage` CLI: every case exits 2 with one clear error line, no traceback,
and changes no file."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from stage.cli import main
from tests.stage.frames import H, W, calibration, make_frame


def _tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` (and the top of every directory) with its checksum."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for d in dirs:
            out[os.path.relpath(os.path.join(dirpath, d), root) + "/"] = "dir"
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = "link" if os.path.islink(p) else hashlib.sha256(Path(p).read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    from stage.store import CameraSpec, TakeWriter

    d = tmp_path_factory.mktemp("corpus")
    cams = ("a", "b")
    with TakeWriter(d / "t.h5", [CameraSpec(c, W, H) for c in cams], fps=30, calibration=calibration(cams)) as w:
        for k in range(3):
            w.write_set({c: make_frame(c, i, k) for i, c in enumerate(cams)})
    with TakeWriter(d / "nocal.h5", [CameraSpec("a", W, H)], fps=30) as w:
        w.write_set({"a": make_frame("a", 0, 0)})
    data = (d / "t.h5").read_bytes()
    (d / "empty.h5").write_bytes(b"")
    (d / "garbage.h5").write_bytes(np.random.default_rng(0).bytes(4096))
    (d / "truncated.h5").write_bytes(data[: len(data) // 2])
    (d / "text.h5").write_text("hello\n")
    (d / "dir.h5").mkdir()
    with h5py.File(d / "plain.h5", "w") as f:
        f["x"] = np.arange(3)
    shutil.copy(d / "t.h5", d / "damaged.h5")
    with h5py.File(d / "damaged.h5", "r+") as f:
        del f["cameras/b/timestamp_ns"]
    good = calibration(["a"]).to_dict()
    (d / "cal.json").write_text(json.dumps(good))
    bad = json.loads(json.dumps(good))
    bad["cameras"][0]["K"][0][0] = float("nan")
    (d / "nan.json").write_text(json.dumps(bad))
    bad = json.loads(json.dumps(good))
    bad["cameras"][0]["t"] = [0, 0]
    (d / "shape.json").write_text(json.dumps(bad))
    (d / "garbage.json").write_text("{not json")
    (d / "list.json").write_text("[1, 2, 3]")
    (d / "garbage.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1 2\n3\n")
    (d / "random.ply").write_bytes(np.random.default_rng(1).bytes(300))
    (d / "meshes").mkdir()
    (d / "meshes" / "frame_000000.ply").write_bytes((d / "garbage.ply").read_bytes())
    (d / "images").mkdir()
    (d / "images" / "a.png").write_bytes(b"not a png")
    (d / "rig.toml").write_text("[[cameras]]\nid = 3\n")
    return d


# (name, argv); paths are relative to the corpus directory
CASES = [
    ("info: missing file", ["info", "missing.h5"]),
    ("info: empty file", ["info", "empty.h5"]),
    ("info: random bytes", ["info", "garbage.h5"]),
    ("info: truncated take", ["info", "truncated.h5"]),
    ("info: text file", ["info", "text.h5"]),
    ("info: a directory", ["info", "dir.h5"]),
    ("info: HDF5 but not a take", ["info", "plain.h5"]),
    ("info: damaged layout", ["info", "damaged.h5"]),
    ("info: recover over an existing file", ["info", "t.h5", "--recover", "nocal.h5"]),
    ("info: recover into a missing directory", ["info", "t.h5", "--recover", "no/such/dir/x.h5"]),
    ("calibration: NaN focal length", ["calibration", "show", "nan.json"]),
    ("calibration: wrong vector size", ["calibration", "show", "shape.json"]),
    ("calibration: not JSON", ["calibration", "show", "garbage.json"]),
    ("calibration: JSON list", ["calibration", "show", "list.json"]),
    ("calibration: missing file", ["calibration", "show", "missing.json"]),
    ("calibration: take without one", ["calibration", "show", "nocal.h5"]),
    ("calibration: damaged take", ["calibration", "show", "garbage.h5"]),
    ("process: random bytes", ["process", "garbage.h5", "--out", "out1"]),
    ("process: empty file", ["process", "empty.h5", "--out", "out2"]),
    ("process: missing take", ["process", "missing.h5", "--out", "out3"]),
    ("process: inverted volume", ["process", "t.h5", "--out", "out4", "--volume", "100", "100", "100", "0", "0", "0"]),
    ("process: NaN volume", ["process", "t.h5", "--out", "out5", "--volume", "nan", "0", "0", "1", "1", "1"]),
    ("process: resolution too small", ["process", "t.h5", "--out", "out6", "--resolution", "5"]),
    ("process: zero support plane", ["process", "t.h5", "--out", "out7", "--support-plane", "0", "0", "0", "1"]),
    ("process: out is the take", ["process", "t.h5", "--out", "t.h5"]),
    ("process: take without calibration", ["process", "nocal.h5", "--out", "out8"]),
    ("process: truncated take", ["process", "truncated.h5", "--out", "out9"]),
    ("process: negative workers", ["process", "t.h5", "--out", "out10", "--workers", "-1"]),
    ("spines: garbage mesh", ["spines", "--meshes", "meshes", "--out", "out11"]),
    ("export: no results", ["export", "meshes", "--out", "x.glb"]),
    ("key: random bytes", ["key", "garbage.h5"]),
    ("key: unknown camera", ["key", "t.h5", "--camera", "zz"]),
    ("key: negative grow", ["key", "t.h5", "--grow", "-3"]),
    ("masks: take without masks", ["masks", "t.h5", "--out", "out12"]),
    ("import: missing images", ["import", "--images", "nothere", "--calibration", "cal.json", "--out", "x.h5"]),
    ("import: NaN calibration", ["import", "--images", "images", "--calibration", "nan.json", "--out", "x.h5"]),
    ("import: not an image", ["import", "--images", "images", "--calibration", "cal.json", "--out", "x.h5"]),
    ("import: negative fps", ["import", "--images", "images", "--calibration", "cal.json", "--out", "x.h5", "--fps", "-1"]),
    ("import: out exists", ["import", "--images", "images", "--calibration", "cal.json", "--out", "t.h5"]),
    ("capture: bad rig", ["capture", "--rig", "rig.toml", "--out", "c.h5", "--frames", "1"]),
    ("capture: missing rig", ["capture", "--rig", "norig.toml", "--out", "c.h5", "--frames", "1"]),
    ("report: not a results dir", ["report", "meshes", "--out", "r.html"]),
]


@pytest.mark.parametrize("argv", [c[1] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_clear_line(corpus, argv, capsys, monkeypatch):
    monkeypatch.chdir(corpus)
    before = _tree(corpus)
    rc = main(["-q", *argv])
    err = capsys.readouterr().err
    assert rc == 2, (argv, rc, err)
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    assert "Traceback" not in err and len(lines[0]) < 400, err
    assert _tree(corpus) == before, "a file changed"
