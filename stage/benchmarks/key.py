"""``stage bench key``: keying throughput (Mpix/s) with 1 and 2 workers, against a plain HSV ``cv2.inRange``.

``--partial``: where the backdrop does not fill the view, per camera at VGA and 1080p: the
plate estimated from 25 frames of the take (input Mpix/s), plate keying (Mpix/s) and the
graph-cut refinement (Mpix/s of the image), on the simulated stage without a backdrop
(:func:`fake_cameras.take.stage_backdrop`; 1080p frames are the VGA ones resized), with the
plate keyer's IoU against the true masks at VGA.

Frames come from the simulated rig (``fake_cameras.take.simulate_take``), so both
keyers are also scored (IoU, boundary F at 2 px) against the ground-truth masks.
The target is to keep up with 12 cameras at 640x480 and 30 fps: about 110 Mpix/s.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

NAME = "key"
HELP = "keying speed (Mpix/s, 1 and 2 workers) and IoU vs a plain cv2.inRange HSV key"

TARGET_MPIX = 12 * 640 * 480 * 30 / 1e6


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="starfish", help="simulated subject (default starfish)")
    p.add_argument("--frames", type=int, default=2, help="simulated time steps (x cameras = images; default 2)")
    p.add_argument("--cameras", type=int, default=12, help="simulated cameras (default 12)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seconds", type=float, default=2.0, help="minimum timed seconds per configuration")
    p.add_argument("--partial", action="store_true",
                   help="plate-from-take estimation, plate keying and graph-cut refinement, per camera at VGA and 1080p")


def _hsv_key(image: np.ndarray) -> np.ndarray:
    import cv2

    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    green = cv2.inRange(hsv, (35, 60, 30), (85, 255, 255))  # the usual green-screen range
    return green == 0


def _timed(fn, items, workers: int, seconds: float) -> float:
    """Images per second of ``fn`` over ``items`` with ``workers`` threads (repeat until ``seconds``)."""
    t0 = time.perf_counter()
    done = 0
    while True:
        if workers == 1:
            for it in items:
                fn(it)
        else:
            with ThreadPoolExecutor(max_workers=workers) as ex:
                list(ex.map(fn, items))
        done += len(items)
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return done / dt


def _bench_partial(args: argparse.Namespace) -> int:
    import cv2

    from fake_cameras.dome import make_dome
    from fake_cameras.take import simulate_take, stage_backdrop
    from pipeline.silhouette_refine import refine_silhouette
    from stage.keying import KeyParams, iou
    from stage.keying.background import take_plate
    from stage.keying.keyer import estimate_model, key_one
    from stage.rig import Volume

    vol = Volume(center=(0.0, 0.0, 500.0), size=(2400.0, 2400.0, 1000.0))
    calib = make_dome(4, size=(640, 480), volume=vol, seed=2, distortion=True)
    print("rendering 25 frames x 4 cameras at 640x480 of the stage without a backdrop (cached after the first run)...")
    sim = simulate_take("biped", calibration=calib, frames=25, backdrop=stage_backdrop("none", calibration=calib, volume=vol),
                        seed=2, volume=vol, scale=1.6, travel=(1800.0, 0.0), workers=1)
    frames_vga, truth = sim.images[:, 1], sim.masks[:, 1]
    print(f"{'size':>10s} {'plate from take':>16s} {'plate keying':>13s} {'graph cut':>10s}   (Mpix/s, one camera, one thread)")
    for w, h in ((640, 480), (1920, 1080)):
        frames = frames_vga if w == 640 else np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_LINEAR)
                                                       for f in frames_vga])
        masks = truth if w == 640 else np.stack([cv2.resize(m.view(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
                                                 .view(bool) for m in truth])
        mpix = w * h / 1e6
        t0 = time.perf_counter()
        est = take_plate(frames)
        t_plate = time.perf_counter() - t0
        params = estimate_model(frames, params=KeyParams(mode="plate"))
        ips = _timed(lambda im, p=params: key_one(im, p), list(frames[:8]), 1, args.seconds)
        keyed = [key_one(im, params)[0] for im in frames]
        hull = [cv2.dilate(m.view(np.uint8), np.ones((9, 9), np.uint8)).view(bool) for m in masks]
        items = list(zip(frames[:4], keyed[:4], hull[:4]))
        gps = _timed(lambda it: refine_silhouette(it[0], it[1], it[2], footprint=2.0), items, 1, args.seconds)
        print(f"{w}x{h:<5d} {frames.shape[0] * mpix / t_plate:16.1f} {ips * mpix:13.1f} {gps * mpix:10.1f}")
        if w == 640:
            ious = [iou(k, g) for k, g in zip(keyed, truth)]
            print(f"{'':10s} plate keying IoU vs true masks: mean {np.mean(ious):.4f}, min {np.min(ious):.4f}; "
                  f"flagged pixels {100 * est.stuck_fraction:.2f} %")
    return 0


def run(args: argparse.Namespace) -> int:
    import cv2

    if getattr(args, "partial", False):
        return _bench_partial(args)

    from stage.keying import KeyParams, boundary_f_score, iou
    from stage.keying.keyer import estimate_model, key_one

    try:
        from fake_cameras.take import simulate_take
    except ImportError as exc:  # pragma: no cover
        raise ValueError(f"the simulated rig (fake_cameras) is needed for this benchmark: {exc}") from None
    print(f"rendering {args.frames} frames x {args.cameras} cameras at {args.width}x{args.height} (cached after the first run)...")
    take = simulate_take(args.subject, n_cameras=args.cameras, frames=args.frames, size=(args.width, args.height), seed=0)
    mpix = args.width * args.height / 1e6
    t0 = time.perf_counter()
    params = [estimate_model(take.images[:, c], params=KeyParams()) for c in range(take.n_cameras)]
    t_model = (time.perf_counter() - t0) / take.n_cameras
    items = [(take.images[f, c], params[c]) for f in range(take.n_frames) for c in range(take.n_cameras)]
    truth = [take.masks[f, c] for f in range(take.n_frames) for c in range(take.n_cameras)]

    ours = [key_one(im, p)[0] for im, p in items]
    hsv = [_hsv_key(im) for im, _ in items]
    scores = {}
    for name, masks in (("stage chroma key", ours), ("cv2.inRange HSV", hsv)):
        ious = np.array([iou(m, g) for m, g in zip(masks, truth)])
        bfs = np.array([boundary_f_score(m, g, tol=2.0) for m, g in zip(masks, truth)])
        scores[name] = (ious.mean(), ious.min(), bfs.mean(), bfs.min())

    threads_before = cv2.getNumThreads()
    rows = []
    try:
        for workers in (1, 2):
            cv2.setNumThreads(1)  # parallelism comes from the worker threads only
            ips = _timed(lambda it: key_one(*it), items, workers, args.seconds)
            rows.append(("stage chroma key", workers, ips))
            ips = _timed(lambda it: _hsv_key(it[0]), items, workers, args.seconds)
            rows.append(("cv2.inRange HSV", workers, ips))
    finally:
        cv2.setNumThreads(threads_before)

    print(f"\nbackdrop model estimation: {1e3 * t_model:.1f} ms per camera (once per take)")
    print(f"target: {TARGET_MPIX:.0f} Mpix/s (12 cameras, 640x480, 30 fps)\n")
    print(f"{'keyer':20s} {'workers':>7s} {'frames/s':>9s} {'Mpix/s':>8s}   "
          f"{'IoU mean':>8s} {'IoU min':>8s} {'BF2 mean':>8s} {'BF2 min':>8s}")
    for name, workers, ips in rows:
        s = scores[name]
        print(
            f"{name:20s} {workers:7d} {ips:9.1f} {ips * mpix:8.1f}   {s[0]:8.4f} {s[1]:8.4f} {s[2]:8.4f} {s[3]:8.4f}"
        )
    best = max(ips for name, _, ips in rows if name == "stage chroma key") * mpix
    verdict = "meets" if best >= TARGET_MPIX else "misses"
    print(f"\nstage chroma key {verdict} the target: {best:.0f} of {TARGET_MPIX:.0f} Mpix/s")
    return 0
