"""write_arrays: several derived arrays in one update of the derived file."""

import numpy as np
import pytest

from fake_cameras.record import record_take
from fake_cameras.take import simulate_take
from stage.store import TakeReader, write_array, write_arrays


def test_write_arrays_matches_write_array_and_replaces(tmp_path):
    sim = simulate_take("starfish", n_cameras=4, frames=2, size=(64, 48), seed=0)
    path = record_take(sim, tmp_path / "t.h5")
    masks = sim.masks[:, 0]
    write_array(path, "cameras/cam01", "masks", sim.masks[:, 1], params={"old": True})
    write_arrays(path, [
        ("cameras/cam00", "masks", masks, {"a": 1}),
        ("cameras/cam00", "mask_valid", np.array([1, 0], np.uint8), None),
        ("cameras/cam01", "masks", ~sim.masks[:, 1], {"new": True}),
    ])
    with TakeReader(path) as r:
        assert np.array_equal(r.masks("cam00"), masks) and r.mask_params("cam00") == {"a": 1}
        assert np.array_equal(r.read_array("cameras/cam00", "mask_valid")[0], [1, 0])
        assert np.array_equal(r.masks("cam01"), ~sim.masks[:, 1]) and r.mask_params("cam01") == {"new": True}
        assert np.array_equal(r.read_array("cameras/cam02", "plate")[0], sim.plate[2])


def test_invalid_input(tmp_path):
    sim = simulate_take("starfish", n_cameras=4, frames=2, size=(64, 48), seed=0)
    path = record_take(sim, tmp_path / "t.h5")
    with pytest.raises(ValueError, match="name"):
        write_arrays(path, [("cameras/cam00", "image", np.zeros(3), None)])
    with pytest.raises(ValueError, match="meta"):
        write_arrays(path, [("meta", "x", np.zeros(3), None)])
    with pytest.raises(ValueError, match="dtype"):
        write_arrays(path, [("cameras/cam00", "x", np.array(["a"]), None)])
    write_arrays(path, [])  # nothing to do
