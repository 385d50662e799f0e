"""``stage export``: a processed take as a rigged, animated glTF model (GLB)."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 62

FORMATS = ("glb", "spine-glb", "bvh")
SEGMENTS = 6  # bones per limb of the glb formats
DEFAULT_NAMES = {"glb": "spine_rig.glb", "spine-glb": "spine.glb", "bvh": "rig.bvh"}  # the file each writes in DIR
#: the options of the formats that use them: any other format refuses them (it would ignore them)
FORMAT_OPTIONS = {"reference": ("glb", "spine-glb"), "segments": ("glb", "spine-glb"), "no_spine_tubes": ("glb",)}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a processed take as a rigged, animated GLB (mesh + skeleton + skinning weights)",
        description="Rig the reference frame's mesh to the take's spine and write a binary glTF 2.0 file: "
        "the surface, a skin whose joints lie along the spine's limbs, bone-heat skinning weights (at most 4 "
        "per vertex) and an animation with one key per frame that plays the take back. "
        "Format 'spine-glb' writes the animated spine alone. Units are converted to metres (glTF). "
        "Format 'bvh' writes the armature of `stage armature` (DIR/rig/rig.json) as BVH motion capture: "
        "its joints, rest offsets and local rotations per frame, in the rig's units.",
    )
    p.add_argument("results", type=Path, metavar="DIR",
                   help="results directory (spine.json, meshes/frame_NNNNNN.ply; for bvh its rig/rig.json, or the rig "
                   "directory itself)")
    p.add_argument("--format", choices=FORMATS, default="glb",
                   help="glb: rigged mesh (default); spine-glb: spine only; bvh: the armature of `stage armature`")
    p.add_argument("--out", type=Path, metavar="FILE", help="output file (default DIR/spine_rig.glb, DIR/spine.glb or DIR/rig.bvh)")
    p.add_argument("--reference", type=int, metavar="FRAME",
                   help="take frame number of the rest pose (default: the spine's reference; glb, spine-glb)")
    p.add_argument("--segments", type=int, metavar="N", help="bones per limb (default 6; glb, spine-glb)")
    p.add_argument("--no-spine-tubes", action="store_true", help="do not add the spine tubes to the rigged mesh (glb)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.gltf_export import NoSpineError, export_rig, spine_to_glb

    d = Path(args.results)
    _check_format_options(args)
    if args.out is not None and Path(args.out).is_dir():
        from stage.cli import UserError

        raise UserError(f"--out {args.out} is a directory: give the file to write (e.g. "
                        f"{Path(args.out) / DEFAULT_NAMES[args.format]})")
    if args.segments is None:
        args.segments = SEGMENTS
    if args.segments < 1:
        raise ValueError(f"--segments must be >= 1, got {args.segments}")
    if args.format == "bvh":
        path = _export_bvh(d, args.out)
    elif args.format == "glb":
        path = export_rig(
            d, out=args.out, reference=args.reference, segments=args.segments, include_spine=not args.no_spine_tubes
        )
    else:
        from pipeline.spine_format import read_spine

        if not (d / "spine.json").is_file():
            raise NoSpineError(f"{d} has no spine.json yet: run the spine stage (`stage process`) before exporting")
        spine = read_spine(d / "spine.json")
        ref = None
        if args.reference is not None:
            fi = [int(x) for x in spine.frame_indices]
            if args.reference not in fi:
                raise ValueError(f"--reference must be a frame number of the take, got {args.reference}")
            ref = fi.index(args.reference)
        from pipeline.results import atomic_write_bytes  # as glb and bvh: never a half-written file

        path = atomic_write_bytes(Path(args.out) if args.out else d / "spine.glb",
                                  spine_to_glb(spine, segments=args.segments, reference=ref))
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def _check_format_options(args: argparse.Namespace) -> None:
    """An option the chosen format does not use is refused in one line naming it (it would be ignored: the BVH's
    rest pose, say, is the armature's, chosen by ``stage armature --reference``)."""
    from stage.cli import UserError

    given = [f"--{name.replace('_', '-')}" for name, formats in FORMAT_OPTIONS.items()  # given: not None, not False
             if getattr(args, name) is not None and getattr(args, name) is not False and args.format not in formats]
    if given:
        why = " (its rest pose and bones are the armature's: stage armature --reference POS)" if args.format == "bvh" else ""
        raise UserError(f"{', '.join(given)}: not an option of --format {args.format}{why}")


def _export_bvh(d: Path, out) -> Path:
    """``DIR/rig/rig.json`` (or ``DIR/rig.json``, a rig directory) as BVH; default ``DIR/rig.bvh``."""
    import json

    from pipeline.armature import bvh_from_rig_json
    from pipeline.results import atomic_write_bytes
    from stage.cli import UserError

    doc_path = next((p for p in (d / "rig" / "rig.json", d / "rig.json") if p.is_file()), None)
    if doc_path is None:
        if not d.is_dir():
            raise FileNotFoundError(f"results directory not found: {d}")
        raise UserError(f"{d} has no rig/rig.json: build the armature first (stage armature {d})")
    try:
        doc = json.loads(doc_path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{doc_path}: unreadable ({exc})") from None
    try:
        text = bvh_from_rig_json(doc)
    except ValueError as exc:
        raise UserError(f"{doc_path}: {exc}") from None
    path = Path(out) if out else d / "rig.bvh"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, text.encode())
    return path
