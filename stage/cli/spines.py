"""``stage spines``: the spine of a mesh sequence (Brostow et al. 2004) -> ``DIR/spine.json``."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 60


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "spines",
        help="compute the spine of a mesh sequence (one OBJ/PLY/OFF per frame)",
        description="Per-frame branching skeletons (in parallel) and one temporally consistent spine "
        "for the whole sequence, written as DIR/spine.json (format capture-stage/spine@1, "
        "see docs/spine-format.md). Files are taken in name order; units as given.",
    )
    p.add_argument("--meshes", required=True, help="glob such as 'DIR/*.obj' (quote it), or a directory")
    p.add_argument("--out", required=True, type=Path, help="output directory (spine.json is written there)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the sequence (default 30)")
    p.add_argument("--units", default=None,
                   help="units of the mesh coordinates: m, cm, mm or um (default mm; a warning when the meshes "
                   "span under 10 or over 100 000 units)")
    p.add_argument("--workers", type=int, default=2, help="worker processes for the per-frame work (default 2)")
    p.add_argument("--bins", type=int, default=None, help="level-set bins per skeleton (default 100)")
    p.add_argument(
        "--min-protrusion",
        type=float,
        default=None,
        help="a tip must protrude by this fraction of sqrt(surface area) (default 0.1)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Also the implementation of ``stage process --meshes`` (which has no --bins/--min-protrusion)."""
    from concurrent.futures import ProcessPoolExecutor
    from contextlib import nullcontext

    from pipeline.frame_skeleton import SpineParams
    from pipeline.meshio import load_mesh, mesh_paths
    from pipeline.spine_format import write_spine
    from pipeline.spine_meshes import spine_from_meshes
    from stage.cli._args import assumed_units

    if args.workers < 0:
        raise ValueError(f"--workers must be >= 0, got {args.workers}")
    paths = mesh_paths(args.meshes)
    units = args.units or assumed_units(load_mesh(paths[0], largest=False)[0])
    given = {"n_bins": getattr(args, "bins", None), "min_protrusion": getattr(args, "min_protrusion", None)}
    params = SpineParams(**{k: v for k, v in given.items() if v is not None})
    print(f"{len(paths)} meshes from {paths[0].parent}")
    pool = ProcessPoolExecutor(max_workers=args.workers) if args.workers > 1 and len(paths) > 1 else nullcontext()
    with pool as executor:
        spine = spine_from_meshes(paths, fps=args.fps, units=units, executor=executor,
                                  progress=not getattr(args, "no_progress", False), params=params)
    out = write_spine(Path(args.out) / "spine.json", spine)
    counts = spine.meta["tip_counts"]
    seen = (~__import__("numpy").isnan(spine.tips[..., 0])).mean()
    print(
        f"K = {spine.K} limbs ({', '.join(spine.limb_ids)}), {len(spine.junction_ids)} junctions; "
        f"tips per frame {min(counts)}..{max(counts)}; limbs seen in {100 * seen:.1f} % of frame-limbs"
    )
    print(f"wrote {out}")
    return 0

