"""``stage bench control``: what the control room costs the capture.

A simulated rig (``fake_cameras``: N cameras filming the starfish in real time) runs as a stage
session behind the real server (``create_app`` with a control room, uvicorn on a local port) with
the live 3-D preview's worker process running, and N HTTP clients that read one camera's MJPEG
preview each (``/stage/cameras/{id}/preview.mjpg``) when previews are on. Phases:

1. ``capture_take`` alone on the same rig: the ``stage bench capture`` figures of a plain capture;
2. idle, no preview streams, then idle with N streams: the process CPU the previews add, per camera;
3. a take recorded from the session with no preview streams, then one with N streams: sets,
   missing camera slots (first and last sets excluded: cut by start and stop), device sequence
   gaps and writer-queue drops -- the previews must not cost a frame;
4. throughout: the preview latency from a frame's grab (host clock) to its bytes being handed to
   the network (p50 / p99), and the 3-D preview's updates per second.

``--board``: the guided calibration instead: the simulated ChArUco board waved in front of the
rig (640x480, 4 fps), a board session recording its take until every camera has ``--min-views``
views and the pairs link every camera, then the calibration job's work on that take (5 held-out
folds): seconds to open the cameras (to render the views, unless the simulator's disk cache has
them), to "enough views" and to the calibration, its warnings and errors.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

NAME = "control"
HELP = "control room: preview latency p50/p99, preview CPU per camera, capture drops with/without previews, 3-D updates/s"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", type=int, default=12, help="simulated cameras, 4-24 (default 12)")
    p.add_argument("--size", default="320x240", help="camera image size WxH (default 320x240)")
    p.add_argument("--fps", type=float, default=30.0, help="rig frame rate (default 30)")
    p.add_argument("--seconds", type=float, default=5.0, help="length of each phase (default 5 s)")
    p.add_argument("--preview-fps", type=float, default=5.0, help="preview frames a second per stream (default 5)")
    p.add_argument("--dir", type=Path, default=None, help="where takes are written (default: a temporary folder)")
    p.add_argument("--board", action="store_true",
                   help="instead: a guided board session on the simulated ChArUco board (640x480, 4 fps, 24 views): "
                   "seconds to 'enough views' and to the calibration with its held-out errors")
    p.add_argument("--min-views", type=int, default=4, help="--board: views per camera that are enough (default 4)")


def _rig(n: int, size: tuple[int, int], fps: float):
    from stage.rig import parse_rig

    return parse_rig({
        "name": "bench-control", "fps": fps,
        "simulation": {"subject": "starfish", "n_cameras": max(n, 4), "frames": 30},
        "cameras": [{"id": f"cam{i:02d}", "driver": "fake", "index": i, "width": size[0], "height": size[1]}
                    for i in range(n)],
    })


def _take_figures(path: Path, *, seconds: float, fps: float, queue_drops: int) -> dict:
    from stage.store import TakeReader

    with TakeReader(path) as r:
        table = r.set_table()
        st = r.sync_stats
    gaps = sum(int(c["sequence_gaps"]) for c in st["cameras"].values())
    missing = int((table[1:-1] < 0).sum())
    return {"sets": int(len(table)), "expected": int(seconds * fps), "missing": missing, "gaps": gaps,
            "queue_drops": int(queue_drops), "drops": missing + gaps + int(queue_drops),
            "spread_median_ms": float(st["spread_median_ms"])}


def _cpu() -> float:
    from stage.benchmarks.capture import cpu_seconds

    return cpu_seconds()


class _Streams:
    """N clients, each reading one camera's MJPEG preview until stopped."""

    def __init__(self, url: str, cams: list[str]) -> None:
        self.stop = threading.Event()
        self.parts = {c: 0 for c in cams}
        self.threads = [threading.Thread(target=self._read, args=(url, c), daemon=True) for c in cams]

    def _read(self, url: str, cid: str) -> None:
        import httpx

        with httpx.Client(timeout=10) as client, client.stream("GET", f"{url}/stage/cameras/{cid}/preview.mjpg") as r:
            for chunk in r.iter_bytes():
                self.parts[cid] += chunk.count(b"--stageframe")
                if self.stop.is_set():
                    return

    def __enter__(self) -> "_Streams":
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(10)


def _record(session, room, out: Path, seconds: float, fps: float) -> dict:
    room.latency_ns.clear()
    session.start_recording(out, take=out.stem, duration_s=seconds)
    session.wait_recording(seconds + 60)
    res = session.recording()["result"]
    fig = _take_figures(out, seconds=seconds, fps=fps, queue_drops=sum(res["queue_drops"].values()))
    fig["latency_ms"] = room.latency_ms()
    return fig


def _row(name: str, f: dict) -> str:
    lat = f.get("latency_ms") or {}
    latency = f"{lat['p50']:.0f} / {lat['p99']:.0f}" if lat.get("n") else "-"
    return (f"  {name:<34} {f['sets']:5d}/{f['expected']:<5d} {f['missing']:8d} {f['gaps']:6d} {f['queue_drops']:6d}"
            f" {f['drops']:6d}   {f['spread_median_ms']:6.2f}   {latency}")


def run(args: argparse.Namespace) -> int:
    import uvicorn

    import fake_cameras  # noqa: F401  (registers the "fake" driver)
    from api.app import create_app
    from api.control import ControlRoom
    from api.live3d import Live3D
    from api.settings import Settings
    from stage.capture import capture_take
    from stage.session import StageSession

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise ValueError("--size must be WxH") from None
    if not 4 <= args.cameras <= 24:
        raise ValueError(f"--cameras must be in 4..24, got {args.cameras}")
    if args.seconds <= 0 or args.fps <= 0 or args.preview_fps <= 0:
        raise ValueError("--seconds, --fps and --preview-fps must be positive")
    if args.board:
        return _board(args)
    rig = _rig(args.cameras, (w, h), args.fps)
    n, T = args.cameras, float(args.seconds)
    tmp = tempfile.TemporaryDirectory(prefix="bench-control-", dir=args.dir)
    root = Path(tmp.name)
    print(f"stage bench control: {n} simulated cameras {w}x{h} at {args.fps:g} fps, previews {args.preview_fps:g}/s "
          f"per camera (downscaled to <= 320 px), {T:g} s phases, {os.cpu_count()} CPUs")
    print("rendering / loading the simulated frames...", flush=True)
    base_out = root / "baseline.h5"
    res = capture_take(rig, base_out, duration_s=T)
    base = _take_figures(base_out, seconds=T, fps=args.fps, queue_drops=sum(res.queue_drops.values()))

    session = StageSession(rig, root / "data" / "takes").open()
    room = ControlRoom(session, preview_fps=args.preview_fps)
    room.live3d = Live3D(room).start()
    settings = Settings(data=root / "data", api_token="bench", workers=1)
    app = create_app(settings, control=room, start_runner=False)
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    url = f"http://127.0.0.1:{port}"
    try:
        while not server.started:
            time.sleep(0.05)
        _wait_live3d(room, 120)
        rows, cpu = _phases(session, room, url, root, n, T, args.fps)
    finally:
        server.should_exit = True
        th.join(30)
        tmp.cleanup()
    l3 = rows.pop("live3d")
    print(f"\npreview CPU: idle process {cpu['idle']:.2f} cores without streams, {cpu['streams']:.2f} with {n}: "
          f"{cpu['per_camera'] * 100:.1f} % of a core per camera ({cpu['parts']} preview frames sent in {T:g} s)")
    print(f"preview latency grab -> bytes sent, {n} streams: idle p50 {cpu['latency']['p50']:.1f} ms, "
          f"p99 {cpu['latency']['p99']:.1f} ms ({cpu['latency']['n']} frames)")
    print(f"live 3-D preview (64^3 hull + spine, worker process): {l3['rate']:.2f} updates/s over the run, "
          f"{l3['recent']:.2f} in the last 5 s, {l3['compute_ms']:.0f} ms per update (median)")
    print(f"\ncapture, {T:g} s takes                   sets/expected  missing   gaps  queue  drops   spread ms  "
          "preview p50/p99 ms")
    print(_row("capture_take alone", base))
    for name, f in rows.items():
        print(_row(name, f))
    return 0


def _wait_live3d(room, timeout: float) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and room.live3d.latest().get("state") not in ("ok", "unavailable", "empty"):
        time.sleep(0.2)


def _phases(session, room, url: str, root: Path, n: int, T: float, fps: float) -> tuple[dict, dict]:
    ids = list(session.ids)
    u0, t0 = room.live3d.updates, time.monotonic()
    c0 = _cpu()
    time.sleep(T)
    idle = (_cpu() - c0) / T
    room.latency_ns.clear()
    with _Streams(url, ids) as streams:
        time.sleep(1.0)  # every stream open
        room.latency_ns.clear()
        c0 = _cpu()
        time.sleep(T)
        with_streams = (_cpu() - c0) / T
        lat = room.latency_ms()
        parts = sum(streams.parts.values())
    rows = {"session take, no previews": _record(session, room, root / "data" / "takes" / "quiet.h5", T, fps)}
    with _Streams(url, ids):
        time.sleep(1.0)
        rows[f"session take, {n} previews streaming"] = _record(session, room, root / "data" / "takes" / "busy.h5", T, fps)
    l3 = room.live3d.latest()
    rows["live3d"] = {"rate": (room.live3d.updates - u0) / (time.monotonic() - t0), "recent": l3.get("updates_per_s", 0.0),
                      "compute_ms": float(np.median(room.live3d.compute_ms)) if room.live3d.compute_ms else float("nan")}
    cpu = {"idle": idle, "streams": with_streams, "per_camera": (with_streams - idle) / n, "latency": lat, "parts": parts}
    return rows, cpu


def _board(args: argparse.Namespace) -> int:
    import fake_cameras  # noqa: F401  (registers the "fake" driver)
    from api.calibrations import CalibrateParams, calibrate_take
    from api.control import BoardSession
    from calib.boards import Charuco
    from stage.rig import parse_rig
    from stage.session import StageSession

    n = args.cameras
    board = Charuco(squares=(7, 5), square_mm=70.0, marker_mm=52.0, dictionary="DICT_4X4_50")  # the simulator's
    rig = parse_rig({
        "name": "bench-board", "fps": 4.0,
        "simulation": {"subject": "board-charuco", "n_cameras": max(n, 4), "frames": 24, "noise": 1.0},
        "cameras": [{"id": f"cam{i:02d}", "driver": "fake", "index": i, "width": 640, "height": 480} for i in range(n)],
    })
    tmp = tempfile.TemporaryDirectory(prefix="bench-board-", dir=args.dir)
    root = Path(tmp.name)
    print(f"stage bench control --board: {n} simulated cameras 640x480 at 4 fps, 24 board views, "
          f"enough = {args.min_views} views per camera and linked pairs of 3 shared views", flush=True)
    t0 = time.perf_counter()
    try:
        with StageSession(rig, root) as session:
            t_open = time.perf_counter() - t0
            session.start_recording(root / "board.h5", take="board")
            bs = BoardSession(session, board, min_views=args.min_views).start()
            t1 = time.perf_counter()
            ok = False
            while time.perf_counter() - t1 < 600 and not ok:
                time.sleep(0.25)
                ok = bs.status()["enough"]
            t_enough = time.perf_counter() - t1
            st = bs.status()
            bs.stop()
            session.stop_recording()
            sets = session.recording()["frames_written"]
        t2, c2 = time.perf_counter(), time.process_time()
        result = calibrate_take(root / "board.h5", params=CalibrateParams(board=board.to_dict(), holdout=5))
        t_cal, c_cal = time.perf_counter() - t2, time.process_time() - c2
    finally:
        tmp.cleanup()
    views = st["views"]
    print(f"cameras opened (views rendered, or read from the simulator's disk cache) in {t_open:.1f} s; "
          f"{'enough views' if ok else 'NOT enough views'} after "
          f"{t_enough:.1f} s ({st['sets_examined']} frame sets examined; views per camera {min(views.values())}.."
          f"{max(views.values())}); board take {sets} frame sets")
    print(f"calibration of the take: {t_cal:.1f} s ({c_cal:.1f} s of CPU); {result.summary()}")
    print(f"warnings: {len(result.warnings)}")
    for w in dict.fromkeys(result.warnings):
        print(f"  warning: {w}")
    return 0
