"""``stage key TAKE.h5``: key every camera of a take and store the masks in it."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

ORDER = 40
log = logging.getLogger("stage.key")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "key",
        help="compute silhouette masks of a take (chroma/luma/plate keying)",
        description="Key every camera of a take: estimate the backdrop model per camera "
        "(from a background plate stored in the take as cameras/<cam>/plate, else from the frames), "
        "compute masks and store them in the take with their parameters. Frames that cannot be keyed "
        "(black, no backdrop visible, subject filling the image) are marked invalid with a warning.",
    )
    p.add_argument("take", type=Path, help="take file (.h5)")
    p.add_argument(
        "--key-mode",
        choices=("chroma", "luma", "plate"),
        default=None,
        help="keying mode (default: the rig's backdrop.key_mode stored in the take; footage without a rig file: "
        "chroma when a backdrop colour covers a large share of the views, else a plate from the take)",
    )
    p.add_argument("--key-layer", action="append", choices=("volume", "graphcut"), default=None, dest="key_layers",
                   help="keying layer, repeatable: volume (pixels whose rays miss the capture volume are background), "
                   "graphcut (colour models seeded by a first hull; needs the calibration)")
    p.add_argument("--volume", type=float, nargs=6, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="the volume layer's box (default: the rig's capture volume)")
    p.add_argument("--plate", type=Path, default=None, metavar="EMPTY_TAKE",
                   help="an empty take of the same cameras: its per-pixel background and noise become the plate "
                   "(stored in the take; mode plate unless --key-mode says otherwise)")
    p.add_argument("--camera", action="append", default=None, help="only this camera (repeatable)")
    p.add_argument("--preview", type=Path, default=None, metavar="DIR", help="write a contact sheet PNG per camera into DIR")
    p.add_argument("--workers", type=int, default=2, help="threads keying frames in parallel (default 2)")
    p.add_argument("--grow", type=int, default=0, help="dilate masks by this many pixels (conservative hulls)")
    p.add_argument(
        "--fill-holes",
        choices=("uncertain", "small", "enclosed", "none"),  # stage.keying.params.FILL_HOLES (not imported: CLI start-up)
        default=None,
        help="holes to fill: of the small ones, 'uncertain' leaves gaps of clean backdrop colour open (default "
        "for chroma), 'small' fills all (default for luma: shadows look like a black backdrop); 'enclosed' fills "
        "every hole the silhouette encloses (default for plate, which also closes gaps narrower than about a "
        "limb's width), 'none'",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from stage.keying.take import key_take
    from stage.store import TakeReader

    with TakeReader(args.take) as r:
        total = sum(r.frame_counts().values())
    key_mode = args.key_mode
    if args.plate is not None:
        from stage.keying.take import store_plates

        noise = store_plates(args.take, args.plate)
        print(f"plates from {args.plate} stored (noise {', '.join(f'{c}: {v:.1f}' for c, v in noise.items())})")
        key_mode = key_mode or "plate"
    bar = tqdm(total=total, unit="frame", desc="key", disable=args.no_progress)
    try:
        summary = key_take(
            args.take,
            key_mode=key_mode,
            cameras=args.camera,
            workers=args.workers,
            grow=args.grow,
            fill_holes=args.fill_holes,
            preview=args.preview,
            progress=bar.update,
            layers=args.key_layers,
            volume=args.volume,
        )
        if "graphcut" in summary["layers"]:
            from pipeline.silhouette_refine import refine_take

            info = refine_take(args.take, volume=args.volume, progress=bar.update)
            print(f"graph-cut refinement: {info['frames']} masks refined ({info['seconds']:.1f} s)")
    finally:
        bar.close()
    from stage.store import derived_path

    layers = f" + {', '.join(summary['layers'])}" if summary["layers"] else ""
    print(
        f"keyed {len(summary['cameras'])} camera(s), {summary['frames']} frames, mode {summary['mode']}{layers} "
        f"({summary['why']}); "
        f"{summary['invalid']} invalid frame(s); masks stored in {derived_path(args.take)}"
    )
    if args.preview is not None:
        print(f"contact sheets in {args.preview}/")
    return 0
