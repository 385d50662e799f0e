"""Key every camera of a take and store the masks in it (the take-level driver of the keyer)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stage.keying.keyer import estimate_model, key_frames
from stage.keying.params import KeyParams, KeyResult
from stage.keying.preview import contact_sheet

if TYPE_CHECKING:
    from stage.store import TakeReader

__all__ = ["key_take", "key_camera", "store_camera_key", "store_camera_keys", "take_key_params", "CameraKey"]

log = logging.getLogger("stage.keying")

_CHUNK = 64  # frames keyed at a time (memory stays bounded on long takes)


def _backdrop_from_rig(rig: dict | None) -> tuple[str | None, str | None]:
    if not rig:
        return None, None
    bd = rig.get("backdrop") or {}
    return bd.get("key_mode"), bd.get("color")


@dataclass
class CameraKey:
    """The keyed masks of one camera, before they are stored (:func:`store_camera_key`)."""

    camera: str
    masks: np.ndarray  # (N, H, W) bool
    valid: np.ndarray  # (N,) bool
    reasons: list[str]
    params: KeyParams  # as fitted, every derived value filled in
    preview: list = field(default_factory=list)  # (frame, mask, matte, valid, reason, index)


def take_key_params(rig: dict | None, *, key_mode: str | None = None, grow: int = 0, fill_holes: str | None = None) -> KeyParams:
    """The keyer's base parameters for a take: the mode and colour of the rig's backdrop
    unless ``key_mode`` is given (chroma by default)."""
    rig_mode, rig_color = _backdrop_from_rig(rig)
    mode = key_mode or rig_mode or "chroma"
    color = rig_color if (mode == "chroma" and rig_color in ("green", "blue", "red")) else None
    polarity = {"black": "dark", "white": "bright"}.get(rig_color or "") if mode == "luma" else None
    return KeyParams(mode=mode, backdrop_color=color, polarity=polarity, grow=grow, fill_holes=fill_holes)  # type: ignore[arg-type]


def key_camera(
    take: str | Path | TakeReader,
    camera: str,
    *,
    base: KeyParams,
    workers: int = 2,
    preview: bool = False,
    progress: Callable[[int], None] | None = None,
) -> CameraKey | None:
    """Key every frame of one camera of a take (backdrop model from 16 frames); stores nothing.

    Returns None for a camera without frames. Runs anywhere the take can be read (a worker
    process too); :func:`store_camera_key` writes the result into the take. ``take`` may be
    an open :class:`stage.store.TakeReader` (left open: several cameras, one opening).
    """
    from contextlib import nullcontext

    from stage.store import TakeReader

    with nullcontext(take) if isinstance(take, TakeReader) else TakeReader(take) as r:
        n = r.n_frames(camera)
        if n == 0:
            log.warning("%s: no frames", camera)
            return None
        plate = r.read_array(f"cameras/{camera}", "plate")[0] if r.has_array(f"cameras/{camera}", "plate") else None
        sample_idx = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(int))
        first = r.frames(camera, 0, min(n, _CHUNK))  # one read; a short take's sample comes from it
        sample = first[sample_idx] if n <= _CHUNK else np.stack([r.frame(camera, int(i)) for i in sample_idx])
        if plate is not None and (plate.dtype != np.uint8 or plate.shape != sample.shape[1:]):
            log.warning("%s: stored plate has shape %s, ignored", camera, plate.shape)
            plate = None
        params = estimate_model(sample, params=base, plate=plate)
        masks = np.zeros((n,) + sample.shape[1:3], bool)
        valid = np.zeros(n, bool)
        reasons = [""] * n
        preview_frames = []
        for start in range(0, n, _CHUNK):
            stop = min(n, start + _CHUNK)
            frames, first = (first, None) if start == 0 else (r.frames(camera, start, stop), None)
            res = key_frames(frames, params=params, plate=plate, workers=workers, camera=camera, progress=progress)
            masks[start:stop] = res.masks
            valid[start:stop] = res.valid
            reasons[start:stop] = res.reasons
            if preview:
                keep = [i for i in range(stop - start) if not res.valid[i]][:3]
                keep += [i for i in np.linspace(0, stop - start - 1, 3).round().astype(int) if i not in keep]
                for i in keep:
                    preview_frames.append((frames[i], res.masks[i], res.matte[i], res.valid[i], res.reasons[i], start + i))
    return CameraKey(camera, masks, valid, reasons, res.params, preview_frames)


def store_camera_key(take: str | Path, key: CameraKey) -> None:
    """Write one camera's masks and their per-frame validity into the take."""
    store_camera_keys(take, [key])


def store_camera_keys(take: str | Path, keys: Sequence[CameraKey]) -> None:
    """Write several cameras' masks and validity in one update of the take's derived data."""
    from stage.store import TakeReader, write_arrays

    arrays = []
    with TakeReader(take) as r:
        for key in keys:
            W, H = r.image_size(key.camera)
            shape = (r.n_frames(key.camera), H, W)
            if key.masks.shape != shape:
                raise ValueError(f"masks of camera {key.camera} must have shape {shape}, got {key.masks.shape}")
            meta = {"key": key.params.to_dict(), "valid": key.valid.tolist(), "reasons": key.reasons}
            arrays.append((f"cameras/{key.camera}", "masks", np.asarray(key.masks, bool), meta))  # no copy of bool masks
            arrays.append((f"cameras/{key.camera}", "mask_valid", key.valid.astype(np.uint8), {"reasons": key.reasons}))
    write_arrays(take, arrays)


def _write_preview(preview_dir: Path, key: CameraKey) -> str | None:
    import cv2

    if not key.preview:
        return None
    pf = key.preview
    sel = pf[:: max(1, len(pf) // 6)][:6]
    sheet = contact_sheet(
        np.stack([s[0] for s in sel]),
        KeyResult(
            masks=np.stack([s[1] for s in sel]),
            matte=np.stack([s[2] for s in sel]),
            valid=np.array([s[3] for s in sel]),
            reasons=[s[4] for s in sel],
            params=key.params,
        ),
        indices=np.array([s[5] for s in sel]),
    )
    out = preview_dir / f"{key.camera}.png"
    if not cv2.imwrite(str(out), sheet):
        raise OSError(f"cannot write {out}")
    return str(out)


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
    from stage.store import TakeReader

    if workers < 1:
        raise ValueError("workers must be >= 1")
    if grow < 0:
        raise ValueError("grow must be >= 0")
    take = Path(take)
    with TakeReader(take) as r:
        all_cameras = list(r.cameras)
        rig = r.rig
    if cameras:
        unknown = [c for c in cameras if c not in all_cameras]
        if unknown:
            raise ValueError(f"cameras: no camera {', '.join(unknown)} in the take (cameras: {', '.join(all_cameras)})")
        selected = [c for c in all_cameras if c in cameras]
    else:
        selected = all_cameras
    base = take_key_params(rig, key_mode=key_mode, grow=grow, fill_holes=fill_holes)
    preview_dir = Path(preview) if preview is not None else None
    if preview_dir is not None:
        preview_dir.mkdir(parents=True, exist_ok=True)
    total = n_invalid = 0
    previews: list[str] = []
    for cam in selected:
        key = key_camera(take, cam, base=base, workers=workers, preview=preview_dir is not None, progress=progress)
        if key is None:
            continue
        store_camera_key(take, key)
        total += len(key.valid)
        n_invalid += int((~key.valid).sum())
        if preview_dir is not None:
            out = _write_preview(preview_dir, key)
            if out:
                previews.append(out)
        fg = 100 * key.masks[key.valid].mean() if key.valid.any() else 0.0
        log.info("%s: %d frames keyed (%s), %d invalid, foreground %.1f %% on average",
                 cam, len(key.valid), base.mode, int((~key.valid).sum()), fg)
    return {"mode": base.mode, "cameras": selected, "frames": total, "invalid": n_invalid, "previews": previews}
