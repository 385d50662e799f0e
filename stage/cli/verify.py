"""``stage verify``: read every chunk of a take and name what is damaged."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ORDER = 23


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "verify",
        help="check a take end to end: its structure and the checksum of every chunk",
        description="Read every chunk of a take (frames, depth, JPEG bytes, timestamps, the frame-set table) and "
        "name the cameras, frames and frame sets that are damaged. Exit status: 0 nothing damaged, 1 damaged "
        "frames (listed), 2 the take cannot be opened at all (one line). Takes written before checksums were "
        "added (`stage info` says so) can only be checked for structure and readable chunks.",
    )
    p.add_argument("take", type=Path, metavar="TAKE.h5")
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from stage.store.verify import verify_take

    if not args.take.is_file():
        raise FileNotFoundError(f"{args.take}: take not found")
    d = verify_take(args.take)
    if args.json:
        print(json.dumps({"path": str(d.path), "ok": d.ok, "checksums": d.checksums, "n_sets": d.n_sets,
                          "frames": d.frames, "sets": d.sets, "problems": d.problems}, indent=1))
    else:
        print(d.summary())
        for line in d.problems:
            print(f"  {line}")
        if not d.checksums:
            print("  note: this take was written without checksums; damage inside its frame data cannot be detected")
    return 0 if d.ok else 1
