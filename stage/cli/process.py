"""``stage process``: keying, reconstruction and spines for a take (or spines for a mesh sequence)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

ORDER = 50
log = logging.getLogger("pipeline.process")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "process",
        help="run keying, reconstruction and spines on a take (writes DIR/spine.json)",
        description="Process a take: key silhouettes (if the take has none), carve a visual hull and extract a "
        "surface per frame set, grow per-frame skeletons and correspond their tips over time into one spine "
        "(Brostow et al. 2004). Results go to DIR, beside the take; re-running on the same DIR resumes. "
        "With --meshes, run the spine stage alone on a mesh sequence from another system.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("take", nargs="?", type=Path, help="take file (.h5) with a calibration")
    src.add_argument("--meshes", metavar="GLOB", help="mesh sequence, one file per frame, e.g. 'DIR/*.obj' (OBJ, PLY, OFF)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="results directory")
    p.add_argument(
        "--until", choices=("key", "surface", "spine"), default="spine", help="last step to run (default: spine)"
    )
    p.add_argument("--key-mode", choices=("chroma", "luma", "plate"), default=None,
                   help="keying mode (default: the rig's; footage without a rig file: chroma when a backdrop colour "
                   "covers a large share of the views, else a plate from the take; process.json says which and why)")
    p.add_argument("--key-layer", action="append", choices=("volume", "graphcut"), default=None, dest="key_layers",
                   help="keying layer, repeatable: volume (pixels whose rays miss the volume are background), graphcut "
                   "(colour models seeded by a first hull cut each camera's silhouettes: walls, lights, people "
                   "outside the volume drop out); default: the rig's, else chosen with the mode")
    p.add_argument("--plate", type=Path, default=None, metavar="EMPTY_TAKE",
                   help="an empty take of the same cameras: its per-pixel background and noise become the plate "
                   "(stored in the take; the keying mode becomes plate unless --key-mode says otherwise)")
    p.add_argument("--rekey", action="store_true", help="key again even if the take holds masks")
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="voxels along the subject's longest side (default: from the rig, a voxel of 2 pixels at the "
        "subject, within a budget of 8M voxels; process.json records the choice)",
    )
    p.add_argument(
        "--volume",
        type=float,
        nargs=6,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="where to look for the subject (default: the rig's capture volume, else derived from the cameras)",
    )
    p.add_argument("--tolerance", type=int, default=0, help="cameras allowed to disagree before a voxel is carved")
    p.add_argument(
        "--margin",
        type=int,
        default=None,
        help="pixels every silhouette grows by before carving (default 1: a conservative hull that keeps thin "
        "parts under sub-pixel calibration error; 0 keeps 2-px gaps between limbs open when the calibration is exact)",
    )
    p.add_argument(
        "--support-plane",
        type=float,
        nargs=4,
        metavar=("A", "B", "C", "D"),
        help="the plane the subject stands on: only a*x + b*y + c*z + d >= 0 is kept (world units); "
        "removes the cone under the base that cameras all looking down cannot carve",
    )
    p.add_argument(
        "--photo-refine",
        action="store_true",
        help="move each hull surface's vertices to where the cameras' colours agree (carves concavities two "
        "cameras see; about 1 s a frame more; see docs/reconstruction.md)",
    )
    p.add_argument("--skip-damaged", action="store_true",
                   help="process a take with damaged frames (`stage verify`) without the frame sets that hold them, "
                   "listed in the log, process.json and report.json (default: stop and name the damage)")
    p.add_argument("--workers", type=int, default=2, help="worker processes for per-frame work (default 2; 0 = in process)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of a mesh sequence (--meshes)")
    p.add_argument("--units", default=None, help="units of a mesh sequence (--meshes), written as given (default mm; "
                   "a warning when the meshes span under 10 or over 100 000 units)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _run_meshes(args: argparse.Namespace) -> int:
    from stage.cli import spines

    return spines.run(args)  # one implementation: `stage spines` (which also takes --bins, --min-protrusion)


def run(args: argparse.Namespace) -> int:
    if args.workers < 0:
        raise ValueError("--workers must be >= 0")
    if args.meshes:
        args.out.mkdir(parents=True, exist_ok=True)
        return _run_meshes(args)
    return process_with_progress(args.take, args.out, args=args)


def process_with_progress(take: Path, out: Path, *, args: argparse.Namespace) -> int:
    from pipeline.process import STEPS, ProcessParams, process_take
    from stage.cli._pool import worker_pool
    from stage.cli._progress import StepBars

    steps = STEPS[: STEPS.index(args.until) + 1]
    kw = {"key_mode": args.key_mode, "rekey": args.rekey, "tolerance": args.tolerance}
    if getattr(args, "key_layers", None):
        kw["key_layers"] = tuple(dict.fromkeys(args.key_layers))
    if getattr(args, "plate", None) is not None:
        from stage.keying.take import store_plates

        noise = store_plates(take, args.plate)
        print(f"plates from {args.plate} stored in {take} (noise {', '.join(f'{c}: {v:.1f}' for c, v in noise.items())})")
        kw["key_mode"] = args.key_mode or "plate"
        kw["rekey"] = True
    if args.resolution is not None:
        kw["resolution"] = args.resolution
    if args.volume is not None:
        kw["volume"] = tuple(args.volume)
    if args.margin is not None:
        kw["silhouette_margin"] = args.margin
    if args.photo_refine:
        kw["photo_refine"] = True
    if getattr(args, "skip_damaged", False):
        kw["skip_damaged"] = True
    if args.support_plane is not None:
        from pipeline.volume import check_plane

        kw["support_plane"] = tuple(check_plane(args.support_plane, "--support-plane").tolist())
    try:
        params = ProcessParams(**kw)
    except ValueError as exc:  # pydantic's ValidationError: one line per problem, the option named
        errors = exc.errors() if hasattr(exc, "errors") else [{"loc": (), "msg": str(exc)}]
        raise ValueError("; ".join(
            f"--{'.'.join(map(str, e['loc'])).replace('_', '-')}: {e['msg'].removeprefix('Value error, ')}" for e in errors
        )) from None
    executor = worker_pool(args.workers)
    try:
        with StepBars(disable=args.no_progress) as progress:
            result = process_take(take, out, steps=steps, params=params, executor=executor, progress=progress)
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    _print_result(result, take, out)
    return 0


def _print_result(result, take: Path, out: Path) -> None:
    rep = result.report
    print(f"processed {result.frames} frame sets of {take} ({', '.join(result.steps)}) in {rep['total_seconds']:.1f} s")
    if result.empty_frames:
        print(f"  empty frames (no subject): {result.empty_frames}")
    if rep.get("damaged_sets"):
        print(f"  skipped frame sets (damaged frames): {rep['damaged_sets']}")
    if result.spine_path is not None:
        spine = json.loads(Path(result.spine_path).read_text())
        print(f"  spine: {len(spine['graph']['limbs'])} limbs -> {result.spine_path}")
    box = (rep.get("grid") or {}).get("box")
    if box:
        print(f"  subject box: {' x '.join(f'{x:.4g}' for x in box['size'])} (voxel {rep['grid']['voxel']:.3g}; "
              f"process.json says why)")
    cons = rep.get("consistency") or {}
    if cons.get("median"):
        print("  silhouette consistency (median IoU of mask and projected surface): "
              + ", ".join(f"{c} {m:.2f}" for c, m in cons["median"].items() if m is not None))
    print(f"  meshes: {out / 'meshes'}/  report: {out / 'report.json'}")
