"""``stage masks TAKE.h5 --out DIR``: export the keyed masks as PNG files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ORDER = 41


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "masks",
        help="export a take's masks as PNG files (DIR/<camera>/<frame>.png)",
        description="Write every mask stored by 'stage key' as an 8-bit PNG (255 = subject) to "
        "DIR/<camera>/<frame:06d>.png, plus DIR/masks.json with the keying parameters and which frames are invalid.",
    )
    p.add_argument("take", type=Path, help="take file (.h5)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output directory")
    p.add_argument("--camera", action="append", default=None, help="only this camera (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np
    from tqdm import tqdm

    from stage.store import TakeReader

    with TakeReader(args.take) as r:
        keyed = r.masks_present()
        if not keyed:
            raise ValueError(f"{args.take}: no masks in this take (run 'stage key {args.take}' first)")
        cams = keyed
        if args.camera:
            missing = [c for c in args.camera if c not in keyed]
            if missing:
                raise ValueError(f"--camera: no masks for {', '.join(missing)} (keyed: {', '.join(keyed)})")
            cams = [c for c in keyed if c in args.camera]
        index = {}
        total = 0
        args.out.mkdir(parents=True, exist_ok=True)
        for cam in cams:
            masks = r.masks(cam)
            assert masks is not None
            params = r.mask_params(cam) or {}
            d = args.out / cam
            d.mkdir(exist_ok=True)
            for i in tqdm(range(masks.shape[0]), desc=cam, unit="mask", disable=args.no_progress, leave=False):
                out = d / f"{i:06d}.png"
                if not cv2.imwrite(str(out), masks[i].astype(np.uint8) * 255):
                    raise OSError(f"cannot write {out}")
            total += masks.shape[0]
            index[cam] = {
                "frames": int(masks.shape[0]),
                "invalid": [i for i, v in enumerate(params.get("valid", [])) if not v],
                "reasons": {str(i): s for i, s in enumerate(params.get("reasons", [])) if s},
                "key": params.get("key"),
            }
    (args.out / "masks.json").write_text(json.dumps(index, indent=1), encoding="utf-8")
    print(f"wrote {total} masks of {len(cams)} camera(s) to {args.out}/")
    return 0
