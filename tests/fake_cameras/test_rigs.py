import pytest

from fake_cameras.rigs import simulated_rig, simulated_rig_dict, write_simulated_rig
from stage.rig import load_rig


def test_rig_file_round_trip(tmp_path):
    p = write_simulated_rig(tmp_path / "rig.toml", 3, subject="quadruped", drop_rate=0.01, depth=True, size=(320, 240))
    rig = load_rig(p)
    assert [c.id for c in rig.cameras] == ["cam00", "cam01", "cam02"]
    assert rig.simulation.subject == "quadruped" and rig.simulation.n_cameras == 4
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
