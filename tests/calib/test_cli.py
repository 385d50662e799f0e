"""``stage calibrate``, ``stage calibration export``, ``stage board`` (through stage.cli.main)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boards import Charuco, Chessboard, save_board
from calib.formats import read_calibration
from stage.cli import main
from tests.conftest import shared_dataset


@pytest.fixture(scope="module")
def stereo_dir(tmp_path_factory):
    root = shared_dataset("opencv_stereo_9x6")
    d = tmp_path_factory.mktemp("stereo")
    for side in ("left", "right"):
        (d / "imgs" / side).mkdir(parents=True)
        for f in sorted(root.glob(f"{side}*.jpg")):
            (d / "imgs" / side / f.name.replace(side, "")).symlink_to(f)
    save_board(Chessboard((9, 6), 25.0), d / "board.toml")
    save_board(Chessboard((10, 7), 25.0), d / "squares_not_corners.toml")
    return d


def test_calibrate_images_then_export(stereo_dir, tmp_path, capsys):
    out = tmp_path / "calib.toml"
    rc = main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(stereo_dir / "board.toml"),
               "--out", str(out), "--world", "camera", "--coverage", str(tmp_path / "cov")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "left" in text and "board triangulated" in text
    calib = read_calibration(out)
    assert calib.names == ["left", "right"]
    assert abs(np.linalg.norm(calib["right"].center) - 83.6) < 1.0
    assert (tmp_path / "cov" / "coverage_left.png").is_file()
    for fmt, ext in (("yaml", ".yml"), ("json", ".json")):
        assert main(["calibration", "export", str(out), "--format", fmt]) == 0
        assert read_calibration(out.with_suffix(ext)) == calib


def test_calibrate_distortion_auto_and_rotation_uncertainty(stereo_dir, tmp_path, capsys):
    import json

    out, rep = tmp_path / "calib.toml", tmp_path / "report.json"
    assert main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(stereo_dir / "board.toml"),
                 "--out", str(out), "--holdout", "0", "--distortion", "auto", "--report", str(rep)]) == 0
    text = capsys.readouterr().out
    assert "rotation deg vs " in text
    report = json.loads(rep.read_text())
    for r in report["intrinsics"].values():
        assert set(r["dropped_by_model_selection"]) <= {"p1", "p2", "k3"}
        assert set(r["dropped_by_model_selection"]) <= set(r["held_at_zero"])
    sig = report["evaluation"]["rotation_sigma_deg"]
    assert sig["reference"] in ("left", "right") and 0 < sig["pairs"]["left - right"] < 1.0
    with pytest.raises(SystemExit):
        main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(stereo_dir / "board.toml"),
              "--distortion", "some"])


def test_calibrate_wrong_board_writes_nothing(stereo_dir, tmp_path, capsys):
    out = tmp_path / "calib.toml"
    # every 4th frame: a failed chessboard search costs ~0.5 s an image, and 4 frames per camera show the same
    rc = main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board",
               str(stereo_dir / "squares_not_corners.toml"), "--out", str(out), "--step", "4"])
    assert rc == 2
    err = capsys.readouterr().err
    # the squares given as corners: the variant search names the inner corners that find the board
    assert "camera left" in err and "corners = [9, 6]" in err and "fix the board file" in err
    assert not out.exists()
    # a board that matches nothing: one line per camera saying what was tried
    save_board(Charuco((5, 7), 30, 22, dictionary="DICT_4X4_50"), tmp_path / "charuco.toml")
    assert main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(tmp_path / "charuco.toml"),
                 "--out", str(out), "--step", "4"]) == 2
    err = capsys.readouterr().err
    assert "camera left" in err and "camera right" in err and "board file matches the print" in err
    assert not out.exists()


def test_board_pdf_and_png(tmp_path):
    save_board(Chessboard((9, 6), 25.0), tmp_path / "b.toml")
    assert main(["board", str(tmp_path / "b.toml"), "--out", str(tmp_path / "b.pdf")]) == 0
    pdf = (tmp_path / "b.pdf").read_bytes()
    # 10 x 7 squares of 25 mm plus a one-square margin each side = 300 x 225 mm
    import re

    box = [float(v) for v in re.search(rb"/MediaBox \[ ?([\d. ]+)\]", pdf).group(1).split()]
    assert abs(box[2] - 300 / 25.4 * 72) < 1.0 and abs(box[3] - 225 / 25.4 * 72) < 1.0
    assert main(["board", str(tmp_path / "b.toml"), "--out", str(tmp_path / "b.png"), "--dpi", "254"]) == 0
    from PIL import Image

    with Image.open(tmp_path / "b.png") as im:
        assert im.size == (3000, 2250)  # 254 dpi = 10 px/mm


def test_invalid_input(tmp_path, capsys):
    save_board(Chessboard((9, 6), 25.0), tmp_path / "b.toml")
    assert main(["calibrate", "--board", str(tmp_path / "b.toml"), "--out", str(tmp_path / "c.toml")]) == 2
    assert "either a take" in capsys.readouterr().err
    assert main(["calibrate", "--images", str(tmp_path / "nope"), "--board", str(tmp_path / "b.toml"),
                 "--out", str(tmp_path / "c.toml")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["board", str(tmp_path / "b.toml"), "--out", str(tmp_path / "b.jpg")]) == 2
    assert ".png or .pdf" in capsys.readouterr().err
    assert main(["calibration", "export", str(tmp_path / "missing.toml"), "--format", "json"]) == 2
    assert not (tmp_path / "c.toml").exists()


def test_calibrate_take_stores_calibration(stereo_dir, tmp_path, capsys):
    import cv2

    from stage import store
    from stage.frame import Frame

    take = tmp_path / "board.h5"
    specs = [store.CameraSpec("left", 640, 480), store.CameraSpec("right", 640, 480)]
    files = {s: sorted((stereo_dir / "imgs" / s).iterdir()) for s in ("left", "right")}
    with store.TakeWriter(take, specs, fps=10) as w:
        for k in range(len(files["left"])):
            fr = {}
            for s in ("left", "right"):
                img = cv2.imread(str(files[s][k]))
                fr[s] = Frame(image=img, camera_id=s, index=k, timestamp_ns=k * 100_000_000,
                              host_timestamp_ns=k * 100_000_000)
            w.write_set(fr)
    # a failing calibration leaves the take untouched
    assert main(["calibrate", str(take), "--board", str(stereo_dir / "squares_not_corners.toml"), "--step", "4"]) == 2
    with store.TakeReader(take) as r:
        assert not r.has_calibration
    capsys.readouterr()
    assert main(["calibrate", str(take), "--board", str(stereo_dir / "board.toml"), "--world", "camera"]) == 0
    with store.TakeReader(take) as r:
        calib = r.calibration
    assert calib.names == ["left", "right"]
    assert abs(np.linalg.norm(calib["right"].center) - 83.6) < 1.0


def test_quiet_calibrate_prints_the_verdict_then_the_held_out_line(stereo_dir, tmp_path, capsys):
    import json

    out = tmp_path / "calib.toml"
    rc = main(["-q", "calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(stereo_dir / "board.toml"),
               "--out", str(out), "--holdout", "3", "--intrinsics", "fixed", "--report", str(tmp_path / "r.json")])
    assert rc == 0
    captured = capsys.readouterr()
    lines = [ln for ln in captured.out.splitlines() if not ln.startswith("  ")]
    assert lines[0].startswith("verdict: ")
    assert lines[1].startswith("held-out reprojection RMS (3-fold over 13 frame sets)")
    assert "detect left" not in captured.err  # no progress bars under -q
    rep = json.loads((tmp_path / "r.json").read_text())
    assert set(rep["evaluation"]["held_out"]["per_camera"]) == {"left", "right"}
    assert rep["evaluation"]["mode"] == "fixed"
    for fmt, name in (("caliscope", "camera_array.toml"), ("colmap", "colmap"), ("nerfstudio", "transforms.json")):
        assert main(["calibration", "export", str(out), "--format", fmt]) == 0
        back = read_calibration(tmp_path / name, **({"units": "mm"} if fmt == "colmap" else {}))
        assert len(back) == 2


def test_calibrate_prints_every_warning(stereo_dir, tmp_path, capsys):
    """The terminal shows every warning of the calibration (report.json's ``warnings``), not only the report's own."""
    import json

    rep = tmp_path / "report.json"
    assert main(["calibrate", "--images", str(stereo_dir / "imgs"), "--board", str(stereo_dir / "board.toml"),
                 "--out", str(tmp_path / "c.toml"), "--step", "3", "--holdout", "0", "--report", str(rep)]) == 0
    text = capsys.readouterr().out
    warnings = json.loads(rep.read_text())["warnings"]
    assert warnings, "this calibration (a third of the views) is expected to warn"
    for w in warnings:
        assert f"warning: {w}" in text, w
