"""``stage calibrate``: calibrate a rig from a board take or per-camera image folders / videos."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Iterator

import numpy as np

from calib.mirror import VARIANT_SAMPLE, decide_mirror, parse_mirror, sample_positions

ORDER = 30

log = logging.getLogger(__name__)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate the cameras from views of a board (intrinsics, then bundle adjustment)",
        description="Detect the board in every camera's frames, calibrate each camera (Zhang), then all "
        "cameras together by bundle adjustment over every frame set that two or more cameras saw, with the "
        "intrinsics held by a prior from each camera's own calibration. Input: a take (TAKE.h5; the calibration "
        "is stored in it) or --images DIR with one folder of images (sorted by name; the n-th image of every "
        "camera is the same moment), one folder holding one video, or one video per camera, named by camera; "
        "--timestamps synchronises videos by time. Cameras that deliver mirrored images are found and "
        "calibrated mirrored (mirror = true). The first line of the report is the held-out reprojection error "
        "(k-fold over frame sets). The world frame is the board in the frame seen by the most cameras (origin "
        "on the board, z up if it lies face up) unless --world camera.",
    )
    p.add_argument("take", nargs="?", type=Path, metavar="TAKE.h5", help="board take to calibrate from")
    p.add_argument("--images", type=Path, metavar="DIR", help="folder with one image folder or video per camera")
    p.add_argument("--board", required=True, type=Path, metavar="BOARD.toml", help="board definition")
    p.add_argument("--out", type=Path, metavar="CALIB.toml",
                   help="calibration file to write (.toml aniposelib, .yml OpenCV, .json; see "
                   "'stage calibration export' for caliscope, COLMAP and nerfstudio)")
    p.add_argument("--timestamps", type=Path, metavar="FILE.csv",
                   help="synchronise the videos by time: caliscope's timestamps.csv (sync_index, cam_id, "
                   "frame_time) or a CSV with camera, frame, time_s (default: frame by frame)")
    p.add_argument("--world", choices=("board", "camera"), default="board",
                   help="world frame: a board pose (default) or the first camera")
    p.add_argument("--world-frame", type=int, metavar="N", help="frame whose board defines the world")
    p.add_argument("--min-change", type=float, default=0.02,
                   help="per-camera intrinsics: skip a view that moved less than this fraction of the image "
                   "diagonal since the last one, unless it links cameras (default 0.02)")
    p.add_argument("--step", type=int, default=1, help="look at every N-th frame (default 1)")
    p.add_argument("--fix-k3", action="store_true", help="fix the k3 distortion term (few views, mild lenses)")
    p.add_argument("--distortion", choices=("prior", "full", "auto"), default="prior",
                   help="distortion model per camera: prior (default) fits all five coefficients with a weak "
                   "zero-mean prior on p1, p2 (sigma 0.001) and k3 (sigma 0.5), so they move only as far as the "
                   "views support; full fits them without a prior; auto holds p1, p2 "
                   "and/or k3 at 0 where the camera's own views do not support them (information criterion): "
                   "steadier principal points when the board covered little of the image")
    p.add_argument("--intrinsics", choices=("prior", "fixed", "free"), default="prior",
                   help="intrinsics in the bundle adjustment: refined under a prior from each camera's own "
                   "calibration (default), kept fixed, or refined freely")
    p.add_argument("--no-intrinsics-refinement", action="store_true", help="same as --intrinsics fixed")
    p.add_argument("--mirror", action="append", default=[], metavar="CAM=auto|true|false",
                   help="whether CAM delivers mirrored images (default auto: decided from where the board is "
                   "found); repeatable")
    p.add_argument("--holdout", type=int, default=5, metavar="K",
                   help="folds of the held-out error (0: skip it; default 5)")
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
            videos = sorted(f for f in p.iterdir() if f.suffix.lower() in VIDEO_EXTS)
            if files:
                out[p.name] = ("folder", p, files)
            elif len(videos) == 1:
                out[p.name] = ("video", videos[0], [])
            elif len(videos) > 1:
                raise ValueError(f"--images {root}: camera folder {p.name} holds {len(videos)} videos "
                                 f"({', '.join(v.name for v in videos[:3])}); keep one video per camera")
        elif p.suffix.lower() in VIDEO_EXTS:
            out[p.stem] = ("video", p, [])
    if not out:
        raise ValueError(f"--images {root}: no camera folders of images and no videos found "
                         f"(expected DIR/<camera>/*.png, DIR/<camera>/<video> or DIR/<camera>.mp4)")
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


def _detect_pass(name, src, board, *, step, flip, frame_set, want, progress):
    """Detect the board in every frame of one camera.

    Returns (detections, sampled images, size, frames read, sampled images with the board).
    """
    from tqdm import tqdm

    from calib.detect import detect_board

    kind, path, files = src
    total = len(files) if kind == "folder" else _video_count(path)
    dets, sample, size, n, as_is = [], [], None, 0, 0
    for k, img in tqdm(_frames(kind, path, files, step), total=(total + step - 1) // step, desc=f"detect {name}",
                       unit="img", disable=not progress, dynamic_ncols=True, leave=False):
        size = (img.shape[1], img.shape[0])
        sampled = n in want
        if sampled:
            sample.append(img)
        n += 1
        frame = k if frame_set is None else frame_set.get(k)
        if frame is None and not sampled:
            continue
        d = detect_board(img, board, frame=-1 if frame is None else frame, mirror=flip)
        as_is += int(sampled and d is not None)
        if d is not None and frame is not None:
            dets.append(d)
    return dets, sample, size, n, as_is


def _probe(name, src, board, *, step, mirror, total):
    """A wrong board file, found on a few evenly spaced frames before the full pass.

    Returns the message naming the board-file variant that finds the board when none of
    ``VARIANT_SAMPLE`` frames shows it as given (a wrong board costs one failed detection per
    frame, so the full pass of a long video would keep the user waiting for nothing); else None.
    """
    from calib.detect import detect_board, find_variant

    n = (total + step - 1) // step
    want = set(np.unique(np.round(np.linspace(0, n - 1, min(VARIANT_SAMPLE, n)))).astype(int).tolist()) if n else set()
    images, frames = [], _frames(*src, step)
    try:
        for i, (_, img) in enumerate(frames):
            if i in want:
                if detect_board(img, board, mirror=bool(mirror)) is not None:
                    return None
                images.append(img)
            if i >= max(want, default=-1):
                break
    finally:
        frames.close()
    v = find_variant(images, board) if len(images) >= 2 else None
    if v is None or v[1] is board:
        return None  # not a board-file problem: the full pass decides
    return (f"camera {name}: the board was not detected in {len(images)} sampled frames, but with the {v[0]} it is "
            f"found in {v[3]}/{len(images)}; fix the board file" + (" (and the camera's mirror mode)" if v[2] else ""))


def _detect_camera(name, src, board, *, step, mirror, frame_set, progress):
    """One camera: detections, size, frames read, whether flipped, and what was found out."""
    kind, path, files = src
    total = len(files) if kind == "folder" else _video_count(path)
    wrong = _probe(name, src, board, step=step, mirror=mirror, total=total)
    if wrong is not None:
        return [], _first_size(src), (total + step - 1) // step, bool(mirror), wrong
    want = sample_positions((total + step - 1) // step)
    dets, sample, size, n, as_is = _detect_pass(name, src, board, step=step, flip=bool(mirror),
                                                frame_set=frame_set, want=want, progress=progress)
    if size is None:
        raise ValueError(f"camera {name}: {path} holds no readable frame")
    flip, msg = decide_mirror(name, len(dets), n, sample, as_is, board, mirror)
    if flip != bool(mirror):
        dets, _, _, n, _ = _detect_pass(name, src, board, step=step, flip=flip, frame_set=frame_set, want=set(),
                                     progress=progress)
    return dets, size, n, flip, msg


def _first_size(src) -> tuple[int, int]:
    frames = _frames(*src, 1)
    try:
        img = next(frames)[1]
    finally:
        frames.close()
    return img.shape[1], img.shape[0]


def _length_notes(counts: dict[str, int], sets) -> list[str]:
    notes = []
    if sets is not None:
        for name, c in counts.items():
            if len(sets[name]) > c:
                notes.append(f"{name}: the timestamps list {len(sets[name])} frames, its video holds {c}; the frame "
                             f"sets past its end lack {name}")
    elif len(set(counts.values())) > 1:
        most = max(counts.values())
        for name, c in counts.items():
            if c < most:
                notes.append(f"{name}: {c} frames, the others up to {most}; matched frame by frame, the frames "
                             f"past {c} lack {name} (give --timestamps if the cameras did not start together)")
    return notes


def detect_images(root: Path, board, *, step: int = 1, min_change: float = 0.02, progress: bool = True,
                  timestamps: Path | None = None, mirror: list[str] | tuple = ()):
    """Detections (every one, frame = frame set) and image sizes per camera from ``--images DIR``.

    Returns
    -------
    detections, sizes, flipped, notes
        ``flipped``: cameras whose board was found only in the flipped image (detections made
        on it; :func:`calib.rig.resolve_flipped` decides why); ``notes``: one line per finding.
    """
    from calib.intrinsics import CalibrationError
    from calib.timestamps import read_timestamps

    srcs = _sources(root)
    names = list(srcs)
    mirror_of = parse_mirror(list(mirror), names)
    notes: list[str] = []
    sets = None
    if timestamps is not None:
        sets, tw = read_timestamps(timestamps, names)
        notes += tw
    detections, sizes, flipped, problems, counts = {}, {}, [], [], {}
    for name, src in srcs.items():
        dets, size, n, flip, msg = _detect_camera(name, src, board, step=step, mirror=mirror_of[name],
                                                  frame_set=None if sets is None else sets[name], progress=progress)
        if msg:
            notes.append(msg)
            if not flip and not dets:
                problems.append(msg)
        if flip:
            flipped.append(name)
        detections[name], sizes[name], counts[name] = dets, size, n * step
        print(f"  {name}: board found in {len(dets)}/{n} frames{' (flipped)' if flip else ''}")
    notes += _length_notes(counts, sets)
    if problems:
        for line in notes:
            print(f"  note: {line}")
        raise CalibrationError("; ".join(problems), cameras=[p.split(":")[0].removeprefix("camera ") for p in problems])
    return detections, sizes, flipped, notes


def detect_take(path: Path, board, *, step: int = 1, min_change: float = 0.02, progress: bool = True,
                mirror: list[str] | tuple = ()):
    """Detections (every one) and image sizes per camera from a take (through ``stage.store.TakeReader``).

    Returns
    -------
    detections, sizes, cameras
        ``detections`` of a camera whose board is found only in the flipped image are made on the
        flipped images; :func:`detect_take_flipped` returns which.
    """
    dets, sizes, cams, _, _ = detect_take_flipped(path, board, step=step, progress=progress, mirror=mirror)
    return dets, sizes, cams


def detect_take_flipped(path: Path, board, *, step: int = 1, progress: bool = True, mirror: list[str] | tuple = ()):
    """:func:`detect_take`, also returning the flipped cameras and the notes (:func:`calib.take_detect.detect_take`)."""
    from tqdm import tqdm

    from calib.intrinsics import CalibrationError
    from calib.take_detect import detect_take as detect_in_take

    bar = tqdm(desc="detect", unit="set", disable=not progress, dynamic_ncols=True, leave=False)

    sets = [0]

    def on_set(done, total):
        bar.total, sets[0] = total, total
        bar.update(1)

    try:
        detections, sizes, cams, flipped, notes = detect_in_take(path, board, step=step, mirror=mirror, on_set=on_set)
    except CalibrationError as exc:
        for line in getattr(exc, "notes", ()):
            print(f"  note: {line}")
        raise
    finally:
        bar.close()
    for name in cams:
        print(f"  {name}: board found in {len(detections[name])}/{sets[0]} frame sets{' (flipped)' if name in flipped else ''}")
    return detections, sizes, cams, flipped, notes


def _detect(args: argparse.Namespace, board, quiet: bool):
    flipped: list[str] = []
    if args.take is not None:
        if not args.take.is_file():
            raise FileNotFoundError(f"take not found: {args.take}")
        detections, sizes, cams, flipped, notes = detect_take_flipped(args.take, board, step=args.step,
                                                                      progress=not quiet, mirror=args.mirror)
        for line in dict.fromkeys(notes):
            print(f"  note: {line}")
    else:
        detections, sizes, flipped, notes = detect_images(
            args.images, board, step=args.step, progress=not quiet, timestamps=args.timestamps, mirror=args.mirror)
        cams = list(sizes)
        for line in dict.fromkeys(notes):
            print(f"  note: {line}")
    return detections, sizes, cams, flipped


def _check_args(args: argparse.Namespace) -> None:
    if (args.take is None) == (args.images is None):
        raise ValueError("give either a take (TAKE.h5) or --images DIR, not both / neither")
    if args.take is None and args.out is None:
        raise ValueError("--out CALIB.toml is required with --images")
    if args.step < 1:
        raise ValueError("--step must be >= 1")
    if args.out is not None and not args.out.parent.exists():
        raise FileNotFoundError(f"--out: folder {args.out.parent} does not exist")
    if args.holdout < 0 or args.holdout == 1:
        raise ValueError("--holdout must be 0 (none) or >= 2")
    if args.timestamps is not None and args.take is not None:
        raise ValueError("--timestamps applies to --images DIR (a take is synchronised already)")


def _write(args: argparse.Namespace, result, detections) -> None:
    """Everything computed: now write (nothing is written when anything before fails)."""
    from calib.fileio import strict_json
    from calib.formats import write_calibration

    calib = result.calibration
    if args.coverage is not None:
        import cv2

        from calib.intrinsics import coverage_image

        args.coverage.mkdir(parents=True, exist_ok=True)
        for name, r in result.intrinsics.items():
            img = coverage_image(detections[name], r.size, rejected=list(r.rejected), title=name)
            cv2.imwrite(str(args.coverage / f"coverage_{name}.png"), img)
        print(f"coverage pictures in {args.coverage}")
    if args.report is not None:
        args.report.write_text(strict_json(result.to_dict()))  # a camera without held-out views: null
    if args.out is not None:
        write_calibration(calib, args.out)
        print(f"wrote {args.out}")
    if args.take is not None:
        from stage.store import attach_calibration

        attach_calibration(args.take, calib)
        print(f"stored the calibration in {args.take}")


class _Once(logging.Filter):
    """Let each distinct log message through once (the held-out folds repeat every calibration step)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg in self.seen:
            return False
        self.seen.add(msg)
        return True


def run(args: argparse.Namespace) -> int:
    once = _Once()
    handlers = logging.getLogger().handlers
    for h in handlers:
        h.addFilter(once)
    try:
        return _run(args)
    finally:
        for h in handlers:
            h.removeFilter(once)


def _run(args: argparse.Namespace) -> int:
    from calib.boards import load_board
    from calib.rig import calibrate_rig, group_warnings

    _check_args(args)
    quiet = bool(getattr(args, "quiet", False))
    board = load_board(args.board)
    if not quiet:
        print(f"board: {board.to_dict()}")
    detections, sizes, cams, flipped = _detect(args, board, quiet or args.no_progress)
    mode = "fixed" if args.no_intrinsics_refinement else args.intrinsics
    result = calibrate_rig(
        detections, sizes, board, cameras=cams, world=args.world, world_frame=args.world_frame,
        intrinsics=mode, fix_k3=args.fix_k3, min_change=args.min_change, holdout_folds=args.holdout,
        flipped=flipped, distortion=args.distortion,
    )
    for line in result.evaluation.get("flipped", ()):
        print(f"  note: {line}")
    if quiet:
        print(result.verdict())
        print(result.summary())
        for w in group_warnings(result.warnings):
            print(f"  warning: {w}")
    else:
        report = result.report()
        print(report)
        shown = [w for w in group_warnings(result.warnings) if f"warning: {w}" not in report]
        if shown:  # every warning of the calibration, also those of the per-camera and bundle solves
            print(f"warnings ({len(shown)}):")
            for w in shown:
                print(f"  warning: {w}")
    _write(args, result, result.evaluation.get("detections", detections))
    return 0
