"""What cameras are attached, on which USB bus, and whether a bus can carry them.

Three sources, each optional (a fresh machine, a container without ``/dev/bus/usb``
or a user without permissions still gets an answer, with warnings instead of
tracebacks):

* V4L2 nodes: ``/dev/video*`` with the name from ``/sys/class/video4linux/*/name``,
  whether the node captures video (``VIDIOC_QUERYCAP``; UVC webcams also create
  metadata nodes that do not), and the USB device (bus, port, link speed) from sysfs;
* USB devices through pyusb with the ``libusb-package`` backend: UVC cameras
  (an interface of video class 0x0E) and Luxonis OAKs (vendor 0x03e7), with the
  bus, port and link speed of each;
* OAK devices depthai can reach (also PoE ones), when depthai is installed.

The most common multi-webcam failure is a USB bus without the isochronous
bandwidth for its cameras: each UVC camera reserves bandwidth for its stream when
it starts, and the second or third camera on a USB 2 bus then fails to start or
delivers nothing. :func:`camera_bandwidth_mbps` and :func:`check_bus_load` (pure
functions) estimate the demand of the cameras a rig puts on each bus against the
bus's budget.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Mapping, Sequence

if TYPE_CHECKING:  # pragma: no cover
    from stage.rig import Rig

__all__ = [
    "VideoNode",
    "UsbDevice",
    "CameraLoad",
    "BusReport",
    "Inventory",
    "LUXONIS_VENDOR_ID",
    "UVC_CLASS",
    "link_speed_mbps",
    "usb_budget_mbps",
    "camera_bandwidth_mbps",
    "check_bus_load",
    "list_video_nodes",
    "list_usb_devices",
    "list_oak_devices",
    "rig_camera_loads",
    "discover",
]

log = logging.getLogger(__name__)

LUXONIS_VENDOR_ID = 0x03E7
UVC_CLASS = 0x0E  # USB video class
_LINUX_FOUNDATION = 0x1D6B  # root hubs
_OAK_PRODUCTS = {0x2485: "OAK (unbooted, ROM)", 0xF63B: "OAK (booted)", 0xF63C: "OAK (bootloader)", 0xF63D: "OAK (flash boot)"}

#: libusb speed codes -> Mbit/s
_LIBUSB_SPEED = {1: 1.5, 2: 12.0, 3: 480.0, 4: 5000.0, 5: 10000.0, 6: 20000.0}

#: share of a link's raw rate that isochronous/bulk video can really use
USB2_BUDGET_FRACTION = 0.6
USB3_BUDGET_FRACTION = 0.8
#: compressed size of MJPG relative to YUYV (typical 1/5 .. 1/10; the conservative end)
MJPG_RATIO = 0.2

_BYTES_PER_PIXEL = {
    "YUYV": 2.0, "YUY2": 2.0, "UYVY": 2.0, "YVYU": 2.0, "Y16": 2.0, "Z16": 2.0, "RAW16": 2.0,
    "NV12": 1.5, "NV21": 1.5, "I420": 1.5, "YU12": 1.5, "YV12": 1.5,
    "GREY": 1.0, "Y8": 1.0, "GRAY8": 1.0,
    "RGB3": 3.0, "BGR3": 3.0, "BGR": 3.0, "RGB": 3.0, "BGR888I": 3.0, "BGR888P": 3.0,
}
_COMPRESSED = {"MJPG", "MJPEG", "JPEG"}


# -- records -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VideoNode:
    """A ``/dev/video*`` node.

    ``capture`` is None when the node could not be queried (no permission);
    ``usb_*`` are None for non-USB devices (e.g. a CSI camera or ``v4l2loopback``).
    """

    path: str
    name: str
    capture: bool | None = None
    driver: str | None = None
    usb_bus: int | None = None
    usb_port: str | None = None
    usb_speed_mbps: float | None = None
    vendor_id: int | None = None
    product_id: int | None = None

    @property
    def index(self) -> int | None:
        m = re.search(r"video(\d+)$", self.path)
        return int(m.group(1)) if m else None


@dataclass(frozen=True)
class UsbDevice:
    """A USB camera: ``kind`` is ``"uvc"`` or ``"oak"``."""

    bus: int
    address: int
    vendor_id: int
    product_id: int
    kind: str
    port: str | None = None
    speed_mbps: float | None = None
    description: str = ""

    @property
    def ids(self) -> str:
        return f"{self.vendor_id:04x}:{self.product_id:04x}"


@dataclass(frozen=True)
class CameraLoad:
    """One configured camera's stream, placed on a bus (``bus`` None = not attached / unknown)."""

    camera_id: str
    bus: int | None
    width: int
    height: int
    fps: float
    pixel_format: str = "YUYV"
    extra_mbps: float = 0.0  # e.g. an OAK's depth stream

    @property
    def mbps(self) -> float:
        return camera_bandwidth_mbps(self.width, self.height, self.fps, self.pixel_format) + self.extra_mbps


@dataclass(frozen=True)
class BusReport:
    """Demand of the cameras on one bus against its budget."""

    bus: int
    link_mbps: float
    budget_mbps: float
    need_mbps: float
    cameras: tuple[tuple[str, float], ...]  # (camera id, Mbit/s)
    link_assumed: bool = False

    @property
    def oversubscribed(self) -> bool:
        return self.need_mbps > self.budget_mbps

    def warning(self) -> str | None:
        """The user-facing warning, or None when the bus has room."""
        if not self.oversubscribed:
            return None
        names = ", ".join(f"{cid} ({mbps:.0f})" for cid, mbps in self.cameras)
        return (
            f"USB bus {self.bus} ({_speed_label(self.link_mbps)}) is oversubscribed: its cameras need "
            f"~{self.need_mbps:.0f} Mbit/s of a ~{self.budget_mbps:.0f} Mbit/s budget [{names}]. "
            "Cameras on it will fail to start or drop frames: use MJPG (mjpg = true), a lower "
            "resolution or fps, or move cameras to another USB controller (another bus)."
        )


@dataclass
class Inventory:
    """Everything :func:`discover` found; ``warnings`` say what could not be looked at."""

    video_nodes: list[VideoNode] = field(default_factory=list)
    usb_devices: list[UsbDevice] = field(default_factory=list)
    oak_devices: list[dict] = field(default_factory=list)
    bus_speeds: dict[int, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return not (
            any(n.capture is not False for n in self.video_nodes) or self.usb_devices or self.oak_devices
        )


# -- pure bandwidth model --------------------------------------------------------------------------


def link_speed_mbps(code: int | None) -> float | None:
    """libusb speed code (``usb.core.Device.speed``) -> Mbit/s (None when unknown)."""
    return _LIBUSB_SPEED.get(int(code)) if code is not None else None


def _speed_label(mbps: float | None) -> str:
    if mbps is None:
        return "unknown speed"
    if mbps <= 12:
        return f"USB 1, {mbps:g} Mbit/s"
    if mbps <= 480:
        return "USB 2 high speed, 480 Mbit/s"
    return f"USB 3, {mbps / 1000:g} Gbit/s"


def usb_budget_mbps(link_mbps: float) -> float:
    """What a bus of this raw rate can really carry for camera streams (Mbit/s).

    USB 2 reserves at most 80 % of each microframe for periodic (isochronous)
    transfers and real controllers manage about 60 % of 480 Mbit/s for video;
    SuperSpeed buses about 80 %.
    """
    if not link_mbps > 0:
        raise ValueError(f"link_mbps must be > 0, got {link_mbps}")
    return link_mbps * (USB2_BUDGET_FRACTION if link_mbps <= 480 else USB3_BUDGET_FRACTION)


def camera_bandwidth_mbps(width: int, height: int, fps: float, pixel_format: str = "YUYV", *, mjpg_ratio: float = MJPG_RATIO) -> float:
    """Estimated stream rate of one camera in Mbit/s.

    ``width * height * bytes_per_pixel * fps * 8``; YUYV has 2 bytes per pixel,
    MJPG about ``mjpg_ratio`` of YUYV (1/5 .. 1/10 in practice).

    Parameters
    ----------
    width, height : int
    fps : float
    pixel_format : str
        Fourcc or depthai type (``YUYV``, ``MJPG``, ``NV12``, ``GREY``, ``BGR``...);
        unknown formats count as 2 bytes per pixel.
    mjpg_ratio : float
        Compressed / YUYV size for MJPG.
    """
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be > 0, got {width}x{height}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if not 0 < mjpg_ratio <= 1:
        raise ValueError(f"mjpg_ratio must be in (0, 1], got {mjpg_ratio}")
    fmt = str(pixel_format).upper()
    bpp = 2.0 * mjpg_ratio if fmt in _COMPRESSED else _BYTES_PER_PIXEL.get(fmt, 2.0)
    return int(width) * int(height) * bpp * float(fps) * 8.0 / 1e6


def check_bus_load(loads: Sequence[CameraLoad], bus_speeds: Mapping[int, float]) -> list[BusReport]:
    """Sum the demand of the cameras on each bus and compare it with the bus's budget.

    Parameters
    ----------
    loads : sequence of CameraLoad
        Cameras with ``bus`` None are skipped (they are not attached).
    bus_speeds : mapping int -> float
        Raw link rate of each bus in Mbit/s (the root hub's speed); a bus missing
        here is assumed to be USB 2 (480), the conservative choice for webcams.

    Returns
    -------
    list of BusReport
        One per bus that carries a camera, sorted by bus number;
        ``report.warning()`` is the message for an oversubscribed one.
    """
    if isinstance(loads, CameraLoad) or not all(isinstance(x, CameraLoad) for x in loads):
        raise ValueError("loads must be a sequence of CameraLoad")
    by_bus: dict[int, list[CameraLoad]] = {}
    for load in loads:
        if load.bus is not None:
            by_bus.setdefault(int(load.bus), []).append(load)
    reports = []
    for bus in sorted(by_bus):
        link = bus_speeds.get(bus)
        assumed = link is None
        link = 480.0 if link is None else float(link)
        cams = tuple((c.camera_id, c.mbps) for c in by_bus[bus])
        reports.append(
            BusReport(bus=bus, link_mbps=link, budget_mbps=usb_budget_mbps(link),
                      need_mbps=sum(m for _, m in cams), cameras=cams, link_assumed=assumed)
        )
    return reports


# -- V4L2 through sysfs ----------------------------------------------------------------------------

_VIDIOC_QUERYCAP = (2 << 30) | (104 << 16) | (ord("V") << 8) | 0  # _IOR('V', 0, struct v4l2_capability)
_CAP_VIDEO_CAPTURE = 0x00000001
_CAP_VIDEO_CAPTURE_MPLANE = 0x00001000
_CAP_DEVICE_CAPS = 0x80000000


def _read(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return None


def _query_capture(node: str) -> bool | None:
    """Whether a V4L2 node captures video (VIDIOC_QUERYCAP); None if it cannot be asked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not Linux
        return None
    try:
        fd = os.open(node, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        buf = bytearray(104)
        fcntl.ioctl(fd, _VIDIOC_QUERYCAP, buf, True)
    except OSError:
        return None
    finally:
        os.close(fd)
    caps, device_caps = struct.unpack_from("<II", buf, 84)
    eff = device_caps if caps & _CAP_DEVICE_CAPS else caps
    return bool(eff & (_CAP_VIDEO_CAPTURE | _CAP_VIDEO_CAPTURE_MPLANE))


def _usb_device_dir(device_link: Path) -> Path | None:
    """sysfs USB device directory (``.../usb1/1-2``) above a video node's ``device`` link."""
    try:
        d = device_link.resolve()
    except OSError:
        return None
    for p in (d, *d.parents):
        if (p / "busnum").is_file() and (p / "devnum").is_file():
            return p
        if p.name.startswith("pci") or p == p.parent:
            break
    return None


def list_video_nodes(*, sysfs: str | Path = "/sys", dev: str | Path = "/dev") -> tuple[list[VideoNode], list[str]]:
    """V4L2 nodes with their names, capture capability and USB placement.

    Parameters
    ----------
    sysfs, dev : path
        Roots of sysfs and devfs (tests point them at a fake tree).

    Returns
    -------
    nodes : list of VideoNode
        Sorted by node number.
    warnings : list of str
    """
    root = Path(sysfs) / "class" / "video4linux"
    warnings: list[str] = []
    if not root.is_dir():
        return [], warnings
    nodes = []
    denied = []
    for entry in root.iterdir():
        if not re.fullmatch(r"video\d+", entry.name):
            continue
        path = str(Path(dev) / entry.name)
        name = _read(entry / "name") or "?"
        drv = None
        try:
            drv = (entry / "device" / "driver").resolve().name if (entry / "device" / "driver").exists() else None
        except OSError:
            pass
        usb = _usb_device_dir(entry / "device")
        bus = port = speed = vid = pid = None
        if usb is not None:
            bus = int(_read(usb / "busnum") or 0) or None
            port = usb.name
            sp = _read(usb / "speed")
            speed = float(sp) if sp and re.fullmatch(r"[\d.]+", sp) else None
            vid = int(_read(usb / "idVendor") or "0", 16) or None
            pid = int(_read(usb / "idProduct") or "0", 16) or None
        capture = _query_capture(path) if os.path.exists(path) else None
        if capture is None and os.path.exists(path) and not os.access(path, os.R_OK):
            denied.append(path)
        nodes.append(VideoNode(path=path, name=name, capture=capture, driver=drv, usb_bus=bus, usb_port=port,
                               usb_speed_mbps=speed, vendor_id=vid, product_id=pid))
    if denied:
        warnings.append(
            f"no permission to open {', '.join(denied)}: add yourself to the 'video' group "
            "(sudo usermod -aG video $USER, then log in again)"
        )
    nodes.sort(key=lambda n: (n.index is None, n.index or 0, n.path))
    return nodes, warnings


# -- USB through pyusb -----------------------------------------------------------------------------


def _usb_backend(warnings: list[str]):
    try:
        import libusb_package
    except ImportError:
        warnings.append("the libusb-package wheel is not installed (pip install libusb-package); trying the system libusb")
        return None
    try:
        return libusb_package.get_libusb1_backend()
    except (OSError, RuntimeError) as exc:
        warnings.append(f"the bundled libusb does not load ({exc}); trying the system libusb")
        return None


def _has_video_interface(dev) -> bool:
    import usb.core

    if dev.bDeviceClass == UVC_CLASS:
        return True
    try:
        for cfg in dev:
            for intf in cfg:
                if intf.bInterfaceClass == UVC_CLASS:
                    return True
    except (usb.core.USBError, NotImplementedError, ValueError):
        return False
    return False


def _usb_description(dev) -> str:
    import usb.core
    import usb.util

    parts = []
    for idx in (dev.iManufacturer, dev.iProduct):
        if not idx:
            continue
        try:
            s = usb.util.get_string(dev, idx)
        except (usb.core.USBError, ValueError, NotImplementedError):
            s = None  # needs opening the device: no permission, or busy
        if s:
            parts.append(s.strip())
    return " ".join(parts)


def list_usb_devices(*, backend=None) -> tuple[list[UsbDevice], dict[int, float], list[str]]:
    """UVC cameras and OAKs on USB, and the link speed of every bus.

    Parameters
    ----------
    backend : pyusb backend, optional
        Default: the ``libusb-package`` wheel's libusb (works without a system
        libusb), else pyusb's own search.

    Returns
    -------
    devices : list of UsbDevice
    bus_speeds : dict int -> float
        Root hub speed of each bus (Mbit/s), else the fastest device seen on it.
    warnings : list of str
        libusb problems (no backend, no permission, no ``/dev/bus/usb``).
    """
    warnings: list[str] = []
    try:
        import usb.core
    except ImportError:
        return [], {}, ["pyusb is not installed (pip install pyusb libusb-package); USB devices not listed"]
    if backend is None:
        backend = _usb_backend(warnings)
    try:
        found = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError:
        warnings.append("no libusb backend found (pip install libusb-package); USB devices not listed")
        return [], {}, warnings
    except (usb.core.USBError, OSError) as exc:
        denied = getattr(exc, "errno", None) in (errno.EACCES, errno.EPERM)
        hint = " (permission denied: see docs/hardware.md for udev rules)" if denied else ""
        warnings.append(f"libusb could not list USB devices: {exc}{hint}")
        return [], {}, warnings
    devices = []
    speeds: dict[int, float] = {}
    roots: dict[int, float] = {}
    for d in found:
        bus = int(d.bus) if d.bus is not None else None
        speed = link_speed_mbps(d.speed)
        if bus is not None and speed is not None:
            if d.idVendor == _LINUX_FOUNDATION and d.bDeviceClass == 0x09:
                roots[bus] = speed
            speeds[bus] = max(speeds.get(bus, 0.0), speed)
        if d.idVendor == LUXONIS_VENDOR_ID:
            kind = "oak"
            desc = _OAK_PRODUCTS.get(d.idProduct, "Luxonis/Movidius device")
        elif _has_video_interface(d):
            kind = "uvc"
            desc = ""
        else:
            continue
        label = _usb_description(d)
        ports = getattr(d, "port_numbers", None)
        port = f"{bus}-{'.'.join(str(p) for p in ports)}" if ports and bus is not None else None
        devices.append(UsbDevice(bus=bus or 0, address=int(d.address or 0), vendor_id=int(d.idVendor),
                                 product_id=int(d.idProduct), kind=kind, port=port, speed_mbps=speed,
                                 description=" - ".join(s for s in (desc, label) if s)))
    speeds.update(roots)
    if not found and sys.platform.startswith("linux") and not os.path.isdir("/dev/bus/usb"):
        warnings.append(
            "/dev/bus/usb does not exist: USB devices are not visible here (in a container, pass "
            "-v /dev/bus/usb:/dev/bus/usb --device-cgroup-rule='c 189:* rmw')"
        )
    devices.sort(key=lambda u: (u.bus, u.port or "", u.address))
    return devices, speeds, warnings


def list_oak_devices() -> tuple[list[dict], list[str]]:
    """OAKs depthai can reach (USB and PoE); a warning instead when depthai is missing."""
    from stage.drivers.base import DriverUnavailableError

    try:
        from stage.drivers.depthai_driver import list_devices

        return list_devices(), []
    except DriverUnavailableError as exc:
        return [], [str(exc)]
    except RuntimeError as exc:
        return [], [f"depthai could not search for devices: {exc}"]


# -- putting it together ---------------------------------------------------------------------------


def discover(*, sysfs: str | Path = "/sys", dev: str | Path = "/dev", usb_backend=None, depthai: bool = True) -> Inventory:
    """Everything attached: V4L2 nodes, USB cameras (+ bus speeds), OAKs via depthai."""
    inv = Inventory()
    nodes, w1 = list_video_nodes(sysfs=sysfs, dev=dev)
    usb_devs, speeds, w2 = list_usb_devices(backend=usb_backend)
    inv.video_nodes, inv.usb_devices, inv.warnings = nodes, usb_devs, w1 + w2
    inv.bus_speeds = dict(speeds)
    for n in nodes:  # sysfs knows the speed of the bus a node sits on even without libusb
        if n.usb_bus is not None and n.usb_speed_mbps is not None and n.usb_bus not in inv.bus_speeds:
            inv.bus_speeds[n.usb_bus] = n.usb_speed_mbps
    if depthai:
        oaks, w3 = list_oak_devices()
        inv.oak_devices = oaks
        inv.warnings += w3
    return inv


def _node_for(device: int | str, nodes: Iterable[VideoNode]) -> VideoNode | None:
    if isinstance(device, str) and device.isdigit():
        device = int(device)
    if isinstance(device, int):
        path = f"/dev/video{device}"
    elif isinstance(device, str) and device.startswith("/dev/"):
        path = os.path.realpath(device)  # /dev/v4l/by-id/... symlinks
    else:
        return None
    for n in nodes:
        if n.path == path or (n.index is not None and path == f"/dev/video{n.index}"):
            return n
    return None


def rig_camera_loads(rig: "Rig", inventory: Inventory) -> tuple[list[CameraLoad], list[str]]:
    """Place each live camera of a rig on its USB bus and estimate its stream.

    Returns
    -------
    loads : list of CameraLoad
        ``bus`` None for cameras that are not attached (or not on USB).
    notes : list of str
        Why a camera could not be placed.
    """
    from stage.drivers.opencv import classify_source

    loads, notes = [], []
    oaks_on_usb = [u for u in inventory.usb_devices if u.kind == "oak"]
    for cam in rig.cameras:
        fps = float(cam.fps or rig.fps)
        if cam.driver == "opencv":
            try:
                src = classify_source(cam.device)
            except ValueError as exc:
                notes.append(f"{cam.id}: {exc}")
                continue
            if not src.live or src.kind == "stream":
                continue  # files and network streams use no USB bandwidth
            fmt = "MJPG" if cam.mjpg else "YUYV"
            node = _node_for(src.target, inventory.video_nodes)
            bus = node.usb_bus if node is not None else None
            if node is None:
                notes.append(f"{cam.id}: {src.describe()} is not attached")
            elif bus is None:
                notes.append(f"{cam.id}: {node.path} is not a USB device")
            loads.append(CameraLoad(cam.id, bus, cam.width, cam.height, fps, fmt))
        elif cam.driver == "depthai":
            fmt = "MJPG" if cam.store == "jpeg" else "BGR"
            extra = camera_bandwidth_mbps(cam.width, cam.height, fps, "RAW16") if cam.depth else 0.0
            bus = None
            if cam.device is None and len(oaks_on_usb) == 1:
                bus = oaks_on_usb[0].bus
            elif not oaks_on_usb:
                notes.append(f"{cam.id}: no OAK attached over USB")
            else:
                notes.append(f"{cam.id}: cannot tell which USB bus OAK {cam.device or '(first free)'} is on")
            loads.append(CameraLoad(cam.id, bus, cam.width, cam.height, fps, fmt, extra_mbps=extra))
    return loads, notes
