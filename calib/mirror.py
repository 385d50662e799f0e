"""Cameras that deliver mirrored images: the per-camera decision and detection in a take.

A board found only in the flipped image of a camera means either a mirroring camera or a
camera that sees the board from behind; :func:`decide_mirror` finds the flip from a sample of
frames, :func:`calib.rig.resolve_flipped` lets the rig decide which of the two it is.
:func:`detect_take` is the detection pass over a take that ``stage calibrate TAKE.h5`` and
the API's calibration job share. ``mirror`` per camera: True / False forces, None decides.
Messages name the override the way the caller spells it (``spelling``): ``--mirror CAM=false``
on the command line (:data:`CLI_SPELLING`), the request field in the API.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["parse_mirror", "decide_mirror", "sample_positions", "detect_take", "SAMPLE", "VARIANT_SAMPLE",
           "CLI_SPELLING"]

SAMPLE = 12  # frames of a camera tried flipped
VARIANT_SAMPLE = 3  # evenly spaced frames of a camera that never showed the board, tried with the board variants
_VALUES = {"auto": None, "true": True, "false": False}
CLI_SPELLING = "--mirror {camera}={value}"  # how stage calibrate spells the per-camera override


def _spell(spelling: str, camera: str, value) -> str:
    return spelling.format(camera=camera, value=value)


def parse_mirror(items, cameras, *, spelling: str = CLI_SPELLING) -> dict[str, bool | None]:
    """``CAM=auto|true|false`` items (or a mapping camera -> value) -> camera -> True / False / None (auto).

    Parameters
    ----------
    spelling : str
        How the caller's user writes one override, with ``{camera}`` and ``{value}``
        (default :data:`CLI_SPELLING`); errors quote the offending item that way.

    Raises
    ------
    ValueError
        Quoting the item for an unknown camera or value.
    """
    out: dict[str, bool | None] = {c: None for c in cameras}
    pairs = list(items.items()) if isinstance(items, dict) else [tuple(i.partition("=")[::2]) for i in items]
    for name, val in pairs:
        item = _spell(spelling, name, val)
        val = str(val).strip().lower() if val is not None else "auto"
        val = val or "true"
        if name not in out:
            raise ValueError(f"{item}: unknown camera {name!r} (cameras: {', '.join(cameras)})")
        if val not in _VALUES:
            raise ValueError(f"{item}: the value must be auto, true or false")
        out[name] = _VALUES[val]
    return out

def decide_mirror(name: str, found: int, total: int, sample: list, as_is: int, board, mirror: bool | None, *,
                  spelling: str = CLI_SPELLING):
    """Whether a camera's images must be flipped, from the board found in a sample of its frames.

    Parameters
    ----------
    spelling : str
        How the user writes the override the messages suggest (:func:`parse_mirror`).
    found, total : int
        Frames with the board / frames read, as delivered (or flipped when ``mirror``).
    sample : list of ndarray
        Frames sampled evenly; ``as_is`` of them showed the board.

    Returns
    -------
    (flip, message)
        ``flip`` True when the board is found only in the flipped image (auto); ``message`` says
        what was found (None when there is nothing to say).
    """
    from calib.boards import Chessboard
    from calib.detect import detect_board, find_variant

    chess = isinstance(board, Chessboard)  # found in a mirrored image too: nothing to decide
    if (mirror is not None or chess) and found:
        return bool(mirror), None
    if not sample or (found >= 0.5 * total and as_is >= 0.5 * len(sample)):
        return bool(mirror), None
    if not chess:
        flipped = sum(detect_board(img, board, mirror=not bool(mirror)) is not None for img in sample)
        if flipped >= max(3, 2 * as_is + 1):
            if mirror is False:
                return False, (f"camera {name}: the board is never detected with mirror = false, but it is found "
                               f"in {flipped}/{len(sample)} sampled frames once the image is flipped: {name} "
                               f"delivers mirrored images; drop {_spell(spelling, name, 'false')} (or turn the "
                               f"camera's mirror mode off)")
            if mirror is None:
                return True, (f"{name} delivers mirrored images or sees the board from behind: the board is found "
                              f"in {flipped}/{len(sample)} sampled frames once the image is flipped ({as_is} as "
                              f"delivered); the rig decides which")
    if found:
        return bool(mirror), None
    pick = np.unique(np.round(np.linspace(0, len(sample) - 1, min(VARIANT_SAMPLE, len(sample)))).astype(int))
    v = find_variant([sample[i] for i in pick], board)
    if v is not None and v[1] is board:
        return bool(mirror), (f"camera {name}: the board was never detected, but once the image is flipped it "
                              f"is found in {v[3]}/{len(pick)} sampled frames; if {name} delivers mirrored "
                              f"images, give {_spell(spelling, name, 'true')}")
    if v is not None:
        return bool(mirror), (f"camera {name}: the board was never detected, but with the {v[0]} it is found in "
                              f"{v[3]}/{len(pick)} sampled frames; fix the board file"
                              + (" (and the camera's mirror mode)" if v[2] else ""))
    return bool(mirror), (f"camera {name}: the board was never detected in {total} frames (nor inverted, "
                          f"legacy, mirrored or with the squares counted as inner corners); check that {name} sees "
                          f"the board, its focus, and that the board file matches the print")


def sample_positions(total: int) -> set[int]:
    """Up to ``SAMPLE`` evenly spaced positions of ``total``."""
    if total <= 0:
        return set()
    return set(np.unique(np.round(np.linspace(0, total - 1, min(SAMPLE, total))).astype(int)).tolist())



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
