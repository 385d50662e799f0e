"""The wording messages share: the frames (or frame sets) a warning names.

A warning said once for many frames names the first :data:`FRAMES_NAMED` of them and counts the rest
(:func:`frames_named`): the keying's invalid masks (``stage.keying.keyer.say_invalid_masks``) and what the
pipeline's per-frame tasks warn of (``pipeline.run.frames_said``) say them alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Integral

__all__ = ["FRAMES_NAMED", "frames_named"]

#: frames a warning names (:func:`frames_named`), the rest counted
FRAMES_NAMED = 5


def frames_named(frames: Sequence[int]) -> str:
    """The first :data:`FRAMES_NAMED` of ``frames``, in their order, comma separated, then ``", ..."`` when there are
    more: ``"1, 2, 3, 4, 5, ..."``.

    Parameters
    ----------
    frames : sequence of int
        The frames (or frame sets) a message names, in the order it names them.

    Returns
    -------
    str
        ``""`` for no frames.

    Raises
    ------
    ValueError
        ``frames`` is not a sequence of integers.
    """
    if isinstance(frames, (str, bytes)) or not isinstance(frames, Sequence) or not all(
            isinstance(k, Integral) and not isinstance(k, bool) for k in frames):
        raise ValueError(f"frames must be a sequence of integers, got {frames!r}")
    return ", ".join(str(k) for k in frames[:FRAMES_NAMED]) + (", ..." if len(frames) > FRAMES_NAMED else "")
