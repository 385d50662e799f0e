"""The frames a warning names (stage.messages): the first five, the rest counted, alike wherever it is said."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stage.messages import FRAMES_NAMED, frames_named


def test_the_first_frames_are_named_and_the_rest_counted():
    assert FRAMES_NAMED == 5
    assert frames_named([]) == ""
    assert frames_named([4]) == "4"
    assert frames_named((1, 3, 5, 7, 9)) == "1, 3, 5, 7, 9"
    assert frames_named([1, 3, 5, 7, 9, 11]) == "1, 3, 5, 7, 9, ..."
    assert frames_named(list(np.arange(10, 40, dtype=np.int64))) == "10, 11, 12, 13, 14, ..."
    assert frames_named(range(12, 0, -1)) == "12, 11, 10, 9, 8, ..."  # in the order given


def test_the_keying_and_the_frames_of_a_step_name_them_alike(caplog):
    """``say_invalid_masks`` (the keying) and ``frames_said`` (a step's per-frame tasks) name seven frames as the
    helper does: the first five, then ``...``."""
    from pipeline.run import frames_said
    from stage.keying.keyer import say_invalid_masks

    rows = [2, 4, 6, 8, 10, 12, 14]
    with caplog.at_level(logging.WARNING, logger="stage.keying"):
        say_invalid_masks(rows, ["black"] * len(rows), camera="cam01")
    assert [r.getMessage() for r in caplog.records] == ["cam01: mask invalid in 7 frames (2, 4, 6, 8, 10, ...): black"]
    said = frames_said("surface", {k: [("empty", None)] for k in rows})
    assert said == [("surface: empty (7 frame sets: 2, 4, 6, 8, 10, ...)",) * 2]


def test_invalid_input():
    for bad in (None, 3, "1, 2", b"12", [1, 2.0], [True], {1, 2}, [None]):
        with pytest.raises(ValueError, match="frames must be a sequence of integers"):
            frames_named(bad)
