"""``stage calibrate``: calibrate a rig from a board take or per-camera image folders / videos."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Iterator

import numpy as np

ORDER = 30

log = logging.getLogger(__name__)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate the cameras from views of a board (intrinsics, then bundle adjustment)",
        description="Detect the board in every camera's frames, calibrate each camera (Zhang), then all "
        "cameras together by bundle adjustment. Input: a take (TAKE.h5; the calibration is stored in it) "
        "or --images DIR with one folder of images (sorted by name; the n-th image of every camera is the "
        "same moment) or one video per camera, named by camera. The world frame is the board in the frame "
        "seen by the most cameras (origin on the board, z up if it lies face up) unless --world camera.",
    )
    p.add_argument("take", nargs="?", type=Path, metavar="TAKE.h5", help="board take to calibrate from")
    p.add_argument("--images", type=Path, metavar="DIR", help="folder with one image folder or video per camera")
    p.add_argument("--board", required=True, type=Path, metavar="BOARD.toml", help="board definition")
    p.add_argument("--out", type=Path, metavar="CALIB.toml",
                   help="calibration file to write (.toml aniposelib, .yml OpenCV, .json)")
    p.add_argument("--world", choices=("board", "camera"), default="board",
                   help="world frame: a board pose (default) or the first camera")
    p.add_argument("--world-frame", type=int, metavar="N", help="frame whose board defines the world")
    p.add_argument("--min-change", type=float, default=0.02,
                   help="keep a view only if the board moved by this fraction of the image diagonal (default 0.02)")
    p.add_argument("--step", type=int, default=1, help="look at every N-th frame (default 1)")
    p.add_argument("--fix-k3", action="store_true", help="fix the k3 distortion term (few views, mild lenses)")
    p.add_argument("--no-intrinsics-refinement", action="store_true",
                   help="keep per-camera intrinsics fixed in the bundle adjustment")
    p.add_argument("--coverage", type=Path, metavar="DIR", help="write a coverage picture per camera here")
    p.add_argument("--report", type=Path, metavar="FILE.json", help="write the full report as JSON")
    p.set_defaults(func=run)


def _sources(root: Path) -> dict[str, tuple[str, Path, list[Path]]]:
    if not root.is_dir():
        raise FileNotFoundError(f"--images {root}: not a directory")
    out: dict[str, tuple[str, Path, list[Path]]] = {}
    for p in sorted(root.iterdir()):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTS)
            if files:
                out[p.name] = ("folder", p, files)
        elif p.suffix.lower() in VIDEO_EXTS:
            out[p.stem] = ("video", p, [])
    if not out:
        raise ValueError(f"--images {root}: no camera folders of images and no videos found "
                         f"(expected DIR/<camera>/*.png or DIR/<camera>.mp4)")
    return out


def _frames(kind: str, path: Path, files: list[Path], step: int) -> Iterator[tuple[int, np.ndarray]]:
    import cv2

    if kind == "video":
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise ValueError(f"video {path} cannot be opened")
        try:
            k = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    return
                if k % step == 0:
                    yield k, img
                k += 1
        finally:
            cap.release()
    else:
        for k, f in enumerate(files):
            if k % step:
                continue
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ValueError(f"image {f} cannot be read")
            yield k, img


def _video_count(path: Path) -> int:
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        return int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()


def detect_images(root: Path, board, *, step: int = 1, min_change: float = 0.02, progress: bool = True):
    """Detections and image sizes per camera from ``--images DIR``."""
    from tqdm import tqdm

    from calib.detect import default_min_corners, detect_board, select_views

    srcs = _sources(root)
    detections, sizes = {}, {}
    for name, (kind, path, files) in srcs.items():
        total = (len(files) if kind == "folder" else _video_count(path)) // step
        dets, size = [], None
        for k, img in tqdm(_frames(kind, path, files, step), total=total, desc=f"detect {name}", unit="img",
                           disable=not progress, dynamic_ncols=True, leave=False):
            size = (img.shape[1], img.shape[0])
            dets.append(detect_board(img, board, frame=k))
        if size is None:
            raise ValueError(f"camera {name}: {path} holds no readable frame")
        keep = select_views(dets, size=size, min_corners=default_min_corners(board), min_change=min_change)
        detections[name] = [dets[i] for i in keep]
        sizes[name] = size
        n_found = sum(d is not None for d in dets)
        print(f"  {name}: board found in {n_found}/{len(dets)} frames, {len(keep)} views kept")
    return detections, sizes


def detect_take(path: Path, board, *, step: int = 1, min_change: float = 0.02, progress: bool = True):
    """Detections and image sizes per camera from a take (through ``stage.store.TakeReader``)."""
    from tqdm import tqdm

    from calib.detect import default_min_corners, detect_board, select_views
    from stage.store import TakeReader

    with TakeReader(path) as r:
        cams = list(r.cameras)
        sizes = {name: tuple(r.image_size(name)) for name in cams}
        raw: dict[str, list] = {name: [] for name in cams}
        # frame sets keep the cameras in sync: the set index is the moment ("frame") of a detection
        for k in tqdm(range(0, r.n_sets, step), desc="detect", unit="set", disable=not progress,
                      dynamic_ncols=True, leave=False):
            for name, img in r.frame_set(k).items():
                raw[name].append(None if img is None else detect_board(img, board, frame=k))
    detections = {}
    for name in cams:
        dets = raw[name]
        keep = select_views(dets, size=sizes[name], min_corners=default_min_corners(board), min_change=min_change)
        detections[name] = [dets[i] for i in keep]
        print(f"  {name}: board found in {sum(d is not None for d in dets)}/{len(dets)} frame sets, "
              f"{len(keep)} views kept")
    return detections, sizes, cams


def run(args: argparse.Namespace) -> int:
    import json

    from calib.boards import load_board
    from calib.formats import write_calibration
    from calib.rig import calibrate_rig

    if (args.take is None) == (args.images is None):
        raise ValueError("give either a take (TAKE.h5) or --images DIR, not both / neither")
    if args.take is None and args.out is None:
        raise ValueError("--out CALIB.toml is required with --images")
    if args.step < 1:
        raise ValueError("--step must be >= 1")
    if args.out is not None and not args.out.parent.exists():
        raise FileNotFoundError(f"--out: folder {args.out.parent} does not exist")
    board = load_board(args.board)
    print(f"board: {board.to_dict()}")
    if args.take is not None:
        if not args.take.is_file():
            raise FileNotFoundError(f"take not found: {args.take}")
        detections, sizes, cams = detect_take(args.take, board, step=args.step, min_change=args.min_change)
    else:
        detections, sizes = detect_images(args.images, board, step=args.step, min_change=args.min_change)
        cams = list(sizes)
    result = calibrate_rig(
        detections, sizes, board, cameras=cams, world=args.world, world_frame=args.world_frame,
        optimize_intrinsics=not args.no_intrinsics_refinement, fix_k3=args.fix_k3,
    )
    print(result.report())
    calib = result.calibration
    # everything computed: now write (nothing is written when anything above fails)
    if args.coverage is not None:
        import cv2

        from calib.intrinsics import coverage_image

        args.coverage.mkdir(parents=True, exist_ok=True)
        for name, r in result.intrinsics.items():
            img = coverage_image(detections[name], r.size, rejected=list(r.rejected), title=name)
            cv2.imwrite(str(args.coverage / f"coverage_{name}.png"), img)
        print(f"coverage pictures in {args.coverage}")
    if args.report is not None:
        args.report.write_text(json.dumps(result.to_dict(), indent=1))
    if args.out is not None:
        write_calibration(calib, args.out)
        print(f"wrote {args.out}")
    if args.take is not None:
        from stage.store import attach_calibration

        attach_calibration(args.take, calib)
        print(f"stored the calibration in {args.take}")
    return 0
