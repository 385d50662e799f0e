"""``stage report``: a self-contained HTML page about a processed take (works offline)."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 64


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="write an offline HTML report of a processed take (3-D spine view, tips, mesh quality, cameras)",
        description="Render DIR (the output of `stage process`) as one self-contained HTML page: an interactive "
        "3-D view of the rigged surface and the animated spine, the tip count over time (Brostow et al. 2004, "
        "Fig. 7), per-frame surface quality, the cameras and their calibration errors, and contact sheets of "
        "frames and masks (when the take is given or named in report.json). plotly.js is embedded: the page "
        "needs no network.",
    )
    p.add_argument("results", type=Path, metavar="DIR", help="results directory (spine.json, report.json, meshes/)")
    p.add_argument("--take", type=Path, metavar="TAKE.h5", help="the take (default: the one named in report.json)")
    p.add_argument("--out", type=Path, metavar="FILE", help="output file (default DIR/report.html)")
    p.add_argument("--max-frames", type=int, default=120, metavar="N", help="animation keys in the 3-D view")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.report import write_report

    path = write_report(args.results, take=args.take, out=args.out, max_frames=args.max_frames)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); open it in a browser (works offline)")
    return 0
