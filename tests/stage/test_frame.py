import numpy as np
import pytest

from stage.frame import Frame


def test_frame_fields():
    img = np.zeros((4, 6, 3), np.uint8)
    f = Frame(img, "c0", 3, 100, 200, depth=np.zeros((4, 6), np.uint16))
    assert f.shape == (4, 6) and f.index == 3 and f.timestamp_ns == 100


def test_invalid_input():
    with pytest.raises(ValueError, match="image"):
        Frame(np.zeros((4, 6), np.uint8), "c0", 0, 0, 0)
    with pytest.raises(ValueError, match="image"):
        Frame(np.zeros((4, 6, 3), np.float32), "c0", 0, 0, 0)
    with pytest.raises(ValueError, match="depth"):
        Frame(np.zeros((4, 6, 3), np.uint8), "c0", 0, 0, 0, depth=np.zeros((4, 5), np.uint16))
