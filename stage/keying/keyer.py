"""``key_frames``: one camera's frames in, silhouettes out.

Estimates the backdrop model once per camera (from the plate when there is one,
else robustly from the frames), computes each frame's backdrop distance with the
chosen mode, turns it into a soft matte and a clean mask
(:mod:`stage.keying.cleanup`), and checks each frame: a black frame, a frame
without visible backdrop or one the subject fills is marked invalid with the
reason logged, and the other frames are keyed as usual.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import cv2
import numpy as np

from stage.keying._color import chi_radius, default_thresholds, sample_pixels, validate_frames
from stage.keying.background import take_plate
from stage.keying.chroma import chroma_distance, estimate_chroma_model
from stage.keying.cleanup import estimate_coverage_fraction, mask_from_distance, soft_matte
from stage.keying.luma import estimate_luma_model, luma_distance
from stage.keying.params import KEY_MODES, PLATE_CLOSE_RELATIVE, KeyingError, KeyParams, KeyResult
from stage.keying.plate import estimate_plate_model, plate_distance
from stage.messages import frames_named

__all__ = ["key_frames", "estimate_model", "key_one"]

log = logging.getLogger(__name__)

_DOF = {"chroma": 2, "luma": 1, "plate": 1}
#: Tail of the backdrop's distance beyond which a pixel is doubtful: gaps the plate mode closes
#: and holes it fills keep the pixels the backdrop explains within its noise (below this tail's
#: radius) open, as backdrop seen through the subject.
DOUBT_TAIL = 0.05


def _border_samples(frames: np.ndarray, stride: int) -> np.ndarray:
    f = frames[:: max(1, frames.shape[0] // 8)]
    parts = [f[:, 0, ::stride], f[:, -1, ::stride], f[:, ::stride, 0], f[:, ::stride, -1]]
    return np.concatenate([p.reshape(-1, 3) for p in parts]).astype(np.float64)


def _frame_ok_for_model(frames: np.ndarray, black_level: float) -> np.ndarray:
    """Frames usable to estimate the model (not black)."""
    p = np.array([_luma_percentile(f, 99.5) for f in frames])
    return p >= black_level


def estimate_model(
    frames: np.ndarray,
    *,
    params: KeyParams,
    plate: np.ndarray | None = None,
    plate_noise: np.ndarray | None = None,
    roi: np.ndarray | None = None,
) -> KeyParams:
    """Resolve the thresholds and estimate the backdrop model for one camera.

    Parameters
    ----------
    frames : (N, H, W, 3) uint8 ndarray
        Frames spread across the take (plate mode without a plate estimates it from them).
    params : KeyParams
    plate : (H, W, 3) uint8 ndarray or None
    plate_noise : (H, W) float ndarray or None
        Per-pixel noise measured on the plate (grey levels); plate mode only.
    roi : (H, W) bool ndarray or None
        Pixels whose rays meet the capture volume (:func:`stage.keying.volume_prior.volume_image`);
        every other pixel is background, in any mode.

    Returns
    -------
    KeyParams
        ``params`` with ``t_lo``, ``t_hi`` and ``model`` filled in.

    Raises
    ------
    KeyingError
        When no backdrop model can be estimated (no usable frame, no backdrop colour).
    """
    if params.fill_holes is None:
        params = params.replace(fill_holes={"luma": "small", "plate": "enclosed"}.get(params.mode, "uncertain"))
    if params.close_relative is None:
        params = params.replace(close_relative=PLATE_CLOSE_RELATIVE if params.mode == "plate" else 0.0)
    d_lo, d_hi = default_thresholds(_DOF[params.mode])
    t_lo = params.t_lo if params.t_lo is not None else d_lo
    t_hi = params.t_hi if params.t_hi is not None else max(d_hi, t_lo * 1.2)
    if t_hi <= t_lo:
        raise ValueError(f"t_hi ({t_hi}) must be greater than t_lo ({t_lo})")
    if params.model is not None:
        resolved = params.replace(t_lo=float(t_lo), t_hi=float(t_hi))
        if roi is not None and "_roi" not in params.model:
            resolved = resolved.replace(model={**params.model, "_roi": roi})
        return _with_coverage(resolved, frames)
    ok = _frame_ok_for_model(frames, params.black_level)
    usable = frames[ok]
    if params.mode == "chroma":
        src = plate[None] if plate is not None else usable
        if src.shape[0] == 0:
            raise KeyingError("no usable frame to estimate the backdrop colour (all frames are black)")
        model = estimate_chroma_model(
            sample_pixels(src, stride=params.sample_stride), backdrop_color=params.backdrop_color
        )
        model["source"] = "plate" if plate is not None else "frames"
    elif params.mode == "luma":
        if usable.shape[0] == 0:
            raise KeyingError("no usable frame to estimate the luma model (all frames are black)")
        model = estimate_luma_model(
            sample_pixels(usable, stride=params.sample_stride),
            polarity=params.polarity,
            border=_border_samples(usable, params.sample_stride),
            t_mid=0.5 * (t_lo + t_hi),
        )
    else:
        model = _plate_model(usable if usable.shape[0] else frames, usable.shape[0], params, plate, plate_noise)
    if roi is not None:
        model["_roi"] = roi
    return _with_coverage(params.replace(t_lo=float(t_lo), t_hi=float(t_hi), model=model), usable)


def _plate_model(src: np.ndarray, n_usable: int, params: KeyParams, plate: np.ndarray | None,
                 plate_noise: np.ndarray | None) -> dict:
    """The plate keyer's model: a given plate (with its noise map when there is one), else a
    plate estimated from the frames (spread across the take), its noise and flagged pixels."""
    stuck = None
    if plate is None:
        if n_usable < 3:
            raise KeyingError("plate mode without a plate needs at least 3 usable frames spread across the take")
        if n_usable < 9:
            log.warning("background plate from only %d frames: a slow subject may stay in it", n_usable)
        est = take_plate(src)
        plate_used, plate_noise, stuck = est.plate, est.noise, est.stuck
        extra = {"source": "take", "samples": est.samples, "stuck_fraction": est.stuck_fraction}
    else:
        plate_used, extra = plate, {"source": "plate"}
    model = estimate_plate_model(src, plate_used, stride=params.sample_stride, shadow_floor=params.shadow_floor)
    if plate_noise is not None:
        model["sigma"] = float(np.median(plate_noise))
        model["_noise"] = plate_noise.astype(np.float32)
    model.update(extra)
    model["_plate"] = plate_used
    if stuck is not None and stuck.any():
        model["_stuck"] = stuck
    return model


def _with_coverage(params: KeyParams, frames: np.ndarray) -> KeyParams:
    if params.coverage_fraction is not None:
        return params
    if frames.shape[0] == 0:
        return params.replace(coverage_fraction=0.5)
    fn = _distance_fn(params)
    idx = np.unique(np.linspace(0, frames.shape[0] - 1, min(frames.shape[0], 12)).round().astype(int))
    frac = estimate_coverage_fraction(
        [fn(frames[i]) for i in idx], t_lo=params.t_lo, t_hi=params.t_hi, coverage_window=params.coverage_window
    )
    return params.replace(coverage_fraction=frac)


def _distance_fn(params: KeyParams) -> Callable[[np.ndarray], np.ndarray]:
    """The mode's distance, then the layers: pixels the subject never leaves are uncertain
    (candidates, not seeds), pixels outside the volume's image are background."""
    model = params.model
    assert model is not None and params.t_hi is not None and params.t_lo is not None
    if params.mode == "chroma":
        t_hi = params.t_hi
        base: Callable[[np.ndarray], np.ndarray] = lambda im: chroma_distance(im, model, t_hi=t_hi)  # noqa: E731
    elif params.mode == "luma":
        base = lambda im: luma_distance(im, model)  # noqa: E731
    else:
        plate = model["_plate"]
        base = lambda im: plate_distance(im, plate, model)  # noqa: E731
    stuck, roi = model.get("_stuck"), model.get("_roi")
    if stuck is None and roi is None:
        return base
    floor = None if stuck is None else stuck.astype(np.float32) * np.float32(0.5 * (params.t_lo + params.t_hi))
    keep = None if roi is None else roi.astype(np.float32)

    def layered(im: np.ndarray) -> np.ndarray:
        d = base(im)
        if floor is not None:
            d = cv2.max(d, floor)
        if keep is not None:
            d = cv2.multiply(d, keep)
        return d

    return layered


def _luma_percentile(image: np.ndarray, q: float) -> float:
    """Percentile of the luma of every 4th pixel (histogram-based, fast)."""
    gray = cv2.cvtColor(np.ascontiguousarray(image[::4, ::4]), cv2.COLOR_BGR2GRAY)
    hist = cv2.calcHist([gray], [0], None, [256], [0, 256]).ravel()
    cum = np.cumsum(hist)
    return float(np.searchsorted(cum, q / 100.0 * cum[-1]))


def _relative_area(params: KeyParams) -> float:
    """Plate keying keeps components of at least 2 % of the largest: without a backdrop, what
    else changes in a lab (compression noise, a flicker, a lamp's reflection) is small beside
    the subject; a backdrop's keyer keeps every component above ``min_area``."""
    if params.min_relative_area is not None:
        return float(params.min_relative_area)
    return 0.02 if params.mode == "plate" else 0.0


def key_one(image: np.ndarray, params: KeyParams) -> tuple[np.ndarray, np.ndarray, str, dict[str, float]]:
    """Key one frame with resolved parameters (see :func:`estimate_model`).

    Returns
    -------
    mask : (H, W) bool ndarray
    matte : (H, W) uint8 ndarray
    reason : str
        Empty when the frame is valid, else why not.
    stats : dict
    """
    assert params.t_lo is not None and params.t_hi is not None and params.coverage_fraction is not None
    h, w = image.shape[:2]
    p995 = _luma_percentile(image, 99.5)
    if p995 < params.black_level:
        reason = f"frame is black (99.5th-percentile luma {p995:.1f} < black_level {params.black_level:g})"
        return np.zeros((h, w), bool), np.zeros((h, w), np.uint8), reason, {"luma_p995": p995}
    dist = _distance_fn(params)(image)
    matte = soft_matte(dist, t_lo=params.t_lo, t_hi=params.t_hi)
    backdrop_frac = 1.0 - cv2.countNonZero(matte) / (h * w)
    mask, stats = mask_from_distance(
        dist,
        t_lo=params.t_lo,
        t_hi=params.t_hi,
        min_area=params.min_area,
        min_relative_area=_relative_area(params),
        fill_holes=params.fill_holes,
        close_radius=params.close_radius,
        close_relative=float(params.close_relative or 0.0),
        t_doubt=chi_radius(DOUBT_TAIL, _DOF[params.mode]),
        grow=params.grow,
        coverage_window=params.coverage_window,
        coverage_fraction=params.coverage_fraction,
    )
    fg_frac = cv2.countNonZero(mask.view(np.uint8)) / (h * w)
    stats.update(backdrop_fraction=backdrop_frac, foreground_fraction=fg_frac, luma_p995=p995)
    reason = ""
    if backdrop_frac < params.min_backdrop_fraction:
        reason = (
            f"no backdrop visible ({100 * backdrop_frac:.2f} % of the pixels match the backdrop model, "
            f"min_backdrop_fraction is {100 * params.min_backdrop_fraction:g} %)"
        )
    elif fg_frac > params.max_foreground_fraction:
        reason = (
            f"subject fills the image ({100 * fg_frac:.1f} % keyed as foreground, "
            f"max_foreground_fraction is {100 * params.max_foreground_fraction:g} %)"
        )
    if reason:
        mask = np.zeros((h, w), bool)
    return mask, matte, reason, stats


def _check_layers(frames: np.ndarray, plate, plate_noise, roi) -> None:
    if plate is not None:
        if not isinstance(plate, np.ndarray) or plate.dtype != np.uint8 or plate.shape != frames.shape[1:]:
            raise ValueError(
                f"plate must be a uint8 array of shape {frames.shape[1:]} (one frame), got "
                f"{getattr(plate, 'dtype', type(plate).__name__)} {getattr(plate, 'shape', '')}"
            )
    for name, arr in (("plate_noise", plate_noise), ("roi", roi)):
        if arr is not None and (not isinstance(arr, np.ndarray) or arr.shape != frames.shape[1:3]):
            raise ValueError(f"{name} must be an array of shape {frames.shape[1:3]}, got {getattr(arr, 'shape', arr)!r}")


def say_invalid_masks(rows: Any, reasons: Any, *, camera: str = "") -> None:
    """One warning per reason of the invalid masks (``reasons[i]`` non-empty): how many frames, the first
    :data:`stage.messages.FRAMES_NAMED` of ``rows`` (the frames' numbers) and the reason; each frame at DEBUG level.

    Parameters
    ----------
    rows : sequence of int
        The frames' numbers, one per reason.
    reasons : sequence of str
        Per frame, why its mask is invalid ("" when it is valid).
    camera : str
        Camera name, the warnings' prefix.

    Raises
    ------
    ValueError
        ``rows`` and ``reasons`` of different lengths.
    """
    rows, reasons = [int(r) for r in rows], list(reasons)
    if len(rows) != len(reasons):
        raise ValueError(f"rows: one per reason ({len(reasons)}), got {len(rows)}")
    prefix = f"{camera}: " if camera else ""
    frames: dict[str, list[int]] = {}
    for i, why in zip(rows, reasons):
        if why:
            log.debug("%sframe %d: mask invalid: %s", prefix, i, why)
            frames.setdefault(why, []).append(i)
    for why, ks in frames.items():
        log.warning("%smask invalid in %d frame%s (%s): %s", prefix, len(ks), "s" if len(ks) != 1 else "",
                    frames_named(ks), why)


def key_frames(
    frames: np.ndarray,
    *,
    mode: str = "chroma",
    plate: np.ndarray | None = None,
    plate_noise: np.ndarray | None = None,
    roi: np.ndarray | None = None,
    params: KeyParams | None = None,
    workers: int = 1,
    camera: str = "",
    progress: Callable[[int], Any] | None = None,
    rows: Any = None,
) -> KeyResult:
    """Key one camera's frames against its backdrop.

    Parameters
    ----------
    frames : (N, H, W, 3) uint8 ndarray
        BGR frames of one camera (a single (H, W, 3) frame is accepted as N = 1).
    mode : {"chroma", "luma", "plate"}
        Keying mode (overridden by ``params.mode`` when ``params`` is given).
    plate : (H, W, 3) uint8 ndarray or None
        Clean background plate of this camera. Chroma mode estimates the backdrop
        colour from it; plate mode differences against it (without one, plate mode
        estimates it from the frames, :func:`stage.keying.background.take_plate`).
    plate_noise : (H, W) float ndarray or None
        Per-pixel noise measured on the plate (plate mode).
    roi : (H, W) bool ndarray or None
        Pixels whose rays meet the capture volume; the rest is background.
    params : KeyParams or None
        Options; ``None`` = defaults for ``mode``.
    workers : int
        Threads keying frames in parallel (OpenCV and NumPy release the GIL).
    camera : str
        Camera name, used in log messages.
    progress : callable or None
        Called with the number of frames finished after each frame (e.g. ``tqdm.update``).
    rows : sequence of int or None
        The frames' numbers in the take, named in the warning of invalid masks (default ``0 .. N-1``); ``False``:
        no warning (a caller keying a camera in chunks says them once, :func:`say_invalid_masks`).

    Returns
    -------
    KeyResult
        ``masks`` (N, H, W) bool, ``matte`` (N, H, W) uint8, ``valid`` (N,) bool,
        ``reasons``, ``params`` (resolved), ``stats``.

    Raises
    ------
    ValueError
        Wrong shapes or dtypes, unknown ``mode``, a plate of the wrong size.
    KeyingError
        No backdrop model can be estimated from any frame (e.g. no backdrop in any
        frame); single bad frames do not raise, they are marked invalid.
    """
    frames = validate_frames(frames)
    if params is None:
        if mode not in KEY_MODES:
            raise ValueError(f"mode must be one of {KEY_MODES}, got {mode!r}")
        params = KeyParams(mode=mode)  # type: ignore[arg-type]
    elif not isinstance(params, KeyParams):
        raise ValueError(f"params must be a KeyParams or None, got {type(params).__name__}")
    _check_layers(frames, plate, plate_noise, roi)
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    resolved = estimate_model(frames, params=params, plate=plate, plate_noise=plate_noise, roi=roi)
    n, h, w = frames.shape[:3]
    masks = np.zeros((n, h, w), bool)
    matte = np.zeros((n, h, w), np.uint8)
    reasons = [""] * n
    stats: list[dict[str, float]] = [{} for _ in range(n)]

    def work(i: int) -> int:
        masks[i], matte[i], reasons[i], stats[i] = key_one(frames[i], resolved)
        return i

    if workers == 1 or n == 1:
        for i in range(n):
            work(i)
            if progress is not None:
                progress(1)
    else:
        with ThreadPoolExecutor(max_workers=int(workers)) as ex:
            for _ in ex.map(work, range(n)):
                if progress is not None:
                    progress(1)
    if rows is not False:
        say_invalid_masks(range(n) if rows is None else rows, reasons, camera=camera)
    valid = np.array([not r for r in reasons], bool)
    model = {k: v for k, v in (resolved.model or {}).items() if not k.startswith("_")}
    return KeyResult(
        masks=masks, matte=matte, valid=valid, reasons=reasons, params=resolved.replace(model=model), stats=stats
    )
