"""The calibration board found in every frame set of a take (``stage calibrate TAKE.h5`` and the
API's calibration job share this pass).

Frame sets keep the cameras in sync, so the set index is the moment ("frame") of a detection. A
camera whose board is found only in its flipped image is detected again on the flipped images
(:func:`calib.mirror.decide_mirror` decides from a sample of its frames; ``mirror`` per camera:
True / False forces, None decides).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from calib.mirror import CLI_SPELLING, decide_mirror, parse_mirror, sample_positions

__all__ = ["detect_take"]


def detect_take(path: Path, board, *, step: int = 1, mirror=(), on_set: Callable[[int, int], None] | None = None,
                spelling: str = CLI_SPELLING):
    """Detect the board in every frame set of a take, flipping the cameras whose board is found only flipped.

    Parameters
    ----------
    path : Path
        The take (read with :class:`stage.store.TakeReader`).
    step : int
        Every ``step``-th frame set.
    mirror : sequence of str or mapping
        ``CAM=auto|true|false`` per camera (:func:`parse_mirror`); unnamed cameras: auto.
    on_set : callable, optional
        Called as ``on_set(done, total)`` after each frame set (progress; it may raise to cancel).
    spelling : str
        How the user writes a ``mirror`` override, for the messages (:func:`parse_mirror`).

    Returns
    -------
    detections, sizes, cameras, flipped, notes
        ``detections[cam]``: a list of ``Detection`` (frame = frame set); ``flipped``: cameras
        detected on the flipped image (:func:`calib.rig.resolve_flipped` decides why).

    Raises
    ------
    calib.intrinsics.CalibrationError
        A camera that never shows the board, with what was found out (a ValueError).
    """
    from calib.detect import detect_board
    from calib.intrinsics import CalibrationError
    from stage.store import TakeReader

    if int(step) < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    with TakeReader(path) as r:
        cams = list(r.cameras)
        mirror_of = parse_mirror(mirror, cams, spelling=spelling)
        sizes = {name: tuple(r.image_size(name)) for name in cams}
        sets = list(range(0, r.n_sets, int(step)))
        raw, sample, as_is = _first_pass(r, cams, board, sets, mirror_of, on_set, detect_board)
        notes, flipped, problems = [], [], []
        for name in cams:
            n_found = sum(d is not None for d in raw[name])
            flip, msg = decide_mirror(name, n_found, len(raw[name]), sample[name], as_is[name], board,
                                      mirror_of[name], spelling=spelling)
            if msg:
                notes.append(msg)
                if not flip and not n_found:
                    problems.append(msg)
            if flip != bool(mirror_of[name]):
                rows = [(k, r.set_rows(k).get(name, -1)) for k in sets]
                raw[name] = [detect_board(r.frame(name, row), board, frame=k, mirror=flip) if row >= 0 else None
                             for k, row in rows]
            if flip:
                flipped.append(name)
    if problems:
        exc = CalibrationError("; ".join(problems), cameras=[p.split(":")[0].removeprefix("camera ") for p in problems])
        exc.notes = notes  # everything found out, for the user
        raise exc
    detections = {name: [d for d in raw[name] if d is not None] for name in cams}
    return detections, sizes, cams, flipped, notes


def _first_pass(r, cams, board, sets, mirror_of, on_set, detect_board):
    """Detections as delivered (or flipped when forced) and the sampled frames of every camera."""
    want = sample_positions(len(sets))
    raw: dict[str, list] = {name: [] for name in cams}
    sample: dict[str, list] = {name: [] for name in cams}
    as_is = dict.fromkeys(cams, 0)
    # frame sets keep the cameras in sync: the set index is the moment ("frame") of a detection
    for i, k in enumerate(sets):
        for name, img in r.frame_set(k).items():
            d = None if img is None else detect_board(img, board, frame=k, mirror=bool(mirror_of[name]))
            raw[name].append(d)
            if i in want and img is not None:
                sample[name].append(img)
                as_is[name] += int(d is not None)
        if on_set is not None:
            on_set(i + 1, len(sets))
    return raw, sample, as_is
