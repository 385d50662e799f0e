"""Cameras that deliver mirrored images: the per-camera decision.

A board found only in the flipped image of a camera means either a mirroring camera or a
camera that sees the board from behind; :func:`decide_mirror` finds the flip from a sample of
frames, :func:`calib.rig.resolve_flipped` lets the rig decide which of the two it is.
The detection pass over a take that ``stage calibrate TAKE.h5`` and the API's calibration job
share reads the take: :func:`calib.take_detect.detect_take`. ``mirror`` per camera: True /
False forces, None decides.
Messages name the override the way the caller spells it (``spelling``): ``--mirror CAM=false``
on the command line (:data:`CLI_SPELLING`), the request field in the API.
"""

from __future__ import annotations

import numpy as np

__all__ = ["parse_mirror", "decide_mirror", "sample_positions", "SAMPLE", "VARIANT_SAMPLE", "CLI_SPELLING"]

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
