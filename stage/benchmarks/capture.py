"""``stage bench capture``: sustained capture from N simulated cameras into HDF5.

Every camera replays pre-made noisy 640x480 frames at its frame rate like a
real device with a 4-buffer ring: when the grabber falls behind, frames are
lost (device sequence gaps). Capture runs through the real
:func:`stage.capture.capture_take` (grabber threads, grouping, SWMR writer
flushed every set). For each compression option and N cameras it reports MB/s
written, dropped frames (sets missing a camera, device gaps, writer-queue
overflows), CPU load, and the largest N with zero drops; the disk's own
sequential write speed (with fsync) is measured in the same run as the ceiling.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from stage.drivers.base import Granted
from stage.frame import Frame

NAME = "capture"
HELP = "sustained capture from N simulated cameras into HDF5 per compression: MB/s, drops, CPU, max N"


class ReplayCamera:
    """Replays pre-made frames at ``fps`` on its own clock, with a ring of ``buffers`` frames."""

    def __init__(
        self, camera_id: str, frames: list[np.ndarray], fps: float, *, offset_ns: int = 0, buffers: int = 4, start: dict | None = None
    ) -> None:
        self.camera_id = camera_id
        self.frames = frames
        self.period = 1e9 / fps
        self.fps = fps
        self.offset_ns = offset_ns
        self.buffers = buffers
        self.next = 0
        self.t0: int | None = None
        self.start = start if start is not None else {}  # shared: cameras expose together (a synced rig)

    def open(self) -> None:
        pass

    def configure(self) -> Granted:
        h, w = self.frames[0].shape[:2]
        return Granted(w, h, self.fps)

    def grab(self) -> Frame:
        now = time.monotonic_ns()
        if self.t0 is None:
            self.t0 = self.start.setdefault("t0", now)
        latest = int((now - self.t0) // self.period)
        if latest - self.next >= self.buffers:  # the ring overflowed: the device dropped frames
            self.next = latest - self.buffers + 1
        due = self.t0 + int(self.next * self.period)
        if due > now:
            time.sleep((due - now) / 1e9)
        k = self.next
        self.next += 1
        return Frame(self.frames[k % len(self.frames)], self.camera_id, k, due + self.offset_ns, max(due, time.monotonic_ns()))

    def close(self) -> None:
        pass


def make_frames(n: int, size: tuple[int, int], seed: int = 0) -> list[np.ndarray]:
    """Green-backdrop-like frames with a moving blob and sensor noise (sigma 2)."""
    import cv2

    w, h = size
    rng = np.random.default_rng(seed)
    base = np.zeros((h, w, 3), np.float32)
    base[..., 1] = np.linspace(110, 190, w, dtype=np.float32)[None, :]
    base[..., 0] = 50
    base[..., 2] = 40
    out = []
    for k in range(n):
        im = base.copy()
        cv2.circle(im, (w // 4 + k * w // (2 * n), h // 2), h // 5, (120, 100, 190), -1)
        out.append(np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8))
    return out


def disk_write_speed(directory: Path, mb: int = 256) -> float:
    """Sequential write speed (MB/s) of ``directory``'s disk, fsync included."""
    buf = np.random.default_rng(0).integers(0, 256, 8 << 20, dtype=np.uint8).tobytes()
    path = directory / "bench_disk_speed.bin"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        t = time.perf_counter()
        n = 0
        while n < mb << 20:
            n += os.write(fd, buf)
        os.fsync(fd)
        dt = time.perf_counter() - t
    finally:
        os.close(fd)
        path.unlink()
    return n / dt / 1e6


def cpu_seconds() -> float:
    try:
        import psutil

        t = psutil.Process().cpu_times()
        return t.user + t.system
    except ImportError:
        t = os.times()
        return t.user + t.system


def run_one(directory: Path, n_cams: int, compression: str, seconds: float, fps: float, size: tuple[int, int], frames) -> dict:
    from stage.capture import capture_take
    from stage.rig import parse_rig

    ids = [f"cam{i:02d}" for i in range(n_cams)]
    rig = parse_rig(
        {
            "name": "bench",
            "fps": fps,
            "cameras": [{"id": c, "driver": "opencv", "device": i, "width": size[0], "height": size[1]} for i, c in enumerate(ids)],
        }
    )
    start: dict = {}
    drivers = {
        c: ReplayCamera(c, frames[i % len(frames)], fps, offset_ns=i * 1_234_567_891, start=start) for i, c in enumerate(ids)
    }
    out = directory / f"bench_{compression}_{n_cams}.h5"
    c0, w0 = cpu_seconds(), time.perf_counter()
    res = capture_take(rig, out, duration_s=seconds, compression=compression, drivers=drivers, overwrite=True)
    wall = time.perf_counter() - w0
    cpu = cpu_seconds() - c0
    size_b = out.stat().st_size
    from stage.store import TakeReader

    with TakeReader(out) as r:  # the first and last sets are cut by start/stop, not drops
        table = r.set_table()
    out.unlink()
    st = res.stats
    expected = int(seconds * fps)
    missing = int((table[1:-1] < 0).sum())
    gaps = sum(s.sequence_gaps for s in st.cameras.values())
    qd = sum(res.queue_drops.values())
    raw_mb = sum(res.frames.values()) * size[0] * size[1] * 3 / 1e6
    return {
        "cameras": n_cams,
        "compression": compression,
        "sets": res.sets,
        "expected_sets": expected,
        "mb_per_s": size_b / 1e6 / res.duration_s,
        "raw_mb_per_s": raw_mb / res.duration_s,
        "ratio": raw_mb * 1e6 / max(size_b, 1),
        "missing": missing,
        "gaps": gaps,
        "queue_drops": qd,
        "drops": missing + gaps + qd,
        "cpu_cores": cpu / wall,
        "sets_per_s": res.fps,
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", default="1,2,4,6,8,12", help="camera counts to try, ascending (default 1,2,4,6,8,12)")
    p.add_argument("--compression", default="none,lz4,gzip", help="compression options (default none,lz4,gzip)")
    p.add_argument("--seconds", type=float, default=3.0, help="capture length per run (default 3 s; longer is steadier)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--size", default="640x480", help="WxH (default 640x480)")
    p.add_argument("--dir", type=Path, default=None, help="where to write (default: a temporary folder; same disk matters)")
    p.add_argument("--disk-mb", type=int, default=256, help="MB written for the disk speed test (default 256)")
    p.add_argument("--keep-going", action="store_true", help="try every camera count even after drops")


def run(args: argparse.Namespace) -> int:
    from stage.store import COMPRESSIONS, have_lz4

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        counts = sorted({int(v) for v in args.cameras.split(",") if v.strip()})
    except ValueError:
        raise ValueError("--size must be WxH and --cameras a comma-separated list of integers") from None
    if not counts or min(counts) < 1 or w < 1 or h < 1:
        raise ValueError("--cameras and --size must be positive")
    comps = [c.strip() for c in args.compression.split(",") if c.strip()]
    bad = [c for c in comps if c not in COMPRESSIONS]
    if bad:
        raise ValueError(f"--compression: unknown {bad} (choose from {', '.join(COMPRESSIONS)})")
    if "lz4" in comps and not have_lz4():
        print("lz4: SKIPPED - the optional package hdf5plugin is not installed (pip install 'capture-stage[fast]')")
        comps.remove("lz4")
    try:
        import psutil  # noqa: F401

        cpu_src = "psutil"
    except ImportError:
        cpu_src = "os.times (psutil not installed)"
    tmp_ctx = tempfile.TemporaryDirectory(prefix="stage-bench-", dir=args.dir) if args.dir is None or args.dir.is_dir() else None
    if tmp_ctx is None:
        raise FileNotFoundError(f"--dir {args.dir}: not a directory")
    with tmp_ctx as tmp:
        d = Path(tmp)
        disk = disk_write_speed(d, args.disk_mb)
        print(f"disk sequential write (fsync'd, {args.disk_mb} MB): {disk:.0f} MB/s   [ceiling]")
        need = w * h * 3 * args.fps / 1e6
        print(f"one {w}x{h} camera at {args.fps:g} fps = {need:.1f} MB/s raw; the disk alone allows ~{int(disk // need)} cameras")
        print(f"cpu: {cpu_src}; {os.cpu_count()} logical cores; runs of {args.seconds:g} s")
        print()
        frames = [make_frames(8, (w, h), seed=s) for s in range(4)]
        hdr = (f"{'compr':>6} {'N':>3} {'sets':>9} {'MB/s disk':>9} {'MB/s raw':>9} "
               f"{'ratio':>5} {'miss':>5} {'gaps':>5} {'qdrop':>5} {'cpu':>5}")
        print(hdr)
        best: dict[str, int] = {}
        for comp in comps:
            best[comp] = 0
            for n in counts:
                r = run_one(d, n, comp, args.seconds, args.fps, (w, h), frames)
                print(
                    f"{comp:>6} {n:>3} {r['sets']:>4}/{r['expected_sets']:<4} {r['mb_per_s']:>9.1f} {r['raw_mb_per_s']:>9.1f} "
                    f"{r['ratio']:>5.2f} {r['missing']:>5} {r['gaps']:>5} {r['queue_drops']:>5} {r['cpu_cores']:>5.2f}",
                    flush=True,
                )
                if r["drops"] == 0 and r["sets"] >= 0.9 * r["expected_sets"]:
                    best[comp] = n
                elif not args.keep_going:
                    break
        print()
        for comp, n in best.items():
            print(f"largest N with zero drops, {comp}: {n if n else 'none'} (tried {', '.join(map(str, counts))})")
        print("cpu = process CPU seconds per wall second (1.0 = one core busy).")
    return 0
