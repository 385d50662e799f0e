"""``stage calibration export``: convert a calibration between formats."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 31


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibration", help="inspect or convert calibration files",
                       description="Calibration files: aniposelib TOML, caliscope camera_array.toml, OpenCV YAML, "
                       "JSON, COLMAP text models, nerfstudio transforms.json; Middlebury *_par.txt and takes (TAKE.h5) "
                       "are read too.")
    csub = p.add_subparsers(dest="calibration_command", metavar="ACTION", required=True)
    e = csub.add_parser("export", help="write a calibration in another format",
                        description="Read CALIB (any supported format, or a take) and write it as aniposelib TOML, "
                        "OpenCV FileStorage YAML, JSON, caliscope camera_array.toml (metres), a COLMAP text model "
                        "(a folder: cameras.txt, images.txt) or nerfstudio transforms.json (metres, OpenCV "
                        "distortion).")
    e.add_argument("calib", type=Path, metavar="CALIB", help="calibration file or TAKE.h5")
    e.add_argument("--format", required=True, choices=("toml", "yaml", "json", "caliscope", "colmap", "nerfstudio"),
                   help="output format")
    e.add_argument("--out", type=Path, metavar="FILE", help="output file (default: CALIB with the new extension)")
    e.set_defaults(func=run_export)
    s = csub.add_parser("show", help="print a calibration's cameras")
    s.add_argument("calib", type=Path, metavar="CALIB")
    s.set_defaults(func=run_show)


def _read(path: Path):
    from calib.formats import read_calibration

    if path.suffix.lower() in (".h5", ".hdf5"):
        from stage.store import TakeReader

        with TakeReader(path) as r:
            c = r.calibration
        if c is None:
            raise ValueError(f"{path}: the take holds no calibration (run stage calibrate on it)")
        return c
    return read_calibration(path)


def run_export(args: argparse.Namespace) -> int:
    from calib.formats import write_calibration

    calib = _read(args.calib)
    default = {"toml": args.calib.with_suffix(".toml"), "yaml": args.calib.with_suffix(".yml"),
               "json": args.calib.with_suffix(".json"), "caliscope": args.calib.parent / "camera_array.toml",
               "colmap": args.calib.parent / "colmap", "nerfstudio": args.calib.parent / "transforms.json"}
    out = args.out if args.out is not None else default[args.format]
    if out.resolve() == args.calib.resolve():
        raise ValueError(f"--out {out} would overwrite the input; give another file")
    write_calibration(calib, out, format=args.format)
    print(f"wrote {out} ({len(calib)} cameras, units {calib.units})")
    return 0


def run_show(args: argparse.Namespace) -> int:
    calib = _read(args.calib)
    print(f"{args.calib}: {len(calib)} cameras, units {calib.units}")
    for c in calib:
        print(f"  {c!r}")
    return 0
