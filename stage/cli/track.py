"""``stage track``: follow one template mesh through a take -> ``tracked/NNNNNN.ply``.

Multi-view (``stage track RESULTS_DIR``), the take is then tracked again with one armature round by default
(``--armature-rounds 1``, :func:`pipeline.track_armature.track_with_armature`); ``--armature-rounds 0`` is the
tracking alone.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

ORDER = 56


#: ``stage track --help``'s description (its two forms in columns)
DESCRIPTION = (
    "Template tracking (Tzionas & Gall 2016, section 3). Two forms:\n"
    "  stage track RESULTS_DIR [--template MESH]      multi-view, after `stage process`: the data are\n"
    "                                                 RESULTS_DIR/meshes/frame_*.ply; the template is the\n"
    "                                                 surface of the spine's reference frame, tracked\n"
    "                                                 forwards and backwards from it (without spine.json:\n"
    "                                                 the first frame's), unless given\n"
    "  stage track TAKE.h5 --template MESH --out DIR  one RGB-D camera: the template (mm, roughly placed)\n"
    "                                                 is placed by rigid ICP on the first frame with depth\n"
    "Writes tracked/NNNNNN.ply in the template's vertex order and tracked/track.json; resumes where a killed\n"
    "run stopped. Frames without depth are skipped and listed.\n"
    "Multi-view, the take is then tracked again with an armature built from that tracking as the articulated\n"
    "prior (one round; --armature-rounds 0: the tracking alone). Limbs that move fast (3 voxels a frame or\n"
    "more): docs/tracking.md, 'Fast motion', has an opt-in, slower chain with an armature of the template's limbs:\n"
    "  stage track RESULTS_DIR --labels --colour --armature-rounds 1 --armature-parts limbs"
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="deform a template mesh frame by frame onto a take (Tzionas & Gall 2016)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("source", type=Path, help="a results directory of `stage process`, or a take file (.h5)")
    p.add_argument("--template", type=Path, default=None,
                   help="template mesh (.ply/.obj/.off, mm); required for a take (default for RESULTS_DIR: the surface "
                   "of the spine's reference frame)")
    p.add_argument("--out", type=Path, default=None, help="output directory for a take (default: beside the take, TAKE_results)")
    p.add_argument("--camera", default=None, help="depth camera of the take (default: the first with depth)")
    p.add_argument("--remove-skin", action="store_true", help="drop skin-coloured pixels (hands) before tracking")
    p.add_argument("--spine-init", action="store_true",
                   help="multi-view: start every patch of every frame from the spine's skinned motion of the template "
                   "(default: only the patches the constant-velocity prediction leaves out of the gate's reach, where the "
                   "surface explains the skinned start better)")
    p.add_argument("--prediction-only", action="store_true",
                   help="multi-view with a spine: start every patch from the constant-velocity prediction, never from the "
                   "spine's skinned step (the default chooses per patch and frame, see docs/tracking.md)")
    p.add_argument("--no-predict", action="store_true",
                   help="start every frame from the previous one, not from the constant-velocity prediction of the two before")
    p.add_argument("--contour", action="store_true", help="add the contour term (depth edges; single RGB-D only)")
    p.add_argument("--colour", action="store_true",
                   help="multi-view: also follow the template's vertices in every camera's colour images (the take named "
                   "by RESULTS_DIR/process.json; feature tracks across each viewing ray pin a slide along the surface); "
                   "off by default there, see docs/tracking.md")
    p.add_argument("--shape-memory", action="store_true",
                   help="multi-view: keep the previous frame's shape in the rigid prior (as one RGB-D camera does); it "
                   "holds the volume and helps where the surfaces are close to the truth; off by default, see docs/tracking.md")
    p.add_argument("--carve", type=int, default=0, metavar="ROUNDS",
                   help="multi-view: after tracking, carve every frame's surface with the silhouettes of the frames around it, "
                   "carried by the tracked motion (shape from silhouette across time, RESULTS_DIR/carved/), and track again "
                   "on those; ROUNDS times (default 0: the surfaces of `stage process`). Best with --shape-memory --colour, "
                   "see docs/tracking.md")
    p.add_argument("--carve-margin", type=float, default=None, metavar="PX",
                   help="with --carve: grow every silhouette by PX pixels (default, per camera: twice the reprojection error "
                   "its calibration records, at most the silhouette margin `stage process` carved the hulls with, "
                   "RESULTS_DIR/process.json; that margin where the calibration records none)")
    p.add_argument("--armature-rounds", "--rig-rounds", dest="rig_rounds", type=_rig_rounds, default=None, metavar="ROUNDS",
                   help="multi-view: after tracking, build an armature from the tracked motion (as `stage armature` does, "
                   "rest frame the template's, the finest segments) and track every frame again with it as the articulated "
                   "prior (its skinned pose on each frame's surface as the start, every vertex drawn to it); build it again "
                   "from that tracking and repeat while the armature explains the surfaces better, at most ROUNDS times, "
                   "keeping the best round; 'auto' = at most 4 (default 1; 0: off, the tracking alone). With --colour "
                   "the colour tracks pull the armature's pose too (they see a round limb's turn about its own axis, "
                   "which the surfaces cannot). Only as good as the armature's segments, see docs/tracking.md. "
                   "--rig-rounds: the old name, kept for one release")
    p.add_argument("--spine-armature", action="store_true",
                   help="multi-view, with armature rounds (one by default; not with --armature-rounds 0): the first round's "
                   "armature is the take's spine (RESULTS_DIR/"
                   "spine.json, built from every frame's visual hull, so it does not inherit the tracking's drift; two "
                   "bones a limb), then the ROUNDS rounds build it from the tracking; better on some fast bipeds and "
                   "quadrupeds, worse on others, on the fast starfish and the slow quadruped, see docs/tracking.md")
    p.add_argument("--armature-parts", choices=("motion", "limbs"), default="motion",
                   help="multi-view, with --labels and armature rounds (one by default; not with --armature-rounds 0): where "
                   "every round's armature gets its parts; "
                   "'motion' (default): the motion segmentation of the tracking, as `stage armature`; 'limbs': the labels' "
                   "body one part and every limb cut along its spine axis where its tracked motion bends, each vertex rigid "
                   "with its part. Better on some fast bipeds, mixed elsewhere, see docs/tracking.md")
    p.add_argument("--labels", action="store_true",
                   help="multi-view: cut the template's rigid patches at its limbs: every template vertex on a limb of the "
                   "take's spine or on the body (from the spine and the template's own sections), the body one patch and "
                   "every limb on its own grid; the armature rounds keep a segment on one limb too. Needs RESULTS_DIR/"
                   "spine.json (without one, one line says so); the labels used are written to tracked/labels.npy. Off by "
                   "default, see docs/tracking.md")
    p.add_argument("--no-colour", action="store_true",
                   help="single RGB-D: use depth alone, not the colour images' feature tracks (which see a round part's twist)")
    p.add_argument("--gamma", type=float, default=None,
                   help="data weight (default: 0.05 when the template's mean triangle area is above 10 mm^2, else 0.005; "
                   "the paper's finding)")
    p.add_argument("--gate", type=float, default=None, help="pair distance gate, mm (default 10 mm scaled with the template's size)")
    p.add_argument("--workers", type=int, default=None,
                   help="multi-view: with 2 or more, one half of the take from the reference frame is tracked in a "
                   "second process while this one tracks the other half, in the tracking and in every armature round "
                   "(default 2; 0 or 1 = in order, in process)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.armature import counted
    from pipeline.track_rgbd import TrackingError, track_rgbd_take
    from stage.cli import UserError
    from stage.cli._progress import StepBars

    src = Path(args.source)
    _check_counts(args)
    if src.exists():
        _check_mode(args, take=src.is_file())
    quiet = bool(getattr(args, "quiet", False)) or args.no_progress
    try:
        with StepBars(disable=quiet) as bars:
            if src.is_dir():
                rep = _track_results(args, src, bars)
                out = src
            elif src.is_file():
                if args.template is None:
                    raise UserError("a take needs --template MESH (the object's scan, in mm)")
                out = args.out if args.out is not None else src.with_name(src.stem + "_results")
                rep = track_rgbd_take(src, args.template, out, camera=args.camera, remove_skin=args.remove_skin,
                                      contour=args.contour, predict=not args.no_predict, colour=not args.no_colour,
                                      progress=bars, gamma=args.gamma, gate=args.gate)
            else:
                raise FileNotFoundError(f"{src}: no such results directory or take file")
    except TrackingError as exc:
        raise UserError(str(exc)) from None
    n = len(rep["frames"])
    vols = [f["volume_ratio"] for f in rep["frames"].values() if f.get("volume_ratio") is not None]
    print(f"tracked {rep['vertices']} vertices through {counted(n, 'frame')} (gamma {rep['gamma']}, gate {rep['gate_mm']:.1f} mm, "
          f"solver {rep['solver']})")
    if vols:
        print(f"volume / template volume: {min(vols):.3f} .. {max(vols):.3f}")
    if "colour_tracks" in rep:
        print(f"colour tracks: {'on' if rep['colour_tracks'] else 'off'}")
    if rep.get("surfaces") == "carved":
        print(f"surfaces: carved across time ({Path(out) / 'carved'})")
    if rep.get("mode") == "multi-view" and rep.get("prior") == "previous":
        print("shape memory: on (the previous frame's shape)")
    if rep.get("rig_rounds"):
        prior = rep["rig_prior"]
        rounds = prior["rounds"]
        fits = ", ".join("-" if r.get("residual_mm") is None else f"{r['residual_mm']:.2f}" for r in rounds)
        segments = ", ".join(f"the spine's {r['segments']} parts" if r.get("armature") == "spine" else
                             f"{r['segments']} from the limbs" if r.get("armature") == "limbs" else str(r["segments"])
                             for r in rounds)
        print(f"tracked again with an armature as the articulated prior: {counted(len(rounds), 'round')} (armature "
              f"segments: {segments}; the armature on the surfaces: {fits} mm), "
              f"kept round {prior.get('kept_round', len(rounds))}")
    if rep["skipped"]:
        print(f"skipped {counted(len(rep['skipped']), 'frame')} without data: {', '.join(map(str, rep['skipped']))}")
    print(f"wrote {Path(out) / 'tracked'}")
    return 0


def _rig_rounds(text: str):
    """``--armature-rounds``: a count >= 0 or ``auto``."""
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be a count >= 0 or 'auto', got {text!r}")
    return n


def armature_rounds(args: argparse.Namespace):
    """``--armature-rounds`` of a results directory: as given, else the track step's default
    (:class:`pipeline.process.TrackParams`: one round)."""
    if args.rig_rounds is not None:
        return args.rig_rounds
    from pipeline.process.params import TrackParams

    return TrackParams.model_fields["armature_rounds"].default


#: the options :func:`pipeline.track.check_track_options` checks, as its keywords (the flags: ``--carve-margin``...)
_TRACK_RULES = ("carve", "carve_margin", "armature_rounds", "spine_armature", "armature_parts", "labels")


def _check_counts(args: argparse.Namespace) -> None:
    """Counts and margins out of range are one clear line."""
    from stage.cli import UserError

    if args.workers is not None and args.workers < 0:
        raise UserError("--workers must be >= 0")
    if args.carve < 0:
        raise UserError("--carve must be >= 0 (rounds)")
    if args.carve_margin is not None and not args.carve_margin >= 0:
        raise UserError("--carve-margin must be >= 0 (pixels)")
    from pipeline.track import check_track_options

    try:
        check_track_options(carve=args.carve, carve_margin=args.carve_margin, armature_rounds=armature_rounds(args),
                            spine_armature=args.spine_armature, armature_parts=args.armature_parts, labels=args.labels,
                            names={k: f"--{k.replace('_', '-')}" for k in _TRACK_RULES})
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _track_results(args: argparse.Namespace, src: Path, bars) -> dict:
    """Multi-view tracking; the backward half in a worker process with ``--workers`` >= 2."""
    from stage.cli._pool import worker_pool

    if args.spine_init and args.prediction_only:
        from stage.cli import UserError

        raise UserError("--spine-init and --prediction-only exclude each other (the skinned step for every patch, or never)")
    kw = dict(template=args.template, progress=bars, gamma=args.gamma, gate=args.gate, spine_init=args.spine_init,
              choose=not args.prediction_only, predict=not args.no_predict, colour=args.colour,
              shape_memory=args.shape_memory, labels="spine" if args.labels else None)
    from pipeline.run import once_per_run

    # one run: what the first tracking, each carve round and each armature round say of the surfaces, said once
    with worker_pool(1) if (2 if args.workers is None else args.workers) >= 2 else contextlib.nullcontext() as ex, \
            once_per_run():
        # one task at a time: one half of the take, of the tracking and of every armature round
        rep = _rounds(src, args.carve, margin=args.carve_margin, executor=ex, **kw)
        if armature_rounds(args):
            from pipeline.track_armature import track_with_armature

            rep = track_with_armature(src, rounds=armature_rounds(args), colour=args.colour, spine=args.spine_armature,
                                      progress=bars, executor=ex, labels="spine" if args.labels else None,
                                      parts=args.armature_parts)
    return rep


def _rounds(src: Path, rounds: int, *, margin=None, **kw) -> dict:
    """:func:`pipeline.carve.track_with_carving`; a carving that cannot run is one clear line."""
    from pipeline.carve import CarveError, track_with_carving
    from stage.cli import UserError

    try:
        return track_with_carving(src, rounds, margin=margin, **kw)
    except CarveError as exc:
        raise UserError(f"--carve: {exc}") from None


#: Options of one mode only: (flag, attribute, its default), for a take file and for a results directory.
_TAKE_ONLY = (("--out", "out", None), ("--camera", "camera", None), ("--remove-skin", "remove_skin", False),
              ("--contour", "contour", False), ("--no-colour", "no_colour", False))
_RESULTS_ONLY = (("--carve", "carve", 0), ("--armature-rounds", "rig_rounds", None), ("--carve-margin", "carve_margin", None),
                 ("--spine-armature", "spine_armature", False), ("--colour", "colour", False),
                 ("--shape-memory", "shape_memory", False), ("--spine-init", "spine_init", False),
                 ("--prediction-only", "prediction_only", False), ("--workers", "workers", None), ("--labels", "labels", False),
                 ("--armature-parts", "armature_parts", "motion"))


def _check_mode(args: argparse.Namespace, *, take: bool) -> None:
    """A flag of the other mode is an error (it would be silently ignored)."""
    from stage.cli import UserError

    for flag, attr, default in (_RESULTS_ONLY if take else _TAKE_ONLY):
        if getattr(args, attr) != default:
            where = "a results directory (multi-view)" if take else "a take file (single RGB-D)"
            raise UserError(f"{flag} applies to {where} only")
