"""``stage armature``: an armature (the articulated model) from motion (Tzionas & Gall 2016, section 4).

``stage armature RESULTS_DIR`` builds the armature of a processed take from its tracked template
(``RESULTS_DIR/tracked/NNNNNN.ply``, one mesh per frame in the template's vertex order) and writes
``RESULTS_DIR/rig/`` (the folder's and files' names are the results format's, docs/armature-format.md);
``stage armature --meshes GLOB --out DIR`` does it for any mesh sequence with shared connectivity
(.ply/.obj/.off). ``stage rig`` is the old name of the command, kept as an alias for one release.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ORDER = 63
ONE_FRAME = "an armature is found from how the subject moves; it needs 2 frames or more"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "armature",
        aliases=["rig"],
        help="build an armature (the articulated model) from motion: segments, joints where the subject bends, skin, "
        "pose per frame (`stage rig`: the old name, kept for one release)",
        description="Segment a mesh sequence with shared connectivity into rigidly moving parts (spectral "
        "clustering of vertex trajectories), put a joint where two parts meet on the curve skeleton, skin the "
        "template with bone-heat weights and fit the articulated model to every frame by least squares. "
        "Writes rig.json (capture-stage/rig@1), segments.npy, posed/NNNNNN.ply, rig.glb and rig.bvh "
        "(docs/armature-format.md; the files keep their names: a results format). `stage rig` is the old name of this "
        "command, kept as an alias for one release. The per-frame surfaces of a processed take do not share connectivity: "
        "a results directory's armature is built from its tracked template (tracked/NNNNNN.ply); when there is none, "
        "the template is tracked through the take first (`stage track RESULTS_DIR` with its defaults: the tracking, "
        "then one armature round; and --labels with --parts limbs; to track otherwise, run `stage track` first).",
    )
    p.add_argument("results", type=Path, nargs="?", metavar="RESULTS_DIR",
                   help="results directory of `stage process` (writes RESULTS_DIR/rig/; tracks the template first "
                   "when there is no tracked/NNNNNN.ply)")
    p.add_argument("--meshes", metavar="GLOB", help="mesh sequence with shared connectivity (e.g. 'seq/*.obj')")
    p.add_argument("--out", type=Path, metavar="DIR", help="output directory (default RESULTS_DIR/rig; required with --meshes)")
    p.add_argument("--units", help="units of the meshes (default: the spine's, else mm)")
    p.add_argument("--fps", type=float, help="frame rate (default: the spine's, else 30)")
    p.add_argument("--lambda-thr", type=float, default=0.7, metavar="T",
                   help="eigenvalue threshold: 0.7 (default) for pronounced motion of reasonably sized parts, "
                   "0.98 for small parts with small motion (over-segments); for RESULTS_DIR, 0.98 is used (and "
                   "said) when the eigenvalues cross the threshold without a gap")
    p.add_argument("--samples", type=int, default=1000, metavar="N", help="sampled vertices for the segmentation (default 1000)")
    p.add_argument("--parts", choices=("motion", "limbs"), default="motion",
                   help="the rigid parts: 'motion' (default) the motion segmentation; 'limbs' for RESULTS_DIR "
                   "tracked with the template's limb/body labels (stage track --labels): the labels' body one part, "
                   "every limb cut along its spine axis (docs/armature-format.md, 'Segments along the limb axes'; "
                   "an untracked RESULTS_DIR is tracked with --labels first; without such labels one line says so "
                   "and the motion segmentation is used)")
    p.add_argument("--reference", type=int, metavar="POS",
                   help="position (0-based) of the rest frame (default: of 8 evenly spaced frames, the one whose curve "
                   "skeleton shows the most tips)")
    p.set_defaults(func=run)


def _spine_meta(results: Path) -> dict:
    sp = results / "spine.json"
    if not sp.is_file():
        return {}
    try:
        d = json.loads(sp.read_text())
        return {"units": d.get("units"), "fps": d.get("fps")}
    except (OSError, ValueError):
        return {}


def _track_first(d: Path, *, quiet: bool, no_progress: bool, labels: bool = False) -> list:
    """``stage track d`` with its defaults (the tracking, then one armature round; and ``--labels`` with ``labels``:
    the parts from the limbs need them), for a processed take without a tracked template, its progress bars shown as this command's are
    (``no_progress``); its tracked meshes."""
    from pipeline.armature_files import tracked_meshes
    from stage.cli import build_parser

    command = ["track", str(d), *(["--labels"] if labels else [])]
    print(f"{d} has no tracked template (tracked/NNNNNN.ply): tracking the template through the take first, "
          f"as `stage {' '.join(command)}` does (the tracking, then one armature round)")
    targs = build_parser().parse_args((["-q"] if quiet else []) + command)
    targs.no_progress = no_progress  # as stage.cli.main decided for this command (a terminal, --progress)
    targs.func(targs)
    return tracked_meshes(d)


#: the options of :func:`pipeline.armature.check_armature_options`, as this command names them
OPTION_NAMES = {"lambda_thr": "--lambda-thr", "n_samples": "--samples", "reference": "--reference"}


def _check_options(args: argparse.Namespace) -> None:
    """The options' values, in their names (``--reference``'s upper end once the frames are known)."""
    import math

    from pipeline.armature import check_armature_options

    check_armature_options(lambda_thr=args.lambda_thr, n_samples=args.samples, reference=args.reference,
                           names=OPTION_NAMES)
    if args.fps is not None and not (args.fps > 0 and math.isfinite(args.fps)):
        raise ValueError(f"--fps must be > 0, got {args.fps}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} is a file: give the directory to write the armature into")


def _check_reference(reference: int | None, n: int) -> None:
    """``--reference``'s upper end, for a sequence of ``n`` frames (the lower one: :func:`_check_options`)."""
    from pipeline.armature import check_armature_options

    check_armature_options(reference=reference, frames=n, names=OPTION_NAMES)


def run(args: argparse.Namespace) -> int:
    from pipeline.armature import armature_counts, build_armature
    from pipeline.armature_files import (
        NoTrackingError,
        limb_parts,
        load_sequence,
        spine_limbs,
        tracked_meshes,
        write_armature,
    )
    from pipeline.meshio import mesh_paths
    from pipeline.motion_segmentation import MIN_GAP
    from stage.cli import UserError
    from stage.cli._args import assumed_units
    from stage.cli._progress import StepBars

    if (args.results is None) == (args.meshes is None):
        raise UserError("give either RESULTS_DIR or --meshes GLOB (see stage armature --help)")
    if args.parts == "limbs" and args.meshes is not None:
        raise UserError("--parts limbs needs RESULTS_DIR (a take tracked with stage track --labels), not --meshes")
    _check_options(args)  # before any work: the tracking a results directory may need first takes minutes
    meta = {}
    if args.meshes is not None:
        if args.out is None:
            raise UserError("--meshes needs --out DIR")
        paths = mesh_paths(args.meshes)
        out = args.out
    else:
        d = Path(args.results)
        if not d.is_dir():
            raise FileNotFoundError(f"results directory not found: {d}")
        try:
            paths = tracked_meshes(d)
        except NoTrackingError as exc:
            surfaces = list((d / "meshes").glob("frame_*.ply"))
            if not surfaces:
                raise UserError(str(exc)) from None
            if len(surfaces) == 1:  # said before the tracking, which could not help
                raise UserError(f"{d} has one frame (meshes/{surfaces[0].name}): {ONE_FRAME}") from None
            _check_reference(args.reference, len(surfaces))  # the tracking follows these frames, none more
            paths = _track_first(d, quiet=args.quiet, no_progress=args.no_progress, labels=args.parts == "limbs")
        meta = _spine_meta(d)
        out = args.out or d / "rig"
    if len(paths) < 1:
        raise UserError("no meshes")
    if len(paths) == 1:
        raise UserError(f"{paths[0]} is the only frame: {ONE_FRAME}")
    _check_reference(args.reference, len(paths))
    vertices, faces, numbers = load_sequence(paths)
    limbs = None if args.meshes is not None else spine_limbs(d, vertices, faces, numbers)  # a take's spine, if any
    found = limb_parts(d, vertices, faces, numbers) if args.parts == "limbs" else None
    units = args.units or meta.get("units") or assumed_units(vertices[0])
    fps = args.fps or meta.get("fps") or 30.0
    with StepBars(disable=args.no_progress) as bars:
        rig = build_armature(
            vertices, faces, units=units, fps=float(fps), frame_indices=numbers, lambda_thr=args.lambda_thr,
            n_samples=args.samples, reference=args.reference, progress=bars,
            peel_parts=args.meshes is not None,  # a tracked template: its tracking noise is no part
            min_gap=None if args.meshes is not None else MIN_GAP,  # a tracked template: the eigengap rule
            limbs=limbs, parts=None if found is None else (found, "limbs"), whole_crossing_paths=True,
        )
        write_armature(rig, out, progress=bars)
    sk = rig.skeleton
    err = rig.fit.errors
    print(
        f"{armature_counts(rig.segmentation.n_segments, int(sk.articulation.sum()), sk.n_joints)}; "
        f"mean vertex error {err.mean():.4g} {units} ({100 * err.mean() / rig.size:.2f} % of size), "
        f"worst frame {err.max():.4g} {units}"
    )
    if rig.segmentation.n_segments == 1:
        print("nothing bends in this sequence: one segment, the armature moves rigidly")
    print(f"wrote {out}/rig.json, rig.glb, rig.bvh, segments.npy, posed/ ({rig.n_frames} frames)")
    return 0
