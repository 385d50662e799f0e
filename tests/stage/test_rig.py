import pytest

from stage.rig import RigError, load_rig, parse_rig


def test_rig_file_roundtrip(tmp_path):
    p = tmp_path / "rig.toml"
    p.write_text(
        'name = "lab"\nfps = 25\nsupport_plane = [0, 0, 1, -5]\n[volume]\ncenter = [0, 0, 400]\nsize = [800, 800, 800]\n'
        '[[cameras]]\nid = "left"\ndriver = "opencv"\ndevice = "/dev/video0"\n'
        '[[cameras]]\nid = "oak"\ndriver = "depthai"\n'
    )
    rig = load_rig(p)
    assert [c.id for c in rig.cameras] == ["left", "oak"]
    assert rig.cameras[1].depth is True
    assert rig.tolerance_ns == 20_000_000  # half of 40 ms
    assert rig.volume.bounds == ((-400, -400, 0), (400, 400, 800))
    assert rig.support_plane == (0, 0, 1, -5) and parse_rig({"cameras": [{"id": "a", "driver": "opencv"}]}).support_plane is None


def test_invalid_input(tmp_path):
    with pytest.raises(RigError, match="unknown key 'cameras.0.devcie'"):
        parse_rig({"cameras": [{"id": "a", "driver": "opencv", "devcie": 0}]})
    with pytest.raises(RigError, match="unknown key 'colour'"):
        parse_rig({"colour": 1, "cameras": [{"id": "a", "driver": "opencv"}]})
    with pytest.raises(RigError, match="fps"):
        parse_rig({"fps": -1, "cameras": [{"id": "a", "driver": "opencv"}]})
    with pytest.raises(RigError, match="support_plane"):
        parse_rig({"support_plane": [0, 0, 0, 1], "cameras": [{"id": "a", "driver": "opencv"}]})
    with pytest.raises(RigError, match="support_plane"):
        parse_rig({"support_plane": [0, 0, 1], "cameras": [{"id": "a", "driver": "opencv"}]})
    with pytest.raises(RigError, match="duplicate camera ids"):
        parse_rig({"cameras": [{"id": "a", "driver": "opencv"}, {"id": "a", "driver": "opencv"}]})
    with pytest.raises(RigError, match="simulation"):
        parse_rig({"cameras": [{"id": "a", "driver": "fake"}]})
    with pytest.raises(RigError, match="driver"):
        parse_rig({"cameras": [{"id": "a", "driver": "gopro"}]})
    with pytest.raises(RigError, match="not found"):
        load_rig(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = ")
    with pytest.raises(RigError, match="not valid TOML"):
        load_rig(bad)
