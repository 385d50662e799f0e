"""``stage capture``: record a synchronized take from every camera of a rig."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 20


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "capture",
        help="record a synchronized take from every camera of a rig into an HDF5 file",
        description="Grab from every camera of the rig at once, group frames into frame sets by "
        "timestamp and write them to one HDF5 take (flushed every set, readable while it is written). "
        "A camera that disconnects is reported and marked missing; the take stays readable.",
    )
    p.add_argument("--rig", required=True, type=Path, metavar="RIG.toml", help="rig file (cameras, fps, volume)")
    p.add_argument("--out", required=True, type=Path, metavar="TAKE.h5", help="take file to write")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frame sets")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--compression",
        choices=("none", "lz4", "gzip"),
        default="none",
        help="filter for raw frames: none (default), lz4 (Blosc/LZ4, needs hdf5plugin), "
        "gzip (slow: cannot keep up with several cameras; see `stage bench capture`)",
    )
    p.add_argument("--calibration", type=Path, metavar="FILE", help="calibration to store in the take (any format `calib` reads)")
    p.add_argument("--overwrite", action="store_true", help="replace TAKE.h5 if it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    import fake_cameras  # noqa: F401 (registers the simulated rig's "fake" driver)
    from stage.capture import capture_take
    from stage.rig import load_rig
    from stage.sync import relock_warnings

    if args.frames is None and args.duration is None:
        raise ValueError("give --frames N and/or --duration S")
    rig = load_rig(args.rig)
    calibration = None
    if args.calibration is not None:
        from calib.formats import read_calibration

        calibration = read_calibration(args.calibration)
    bar = tqdm(
        total=args.frames,
        unit="set",
        desc=f"capture {len(rig.cameras)} cam",
        disable=args.no_progress,
        dynamic_ncols=True,
    )

    def progress(p) -> None:
        bar.update(p.sets - bar.n)
        post = {"fps": f"{p.fps:.1f}", "drops": p.drops + p.queue_drops}
        if p.disconnected:
            post["lost"] = ",".join(p.disconnected)
        bar.set_postfix(post, refresh=False)

    try:
        res = capture_take(
            rig,
            args.out,
            frames=args.frames,
            duration_s=args.duration,
            compression=args.compression,
            calibration=calibration,
            progress=progress,
            overwrite=args.overwrite,
        )
    finally:
        bar.close()
    st = res.stats
    print(f"wrote {res.path}: {res.sets} frame sets in {res.duration_s:.1f} s ({res.fps:.1f} sets/s), stopped: {res.stopped}")
    print(
        f"  sync: {st.sets_complete} complete / {st.sets_incomplete} incomplete sets, "
        f"spread median {st.spread_median_ms:.2f} ms, max {st.spread_max_ms:.2f} ms"
    )
    for cid, n in res.frames.items():
        cs = st.cameras[cid]
        extra = f", DISCONNECTED: {res.disconnected[cid]}" if cid in res.disconnected else ""
        print(
            f"  {cid}: {n} frames, missing in {cs.missing} sets, device gaps {cs.sequence_gaps}, "
            f"writer drops {res.queue_drops.get(cid, 0)}{extra}"
        )
    for line in relock_warnings(st.to_dict()):
        print(f"  warning: {line}")
    return 1 if res.disconnected else 0
