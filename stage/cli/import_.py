"""``stage import``: build a take from another rig's images or videos and its calibration."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 21


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="build a take from another rig's footage (image folders, videos or single images) and its calibration",
        description="DIR holds one entry per camera, named as in the calibration: a folder of images "
        "(sorted by name), a video file, or a single image (a Middlebury *_par.txt names its images "
        "directly). The calibration may be aniposelib TOML ([cam_N] tables: name, size, matrix, "
        "distortions, rotation as a Rodrigues vector, translation; world->camera), OpenCV FileStorage "
        "YAML or XML (also EasyMocap's intri.yml/extri.yml), Qualisys QTM .qca.txt, caliscope "
        "camera_array.toml, COLMAP, nerfstudio transforms.json, Middlebury *_par.txt or capture-stage "
        "JSON. JPEG files are stored as they are.",
    )
    p.add_argument("--images", required=True, type=Path, metavar="DIR", help="folder with one entry per camera")
    p.add_argument("--calibration", required=True, type=Path, metavar="FILE", help="calibration file")
    p.add_argument("--out", required=True, type=Path, metavar="TAKE.h5", help="take file to write")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate of the take (default: the videos' own; 30 for image folders)")
    p.add_argument("--storage", choices=("auto", "raw", "jpeg"), default="auto",
                   help="auto (default): keep JPEG files as they are, raw otherwise")
    p.add_argument("--compression", choices=("none", "lz4", "gzip"), default="none", help="filter for raw frames")
    p.add_argument("--max-frames", type=int, metavar="N", help="import at most N frame sets")
    p.add_argument("--overwrite", action="store_true", help="replace TAKE.h5 if it exists")
    p.add_argument(
        "--support-plane",
        type=float,
        nargs=4,
        metavar=("A", "B", "C", "D"),
        help="the plane the subject stands on (a*x + b*y + c*z + d >= 0 kept, calibration units), stored "
        "in the take for `stage process`: cameras that all look down cannot carve under the subject's base",
    )
    p.add_argument("--scale", type=float, default=1.0, metavar="S",
                   help="resize every frame by S in (0, 1] on import (intrinsics follow), e.g. 0.5 for a quick look")
    p.add_argument("--masks", type=Path, metavar="MASKS_DIR", default=None,
                   help="silhouettes made elsewhere: one folder per camera (named as in the calibration), one image "
                   "per frame, non-zero = subject; stored as the take's masks, so `stage process` skips keying")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from stage.importer import import_take

    bar = tqdm(unit="set", desc="import", dynamic_ncols=True, disable=args.no_progress or None)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        res = import_take(
            args.images,
            args.calibration,
            args.out,
            fps=args.fps,
            storage=args.storage,
            compression=args.compression,
            overwrite=args.overwrite,
            max_frames=args.max_frames,
            support_plane=args.support_plane,
            scale=args.scale,
            masks=args.masks,
            progress=progress,
        )
    finally:
        bar.close()
    rate = {"given": "--fps", "videos": "the videos' own", "default": "no video states one: --fps gives it"}[res.fps_source]
    print(f"wrote {res.path}: {len(res.frames)} cameras, {res.sets} frame sets at {res.fps:g} fps ({rate}), "
          f"calibration units {res.units!r}"
          + (f"; masks from {args.masks} stored (keying skipped)" if args.masks is not None else ""))
    for c, n in res.frames.items():
        print(f"  {c}: {n} frames ({res.storage[c]})")
    return 0
