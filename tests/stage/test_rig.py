from typing import Annotated, Literal

import pytest
from pydantic import BaseModel, ConfigDict, Field

import fake_cameras  # noqa: F401 (registers the simulator's driver: its cameras and [simulation] table)
import stage.drivers  # noqa: F401 (registers the built-in drivers' camera models)
from stage.drivers.registry import _DRIVERS, open_driver, register_driver
from stage.rig import _CAMERA_CONFIGS, CameraConfig, RigError, load_rig, parse_rig


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
    with pytest.raises(RigError, match=r"cameras\.0\.driver: unknown driver 'gopro'; known: \['depthai', 'fake', 'opencv'"):
        parse_rig({"cameras": [{"id": "a", "driver": "gopro"}]})
    with pytest.raises(RigError, match="simulation.frames"):
        parse_rig({"simulation": {"frames": 0}, "cameras": [{"id": "a", "driver": "fake"}]})
    with pytest.raises(RigError, match=r"cameras\.1\.device"):  # each camera against its own driver's model
        parse_rig({"cameras": [{"id": "a", "driver": "opencv"}, {"id": "b", "driver": "depthai", "device": 3}]})
    with pytest.raises(RigError, match="not found"):
        load_rig(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = ")
    with pytest.raises(RigError, match="not valid TOML"):
        load_rig(bad)


class _ToyConfig(CameraConfig):
    driver: Literal["toy"]
    gain: Annotated[float, Field(ge=0)] = 1.0


class _ToyTable(BaseModel):
    model_config = ConfigDict(extra="forbid")
    level: int = 0


class _ToyCamera:
    config_model = _ToyConfig

    def __init__(self, config, rig):
        self.config, self.rig = config, rig


@pytest.fixture
def toy_driver():
    """A driver from outside stage: its module declares its config model and registers it."""
    register_driver("toy", _ToyCamera, needs_rig=True, table=("toy_room", _ToyTable))
    yield
    _DRIVERS.pop("toy")
    _CAMERA_CONFIGS.pop("toy")


def test_a_registered_driver_validates_its_own_cameras_and_table(toy_driver):
    rig = parse_rig({"toy_room": {"level": 2}, "cameras": [{"id": "t", "driver": "toy", "gain": 3},
                                                           {"id": "w", "driver": "opencv", "device": 1}]})
    assert isinstance(rig.cameras[0], _ToyConfig) and rig.cameras[0].gain == 3.0
    assert rig.table("toy_room").level == 2 and rig.cameras[1].device == 1
    assert rig.model_dump()["cameras"][0]["gain"] == 3.0  # the driver's own fields survive a dump
    drv = open_driver(rig.cameras[0], rig)
    assert isinstance(drv, _ToyCamera) and drv.rig is rig and drv.config.fps == rig.fps
    with pytest.raises(RigError, match=r"cameras\.0\.gain"):
        parse_rig({"toy_room": {}, "cameras": [{"id": "t", "driver": "toy", "gain": -1}]})
    with pytest.raises(RigError, match="unknown key 'cameras.0.device'"):
        parse_rig({"toy_room": {}, "cameras": [{"id": "t", "driver": "toy", "device": 0}]})
    with pytest.raises(RigError, match=r"toy_room: toy cameras need a \[toy_room\] table"):
        parse_rig({"cameras": [{"id": "t", "driver": "toy"}]})
    with pytest.raises(ValueError, match="toy cameras need the rig"):
        open_driver(rig.cameras[0])


def test_register_driver_needs_a_config_model():
    class NoModel:
        pass

    with pytest.raises(ValueError, match="config_model"):
        register_driver("nomodel", NoModel)
    with pytest.raises(ValueError, match="table"):
        register_driver("toy2", _ToyCamera, table=("cameras", _ToyTable))  # a key the rig file has already
    assert "nomodel" not in _DRIVERS and "toy2" not in _DRIVERS
