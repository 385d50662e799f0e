"""``stage key TAKE.h5``: key every camera of a take and store the masks in it."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

ORDER = 40
log = logging.getLogger("stage.key")

_CHUNK = 64  # frames keyed at a time (memory stays bounded on long takes)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "key",
        help="compute silhouette masks of a take (chroma/luma/plate keying)",
        description="Key every camera of a take: estimate the backdrop model per camera "
        "(from a background plate stored in the take as cameras/<cam>/plate, else from the frames), "
        "compute masks and store them in the take with their parameters. Frames that cannot be keyed "
        "(black, no backdrop visible, subject filling the image) are marked invalid with a warning.",
    )
    p.add_argument("take", type=Path, help="take file (.h5)")
    p.add_argument(
        "--key-mode",
        choices=("chroma", "luma", "plate"),
        default=None,
        help="keying mode (default: the rig's backdrop.key_mode stored in the take, else chroma)",
    )
    p.add_argument("--camera", action="append", default=None, help="only this camera (repeatable)")
    p.add_argument("--preview", type=Path, default=None, metavar="DIR", help="write a contact sheet PNG per camera into DIR")
    p.add_argument("--workers", type=int, default=2, help="threads keying frames in parallel (default 2)")
    p.add_argument("--grow", type=int, default=0, help="dilate masks by this many pixels (conservative hulls)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _backdrop_from_rig(rig: dict | None) -> tuple[str | None, str | None]:
    if not rig:
        return None, None
    bd = rig.get("backdrop") or {}
    return bd.get("key_mode"), bd.get("color")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from stage.keying import KeyParams, contact_sheet, key_frames
    from stage.keying.keyer import estimate_model
    from stage.store import TakeReader, write_array, write_masks

    if args.workers < 1:
        raise ValueError("--workers must be >= 1")
    if args.grow < 0:
        raise ValueError("--grow must be >= 0")
    with TakeReader(args.take) as r:
        cameras = list(r.cameras)
        rig_mode, rig_color = _backdrop_from_rig(r.rig)
        counts = r.frame_counts()
    if args.camera:
        unknown = [c for c in args.camera if c not in cameras]
        if unknown:
            raise ValueError(f"--camera: no camera {', '.join(unknown)} in the take (cameras: {', '.join(cameras)})")
        cameras = [c for c in cameras if c in args.camera]
    mode = args.key_mode or rig_mode or "chroma"
    color = rig_color if (mode == "chroma" and rig_color in ("green", "blue", "red")) else None
    polarity = {"black": "dark", "white": "bright"}.get(rig_color or "") if mode == "luma" else None
    base = KeyParams(mode=mode, backdrop_color=color, polarity=polarity, grow=args.grow)
    if args.preview is not None:
        args.preview.mkdir(parents=True, exist_ok=True)
    total = sum(counts[c] for c in cameras)
    bar = tqdm(total=total, unit="frame", desc=f"key ({mode})", disable=args.no_progress)
    n_invalid = 0
    try:
        for cam in cameras:
            n = counts[cam]
            if n == 0:
                log.warning("%s: no frames", cam)
                continue
            with TakeReader(args.take) as r:
                plate = r.read_array(f"cameras/{cam}", "plate")[0] if r.has_array(f"cameras/{cam}", "plate") else None
                sample_idx = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(int))
                sample = np.stack([r.frame(cam, int(i)) for i in sample_idx])
                if plate is not None and (plate.dtype != np.uint8 or plate.shape != sample.shape[1:]):
                    log.warning("%s: stored plate has shape %s, ignored", cam, plate.shape)
                    plate = None
                params = estimate_model(sample, params=base, plate=plate)
                masks = np.zeros((n,) + sample.shape[1:3], bool)
                valid = np.zeros(n, bool)
                reasons = [""] * n
                preview_frames, preview_idx = [], []
                for start in range(0, n, _CHUNK):
                    stop = min(n, start + _CHUNK)
                    frames = np.stack([r.frame(cam, i) for i in range(start, stop)])
                    res = key_frames(frames, params=params, plate=plate, workers=args.workers, camera=cam, progress=bar.update)
                    masks[start:stop] = res.masks
                    valid[start:stop] = res.valid
                    reasons[start:stop] = res.reasons
                    if args.preview is not None:
                        keep = [i for i in range(stop - start) if not res.valid[i]][:3]
                        keep += [i for i in np.linspace(0, stop - start - 1, 3).round().astype(int) if i not in keep]
                        for i in keep:
                            preview_frames.append((frames[i], res.masks[i], res.matte[i], res.valid[i], res.reasons[i], start + i))
            recorded = res.params.to_dict()
            meta = {"key": recorded, "valid": valid.tolist(), "reasons": reasons}
            write_masks(args.take, cam, masks, params=meta)
            write_array(args.take, f"cameras/{cam}", "mask_valid", valid.astype(np.uint8), params={"reasons": reasons})
            n_invalid += int((~valid).sum())
            if args.preview is not None and preview_frames:
                from stage.keying.params import KeyResult

                sel = preview_frames[:: max(1, len(preview_frames) // 6)][:6]
                sheet = contact_sheet(
                    np.stack([s[0] for s in sel]),
                    KeyResult(
                        masks=np.stack([s[1] for s in sel]),
                        matte=np.stack([s[2] for s in sel]),
                        valid=np.array([s[3] for s in sel]),
                        reasons=[s[4] for s in sel],
                        params=res.params,
                    ),
                    indices=np.array([s[5] for s in sel]),
                )
                import cv2

                out = args.preview / f"{cam}.png"
                if not cv2.imwrite(str(out), sheet):
                    raise OSError(f"cannot write {out}")
            log.info(
                "%s: %d frames keyed (%s), %d invalid, foreground %.1f %% on average",
                cam, n, mode, int((~valid).sum()), 100 * masks[valid].mean() if valid.any() else 0.0,
            )
    finally:
        bar.close()
    print(f"keyed {len(cameras)} camera(s), {total} frames, mode {mode}; {n_invalid} invalid frame(s); masks stored in {args.take}")
    if args.preview is not None:
        print(f"contact sheets in {args.preview}/")
    return 0
