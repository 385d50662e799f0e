"""calib.mirror and calib.take_detect: the per-camera mirror option and the take detection pass (the flipped-image
path itself is tested on rendered takes in test_handheld.py and tests/api/test_calibrations.py)."""

from __future__ import annotations

import pytest

from calib.mirror import parse_mirror, sample_positions
from calib.take_detect import detect_take


def test_parse_mirror_items_and_mapping():
    cams = ["a", "b", "c"]
    assert parse_mirror(["a=true", "b=FALSE", "c=auto"], cams) == {"a": True, "b": False, "c": None}
    assert parse_mirror(["a"], cams) == {"a": True, "b": None, "c": None}  # CAM alone: true
    assert parse_mirror({"b": "true"}, cams) == {"a": None, "b": True, "c": None}


def test_sample_positions_are_even_and_bounded():
    assert sample_positions(0) == set()
    assert sample_positions(5) == {0, 1, 2, 3, 4}
    got = sorted(sample_positions(1000))
    assert len(got) == 12 and got[0] == 0 and got[-1] == 999


def test_invalid_input(tmp_path):
    with pytest.raises(ValueError, match="--mirror x=true: unknown camera 'x'"):
        parse_mirror(["x=true"], ["a"])
    with pytest.raises(ValueError, match='parameters.mirror.a = "maybe": the value must be auto, true or false'):
        parse_mirror({"a": "maybe"}, ["a"], spelling='parameters.mirror.{camera} = "{value}"')
    with pytest.raises(ValueError, match="step"):
        detect_take(tmp_path / "none.h5", None, step=0)
