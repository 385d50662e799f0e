"""Discovery of attached cameras and the USB bandwidth check, with fake sysfs trees and fake USB records."""

from __future__ import annotations

from pathlib import Path

import pytest

import stage.discovery as disc
from stage.cli import main
from stage.discovery import (
    CameraLoad,
    Inventory,
    VideoNode,
    camera_bandwidth_mbps,
    check_bus_load,
    list_usb_devices,
    list_video_nodes,
    rig_camera_loads,
    usb_budget_mbps,
)
from stage.rig import parse_rig

# -- the pure bandwidth model --------------------------------------------------------------------


def test_bandwidth_formula():
    assert camera_bandwidth_mbps(640, 480, 30, "YUYV") == pytest.approx(640 * 480 * 2 * 30 * 8 / 1e6)
    assert camera_bandwidth_mbps(640, 480, 30, "MJPG") == pytest.approx(640 * 480 * 2 * 30 * 8 / 1e6 * disc.MJPG_RATIO)
    assert camera_bandwidth_mbps(1280, 720, 30, "NV12") == pytest.approx(1280 * 720 * 1.5 * 30 * 8 / 1e6)
    assert usb_budget_mbps(480) == pytest.approx(0.6 * 480)


def test_four_yuyv_webcams_oversubscribe_one_usb2_bus_mjpg_does_not():
    yuyv = [CameraLoad(f"cam{i}", 1, 640, 480, 30, "YUYV") for i in range(4)]
    (report,) = check_bus_load(yuyv, {1: 480.0})
    assert report.oversubscribed
    assert report.need_mbps == pytest.approx(4 * 147.456)
    msg = report.warning()
    for i in range(4):
        assert f"cam{i}" in msg
    assert "MJPG" in msg and "another USB controller" in msg and "bus 1" in msg

    mjpg = [CameraLoad(f"cam{i}", 1, 640, 480, 30, "MJPG") for i in range(4)]
    (report,) = check_bus_load(mjpg, {1: 480.0})
    assert not report.oversubscribed and report.warning() is None


def test_buses_are_checked_separately():
    loads = [
        CameraLoad("a", 1, 640, 480, 30, "YUYV"),
        CameraLoad("b", 2, 640, 480, 30, "YUYV"),
        CameraLoad("c", 3, 640, 480, 30, "YUYV"),
        CameraLoad("d", 3, 640, 480, 30, "YUYV"),
        CameraLoad("offline", None, 1920, 1080, 60, "YUYV"),
    ]
    reports = check_bus_load(loads, {1: 480.0, 2: 5000.0})
    assert [r.bus for r in reports] == [1, 2, 3]
    assert [r.oversubscribed for r in reports] == [False, False, True]  # two YUYV 640x480@30 exceed 288 Mbit/s
    assert reports[2].link_assumed and reports[2].link_mbps == 480.0
    assert all("offline" not in dict(r.cameras) for r in reports)


# -- V4L2 nodes from a fake sysfs --------------------------------------------------------------


def make_sysfs(root: Path) -> Path:
    sysfs = root / "sys"
    usbdev = sysfs / "devices/pci0000:00/0000:00:14.0/usb1/1-2"
    for intf, node in (("1-2:1.0", "video0"), ("1-2:1.0", "video1")):
        d = usbdev / intf / "video4linux" / node
        d.mkdir(parents=True, exist_ok=True)
    for name, value in {"busnum": "1", "devnum": "5", "speed": "480", "idVendor": "046d", "idProduct": "0825"}.items():
        (usbdev / name).write_text(value + "\n")
    platform = sysfs / "devices/platform/vivid.0/video4linux/video4"
    platform.mkdir(parents=True)
    cls = sysfs / "class/video4linux"
    cls.mkdir(parents=True)
    for node, target, name in (
        ("video0", usbdev / "1-2:1.0" / "video4linux/video0", "C270 HD WEBCAM"),
        ("video1", usbdev / "1-2:1.0" / "video4linux/video1", "C270 HD WEBCAM"),
        ("video4", platform, "vivid-000-vid-cap"),
    ):
        (cls / node).symlink_to(target)
        (target / "name").write_text(name + "\n")
        (target / "device").symlink_to(target.parent.parent)
    return sysfs


def test_video_nodes_from_sysfs(tmp_path):
    sysfs = make_sysfs(tmp_path)
    nodes, warnings = list_video_nodes(sysfs=sysfs, dev=tmp_path / "dev")
    assert warnings == []
    assert [n.path for n in nodes] == [str(tmp_path / "dev" / f"video{i}") for i in (0, 1, 4)]
    cam = nodes[0]
    assert cam.name == "C270 HD WEBCAM" and cam.index == 0
    assert (cam.usb_bus, cam.usb_port, cam.usb_speed_mbps) == (1, "1-2", 480.0)
    assert (cam.vendor_id, cam.product_id) == (0x046D, 0x0825)
    assert cam.capture is None  # no device node to query here
    assert nodes[2].name == "vivid-000-vid-cap" and nodes[2].usb_bus is None


def test_no_sysfs_is_no_nodes(tmp_path):
    assert list_video_nodes(sysfs=tmp_path / "nothing") == ([], [])


# -- USB devices from fake pyusb records ---------------------------------------------------------


class FakeInterface:
    def __init__(self, cls):
        self.bInterfaceClass = cls


class FakeUsb:
    def __init__(self, vid, pid, bus, address, speed, ports, dev_class=0, interfaces=()):
        self.idVendor, self.idProduct, self.bus, self.address = vid, pid, bus, address
        self.speed, self.port_numbers, self.bDeviceClass = speed, ports, dev_class
        self.iManufacturer = self.iProduct = 0
        self._configs = [[FakeInterface(c) for c in interfaces]]

    def __iter__(self):
        return iter(self._configs)


FAKE_BUS = [
    FakeUsb(0x1D6B, 0x0002, 1, 1, 3, None, dev_class=9),  # USB 2 root hub
    FakeUsb(0x1D6B, 0x0003, 2, 1, 4, None, dev_class=9),  # USB 3 root hub
    FakeUsb(0x046D, 0x0825, 1, 5, 3, (2,), dev_class=0xEF, interfaces=(0x0E, 0x0E, 0x01)),  # UVC webcam
    FakeUsb(0x046D, 0xC31C, 1, 6, 2, (3,), interfaces=(0x03,)),  # a keyboard: not a camera
    FakeUsb(0x03E7, 0xF63B, 2, 3, 4, (1, 4)),  # booted OAK on USB 3
]


@pytest.fixture
def fake_usb(monkeypatch):
    import usb.core

    def find(find_all=False, backend=None, **kw):
        assert find_all
        return iter(FAKE_BUS)

    monkeypatch.setattr(usb.core, "find", find)


def test_usb_cameras_and_bus_speeds(fake_usb):
    devices, speeds, warnings = list_usb_devices()
    assert warnings == []
    assert [(d.kind, d.ids, d.bus, d.port) for d in devices] == [
        ("uvc", "046d:0825", 1, "1-2"),
        ("oak", "03e7:f63b", 2, "2-1.4"),
    ]
    assert speeds == {1: 480.0, 2: 5000.0}
    assert "booted" in devices[1].description


def test_libusb_errors_are_warnings(monkeypatch):
    import usb.core

    def no_backend(**kw):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    devices, speeds, warnings = list_usb_devices()
    assert devices == [] and speeds == {} and "no libusb backend" in warnings[0]

    def denied(**kw):
        raise usb.core.USBError("Access denied (insufficient permissions)", errno=13)

    monkeypatch.setattr(usb.core, "find", denied)
    devices, _, warnings = list_usb_devices()
    assert devices == [] and "could not list" in warnings[0] and "udev" in warnings[0]


def test_rig_cameras_placed_on_buses(tmp_path):
    rig = parse_rig({
        "fps": 30,
        "cameras": [
            {"id": "left", "driver": "opencv", "device": "/dev/video0", "mjpg": False},
            {"id": "right", "driver": "opencv", "device": 2, "mjpg": False},
            {"id": "file", "driver": "opencv", "device": str(tmp_path / "x.avi")},
            {"id": "away", "driver": "opencv", "device": 7},
        ],
    })
    inv = Inventory(
        video_nodes=[VideoNode("/dev/video0", "a", True, usb_bus=1), VideoNode("/dev/video2", "b", True, usb_bus=1)],
        bus_speeds={1: 480.0},
    )
    loads, notes = rig_camera_loads(rig, inv)
    assert [(c.camera_id, c.bus, c.pixel_format) for c in loads] == [
        ("left", 1, "YUYV"), ("right", 1, "YUYV"), ("away", None, "MJPG")
    ]
    assert any("away" in n and "not attached" in n for n in notes)
    (report,) = check_bus_load(loads, inv.bus_speeds)
    assert report.oversubscribed  # two YUYV webcams at 640x480@30 on one USB 2 bus


# -- the CLI -------------------------------------------------------------------------------------


@pytest.fixture
def nothing_attached(monkeypatch, tmp_path):
    import usb.core

    real = disc.discover
    monkeypatch.setattr(usb.core, "find", lambda **kw: iter(()))
    monkeypatch.setattr(disc, "list_oak_devices", lambda: ([], []))
    monkeypatch.setattr(disc, "discover", lambda **kw: real(**{**kw, "sysfs": tmp_path / "sys", "dev": tmp_path / "dev"}))


def test_cli_nothing_attached(nothing_attached, capsys):
    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert "no cameras found" in out
    assert "Traceback" not in out


def test_cli_on_this_machine(capsys):
    """The real discovery, end to end; only meaningful where nothing is attached."""
    inv = disc.discover(depthai=False)
    if not inv.empty:
        pytest.skip("cameras are attached to this machine")
    assert main(["cameras", "--no-depthai"]) == 0
    assert "no cameras found" in capsys.readouterr().out


def test_cli_rig_bandwidth_warning(monkeypatch, tmp_path, capsys):
    sysfs = make_sysfs(tmp_path)
    real = disc.discover
    monkeypatch.setattr(disc, "list_usb_devices", lambda **kw: ([], {}, []))
    monkeypatch.setattr(disc, "discover", lambda **kw: real(**{**kw, "sysfs": sysfs, "dev": "/dev", "depthai": False}))
    rig = tmp_path / "rig.toml"
    rig.write_text(
        '[[cameras]]\nid = "c0"\ndriver = "opencv"\ndevice = 0\nmjpg = false\n'
        '[[cameras]]\nid = "c1"\ndriver = "opencv"\ndevice = 1\nmjpg = false\n'
    )
    assert main(["cameras", "--rig", str(rig)]) == 0
    out = capsys.readouterr().out
    assert "C270 HD WEBCAM" in out and "USB bus 1" in out
    assert "WARNING" in out and "oversubscribed" in out and "c0" in out and "c1" in out
    rig.write_text(rig.read_text().replace("mjpg = false", "mjpg = true"))
    assert main(["cameras", "--rig", str(rig)]) == 0
    assert "WARNING" not in capsys.readouterr().out


def test_invalid_input(tmp_path, capsys):
    with pytest.raises(ValueError, match="width and height"):
        camera_bandwidth_mbps(0, 480, 30)
    with pytest.raises(ValueError, match="fps"):
        camera_bandwidth_mbps(640, 480, 0)
    with pytest.raises(ValueError, match="mjpg_ratio"):
        camera_bandwidth_mbps(640, 480, 30, "MJPG", mjpg_ratio=0)
    with pytest.raises(ValueError, match="link_mbps"):
        usb_budget_mbps(0)
    with pytest.raises(ValueError, match="CameraLoad"):
        check_bus_load([("cam", 1)], {})
    assert main(["cameras", "--rig", str(tmp_path / "missing.toml")]) == 2
    assert "rig file not found" in capsys.readouterr().err
