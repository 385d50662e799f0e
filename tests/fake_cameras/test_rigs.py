import pytest

from fake_cameras.rigs import simulated_rig, simulated_rig_dict, write_simulated_rig
from stage.rig import load_rig


def test_rig_file_round_trip(tmp_path):
    p = write_simulated_rig(tmp_path / "rig.toml", 3, subject="quadruped", drop_rate=0.01, depth=True, size=(320, 240))
    rig = load_rig(p)
    assert [c.id for c in rig.cameras] == ["cam00", "cam01", "cam02"]
    assert rig.table("simulation").subject == "quadruped" and rig.table("simulation").n_cameras == 4
    assert all(c.driver == "fake" and c.depth and c.width == 320 for c in rig.cameras)
    offsets = [c.clock_offset_ms for c in rig.cameras]
    assert len(set(offsets)) == 3 and all(abs(o) <= 20 for o in offsets)
    assert simulated_rig(3, subject="quadruped", drop_rate=0.01, depth=True, size=(320, 240)) == rig


def test_invalid_input():
    with pytest.raises(ValueError, match="n_cameras"):
        simulated_rig_dict(0)
    with pytest.raises(ValueError, match="n_cameras"):
        simulated_rig_dict(5, dome_cameras=4)
    with pytest.raises(ValueError, match="subject"):
        simulated_rig_dict(2, subject="dragon")
    with pytest.raises(ValueError, match="drop_rate"):
        simulated_rig_dict(2, drop_rate=2.0)


def test_rig_carries_the_capture_volume(tmp_path):
    """A simulated take's rig file holds the take's capture volume (processing searches it)."""
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from stage.rig import Volume
    from stage.store import TakeReader

    vol = Volume(center=(10.0, 0.0, 300.0), size=(900.0, 600.0, 600.0))
    assert simulated_rig_dict(4, volume=vol)["volume"] == {"center": [10.0, 0.0, 300.0], "size": [900.0, 600.0, 600.0]}
    assert simulated_rig_dict(4)["volume"] == {"center": [0.0, 0.0, 375.0], "size": [750.0, 750.0, 750.0]}
    sim = simulate_take("starfish", n_cameras=4, frames=1, size=(160, 120), volume=vol)
    with TakeReader(record_take(sim, tmp_path / "t.h5")) as r:
        assert r.rig["volume"]["size"] == [900.0, 600.0, 600.0]
