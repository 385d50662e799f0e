"""Key every camera of a take and store the masks in it (the take-level driver of the keyer)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stage.keying.keyer import estimate_model, key_frames, say_invalid_masks
from stage.keying.params import KeyParams, KeyResult
from stage.keying.preview import contact_sheet

if TYPE_CHECKING:
    from stage.store import TakeReader

__all__ = [
    "key_take", "key_camera", "store_camera_key", "store_camera_keys", "store_plates", "take_key_params", "CameraKey",
    "choose_key_mode", "resolve_key_choice", "rig_volume", "rig_layers",
]

log = logging.getLogger("stage.keying")

_CHUNK = 64  # frames keyed at a time (memory stays bounded on long takes)


def _backdrop_from_rig(rig: dict | None) -> tuple[str | None, str | None]:
    if not rig:
        return None, None
    bd = rig.get("backdrop") or {}
    return bd.get("key_mode"), bd.get("color")


def rig_layers(rig: dict | None) -> tuple[str, ...] | None:
    """The keying layers the rig file names (``[backdrop] layers``), None when it names none."""
    bd = (rig or {}).get("backdrop") or {}
    layers = bd.get("layers")
    return None if layers is None else tuple(layers)


#: A backdrop colour must cover this share of the sampled pixels in most cameras for the
#: footage's default to be chroma keying (else a plate from the take).
BACKDROP_SHARE = 0.25
#: Below this share of backdrop pixels (but above :data:`BACKDROP_SHARE`) the backdrop is
#: partial and the default adds the graph-cut layer.
FULL_BACKDROP_SHARE = 0.8


def choose_key_mode(take: str | Path | TakeReader, *, frames_per_camera: int = 3,
                    skip: Mapping[str, Collection[int]] | None = None) -> dict:
    """The keying default for footage without a rig file, chosen from the footage itself.

    A few frames per camera (spread across the take) are searched for a dominant saturated
    backdrop colour (:func:`stage.keying.chroma.backdrop_share`). When one covers at
    least :data:`BACKDROP_SHARE` of the pixels in most cameras: chroma, with the ``volume``
    layer, and the ``graphcut`` layer when it covers less than :data:`FULL_BACKDROP_SHARE`
    in some camera (walls and lights beside a partial backdrop); else a plate from the take.

    ``skip``: per camera, rows never read (damaged frames, :func:`stage.store.verify.verify_take`).

    Returns
    -------
    dict
        ``{"mode", "layers", "backdrop_share" (per camera), "why"}``.
    """
    from contextlib import nullcontext

    from stage.keying._color import sample_pixels
    from stage.keying.chroma import backdrop_share
    from stage.store import TakeReader

    shares: dict[str, float] = {}
    with nullcontext(take) if isinstance(take, TakeReader) else TakeReader(take) as r:
        for cam in r.cameras:
            rows = _readable_rows(r.n_frames(cam), (skip or {}).get(cam, ()))
            if len(rows) == 0:
                continue
            sample = np.stack([r.frame(cam, int(i)) for i in _spread(rows, frames_per_camera)])
            shares[cam] = backdrop_share(sample_pixels(sample, stride=8))[0]
    vals = np.array(list(shares.values()) or [0.0])
    typical = float(np.median(vals))
    if typical >= BACKDROP_SHARE:
        least = float(vals.min())
        layers = ("volume",) if least >= FULL_BACKDROP_SHARE else ("volume", "graphcut")
        why = (f"a backdrop colour covers {100 * typical:.0f} % of the sampled pixels (median over the cameras, "
               f"least {100 * least:.0f} %; chroma from {100 * BACKDROP_SHARE:.0f} %, partial where a camera sees "
               f"less than {100 * FULL_BACKDROP_SHARE:.0f} %)")
        return {"mode": "chroma", "layers": list(layers), "backdrop_share": shares, "why": why}
    why = (f"no backdrop colour covers {100 * BACKDROP_SHARE:.0f} % of the views (median {100 * typical:.1f} %): "
           "a plate estimated from the take")
    return {"mode": "plate", "layers": [], "backdrop_share": shares, "why": why}


def _readable_rows(n: int, skip: Collection[int]) -> np.ndarray:
    """Rows ``0..n-1`` less those in ``skip``."""
    return np.setdiff1d(np.arange(n), np.fromiter(skip, int, count=len(skip)))


def _spread(rows: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` of ``rows`` spread evenly from the first to the last."""
    return rows[np.unique(np.linspace(0, len(rows) - 1, min(len(rows), k)).round().astype(int))]


def _read_frames(r, camera: str, start: int, stop: int, skip: set[int]) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``start:stop`` of a camera but those in ``skip`` (never read), and their rows."""
    rows = np.array([i for i in range(start, stop) if i not in skip], int)
    if len(rows) == stop - start:
        return r.frames(camera, start, stop), rows  # one read
    W, H = r.image_size(camera)
    return (np.stack([r.frame(camera, int(i)) for i in rows]) if len(rows) else np.zeros((0, H, W, 3), np.uint8)), rows


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


def _stored_plate(r, camera: str, shape: tuple[int, ...]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The plate stored in the take for ``camera`` (and its noise map), or None."""
    group = f"cameras/{camera}"
    plate = r.read_array(group, "plate")[0] if r.has_array(group, "plate") else None
    if plate is not None and (plate.dtype != np.uint8 or plate.shape != shape):
        log.warning("%s: stored plate has shape %s, ignored", camera, plate.shape)
        return None, None
    noise = r.read_array(group, "plate_noise")[0] if plate is not None and r.has_array(group, "plate_noise") else None
    if noise is not None and noise.shape != shape[:2]:
        noise = None
    return plate, noise


def _volume_roi(r, camera: str, volume) -> np.ndarray | None:
    if volume is None or not r.has_calibration or camera not in r.calibration.names:
        return None
    from stage.keying.volume_prior import volume_image

    return volume_image(r.calibration[camera], np.asarray(volume, float))


def key_camera(
    take: str | Path | TakeReader,
    camera: str,
    *,
    base: KeyParams,
    workers: int = 2,
    preview: bool = False,
    progress: Callable[[int], None] | None = None,
    volume=None,
    skip: Collection[int] = (),
) -> CameraKey | None:
    """Key every frame of one camera of a take (backdrop model from frames spread across the
    take: 16, or 25 for a plate estimated from the take); stores nothing.

    Returns None for a camera without frames. Runs anywhere the take can be read (a worker
    process too); :func:`store_camera_key` writes the result into the take. ``take`` may be
    an open :class:`stage.store.TakeReader` (left open: several cameras, one opening).
    ``volume`` (``[xmin, ymin, zmin, xmax, ymax, zmax]``, calibration units): the volume
    layer, pixels whose rays miss it are background. ``skip``: rows never read (damaged frames,
    :func:`stage.store.verify.verify_take`): their masks are empty and invalid.
    """
    from contextlib import nullcontext

    from stage.store import TakeReader

    with nullcontext(take) if isinstance(take, TakeReader) else TakeReader(take) as r:
        n = r.n_frames(camera)
        if n == 0:
            log.warning("%s: no frames", camera)
            return None
        W, H = r.image_size(camera)
        plate, plate_noise = _stored_plate(r, camera, (H, W, 3))
        k = 25 if base.mode == "plate" and plate is None else 16
        skip = set(int(i) for i in skip)
        readable = _readable_rows(n, skip)
        if len(readable) == 0:
            log.warning("%s: every frame is damaged", camera)
            return None
        sample_idx = _spread(readable, k)
        first = _read_frames(r, camera, 0, min(n, _CHUNK), skip)  # one read; a short take's sample comes from it
        sample = (first[0][np.searchsorted(first[1], sample_idx)] if n <= _CHUNK
                  else np.stack([r.frame(camera, int(i)) for i in sample_idx]))
        roi = _volume_roi(r, camera, volume)
        params = estimate_model(sample, params=base, plate=plate, plate_noise=plate_noise, roi=roi)
        _warn_stuck(camera, params)
        masks = np.zeros((n,) + sample.shape[1:3], bool)
        valid = np.zeros(n, bool)
        reasons = ["damaged frame (not read)" if i in skip else "" for i in range(n)]  # damaged: empty, invalid
        preview_frames = []
        for start in range(0, n, _CHUNK):
            stop = min(n, start + _CHUNK)
            (frames, rows), first = (first, None) if start == 0 else (_read_frames(r, camera, start, stop, skip), None)
            if len(rows) == 0:
                continue
            res = key_frames(frames, params=params, plate=plate, workers=workers, camera=camera, progress=progress,
                             rows=False)  # (said once for the camera, below)
            masks[rows] = res.masks
            valid[rows] = res.valid
            for i, why in zip(rows, res.reasons):
                reasons[i] = why
            if preview:
                keep = [i for i in range(len(rows)) if not res.valid[i]][:3]
                keep += [i for i in np.linspace(0, len(rows) - 1, 3).round().astype(int) if i not in keep]
                for i in keep:
                    preview_frames.append((frames[i], res.masks[i], res.matte[i], res.valid[i], res.reasons[i], int(rows[i])))
    say_invalid_masks(range(n), ["" if i in skip else why for i, why in enumerate(reasons)], camera=camera)
    return CameraKey(camera, masks, valid, reasons, res.params, preview_frames)


#: Share of the image the subject may never leave before the plate from the take is called unreliable.
STUCK_WARN_FRACTION = 0.002


def _warn_stuck(camera: str, params: KeyParams) -> None:
    frac = float((params.model or {}).get("stuck_fraction", 0.0))
    if frac > STUCK_WARN_FRACTION:
        log.warning("%s: the plate from the take is unreliable on %.2f %% of the image (no colour held there in a "
                    "quarter of the frames sampled across the take: the subject, or something else that moves, never "
                    "leaves those pixels); they are keyed as uncertain. An empty take gives a clean plate: "
                    "--plate EMPTY_TAKE", camera, 100 * frac,
                    extra={"job_message": f"{camera}: the plate from the take is unreliable on {100 * frac:.2f} % of "
                           "the image (no colour held there in a quarter of the frames sampled across the take: the "
                           "subject, or something else that moves, never leaves those pixels); they are keyed as "
                           "uncertain. An empty take's plates, stored with the take, give a clean plate"})


def store_plates(take: str | Path, empty: str | Path, *, frames: int = 25) -> dict[str, float]:
    """Estimate every camera's plate and noise map from an empty take and store them in ``take``
    (``cameras/<cam>/plate``, ``cameras/<cam>/plate_noise``), where the keyer finds them.

    Returns the noise (median, grey levels) per camera.

    Raises
    ------
    ValueError
        A camera of ``take`` missing from ``empty``, or of another image size.
    """
    from stage.keying.background import sample_indices, take_plate
    from stage.store import TakeReader, write_arrays

    out: dict[str, float] = {}
    arrays = []
    with TakeReader(take) as r, TakeReader(empty) as e:
        for cam in r.cameras:
            if cam not in e.cameras:
                raise ValueError(f"--plate {empty}: no camera {cam} (it has {', '.join(e.cameras)})")
            if tuple(e.image_size(cam)) != tuple(r.image_size(cam)):
                raise ValueError(f"--plate {empty}: camera {cam} is {e.image_size(cam)}, the take's is {r.image_size(cam)}")
            n = e.n_frames(cam)
            if n == 0:
                raise ValueError(f"--plate {empty}: camera {cam} has no frames")
            stack = np.stack([e.frame(cam, int(i)) for i in sample_indices(n, frames)])
            if stack.shape[0] >= 3:
                est = take_plate(stack)
                plate, noise = est.plate, est.noise
            else:
                plate, noise = stack[0], None
            arrays.append((f"cameras/{cam}", "plate", plate, {"source": str(empty), "frames": int(stack.shape[0])}))
            if noise is not None:
                arrays.append((f"cameras/{cam}", "plate_noise", noise, {"source": str(empty)}))
                out[cam] = float(np.median(noise))
            else:
                out[cam] = float("nan")
    write_arrays(take, arrays)
    return out


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
    layers: Sequence[str] | None = None,
    volume=None,
) -> dict:
    """Key the frames of every camera of a take and write masks into the take.

    Parameters
    ----------
    take : path
        Take file (.h5).
    key_mode : {"chroma", "luma", "plate"}, optional
        Default: the take's rig ``backdrop.key_mode``, else chosen from the footage
        (:func:`choose_key_mode`).
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
    layers : sequence of str, optional
        Keying layers (:data:`stage.keying.params.KEY_LAYERS`): ``volume`` here (pixels whose
        rays miss the capture volume are background); ``graphcut`` is a pipeline step
        (:mod:`pipeline.silhouette_refine`) and is ignored here. Default: the rig's, else the
        footage's choice.
    volume : (6,) floats, optional
        The volume layer's box (default: the rig's capture volume).

    Returns
    -------
    dict
        ``{"mode", "layers", "why", "cameras", "frames", "invalid", "previews"}``.
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
    choice = resolve_key_choice(take, rig, key_mode=key_mode, layers=layers)
    base = take_key_params(rig, key_mode=choice["mode"], grow=grow, fill_holes=fill_holes)
    vol = volume if volume is not None else rig_volume(rig)
    if "volume" in choice["layers"] and vol is None:
        log.warning("volume layer: the take's rig has no capture volume and none was given (--volume); layer skipped",
                    extra={"job_message": "volume layer: the take's rig has no capture volume and none was given "
                           "(parameters.volume); layer skipped"})
    vol = vol if "volume" in choice["layers"] else None
    preview_dir = Path(preview) if preview is not None else None
    if preview_dir is not None:
        preview_dir.mkdir(parents=True, exist_ok=True)
    total = n_invalid = 0
    previews: list[str] = []
    for cam in selected:
        key = key_camera(take, cam, base=base, workers=workers, preview=preview_dir is not None, progress=progress,
                         volume=vol)
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
    return {"mode": base.mode, "layers": choice["layers"], "why": choice["why"], "cameras": selected, "frames": total,
            "invalid": n_invalid, "previews": previews}


def rig_volume(rig: dict | None) -> np.ndarray | None:
    """The rig's capture volume as ``[xmin, ymin, zmin, xmax, ymax, zmax]``, or None."""
    v = (rig or {}).get("volume")
    if not v:
        return None
    c, s = np.asarray(v["center"], float), np.asarray(v["size"], float)
    return np.r_[c - s / 2, c + s / 2]


def resolve_key_choice(take, rig: dict | None, *, key_mode: str | None = None,
                       layers: Sequence[str] | None = None, skip: Mapping[str, Collection[int]] | None = None) -> dict:
    """The keying mode and layers of a take: what was asked for, else the rig file's, else chosen
    from the footage (:func:`choose_key_mode`); logged with the reason.

    Returns
    -------
    dict
        ``{"mode", "layers", "why"}`` (and ``backdrop_share`` when chosen from the footage).
    """
    from stage.keying.params import KEY_LAYERS

    bad = [x for x in (layers or ()) if x not in KEY_LAYERS]
    if bad:
        raise ValueError(f"layers must be among {KEY_LAYERS}, got {bad}")
    rig_mode, _ = _backdrop_from_rig(rig)
    if key_mode is not None:
        choice = {"mode": key_mode, "layers": list(layers or rig_layers(rig) or ()), "why": "asked for"}
    elif rig_mode is not None:
        choice = {"mode": rig_mode, "layers": list(layers if layers is not None else rig_layers(rig) or ()),
                  "why": "the rig file's backdrop"}
    else:
        choice = choose_key_mode(take, skip=skip)
        if layers is not None:
            choice["layers"] = list(layers)
    log.info("keying: %s%s (%s)", choice["mode"], f" + {', '.join(choice['layers'])}" if choice["layers"] else "",
             choice["why"])
    return choice
