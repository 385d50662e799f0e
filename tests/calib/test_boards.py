"""Board definitions, rendering and detection (calib.boards, calib.detect)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from calib.boards import BoardError, Charuco, Chessboard, load_board, parse_board, save_board
from calib.detect import Detection, detect_board, select_views


def _expected(board, px_per_mm, margin_mm=None):
    A = board.image_transform(px_per_mm=px_per_mm, margin_mm=margin_mm)
    op = board.object_points()
    return op[:, :2] @ A[:2, :2].T + A[:2, 2]


def test_parse_and_roundtrip(tmp_path):
    b = parse_board({"type": "chessboard", "corners": [9, 6], "square_mm": 25})
    assert b == Chessboard((9, 6), 25.0) and b.n_corners == 54
    c = parse_board({"type": "charuco", "squares": [4, 5], "square_mm": 54, "marker_mm": 40.5,
                     "dictionary": "DICT_4X4_1000", "legacy": False, "inverted": True})
    assert c.grid == (3, 4) and c.n_corners == 12 and c.inverted
    for board in (b, c):
        p = tmp_path / f"{board.type}.toml"
        save_board(board, p)
        assert load_board(p) == board
        assert parse_board(tomllib.loads(board.to_toml())) == board


def test_object_points_match_opencv():
    c = Charuco((5, 7), 30, 22, dictionary="DICT_4X4_50")
    np.testing.assert_allclose(c.object_points(), c.to_cv().getChessboardCorners(), atol=1e-9)
    b = Chessboard((4, 3), 10)
    op = b.object_points()
    assert op.shape == (12, 3) and np.all(op[:, 2] == 0)
    np.testing.assert_allclose(op[5], [10, 10, 0])  # row-major: index 5 = column 1, row 1
    pairs = b.neighbor_pairs()
    np.testing.assert_allclose(np.linalg.norm(op[pairs[:, 0]] - op[pairs[:, 1]], axis=1), 10)


def test_legacy_flag_reaches_opencv():
    assert Charuco((4, 6), 30, 20, dictionary="DICT_4X4_50", legacy=True).to_cv().getLegacyPattern()
    assert not Charuco((4, 6), 30, 20, dictionary="DICT_4X4_50").to_cv().getLegacyPattern()


@pytest.mark.parametrize("rot", [0, 1, 2, 3])
@pytest.mark.parametrize("method", ["classic", "sb"])
def test_chessboard_detection_canonical_order(rot, method):
    """Both detectors, any in-plane rotation: corners come back in the board frame's order."""
    b = Chessboard((9, 6), 10)
    img = b.image(px_per_mm=3)
    exp = _expected(b, 3)
    h, w = img.shape
    img_r = np.ascontiguousarray(np.rot90(img, rot))
    # where the expected corners go under np.rot90 (counter-clockwise)
    e = exp.copy()
    for _ in range(rot):
        e = np.stack([e[:, 1], (w - 1) - e[:, 0]], axis=1)
        h, w = w, h
    d = detect_board(img_r, b, method=method)
    assert d is not None and len(d) == 54
    assert np.abs(d.corners - e).max() < 0.5


@pytest.mark.parametrize("inverted", [False, True])
def test_charuco_detection_and_inverted_print(inverted):
    c = Charuco((5, 7), 30, 22, dictionary="DICT_4X4_50", inverted=inverted)
    img = c.image(px_per_mm=3)
    d = detect_board(img, c)
    assert d is not None and len(d) == c.n_corners
    assert np.abs(d.corners - _expected(c, 3)[d.ids]).max() < 0.5
    # the same print read with the wrong polarity is not found
    other = Charuco((5, 7), 30, 22, dictionary="DICT_4X4_50", inverted=not inverted)
    assert detect_board(img, other) is None


def test_charuco_drawn_where_opencv_cannot_draw_it():
    """At 60 pixels a square OpenCV's generateImage fails on this board (a marker one pixel past the pattern); the
    board is then drawn at twice the size and averaged down: every corner is found where ``image_transform`` puts it,
    within the 0.5 px the other sizes are held to."""
    import cv2

    c = Charuco((7, 5), 70.0, 52.0, dictionary="DICT_4X4_50")
    with pytest.raises(cv2.error):  # the size is one OpenCV fails on (else this test checks nothing)
        c.to_cv().generateImage((420, 300), marginSize=0, borderBits=1)
    img = c.image(px_per_mm=60 / 70.0)
    A = c.image_transform(px_per_mm=60 / 70.0)
    assert img.shape == (300 + 2 * 60, 420 + 2 * 60) and np.allclose(A[:2, :2], np.eye(2) * 60 / 70.0)
    d = detect_board(img, c)
    assert d is not None and len(d) == c.n_corners
    assert np.abs(d.corners - _expected(c, 60 / 70.0)[d.ids]).max() < 0.5


def test_wrong_corner_count_not_detected():
    img = Chessboard((9, 6), 10).image(px_per_mm=3)
    assert detect_board(img, Chessboard((8, 6), 10)) is None


def test_select_views_keeps_moving_views():
    base = Chessboard((4, 3), 10).object_points()[:, :2] * 3 + 100
    dets = [Detection(np.arange(12), base + [dx, 0], frame=i) for i, dx in enumerate([0, 1, 2, 40, 41, 100])]
    dets.insert(2, None)
    keep = select_views(dets, size=(640, 480), min_corners=12, min_change=0.02)
    assert [dets[i].frame for i in keep] == [0, 3, 5]
    assert select_views(dets, size=(640, 480), min_corners=13) == []


def test_invalid_input(tmp_path):
    bad = [
        {"type": "chessboard", "corners": [9], "square_mm": 25},
        {"type": "chessboard", "corners": [9, 6]},
        {"type": "chessboard", "corners": [9, 6], "square_mm": -1},
        {"type": "chessboard", "corners": [9, 6], "square_mm": 25, "colour": "red"},
        {"type": "charuco", "squares": [4, 5], "square_mm": 20, "marker_mm": 30},
        {"type": "charuco", "squares": [4, 5], "square_mm": 30, "marker_mm": 20, "dictionary": "DICT_9X9"},
        {"type": "charuco", "squares": [20, 20], "square_mm": 30, "marker_mm": 20, "dictionary": "DICT_4X4_50"},
        {"type": "charuco", "squares": [4, 5], "square_mm": 30, "marker_mm": 20, "legacy": "yes"},
        {"type": "circles"},
    ]
    keys = ["corners", "square_mm", "square_mm", "colour", "marker_mm", "dictionary", "dictionary", "legacy", "type"]
    for d, key in zip(bad, keys):
        with pytest.raises(BoardError, match=key):
            parse_board(d)
    with pytest.raises(FileNotFoundError):
        load_board(tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("type = chessboard\n")
    with pytest.raises(BoardError, match="TOML"):
        load_board(tmp_path / "bad.toml")
    b = Chessboard((9, 6), 25)
    with pytest.raises(ValueError, match="px_per_mm"):
        b.image(px_per_mm=0)
    with pytest.raises(ValueError, match="board"):
        detect_board(np.zeros((10, 10), np.uint8), {"type": "chessboard"})
    with pytest.raises(ValueError, match="image"):
        detect_board(np.zeros((10,), np.uint8), b)
    with pytest.raises(ValueError, match="method"):
        detect_board(np.zeros((10, 10), np.uint8), b, method="fast")
    with pytest.raises(ValueError, match="size"):
        select_views([], size=(0, 10))
    with pytest.raises(ValueError, match="min_change"):
        select_views([], size=(10, 10), min_change=-1)


def test_find_variant_names_the_first_variant_that_finds_the_board():
    """Rendered prints: a mirrored image, an inverted print and a wrong board file."""
    import dataclasses

    from calib.detect import find_variant

    board = Charuco((5, 7), 30, 22, dictionary="DICT_4X4_50")
    img = board.image(px_per_mm=3.0)
    assert detect_board(img, board) is not None
    desc, b, mirror, found = find_variant([img[:, ::-1]] * 3, board)
    assert (desc, b, mirror, found) == ("mirrored images", board, True, 3)
    desc, b, mirror, found = find_variant([255 - img] * 3, board)
    assert b == dataclasses.replace(board, inverted=True) and not mirror and "inverted = true" in desc
    chess = Chessboard((9, 6), 25.0)
    assert find_variant([chess.image(px_per_mm=2.0)] * 3, Chessboard((12, 9), 25.0)) is None
    assert find_variant([], board) is None
    # found in one image of three: below min_found
    blank = np.full_like(img, 255)
    assert find_variant([img[:, ::-1], blank, blank], board) is None
    assert find_variant([img[:, ::-1], blank, blank], board, min_found=1)[3] == 1


def test_find_variant_names_the_inner_corners_when_the_squares_were_given():
    from calib.detect import find_variant

    img = Chessboard((9, 6), 25.0).image(px_per_mm=2.0)
    desc, b, mirror, found = find_variant([img] * 3, Chessboard((10, 7), 25.0))
    assert desc == "board file with corners = [9, 6]" and b.corners == (9, 6) and not mirror and found == 3
