"""Key every camera of a take and store the masks in it (the take-level driver of the keyer)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from stage.keying.keyer import estimate_model, key_frames
from stage.keying.params import KeyParams, KeyResult
from stage.keying.preview import contact_sheet

__all__ = ["key_take"]

log = logging.getLogger("stage.keying")

_CHUNK = 64  # frames keyed at a time (memory stays bounded on long takes)


def _backdrop_from_rig(rig: dict | None) -> tuple[str | None, str | None]:
    if not rig:
        return None, None
    bd = rig.get("backdrop") or {}
    return bd.get("key_mode"), bd.get("color")


def key_take(
    take: str | Path,
    *,
    key_mode: str | None = None,
    cameras: Sequence[str] | None = None,
    workers: int = 2,
    grow: int = 0,
    fill_holes: str | None = None,
    preview: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Key the frames of every camera of a take and write masks into the take.

    Parameters
    ----------
    take : path
        Take file (.h5).
    key_mode : {"chroma", "luma", "plate"}, optional
        Default: the take's rig ``backdrop.key_mode``, else ``"chroma"``.
    cameras : sequence of str, optional
        Only these cameras (default all).
    workers : int
        Threads keying frames in parallel.
    grow : int
        Dilate masks by this many pixels (conservative hulls).
    fill_holes : {"uncertain", "small", "none"}, optional
        Which small holes to fill (:class:`stage.keying.KeyParams`); default by mode.
    preview : path, optional
        Directory for one contact sheet PNG per camera (frame, matte, overlay).
    progress : callable, optional
        Called with the number of frames just keyed.

    Returns
    -------
    dict
        ``{"mode", "cameras", "frames", "invalid", "previews"}``.
    """
    from stage.store import TakeReader, write_array, write_masks

    if workers < 1:
        raise ValueError("workers must be >= 1")
    if grow < 0:
        raise ValueError("grow must be >= 0")
    take = Path(take)
    with TakeReader(take) as r:
        all_cameras = list(r.cameras)
        rig_mode, rig_color = _backdrop_from_rig(r.rig)
        counts = r.frame_counts()
    if cameras:
        unknown = [c for c in cameras if c not in all_cameras]
        if unknown:
            raise ValueError(f"cameras: no camera {', '.join(unknown)} in the take (cameras: {', '.join(all_cameras)})")
        selected = [c for c in all_cameras if c in cameras]
    else:
        selected = all_cameras
    mode = key_mode or rig_mode or "chroma"
    color = rig_color if (mode == "chroma" and rig_color in ("green", "blue", "red")) else None
    polarity = {"black": "dark", "white": "bright"}.get(rig_color or "") if mode == "luma" else None
    base = KeyParams(mode=mode, backdrop_color=color, polarity=polarity, grow=grow, fill_holes=fill_holes)  # type: ignore[arg-type]
    preview_dir = Path(preview) if preview is not None else None
    if preview_dir is not None:
        preview_dir.mkdir(parents=True, exist_ok=True)
    total = sum(counts[c] for c in selected)
    n_invalid = 0
    previews: list[str] = []
    for cam in selected:
        n = counts[cam]
        if n == 0:
            log.warning("%s: no frames", cam)
            continue
        with TakeReader(take) as r:
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
            preview_frames = []
            for start in range(0, n, _CHUNK):
                stop = min(n, start + _CHUNK)
                frames = np.stack([r.frame(cam, i) for i in range(start, stop)])
                res = key_frames(frames, params=params, plate=plate, workers=workers, camera=cam, progress=progress)
                masks[start:stop] = res.masks
                valid[start:stop] = res.valid
                reasons[start:stop] = res.reasons
                if preview_dir is not None:
                    keep = [i for i in range(stop - start) if not res.valid[i]][:3]
                    keep += [i for i in np.linspace(0, stop - start - 1, 3).round().astype(int) if i not in keep]
                    for i in keep:
                        preview_frames.append((frames[i], res.masks[i], res.matte[i], res.valid[i], res.reasons[i], start + i))
        recorded = res.params.to_dict()
        meta = {"key": recorded, "valid": valid.tolist(), "reasons": reasons}
        write_masks(take, cam, masks, params=meta)
        write_array(take, f"cameras/{cam}", "mask_valid", valid.astype(np.uint8), params={"reasons": reasons})
        n_invalid += int((~valid).sum())
        if preview_dir is not None and preview_frames:
            import cv2

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
            out = preview_dir / f"{cam}.png"
            if not cv2.imwrite(str(out), sheet):
                raise OSError(f"cannot write {out}")
            previews.append(str(out))
        log.info(
            "%s: %d frames keyed (%s), %d invalid, foreground %.1f %% on average",
            cam, n, mode, int((~valid).sum()), 100 * masks[valid].mean() if valid.any() else 0.0,
        )
    return {"mode": mode, "cameras": selected, "frames": total, "invalid": n_invalid, "previews": previews}
