"""``stage cameras``: list attached cameras, their USB buses, and check a rig's bus bandwidth."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict

ORDER = 10


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cameras",
        help="list attached cameras (V4L2, UVC, OAK) and their USB buses",
        description=(
            "List what is attached: V4L2 video nodes (/dev/video*), USB cameras (UVC class, "
            "Luxonis OAK vendor 03e7) with the USB bus each sits on and its speed, and OAKs "
            "depthai can reach. With --rig, estimate the bandwidth the rig's cameras need on "
            "each bus and warn when a bus is oversubscribed (the most common multi-webcam failure)."
        ),
    )
    p.add_argument("--rig", metavar="RIG.toml", help="rig file whose cameras to check against the buses")
    p.add_argument("--json", action="store_true", help="print the inventory as JSON")
    p.add_argument("--no-depthai", action="store_true", help="do not ask depthai for OAK devices")
    p.set_defaults(func=run)


def _mbps(v: float | None) -> str:
    if v is None:
        return "speed unknown"
    return f"{v:g} Mbit/s" if v < 1000 else f"{v / 1000:g} Gbit/s"


def _usb_label(v: float | None) -> str:
    if v is None:
        return ""
    return "USB 2" if v <= 480 else "USB 3"


def run(args: argparse.Namespace) -> int:
    from stage.discovery import check_bus_load, discover, rig_camera_loads

    rig = None
    if args.rig:
        import stage.drivers  # noqa: F401 (the built-in drivers register their camera models)
        from stage.rig import load_rig

        rig = load_rig(args.rig)  # RigError (a ValueError) -> "stage cameras: error: ..."
    inv = discover(depthai=not args.no_depthai)
    loads, notes, reports = [], [], []
    if rig is not None:
        loads, notes = rig_camera_loads(rig, inv)
        reports = check_bus_load(loads, inv.bus_speeds)
    if args.json:
        print(json.dumps(_as_json(inv, rig, loads, notes, reports), indent=2))
        return 0
    for w in inv.warnings:
        print(f"warning: {w}")
    if inv.empty:
        print("no cameras found: no V4L2 video nodes, no UVC or OAK USB devices"
              + ("" if args.no_depthai else ", no OAK reachable by depthai"))
        print("  (plug a camera in; check permissions and udev rules: docs/hardware.md)")
    else:
        _print_inventory(inv)
    if rig is not None:
        _print_rig_load(rig, loads, notes, reports)
    return 0


def _as_json(inv, rig, loads, notes, reports) -> dict:
    out = {
        "video_nodes": [asdict(n) for n in inv.video_nodes],
        "usb_devices": [asdict(u) for u in inv.usb_devices],
        "oak_devices": inv.oak_devices,
        "bus_speeds_mbps": inv.bus_speeds,
        "warnings": inv.warnings,
    }
    if rig is not None:
        out["rig"] = {
            "cameras": [{**asdict(c), "mbps": c.mbps} for c in loads],
            "buses": [{**asdict(r), "oversubscribed": r.oversubscribed, "warning": r.warning()} for r in reports],
            "notes": notes,
        }
    return out


def _print_inventory(inv) -> None:
    """Video nodes, USB cameras, OAK devices and bus speeds, as found."""
    if inv.video_nodes:
        print("V4L2 video nodes:")
        for n in inv.video_nodes:
            cap = {True: "capture", False: "no capture (metadata node)", None: "capability unknown"}[n.capture]
            where = (f"USB bus {n.usb_bus} port {n.usb_port} ({_usb_label(n.usb_speed_mbps)}, {_mbps(n.usb_speed_mbps)})"
                     if n.usb_bus is not None else "not on USB")
            print(f"  {n.path:<13} {n.name!r:<32} {cap:<27} {where}")
    if inv.usb_devices:
        print("USB cameras:")
        for u in inv.usb_devices:
            kind = "OAK" if u.kind == "oak" else "UVC"
            print(f"  bus {u.bus:<3} port {u.port or '?':<10} {u.ids}  {kind:<4} "
                  f"{_usb_label(u.speed_mbps):<6} {_mbps(u.speed_mbps):<14} {u.description}")
            if u.kind == "oak" and u.product_id == 0xF63B and u.speed_mbps is not None and u.speed_mbps <= 480:
                print("    warning: this OAK runs on a USB 2 link; use a USB 3 port and cable for full frame rates")
    if inv.oak_devices:
        print("OAK devices (depthai):")
        for d in inv.oak_devices:
            print(f"  {d['id']}  {d['name']:<16} {d['protocol']:<20} {d['state']:<12} {d['platform']}")
    if inv.bus_speeds:
        print("USB buses: " + ", ".join(f"{b}: {_mbps(s)}" for b, s in sorted(inv.bus_speeds.items())))


def _print_rig_load(rig, loads, notes, reports) -> None:
    """The rig's estimated USB bandwidth per camera and per bus, with warnings."""
    print(f"rig {rig.name!r}: estimated USB bandwidth")
    for c in loads:
        place = f"bus {c.bus}" if c.bus is not None else "not placed"
        print(f"  {c.camera_id:<12} {c.width}x{c.height} @ {c.fps:g} fps {c.pixel_format:<5} ~{c.mbps:7.1f} Mbit/s  {place}")
    if not loads:
        print("  (no live USB cameras in the rig)")
    for note in notes:
        print(f"  note: {note}")
    for r in reports:
        state = "OVERSUBSCRIBED" if r.oversubscribed else "ok"
        assumed = " (speed assumed)" if r.link_assumed else ""
        print(f"  bus {r.bus}{assumed}: needs ~{r.need_mbps:.0f} of ~{r.budget_mbps:.0f} Mbit/s  {state}")
    for r in reports:
        if r.warning():
            print(f"WARNING: {r.warning()}")
